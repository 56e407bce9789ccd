"""``ocpkit bench model``: median time to evaluate each robot's affine model (A_d, B_d, w_d) per control step.

Printed next to pinocchio's ``computeABADerivatives`` (continuous ∂q̈/∂q, ∂q̈/∂q̇, ∂q̈/∂τ in C++) on the same
states, as a reference ratio. Ours includes the RK4 discretization over dt = 0.01 s and goes through
CasADi's SX virtual machine from Python.
"""
from __future__ import annotations

import time

import numpy as np


def _median_time(fn, args_list, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        for args in args_list:
            t = time.perf_counter()
            fn(*args)
            times.append(time.perf_counter() - t)
    return float(np.median(times))


def bench_model(links=range(1, 14), *, states: int = 20, repeats: int = 5, seed: int = 0, out=print) -> list[dict]:
    """Benchmark nlink:1 … nlink:13, the Puma 560 and the Baxter arm; returns one row per robot."""
    import pinocchio as pin

    from ocpkit.problems.baxter import Baxter
    from ocpkit.problems.nlink import NLink, planar_chain
    from ocpkit.problems.puma560 import Puma560

    robots = [(NLink(n), planar_chain(n), 0.0) for n in links]
    robots += [(Puma560(), None, None), (Baxter(), None, None)]
    rows = []
    out(f"{'robot':<10} {'nx':>3} {'affine [us]':>12} {'pinocchio ABA derivs [us]':>26} {'ratio':>7}")
    for problem, pin_model, _ in robots:
        pin_model = problem.pin_model if pin_model is None else pin_model
        model = problem.model()
        ocp = problem.ocp()
        affine = ocp.affine()
        rng = np.random.default_rng(seed)
        samples = [problem.sample(int(s)) for s in rng.integers(0, 2**31, states)]
        n = model.nu
        args = [(x0, np.zeros(n)) for x0, _ in samples]
        affine(*args[0])  # first call allocates work vectors
        t_affine = _median_time(affine, args, repeats)
        data = pin_model.createData()
        pin_args = [(pin_model, data, x0[: pin_model.nq], x0[pin_model.nq:], np.zeros(pin_model.nv)) for x0, _ in samples]
        t_pin = _median_time(pin.computeABADerivatives, pin_args, repeats)
        row = {"robot": problem.name, "nx": model.nx, "affine_s": t_affine, "pinocchio_s": t_pin,
               "ratio": t_affine / t_pin}
        rows.append(row)
        out(f"{problem.name:<10} {model.nx:>3} {t_affine * 1e6:>12.1f} {t_pin * 1e6:>26.1f} {row['ratio']:>7.0f}")
    return rows


if __name__ == "__main__":
    bench_model()

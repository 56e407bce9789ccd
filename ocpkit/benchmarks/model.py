"""``ocpkit bench model``: median time to evaluate each robot's affine model (A_d, B_d, w_d) per control step.

Printed next to pinocchio's ``computeABADerivatives`` (continuous ∂q̈/∂q, ∂q̈/∂q̇, ∂q̈/∂τ in C++) on the same
states, as a reference ratio. Ours includes the RK4 discretization over dt = 0.01 s and goes through
CasADi's SX virtual machine from Python.

Then the plants: wall time to simulate one second (100 control periods of 10 RK4 sub-steps, zero input, from the
seeded starts) with ocpkit's plant (the problem's ``plant().rk4``, CasADi from Python) and with MuJoCo
(:class:`ocpkit.sim.mujoco_plant.MuJoCoPlant`, its RK4 at the same sub-step; "–" for the Baxter arm, whose plant is a
sampled servo, or without MuJoCo installed).
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


def _one_second(step, starts, nu: int, dt: float) -> float:
    """Median wall time (s) to simulate one second with ``step`` F(x, u) -> x⁺, once from each start."""
    times, u = [], np.zeros(nu)
    for x in starts:
        t = time.perf_counter()
        for _ in range(round(1.0 / dt)):
            x = step(x, u)
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def bench_model(links=range(1, 14), *, states: int = 20, repeats: int = 5, seed: int = 0, out=print) -> list[dict]:
    """Benchmark nlink:1 … nlink:13, the Puma 560 and the Baxter arm; returns one row per robot (``plant_s`` and
    ``mujoco_s``: seconds to simulate one second, NaN where MuJoCo cannot)."""
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
        pin_args = [
            (pin_model, data, x0[: pin_model.nq], x0[pin_model.nq :], np.zeros(pin_model.nv)) for x0, _ in samples
        ]
        t_pin = _median_time(pin.computeABADerivatives, pin_args, repeats)
        row = {
            "robot": problem.name,
            "nx": model.nx,
            "affine_s": t_affine,
            "pinocchio_s": t_pin,
            "ratio": t_affine / t_pin,
        }
        rows.append(row)
        out(f"{problem.name:<10} {model.nx:>3} {t_affine * 1e6:>12.1f} {t_pin * 1e6:>26.1f} {row['ratio']:>7.0f}")
    out(f"\n{'robot':<10} {'plant: 1 s simulated [ms]':>26} {'MuJoCo: 1 s simulated [ms]':>27} {'ratio':>7}")
    for (problem, _, _), row in zip(robots, rows):
        plant, dt = problem.plant(), problem.dt
        starts = [problem.sample(seed + s)[0] for s in range(max(1, repeats))]
        step = plant.rk4(dt, 10)
        step(starts[0], np.zeros(plant.nu))  # first call allocates work vectors
        row["plant_s"] = _one_second(lambda x, u: np.asarray(step(x, u)).ravel(), starts, plant.nu, dt)
        row["mujoco_s"] = _mujoco_second(problem, starts, dt)
        mj = "–" if np.isnan(row["mujoco_s"]) else f"{row['mujoco_s'] * 1e3:.2f}"
        ratio = "–" if np.isnan(row["mujoco_s"]) else f"{row['plant_s'] / row['mujoco_s']:.1f}"
        out(f"{problem.name:<10} {row['plant_s'] * 1e3:>26.2f} {mj:>27} {ratio:>7}")
    return rows


def _mujoco_second(problem, starts, dt: float) -> float:
    """:func:`_one_second` on MuJoCo (NaN where it is not installed or cannot simulate the problem)."""
    try:
        from ocpkit.sim.mujoco_plant import MuJoCoPlant

        plant = MuJoCoPlant(problem)
    except (ImportError, ValueError):
        return float("nan")
    return _one_second(plant.stepper(dt, 10), starts, plant.nu, dt)


if __name__ == "__main__":
    bench_model()

"""What the controller's integrator (``problem.ocp(integrator=...)``, :data:`ocpkit.model.dynamics.INTEGRATORS`) costs
and loses.

:func:`bench_sensitivities`: µs per stage of the affine model (A_d, B_d, w_d), compiled C mapped over the horizon as the
real-time iteration evaluates it, with RK4 and with Euler, beside its parts — f and its Jacobian
(:attr:`ocpkit.model.dynamics.Model.jacobian`) — and pinocchio's analytical ``computeABADerivatives`` (C++, one call
from Python: its bindings' overhead included); and each integrator's one-step error, the median over the sampled states
of max |F(x, u) − x⁺| with x⁺ from RK4 over 100 sub-steps.

:func:`bench_integrators`: closed loops on the plant (RK4, never changed) of the real-time iteration
(``RealTimeIteration(ocp)``, solver "rti", its Python step, so that the integrator measured is
:mod:`ocpkit.model.dynamics`'s) and of IPOPT, each predicting with each integrator: actual costs
(:func:`ocpkit.sim.metrics.actual_cost`) per seed as ratios, IPOPT with RK4 the reference. The tutorial's cart-pole
(:func:`ocpkit.benchmarks.nlp.example_cartpole`) swings up from hanging as in :func:`ocpkit.benchmarks.nlp.bench_nlp`.

``python -m ocpkit.benchmarks.sensitivities`` prints both tables.
"""

from __future__ import annotations

import time

import numpy as np

from ocpkit import problems as registry
from ocpkit.codegen.compiled import compile_function
from ocpkit.sim.metrics import actual_cost
from ocpkit.model.dynamics import INTEGRATORS
from ocpkit.numeric import BufferedFunction
from ocpkit.sim.simulate import simulate


def _states(problem, count: int, seed: int):
    """``count`` sampled configurations with random velocities and inputs (columns), for timing."""
    rng = np.random.default_rng(seed)
    model = problem.model()
    x = np.stack([problem.sample(int(s))[0] for s in rng.integers(0, 2**31, count)], axis=1)
    n = model.nx // 2
    x[n:] = rng.uniform(-1.0, 1.0, (model.nx - n, count))
    return x, rng.uniform(-1.0, 1.0, (model.nu, count))


def _per_call(fn, args, repeats: int) -> float:
    """Median seconds of ``fn(*args)`` over ``repeats`` calls (after one to warm up)."""
    fn(*args)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn(*args)
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def bench_sensitivities(
    problems=("puma560", "baxter", "nlink:13", "panda"),
    *,
    stages: int = 50,
    repeats: int = 200,
    seed: int = 0,
    out=print,
) -> list[dict]:
    """µs per stage of f, its Jacobian and the affine model per integrator (compiled at the default -O1, mapped over
    ``stages``), and of pinocchio's computeABADerivatives per call; one row per problem."""
    import pinocchio as pin

    rows = []
    out(
        f"{'problem':<10}{'nx':>4}{'f':>7}{'jacobian':>10}"
        + "".join(f"{'affine ' + i:>14}" for i in INTEGRATORS)
        + f"{'pinocchio':>11}"
        + "".join(f"{'error ' + i:>13}" for i in INTEGRATORS)
        + "   (µs per stage; compile s)"
    )
    for name in problems:
        problem = registry.make(name)
        model = problem.model()
        X, U = _states(problem, stages, seed)
        fns = {"f": model.f, "jacobian": model.jacobian}
        fns.update({i: model.affine(problem.dt, 1, i) for i in INTEGRATORS})
        row = {"problem": name, "nx": model.nx}
        built = []
        for key, fn in fns.items():
            t0 = time.perf_counter()
            mapped = BufferedFunction(compile_function(fn.map(stages)))
            built.append(time.perf_counter() - t0)
            row[key] = _per_call(mapped, (X, U), repeats) / stages * 1e6
        pin_model = problem.pin_model
        data, n = pin_model.createData(), pin_model.nv
        row["pinocchio"] = (
            _per_call(pin.computeABADerivatives, (pin_model, data, X[:n, 0], X[n:, 0], U[:, 0]), 20 * repeats) * 1e6
        )
        fine = np.asarray(model.rk4(problem.dt, 100).map(stages)(X, U))
        for i in INTEGRATORS:
            step = np.asarray(model.discrete(problem.dt, 1, i).map(stages)(X, U))
            row["error " + i] = float(np.median(np.abs(step - fine).max(axis=0)))
        rows.append(row)
        out(
            f"{name:<10}{model.nx:>4}{row['f']:>7.1f}{row['jacobian']:>10.1f}"
            + "".join(f"{row[i]:>14.1f}" for i in INTEGRATORS)
            + f"{row['pinocchio']:>11.1f}"
            + "".join(f"{row['error ' + i]:>13.1e}" for i in INTEGRATORS)
            + f"   ({', '.join(f'{t:.0f}' for t in built)})"
        )
    return rows


def bench_integrators(
    problems=None,
    *,
    seeds=(0, 1, 2),
    steps: int = 50,
    knots: int = 5,
    horizon: int = 50,
    methods=("rti", "ipopt"),
    out=print,
) -> list[dict]:
    """Closed-loop actual cost, median step (ms) and final error max |x_H − x_goal| of ``methods`` (the solvers
    "rti", one iteration, and "ipopt", converged: what the integrator costs without RTI's inexactness) with each
    integrator, over ``steps`` control steps from ``problem.sample(seed)``, and the cost ratios euler/rk4 per method
    and, with "ipopt", RTI's over IPOPT's with RK4 (the reference); one row per problem and seed. ``problems``
    (default: puma560, baxter, nlink:13 and, from the source tree, the tutorial's cart-pole): problem specs; the
    tutorial's cart-pole (:func:`ocpkit.benchmarks.nlp.example_cartpole`) swings up (10 knots, its own horizon, its
    duration + 1 s) as in :func:`ocpkit.benchmarks.nlp.bench_nlp`."""
    from ocpkit.benchmarks.nlp import is_example_cartpole, with_example_cartpole
    from ocpkit import solvers

    kinds = [f"{m} {i}" for m in methods for i in INTEGRATORS]
    ratios = {f"{m} e/r": (f"{m} euler", f"{m} rk4") for m in methods}
    if "rti" in methods and "ipopt" in methods:
        ratios.update({f"rti {i}/ipopt": (f"rti {i}", "ipopt rk4") for i in INTEGRATORS})
    out(
        f"{'problem':<18}{'seed':>5}{'steps':>6}"
        + "".join(f"{k + ' cost':>17}" for k in kinds)
        + "".join(f"{k + ' ms':>15}" for k in kinds)
        + "".join(f"{k + ' err':>16}" for k in kinds)
        + "".join(f"{r:>16}" for r in ratios)
    )
    if problems is None:
        problems = with_example_cartpole(["puma560", "baxter", "nlink:13"])
    rows = []
    for name in problems:
        swing = is_example_cartpole(name)
        problem = registry.make(name)
        p, T = (10, None) if swing else (knots, horizon)
        ocps = {i: problem.ocp(knots=p, horizon=T, integrator=i, compiled=True) for i in INTEGRATORS}
        for ocp in ocps.values():
            ocp.affine()  # compiled (or loaded from the cache) before any step is timed
        duration = problem.duration + 1.0 if swing else steps * ocps["rk4"].dt
        # RTI's Python step: where LinearMPC would build its C step (ocpkit.export.native), that one has its own
        # integrator
        controllers = {
            f"{m} {i}": solvers.make(m, ocps[i], **({"native": False} if m == "rti" else {}))
            for m in methods
            for i in INTEGRATORS
        }
        for seed in seeds:
            x0, goal = problem.sample(seed)
            if swing:  # from hanging, θ = π
                x0 = np.r_[x0[0], np.pi + x0[1], x0[2:]]
            row = {"problem": "cartpole swing-up" if swing else name, "seed": seed}
            for kind, ctrl in controllers.items():
                traj = simulate(problem.plant(), ctrl, x0, goal, duration)
                row[kind] = actual_cost(traj, ocps["rk4"])
                row[kind + " ms"] = 1e3 * float(np.median(traj.times()))
                row[kind + " fallbacks"] = traj.fallbacks
                row[kind + " err"] = float(np.abs(traj.x[-1] - goal).max())
                row["steps"] = len(traj.solutions)
            row.update({r: row[a] / row[b] for r, (a, b) in ratios.items()})
            rows.append(row)
            out(
                f"{row['problem']:<18}{seed:>5}{row['steps']:>6}"
                + "".join(f"{row[k]:>17.6g}" for k in kinds)
                + "".join(f"{row[k + ' ms']:>15.2f}" for k in kinds)
                + "".join(f"{row[k + ' err']:>16.4f}" for k in kinds)
                + "".join(f"{row[r]:>16.4f}" for r in ratios)
            )
    return rows


if __name__ == "__main__":
    bench_sensitivities()
    bench_integrators()

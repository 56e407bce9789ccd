"""Solve time of the IPOPT baseline (NonlinearMPC) per control step, traditional vs knots, beside LinearMPC.

For each problem, parameterization and seeded trial, NonlinearMPC runs the closed loop on the plant; LinearMPC
is then timed on the very same sequence of states (each warm-started from its own previous step), so both
columns answer the same problems. Times are the per-step totals (model + build + solve) in milliseconds.
"""
from __future__ import annotations

import time

import numpy as np

from ocpkit import problems as registry
from ocpkit._checks import integer
from ocpkit.simulate import simulate

PAPER_PROBLEMS = tuple(f"nlink:{n}" for n in range(1, 8)) + ("puma560",)
FALLBACK_PROBLEMS = ("pendulum:linear", "pendulum")


def default_problems() -> list[str]:
    """nlink 1…7 and the Puma where registered; the pendulums when none of them is."""
    known = set(registry.names())
    chosen = [name for name in PAPER_PROBLEMS if name.partition(":")[0] in known]
    return chosen or list(FALLBACK_PROBLEMS)


def bench_nlp(problems=None, knots=(None, 3, 5), samples: int = 3, steps: int = 20, *, method: str = "ipopt",
              echo: bool = True) -> list[dict]:
    """Median per-step solve time of NonlinearMPC and LinearMPC on the same states; one row per problem × knots.

    ``knots`` None is traditional MPC (p = T). ``samples`` seeded start/goal pairs (``Problem.sample``), each
    run for ``steps`` control steps. Prints a table when ``echo``; returns the rows as dicts.
    """
    from ocpkit.solvers.nlp import NonlinearMPC
    from ocpkit.solvers.qp import LinearMPC

    if isinstance(problems, str):
        raise TypeError(f"problems must be a list of problem names, got the string {problems!r}")
    names = default_problems() if problems is None else list(problems)
    samples = integer(samples, "samples", 1)
    steps = integer(steps, "steps", 1)
    knots = tuple(knots)
    if not knots:
        raise ValueError("knots must name at least one parameterization (None for traditional MPC)")
    rows = []
    if echo:
        print(f"{'problem':<16}{'knots':>6}{'build s':>9}{'ipopt ms':>10}{'iters':>7}{'fallbk':>7}"
              f"{'qp ms':>9}{'ratio':>8}")
    for name in names:
        prob = registry.make(name)
        for p in knots:
            ocp = prob.ocp(knots=p)
            t0 = time.perf_counter()
            nl = NonlinearMPC(ocp, method=method)
            build = time.perf_counter() - t0
            lin = LinearMPC(ocp)
            t_nl, t_lin, iters, fallbacks = [], [], [], 0
            for seed in range(samples):
                x0, goal = prob.sample(seed)
                traj = simulate(prob.plant(), nl, x0, goal, steps * ocp.dt)
                t_nl += list(traj.times())
                iters += [s.iterations for s in traj.solutions]
                fallbacks += traj.fallbacks
                lin.reset()
                t_lin += [lin.solve(x, goal).times["total"] for x in traj.x[:-1]]
            row = {"problem": name, "knots": "T" if p is None else p, "build_s": build,
                   "nlp_ms": 1e3 * float(np.median(t_nl)), "nlp_iterations": float(np.median(iters)),
                   "nlp_fallbacks": fallbacks, "qp_ms": 1e3 * float(np.median(t_lin)),
                   "steps": len(t_nl)}
            row["ratio"] = row["nlp_ms"] / row["qp_ms"]
            rows.append(row)
            if echo:
                print(f"{name:<16}{row['knots']!s:>6}{build:>9.2f}{row['nlp_ms']:>10.2f}"
                      f"{row['nlp_iterations']:>7.0f}{fallbacks:>7d}{row['qp_ms']:>9.2f}{row['ratio']:>8.1f}",
                      flush=True)
    return rows

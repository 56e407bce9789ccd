"""`ocpkit bench qp`: model/build/solve/total medians for sparse|condensed × traditional|knots (Section V-F)."""

from __future__ import annotations

import numpy as np

from ocpkit.problems import make
from ocpkit.solvers.qp import LinearMPC

PARTS = ("model", "build", "solve", "total")


def bench_qp(
    problems=("pendulum:linear", "pendulum", "nlink:3", "nlink:7"),
    horizons=(50, 100),
    knots=5,
    samples=30,
    qp="proxqp",
    seed=0,
    out=print,
) -> list[dict]:
    """One MPC solve per sampled state for every configuration, interleaved so all see the same machine load."""
    rows = []
    for name in problems:
        problem = make(name)
        for T in horizons:
            configs = {
                (form, p): LinearMPC(
                    problem.ocp(horizon=T, knots=p), form=form, qp=qp, warm_start=False, time_limit=float("inf")
                )
                for form in ("sparse", "condensed")
                for p in (None, knots)
            }
            times = {key: {part: [] for part in PARTS} for key in configs}
            for s in range(samples):
                x0, goal = problem.sample(seed + s)
                for key, ctrl in configs.items():
                    ctrl.reset()
                    sol = ctrl.solve(x0, goal)
                    for part in PARTS:
                        times[key][part].append(sol.times[part])
            for (form, p), t in times.items():
                rows.append(
                    {
                        "problem": name,
                        "horizon": T,
                        "form": form,
                        "knots": p or T,
                        **{part: float(np.median(v)) for part, v in t.items()},
                    }
                )
    _print(rows, qp, knots, out)
    return rows


def _print(rows, qp, knots, out):
    out(f"QP backend {qp}; medians in ms; ratio = traditional total / knots({knots}) total, same form")
    out(f"{'problem':16} {'T':>4} {'form':10} {'knots':>5} " + " ".join(f"{p:>8}" for p in PARTS) + f" {'ratio':>7}")
    by_key = {(r["problem"], r["horizon"], r["form"], r["knots"]): r for r in rows}
    for r in rows:
        trad = by_key[(r["problem"], r["horizon"], r["form"], r["horizon"])]
        ratio = trad["total"] / r["total"]
        out(
            f"{r['problem']:16} {r['horizon']:>4} {r['form']:10} {r['knots']:>5} "
            + " ".join(f"{1e3 * r[p]:8.3f}" for p in PARTS)
            + f" {ratio:7.2f}"
        )

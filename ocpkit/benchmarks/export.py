"""Benchmark: median step time of the exported, compiled C step vs Python's LinearMPC (issue 7)."""
from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from ocpkit._checks import integer
from ocpkit.export import ExportedMPC, build, export


def default_problems() -> list[str]:
    """nlink:1 … nlink:13 when the n-link robots are registered, else the pendulum."""
    from ocpkit.problems import names

    return [f"nlink:{n}" for n in range(1, 14)] if "nlink" in names() else ["pendulum"]


def bench_export(problems=None, *, horizon: int = 100, knots: int = 5, qp: str = "daqp", steps: int = 50,
                 seed: int = 0, out_root=None, linearization: str = "goal", out=print) -> list[dict]:
    """Per problem: export + build times, and the median step time (s) of the C step and of LinearMPC.

    Both controllers see the same states: a closed loop of ``steps`` steps on the discrete model driven by
    LinearMPC's input (condensed, ProxQP), from ``problem.sample(seed)``. ``max_abs_du`` is the largest
    difference between the two first inputs over the loop.
    """
    from ocpkit.problems import filename, make
    from ocpkit.solvers.qp import LinearMPC

    problems = default_problems() if problems is None else list(problems)
    steps = integer(steps, "steps", 1)
    root = Path(tempfile.mkdtemp(prefix="ocpkit-bench-export-") if out_root is None else out_root)
    rows = []
    for name in problems:
        problem = make(name)
        ocp = problem.ocp(knots=knots, horizon=horizon)
        out_dir = root / filename(name)
        t0 = time.perf_counter()
        info = export(ocp, out_dir, qp=qp, linearization=linearization)
        t1 = time.perf_counter()
        build(info.out_dir)
        t2 = time.perf_counter()
        c = ExportedMPC(ocp, info.out_dir, name=info.name)
        py = LinearMPC(ocp, form="condensed", linearization=linearization)
        F = ocp.discrete()
        x, goal = problem.sample(seed)
        t_c, t_py, du, py_fails, c_fails = [], [], 0.0, 0, 0
        for _ in range(steps):
            a, b = py.solve(x, goal), c.solve(x, goal)
            t_py.append(a.times["total"])
            t_c.append(b.times["solve"])
            du = max(du, float(np.abs(a.u - b.u).max()))
            py_fails += not a.ok
            c_fails += not b.ok
            x = np.asarray(F(x, a.u)).ravel()
        rows.append({"problem": name, "nx": ocp.nx, "nu": ocp.nu, "horizon": horizon, "knots": knots, "qp": qp,
                     "export_s": t1 - t0, "build_s": t2 - t1, "c_median_s": float(np.median(t_c)),
                     "python_median_s": float(np.median(t_py)),
                     "speedup": float(np.median(t_py) / np.median(t_c)), "max_abs_du": du,
                     "python_failures": py_fails, "c_failures": c_fails})
    out(f"exported C step vs Python LinearMPC (condensed, horizon {horizon}, knots {knots}, {qp}); medians\n"
        + format_table(rows))
    return rows


def format_table(rows: list[dict]) -> str:
    """The benchmark rows as a fixed-width text table (times in ms)."""
    head = f"{'problem':<10} {'nx':>3} {'nu':>3} {'C ms':>9} {'Python ms':>10} {'speedup':>8} {'max|du|':>9} " \
           f"{'fails py/C':>10} {'build s':>8}"
    lines = [head]
    for r in rows:
        lines.append(f"{r['problem']:<10} {r['nx']:>3} {r['nu']:>3} {1e3 * r['c_median_s']:>9.3f} "
                     f"{1e3 * r['python_median_s']:>10.3f} {r['speedup']:>8.1f} {r['max_abs_du']:>9.2e} "
                     f"{r['python_failures']:>4}/{r['c_failures']:<5} {r['build_s']:>8.1f}")
    return "\n".join(lines)

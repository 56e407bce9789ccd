"""Benchmark: the exported C step at robot scale — generated C size, build time, C step vs Python's LinearMPC
step and their round-trip error, side by side (issues 7 and 18)."""

from __future__ import annotations

import os
import re
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from ocpkit._checks import integer
from ocpkit.export import ExportedMPC, build, export

DEFAULT_PROBLEMS = ("pendulum", "nlink:3", "nlink:7", "nlink:13", "puma560", "baxter")


def default_problems() -> list[str]:
    """The issue-18 set (pendulum, nlink:3/7/13, puma560, baxter) among the registered problems."""
    from ocpkit.problems import make

    found = []
    for name in DEFAULT_PROBLEMS:
        try:
            make(name)
        except ValueError:
            continue
        found.append(name)
    return found


def bench_export(
    problems=None,
    *,
    horizon: int = 100,
    knots: int = 5,
    qp: str = "daqp",
    steps: int = 50,
    seed: int = 0,
    out_root=None,
    linearization: str = "goal",
    example: bool = True,
    out=print,
) -> list[dict]:
    """Per problem: generated C size, export and build times, the median and worst step time (s) of the C step
    (through ctypes, each step right after LinearMPC's, so with the caches Python left; and of the folder's own
    ``./example`` closed loop, C only) beside LinearMPC's, the C step's split (medians of its affine model,
    condensing and QP solve, timed in C), and the round-trip error.

    Both controllers see the same states: a closed loop of ``steps`` steps on the discrete model driven by
    LinearMPC's input (condensed, ProxQP at eps 1e-10), from ``problem.sample(seed)``, after one untimed warm-up
    step of each (then reset). ``max_abs_du`` is the
    largest difference between the two first inputs and knots over the loop. ``build_s`` is ``make lib``
    (every source compiled once, two jobs); the example then only links.
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
        x, goal = problem.sample(seed)
        t0 = time.perf_counter()
        info = export(ocp, out_dir, qp=qp, linearization=linearization, x0=x, goal=goal, force=True)
        t1 = time.perf_counter()
        build(info.out_dir)
        t2 = time.perf_counter()
        example_s = example_worst = float("nan")
        if example:
            build(info.out_dir, target="example")
            run = subprocess.run(
                ["./example"],
                cwd=info.out_dir,
                capture_output=True,
                text=True,
                env={**os.environ, "OMP_NUM_THREADS": "1"},
            )
            found = re.search(r"median step ([0-9.]+) us  worst ([0-9.]+) us", run.stdout)
            example_s, example_worst = (
                (1e-6 * float(found.group(1)), 1e-6 * float(found.group(2))) if found else (float("nan"), float("nan"))
            )
        py = LinearMPC(ocp, form="condensed", eps=1e-10, linearization=linearization)
        F = ocp.discrete()
        t_c, t_py, split, du, py_fails, c_fails = [], [], [], 0.0, 0, 0
        with ExportedMPC(ocp, info.out_dir, name=info.name) as c:
            for ctl in (py, c):  # warm-up (first calls: page faults, set-up), then both start cold
                ctl.solve(x, goal)
                ctl.reset()
            for _ in range(steps):
                a, b = py.solve(x, goal), c.solve(x, goal)
                t_py.append(a.times["total"])
                t_c.append(c.step_seconds)
                split.append([b.times[k] for k in ("model", "build", "solve")])
                du = max(du, float(np.abs(a.u - b.u).max()), float(np.abs(a.knots - b.knots).max()))
                py_fails += not a.ok
                c_fails += not b.ok
                x = np.asarray(F(x, a.u)).ravel()
        m_s, b_s, q_s = (float(v) for v in np.median(split, axis=0))
        rows.append(
            {
                "problem": name,
                "nx": ocp.nx,
                "nu": ocp.nu,
                "horizon": horizon,
                "knots": knots,
                "qp": qp,
                "c_bytes": info.c_bytes,
                "export_s": t1 - t0,
                "build_s": t2 - t1,
                "c_median_s": float(np.median(t_c)),
                "c_worst_s": float(np.max(t_c)),
                "c_model_s": m_s,
                "c_build_s": b_s,
                "c_qp_s": q_s,
                "example_median_s": example_s,
                "example_worst_s": example_worst,
                "python_median_s": float(np.median(t_py)),
                "python_worst_s": float(np.max(t_py)),
                "speedup": float(np.median(t_py) / np.median(t_c)),
                "max_abs_du": du,
                "python_failures": py_fails,
                "c_failures": c_fails,
            }
        )
        if out is print:  # progress: a row as soon as it is measured
            print(format_table(rows[-1:], header=len(rows) == 1), flush=True)
    out(
        f"exported C step vs Python LinearMPC (condensed, horizon {horizon}, knots {knots}, {qp}; {steps} steps); "
        f"medians and worst over the steps; C split = affine model / condensing / QP solve (medians, timed in C); "
        f"cores: {os.cpu_count()}, load: {_load()}\n" + format_table(rows)
    )
    return rows


def _load() -> str:
    try:
        return " ".join(f"{v:.1f}" for v in os.getloadavg())
    except OSError:
        return "n/a"


def format_table(rows: list[dict], header: bool = True) -> str:
    """The benchmark rows as a fixed-width text table (sizes in kB, times in ms, build in s)."""
    head = (
        f"{'problem':<10} {'nx':>3} {'nu':>3} {'C kB':>6} {'build s':>8} {'C ms':>7} {'C worst':>8} "
        f"{'C model/cond/QP ms':>19} {'example ms':>10} {'ex. worst':>9} {'Python ms':>10} {'Py worst':>9} "
        f"{'speedup':>8} {'max|du|':>9} {'fails py/C':>10}"
    )
    lines = [head] if header else []
    for r in rows:
        split = "/".join(f"{1e3 * r[k]:.3f}" for k in ("c_model_s", "c_build_s", "c_qp_s"))
        lines.append(
            f"{r['problem']:<10} {r['nx']:>3} {r['nu']:>3} {r['c_bytes'] / 1e3:>6.0f} {r['build_s']:>8.1f} "
            f"{1e3 * r['c_median_s']:>7.3f} {1e3 * r['c_worst_s']:>8.3f} "
            f"{split:>19} {1e3 * r['example_median_s']:>10.3f} {1e3 * r['example_worst_s']:>9.3f} "
            f"{1e3 * r['python_median_s']:>10.3f} {1e3 * r['python_worst_s']:>9.3f} {r['speedup']:>8.1f} "
            f"{r['max_abs_du']:>9.2e} "
            f"{r['python_failures']:>4}/{r['c_failures']:<5}"
        )
    return "\n".join(lines)


README_OBSTACLE = ((0.4, -0.25, 0.35), 0.08)  # the README's Panda reach: this sphere, target (0.4, 0, 0.3), sample(0)
README_TARGET = (0.4, 0.0, 0.3)


def readme_obstacles(problem, count: int, seed: int = 0) -> list:
    """The README Panda case's sphere and ``count`` − 1 more balls (radius 1-4 cm) about the hand's straight path to
    the target (centres at 20-80 % of the way, 8 cm normal scatter per axis), each 3 cm clear of the arm at the start
    (``problem.sample(0)``) and of the target point."""
    from ocpkit.model.kinematics import spheres_along_links
    from ocpkit.model.task import Sphere, clearances

    kin = problem.kinematics
    q0 = problem.sample(0)[0][: kin.n]
    robot = spheres_along_links(kin, problem.link_radius)
    start, target = kin.positions(problem.end_effector, q0)[0], np.asarray(README_TARGET)
    rng, balls = np.random.default_rng(seed), [Sphere(*README_OBSTACLE)]
    while len(balls) < count:
        centre = start + rng.uniform(0.2, 0.8) * (target - start) + rng.normal(0.0, 0.08, 3)
        ball = Sphere(tuple(centre), float(rng.uniform(0.01, 0.04)))
        if clearances(kin, robot, [ball], q0[None])[0] > 0.03 and np.linalg.norm(centre - target) > ball.radius + 0.03:
            balls.append(ball)
    return balls


def bench_obstacle_steps(
    counts=(1, 10, 100), *, steps: int = 100, linearization: str = "plan", out=print
) -> list[dict]:
    """The C step against the Python step with obstacles (issue 43): the README's Panda reach past 1, 10, 100 balls
    (:func:`readme_obstacles`), LinearMPC(native=True) and LinearMPC(native=False), each in its own closed loop of
    ``steps`` steps on the discrete model from the same start, steps interleaved (the machine's load falls alike on
    both), compiled parts ready. Per count and controller: median and largest step time (``Solution.times["total"]``,
    the certificate's rollout on the nonlinear model included), the statuses and the smallest true clearance; for the
    C step its split (medians over the steps it answered, ``path`` "C step": affine model, condensing with the task's
    terms and obstacle rows, DAQP; timed in C) and the steps its hard QP could not answer that the QP with the
    obstacle rows softened answered, in Python (``path`` SOFTENED_AFTER_C)."""
    from ocpkit import problems as registry
    from ocpkit.model.kinematics import spheres_along_links
    from ocpkit.solvers.qp import SOFTENED_AFTER_C, LinearMPC
    from ocpkit.model.task import clearances, reach

    panda = registry.make("panda")
    robot = spheres_along_links(panda.kinematics, panda.link_radius)
    steps = integer(steps, "steps", 1)
    rows = []
    for count in counts:
        balls = readme_obstacles(panda, count)
        ocp = reach(panda, balls, knots=5)
        x0, _ = panda.sample(0)
        goal = ocp.goal(x0, position=README_TARGET)
        t0 = time.perf_counter()
        loops = {"C": LinearMPC(ocp, native=True, linearization=linearization)}
        build_s = time.perf_counter() - t0
        loops["Python"] = LinearMPC(ocp, native=False, linearization=linearization)
        loops["Python"].wait_compiled(600)
        F = ocp.discrete()
        states = {name: [x0] for name in loops}
        sols = {name: [] for name in loops}
        for _ in range(steps):
            for name, ctrl in loops.items():
                sol = ctrl.solve(states[name][-1], goal)
                sols[name].append(sol)
                states[name].append(np.asarray(F(states[name][-1], sol.u)).ravel())
        row = {"obstacles": count, "steps": steps, "build_s": build_s}
        for name in loops:
            t = np.array([s.times["total"] for s in sols[name]])
            statuses = {}
            for sol in sols[name]:
                statuses[sol.status] = statuses.get(sol.status, 0) + 1
            q = np.array(states[name])[:, : panda.kinematics.n]
            row[name] = {
                "median_s": float(np.median(t)),
                "max_s": float(t.max()),
                "statuses": statuses,
                "min_clearance": float(clearances(panda.kinematics, robot, balls, q).min()),
            }
        answered = [s for s in sols["C"] if s.path == "C step"]
        row["C"]["split_s"] = (
            [float(v) for v in np.median([[s.times[k] for k in ("model", "build", "solve")] for s in answered], axis=0)]
            if answered
            else []
        )
        row["C"]["softened_in_python"] = sum(s.path == SOFTENED_AFTER_C for s in sols["C"])
        rows.append(row)
    lines = [
        f"Panda README reach, LinearMPC {linearization!r}, C step (native=True) and Python step each in its own "
        f"closed loop, {steps} steps; cores {os.cpu_count()}, load {_load()}"
    ]
    for r in rows:
        c, py = r["C"], r["Python"]
        lines.append(
            f"{r['obstacles']:>4} obstacles: C {1e3 * c['median_s']:.2f} / {1e3 * c['max_s']:.2f} ms "
            f"(median / max; in C model/condensing/QP "
            f"{'/'.join(f'{1e3 * v:.2f}' for v in c['split_s'])} ms; softened in Python "
            f"{c['softened_in_python']}), Python {1e3 * py['median_s']:.2f} / {1e3 * py['max_s']:.2f} ms; "
            f"statuses C {c['statuses']} Python {py['statuses']}; min clearance C {c['min_clearance']:.4f} "
            f"Python {py['min_clearance']:.4f} m"
        )
    out("\n".join(lines))
    return rows

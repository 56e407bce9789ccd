"""``ocpkit bench task``: what a task in task space costs LinearMPC's step, against its joint-space step.

For each robot, one closed loop per variant from the same seeded starts, steps interleaved round-robin so that the
machine's load falls alike on every variant (each keeps its own state): the joint-space step (today's default: the C
step where it applies, and the Python step), the reach task (frame-position term, :func:`ocpkit.model.task.reach`) and
the reach task with a ball on the way. Every controller waits for its compiled parts first (the steady state). Printed:
median and 95th-percentile step time, the ratio of medians to the joint-space default, the successes and the end
effector's final distance to its target (the worst over the seeds).

:func:`bench_obstacles` times LinearMPC's obstacle steps as the obstacles multiply (issue 43): the Panda reaching past
1, 10, 100 balls scattered about the straight path of its hand, and the construction of a controller for 1,000.
"""

from __future__ import annotations

import time

import numpy as np


def _scene(problem, seed: int):
    """Start, target point (the end effector at a sampled goal) and a ball half-way on the straight path between
    them, of radius 0.15 × their distance (at most 0.08 m), at least 3 cm clear of the robot's link spheres at the start
    and at the goal (else the next sample: seed·1000 + 1, + 2, …)."""
    from ocpkit.model.kinematics import spheres_along_links
    from ocpkit.model.task import Sphere, clearances

    kin = problem.kinematics
    robot = spheres_along_links(kin, problem.link_radius)
    for draw in range(1000):
        x0, goal = problem.sample(seed * 1000 + draw)
        ends = np.vstack([x0[: kin.n], goal[: kin.n]])
        start, target = kin.positions(problem.end_effector, ends)
        ball = Sphere(tuple(0.5 * (start + target)), min(0.08, max(0.02, 0.15 * float(np.linalg.norm(target - start)))))
        if clearances(kin, robot, [ball], ends).min() > 0.03:
            return x0, goal, target, ball
    raise ValueError(f"no clear scene for {problem!r} from seed {seed}")


def _scattered(problem, seed: int, count: int):
    """Start, target point and ``count`` balls (radius 1-4 cm) about the straight path between them (centres at
    20-80 % of the way, 8 cm normal scatter per axis), each at least 3 cm clear of the robot's link spheres at the
    start and at the goal."""
    from ocpkit.model.kinematics import spheres_along_links
    from ocpkit.model.task import Sphere, clearances

    kin = problem.kinematics
    robot = spheres_along_links(kin, problem.link_radius)
    x0, goal = problem.sample(seed)
    ends = np.vstack([x0[: kin.n], goal[: kin.n]])
    start, target = kin.positions(problem.end_effector, ends)
    rng, balls = np.random.default_rng(seed), []
    while len(balls) < count:
        centre = start + rng.uniform(0.2, 0.8) * (target - start) + rng.normal(0.0, 0.08, 3)
        ball = Sphere(tuple(centre), float(rng.uniform(0.01, 0.04)))
        if clearances(kin, robot, [ball], ends).min() > 0.03:
            balls.append(ball)
    return x0, target, balls


def bench_obstacles(
    counts=(1, 10, 100), *, seeds=(11, 12, 13), duration: float = 1.0, build: int = 1000, out=print
) -> list[dict]:
    """Per obstacle count: LinearMPC (trajectory linearization, its defaults) on the Panda's reach past that many balls
    (:func:`_scattered`), a ``duration`` closed loop per seed: median and largest step time, the statuses, the
    smallest true clearance; then the seconds to build a controller for ``build`` balls and take its first step."""
    from ocpkit import problems as registry
    from ocpkit.model.kinematics import spheres_along_links
    from ocpkit.sim.simulate import simulate
    from ocpkit.solvers.qp import LinearMPC
    from ocpkit.model.task import clearances, reach

    panda = registry.make("panda")
    robot = spheres_along_links(panda.kinematics, panda.link_radius)
    rows = []
    out(f"{'obstacles':>9} {'seed':>4} {'median [ms]':>11} {'max [ms]':>9} {'min clearance [m]':>17}  statuses")
    for count in counts:
        for seed in seeds:
            x0, target, balls = _scattered(panda, seed, count)
            ocp = reach(panda, balls)
            traj = simulate(
                panda.plant(), LinearMPC(ocp, linearization="trajectory"), x0, ocp.goal(x0, position=target), duration
            )
            t = np.array([s.times["total"] for s in traj.solutions])
            statuses = {}
            for sol in traj.solutions:
                statuses[sol.status] = statuses.get(sol.status, 0) + 1
            row = {
                "obstacles": count,
                "seed": seed,
                "median_s": float(np.median(t)),
                "max_s": float(t.max()),
                "statuses": statuses,
                "min_clearance": float(clearances(panda.kinematics, robot, balls, traj.x[:, :7]).min()),
            }
            rows.append(row)
            out(
                f"{count:>9} {seed:>4} {1e3 * row['median_s']:>11.1f} {1e3 * row['max_s']:>9.1f} "
                f"{row['min_clearance']:>17.4f}  {statuses}"
            )
    if build:
        x0, target, balls = _scattered(panda, seeds[0], build)
        start = time.perf_counter()
        ocp = reach(panda, balls)
        made = time.perf_counter()
        ctrl = LinearMPC(ocp, linearization="trajectory")
        built = time.perf_counter()
        sol = ctrl.solve(x0, ocp.goal(x0, position=target))
        done = time.perf_counter()
        row = {
            "obstacles": build,
            "reach_s": made - start,
            "controller_s": built - made,
            "first_step_s": done - built,
            "status": sol.status,
        }
        rows.append(row)
        out(
            f"{build} obstacles: reach {row['reach_s']:.2f} s, LinearMPC {row['controller_s']:.2f} s, first step "
            f"{row['first_step_s']:.2f} s ({sol.status})"
        )
    return rows


def bench_task(
    problems=("panda", "nlink:3"), *, steps: int = 200, seeds: int = 2, knots: int = 5, out=print
) -> list[dict]:
    """Per robot and variant: step-time median and p95 (ms), ratio to the joint-space default, successes."""
    from ocpkit import problems as registry
    from ocpkit.solvers.qp import LinearMPC
    from ocpkit.model.task import reach

    rows = []
    out(
        f"{'robot':<10} {'variant':<24} {'median [ms]':>11} {'p95 [ms]':>9} {'ratio':>6} {'success':>9} "
        f"{'worst final dist [m]':>20}"
    )
    for spec in problems:
        problem = registry.make(spec)
        kin = problem.kinematics
        times: dict = {}
        stats: dict = {}
        for seed in range(seeds):
            x0, goal, target, ball = _scene(problem, seed)
            joint = problem.ocp(knots=knots)
            task, blocked = reach(problem, knots=knots), reach(problem, [ball], knots=knots)
            variants = {
                "joint space (default)": (LinearMPC(joint), goal),
                "joint space (Python)": (LinearMPC(joint, native=False), goal),
                "reach": (LinearMPC(task), task.goal(x0, position=target)),
                "reach + ball": (LinearMPC(blocked), blocked.goal(x0, position=target)),
            }
            states, plant = {}, problem.plant().rk4(problem.dt, 10)
            for name, (ctrl, _) in variants.items():
                ctrl.wait_compiled()
                states[name] = x0.copy()
                stats.setdefault(name, {"ok": 0, "steps": 0, "dist": []})
            for _ in range(steps):
                for name, (ctrl, g) in variants.items():
                    t = time.perf_counter()
                    sol = ctrl.solve(states[name], g)
                    times.setdefault(name, []).append(time.perf_counter() - t)
                    states[name] = np.asarray(plant(states[name], sol.u), dtype=float).ravel()
                    s = stats[name]
                    s["ok"] += sol.ok
                    s["steps"] += 1
            for name in variants:
                if name.startswith("reach"):
                    end = kin.positions(problem.end_effector, states[name][: kin.n])[0]
                    stats[name]["dist"].append(float(np.linalg.norm(end - target)))
        base = float(np.median(times["joint space (default)"]))
        for name, t in times.items():
            s, med = stats[name], float(np.median(t))
            row = {
                "robot": problem.name,
                "variant": name,
                "median_s": med,
                "p95_s": float(np.percentile(t, 95)),
                "ratio": med / base,
                "success": s["ok"] / s["steps"],
                "final_distance": max(s["dist"]) if s["dist"] else float("nan"),
            }
            rows.append(row)
            dist = f"{row['final_distance']:.4f}" if s["dist"] else "-"
            out(
                f"{problem.name:<10} {name:<24} {1e3 * med:>11.3f} {1e3 * row['p95_s']:>9.3f} {row['ratio']:>6.2f} "
                f"{s['ok']:>4}/{s['steps']:<4} {dist:>20}"
            )
    return rows


if __name__ == "__main__":
    bench_task()

"""The commands of a controller on a problem: solve, simulate and demo (the others: study and reproduce in
:mod:`ocpkit.cli.study`, bench in :mod:`ocpkit.cli.bench`, build in :mod:`ocpkit.cli.build`, export in
:mod:`ocpkit.cli.export`)."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import sys
import threading
import time
from pathlib import Path

import numpy as np

from ocpkit import problems, solvers
from ocpkit.cli.checks import check_output_file, check_output_folder, check_size
from ocpkit.cli.options import make_ocp, solver_options
from ocpkit.cli.task import Reach, motion_files, reach_ocp, reach_task
from ocpkit.cli.task_report import point_text, reach_line, reach_panels, reach_report
from ocpkit.controller import Controller


def make_controller(args, task: Reach | None = None) -> tuple:
    """(problem, its OCP, the controller) the command line asks for; with a reach task, the OCP carries it."""
    options = solver_options(args)
    problem = problems.make(args.problem)
    check_size(problem, args)
    if task is None:
        ocp = make_ocp(problem, args, error=args.error, compiled=args.compiled)
    else:
        ocp = reach_ocp(problem, args, task, error=args.error, compiled=args.compiled)
    return problem, ocp, solvers.make(args.solver, ocp, **options)


def seeded_start(problem, ocp, seed: int, task: Reach | None) -> tuple:
    """The seeded start and goal; with a reach task the goal is its targets, at rest (joint velocities zero)."""
    x0, goal = problem.sample(seed)
    return (x0, goal) if task is None else (x0, task.goal(ocp, x0))


# Seconds a phase of work runs before it is said on stderr (said_if_slow): quick runs stay quiet.
SLOW = 1.0


@contextlib.contextmanager
def said_if_slow(text: str):
    """``text…`` on stderr once the block has run ``SLOW`` seconds: what a long wait is spent on (quick work prints
    nothing)."""
    timer = threading.Timer(SLOW, lambda: print(f"ocpkit: {text}…", file=sys.stderr, flush=True))
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()


class _Progress:
    """A closed loop's progress on stderr, "simulating 200 steps: 40/200 (5 s)": first after ``FIRST`` seconds, then
    every ``EVERY`` (quick runs print nothing); a simulate() callback."""

    FIRST, EVERY = 2.0, 5.0

    def __init__(self, steps: int):
        self.steps, self.start = steps, time.perf_counter()
        self.next = self.start + self.FIRST

    def __call__(self, k: int, x, solution) -> None:
        now = time.perf_counter()
        if now >= self.next and k + 1 < self.steps:
            print(
                f"ocpkit: simulating {self.steps} steps: {k + 1}/{self.steps} ({now - self.start:.0f} s)",
                file=sys.stderr,
                flush=True,
            )
            self.next = now + self.EVERY


def _label(ctrl: Controller) -> str:
    """The controller's repr with its OCP as its knot count: "LinearMPC(condensed, daqp, C step, 5 knots)"."""
    return repr(ctrl).replace(repr(ctrl.ocp), f"{ctrl.ocp.knots} knots")


def _solve(args):
    task = reach_task(args)
    problem, ocp, ctrl = make_controller(args, task)
    x0, goal = seeded_start(problem, ocp, args.seed, task)
    sol = ctrl.solve(x0, goal)
    extra = {}
    if task is not None:  # the plan: the OCP's model from x0 under the solved knots, x_0 … x_T
        extra["reach"] = reach_report(problem, ocp, task, ctrl.rollout(x0, ocp.parameterization.inputs(sol.knots)))
    if args.json:
        print(
            json.dumps(
                {
                    "problem": args.problem,
                    "solver": args.solver,
                    "controller": repr(ctrl),
                    "x0": x0.tolist(),
                    "goal": goal.tolist(),
                    **sol.to_dict(),
                    **extra,
                }
            )
        )
    else:
        print(
            f"{ctrl!r}\nx0 = {x0}, goal = {goal}\nu = {sol.u}  status = {sol.status} ({sol.raw_status}), "
            f"{sol.iterations} iterations, total {1e3 * sol.times['total']:.3f} ms"
        )
        if task is not None:
            print(reach_line(extra["reach"], f"at the plan's end (x_T, T = {ocp.horizon}, the OCP's model)"))
    return 0 if sol.ok else 1


def _run_closed_loop(
    problem, ctrl: Controller, seed: int, duration: float | None = None, start=None, plant=None, obstacles=None
):
    """The closed loop from the seeded start (or ``start``, (x0, goal), the goal a vector or a Reference) against
    ``plant`` (default the problem's), the task's obstacles moving along ``obstacles`` (an ObstaclePath) where given,
    after one untimed solve that compiles what the controller needs (Taichi kernels take seconds), never counted in
    the step times; a first solve over a second and a loop over two seconds are said on stderr as they run."""
    from ocpkit.model.reference import Reference
    from ocpkit.sim.metrics import actual_cost
    from ocpkit.sim.simulate import simulate

    x0, goal = problem.sample(seed) if start is None else start
    ocp = ctrl.ocp
    first_goal = goal.window(0.0, ocp.dt, ocp.horizon) if isinstance(goal, Reference) else goal
    moved = {} if obstacles is None else {"obstacles": obstacles.window(0.0, ocp.dt, ocp.horizon)}
    start = time.perf_counter()
    with said_if_slow(f"{_label(ctrl)}: first solve, compiling what it needs (not in the step times)"):
        ctrl.solve(x0, first_goal, **moved)  # simulate() resets the controller: this solve only compiles, warms up
    first = time.perf_counter() - start
    if first > SLOW:
        print(f"ocpkit: first solve took {first:.1f} s", file=sys.stderr)
    duration = duration or problem.duration
    traj = simulate(
        plant or problem.plant(),
        ctrl,
        x0,
        goal,
        duration,
        callback=_Progress(int(round(duration / ocp.dt))),
        obstacles=obstacles,
    )
    return traj, actual_cost(traj, ctrl.ocp)


def _labels(problem) -> dict:
    """The plant's state and input names for the figure's axes, with units where the joints say them: a revolute
    joint's angle [rad], rate [rad/s] and torque (an input named tau…) [N·m], a prismatic one's [m], [m/s], [N];
    a set-point input has its joint's position unit. Joints from the problem's kinematics (the pendulum's one
    joint is revolute); other problems' names are shown as their model gives them."""
    plant = problem.plant()
    if hasattr(type(problem), "kinematics"):
        revolute = list(problem.kinematics.chain.revolute)
    else:
        revolute = [True] if problem.name.startswith("pendulum") else []
    n = len(revolute)
    if not n or plant.nx != 2 * n or plant.nu != n:
        return {"state_names": plant.state_names, "input_names": plant.input_names}
    position, rate = (["rad" if r else "m" for r in revolute], ["rad/s" if r else "m/s" for r in revolute])
    effort = [
        ("N·m" if r else "N") if name.startswith("tau") else p
        for r, name, p in zip(revolute, plant.input_names, position)
    ]
    return {
        "state_names": [f"{s} [{u}]" for s, u in zip(plant.state_names, position + rate)],
        "input_names": [f"{s} [{u}]" for s, u in zip(plant.input_names, effort)],
    }


def _time_summary(traj) -> dict:
    t = traj.times("total")
    return {
        "median_ms": 1e3 * float(np.median(t)),
        "p90_ms": 1e3 * float(np.percentile(t, 90)),
        "max_ms": 1e3 * float(t.max()),
    }


def _mujoco_options(args) -> list:
    """(option, given value, default) of simulate's options that only a MuJoCo plant takes."""
    return [
        ("--mjcf", args.mjcf, None),
        ("--joint-map", args.joint_map, None),
        ("--frictionloss", args.frictionloss, 0.0),
        ("--armature", args.armature, 0.0),
        ("--floor", args.floor, None),
        ("--limits", args.limits, None),
        ("--mujoco-integrator", args.mujoco_integrator, "rk4"),
    ]


def _plant(problem, args):
    """The plant of --plant: None for the problem's own, else a MuJoCoPlant of its robot or of --mjcf."""
    if args.plant == "ocpkit":
        return None
    from ocpkit.sim.mujoco_plant import MuJoCoPlant

    joint_map = None
    if args.joint_map:
        items = [item.strip() for item in args.joint_map.split(",")]
        pairs = [item.partition("=") for item in items]
        if any(sep for _, sep, _ in pairs) and not all(sep and a and b for a, sep, b in pairs):
            raise ValueError(f"--joint-map must be MJCF joint names J1,J2,… or pairs NAME=J,…, got {args.joint_map!r}")
        joint_map = {a: b for a, _, b in pairs} if pairs[0][1] else items
    return MuJoCoPlant(
        problem,
        mjcf=args.mjcf,
        joint_map=joint_map,
        integrator=args.mujoco_integrator,
        frictionloss=args.frictionloss,
        armature=args.armature,
        floor=args.floor,
        limits=args.limits,
    )


def _simulate(args):
    from ocpkit.sim import plots

    if args.out is not None:
        check_output_file(args.out, "--out")
    if args.animate is not None:
        from ocpkit.sim import animation

        check_output_file(animation.check_path(args.animate, "--animate"), "--animate")
    task = reach_task(args)
    if args.plant != "mujoco":
        given = [option for option, value, default in _mujoco_options(args) if value != default]
        if given:
            raise ValueError(f"{given[0]} applies to --plant mujoco only")
    if args.joint_map and not args.mjcf:
        raise ValueError("--joint-map names the joints of an MJCF file: give --mjcf too")
    motion = motion_files(args)
    if args.no_preview and motion["reference"] is None:
        raise ValueError("--no-preview applies to --reference only")
    problem, ocp, ctrl = make_controller(args, task)
    plant = _plant(problem, args)
    if args.animate is not None:
        animation.Skeleton(problem, None if task is None else task.frame)  # a robot it cannot draw fails before the run
    x0, goal = seeded_start(problem, ocp, args.seed, task)
    reference, obstacles = _motion(ocp, goal, motion, args.no_preview)
    if reference is not None and task is None:
        x0 = reference.at(0.0)[: ocp.nx]  # a joint reference starts the run on itself
    traj, cost = _run_closed_loop(
        problem,
        ctrl,
        args.seed,
        args.duration,
        start=(x0, goal if reference is None else reference),
        plant=plant,
        obstacles=obstacles,
    )
    shown, title = traj, f"{args.problem}, seed {args.seed}" + (", MuJoCo plant" if args.plant == "mujoco" else "")
    if task is not None:
        # the joint angles have no goal in a reach task (x_goal's angles are the start's, weighted zero): none drawn
        goal = traj.goal.copy()
        goal[: problem.kinematics.n] = np.nan
        shown = dataclasses.replace(traj, goal=goal)
        title += f", {task.frame} to {point_text(task.target)}"
    fig = None
    if args.out is not None:  # a figure only when asked: never one overwritten unasked
        panels = None if task is None else reach_panels(problem, ocp, task, traj.x)
        fig = plots.closed_loop({_label(ctrl): shown}, args.out, title=title, task=panels, **_labels(problem))
    # success: status "success" only; a soft step applied the solver's input but broke a clearance or state bound
    if reference is not None:  # against the reference at each time: the tracking error, no single target to reach
        progress = _Tracking(traj, problem, ocp, task)
    elif task is None:
        progress = traj.progress()
    else:
        progress = traj.progress(problem.kinematics, task.frame, task.target)
    summary = {
        "problem": args.problem,
        "solver": args.solver,
        "controller": repr(ctrl),
        "actual_cost": cost,
        "successes": traj.successes,
        "soft": traj.soft_steps,
        "soft_causes": traj.soft_causes(),
        "fallbacks": traj.fallbacks,
        "fallback_causes": traj.fallback_causes(),
        "steps": len(traj.solutions),
        "progress": progress.to_dict(),
        "total_time": _time_summary(traj),
        "figure": None if fig is None else str(fig),
        "plant": "ocpkit" if plant is None else repr(plant),
    }
    if task is not None and reference is None:
        summary["reach"] = reach_report(
            problem,
            ocp,
            task,
            traj.x,
            dt=float(traj.t[1] - traj.t[0]),
            success_while_colliding=traj.success_while_colliding(ocp),
            moving=traj.obstacles,
        )
    if args.animate is not None:  # a reach task's target (moving with a reference) and obstacles, else the goal pose
        target = None if task is None else task.target if reference is None else traj.targets(ocp)
        scene = {} if task is None else {"target": target, "obstacles": task.obstacles, "frame": task.frame}
        summary["animation"] = str(animation.animate(traj, args.animate, problem, title=title, **scene))
    if args.json:
        print(json.dumps(summary))
    else:
        soft = f" ({summary['soft_causes']})" if traj.soft_steps else ""
        causes = f" ({summary['fallback_causes']})" if traj.fallbacks else ""
        print(
            f"{ctrl!r}: actual cost {cost:.4f}; {len(traj.solutions)} steps: {traj.successes} success, "
            f"{traj.soft_steps} soft{soft}, {traj.fallbacks} fallbacks{causes}; "
            f"total solve time median {summary['total_time']['median_ms']:.3f} ms "
            f"(p90 {summary['total_time']['p90_ms']:.3f} ms, max {summary['total_time']['max_ms']:.3f} ms)"
            + ("" if fig is None else f"\nfigure: {fig}")
            + ("" if plant is None else f"\nplant: {plant!r}")
        )
        if "reach" in summary:
            print(reach_line(summary["reach"], f"after {traj.t[-1]:g} s"))
        print(progress.text())
        if args.animate is not None:
            print(f"animation: {summary['animation']}")
    return 0


def _motion(ocp, goal, files: dict, no_preview: bool):
    """(the Reference of ``files["reference"]`` (goal entries it leaves out from ``goal``; without preview with
    ``no_preview``) or None, the ObstaclePath of ``files["obstacle_path"]`` or None)."""
    from ocpkit.model.reference import ObstaclePath, Reference

    reference = None
    if files["reference"] is not None:
        reference = Reference.load(files["reference"], ocp, default=goal)
        reference = reference.without_preview() if no_preview else reference
    obstacles = None
    if files["obstacle_path"] is not None:
        declared = ocp.task.obstacles if ocp.task is not None else []
        if not declared:
            raise ValueError(
                "--obstacle-path moves the task's obstacles: declare them with --obstacle (or the task file)"
            )
        obstacles = ObstaclePath.load(files["obstacle_path"], declared)
    return reference, obstacles


class _Tracking:
    """The loop's tracking error against its reference at each recorded time (:meth:`Trajectory.tracking_error`):
    the task frame's distance to the reference's target point (m), or max_i |x_i − x_ref,i| for a joint goal; its
    RMS and max."""

    def __init__(self, traj, problem, ocp, task):
        if task is None:
            self.error, self.what, self.unit = traj.tracking_error(), "max |x − x_ref|", ""
        else:
            error = traj.tracking_error(problem.kinematics, task.frame, traj.targets(ocp))
            self.error, self.what, self.unit = error, "distance", " m"

    def to_dict(self) -> dict:
        return {"rms_error": float(np.sqrt(np.mean(self.error**2))), "max_error": float(self.error.max())}

    def text(self) -> str:
        d = self.to_dict()
        rms, worst = (f"{d[k]:.4g}{self.unit}" for k in ("rms_error", "max_error"))
        return f"tracking: {self.what} to the reference RMS {rms}, max {worst}"


def _demo(args):
    """Every registered controller configuration on one seeded pendulum swing, side by side."""
    from ocpkit.sim import plots
    from ocpkit.solvers.qp import LinearMPC

    check_output_folder(args.out, "--out")
    problem = problems.make(args.problem)
    x0, goal = problem.sample(args.seed)
    configs = {}
    for knots in (None, 5):
        label = "traditional" if knots is None else f"knots={knots}"
        ocp = problem.ocp(knots=knots)
        for form in ("sparse", "condensed"):
            for qp in ("proxqp", "osqp"):
                configs[f"qp {form} {qp} {label}"] = LinearMPC(ocp, form=form, qp=qp)
        for name in solvers.names():
            if name != "qp":
                configs[f"{name} {label}"] = solvers.make(name, ocp)
    print(
        f"{args.problem}: x0 = {np.round(x0, 3)}, goal = {np.round(goal, 3)}, {problem.duration} s at "
        f"{1 / problem.dt:.0f} Hz, horizon {problem.horizon}"
    )
    print(
        f"{'controller':36} {'actual cost':>12} {'ratio':>8} {'final err':>9} {'median ms':>10} {'p90 ms':>8} "
        f"{'fallbacks':>9}"
    )
    trajs, base = {}, None
    for label, ctrl in configs.items():
        traj, cost = _run_closed_loop(problem, ctrl, args.seed)
        base = cost if base is None else base
        t = _time_summary(traj)
        final = float(np.abs(traj.x[-1] - goal).max())  # a plan that drifts off the goal shows here, not in the ratio
        print(
            f"{label:36} {cost:12.4f} {cost / base:8.4f} {final:9.3g} {t['median_ms']:10.3f} {t['p90_ms']:8.3f} "
            f"{traj.fallbacks:9d}"
        )
        trajs[label] = traj
    fig = plots.closed_loop(
        trajs,
        Path(args.out) / f"{args.problem}.png",
        title=f"{args.problem}: closed loop, seed {args.seed}",
        **_labels(problem),
    )
    print(f"ratio = actual cost / first row's; final err = max |x − goal| at the end; figure: {fig}")
    return 0


# `ocpkit COMMAND` for the commands of a controller on a problem (the others: ocpkit.cli)
COMMANDS = {"solve": _solve, "simulate": _simulate, "demo": _demo}

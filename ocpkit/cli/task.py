"""Task-space targets on the command line: --target, --obstacle, --frame and --task (:func:`ocpkit.task.reach`), and
how a run did on them."""
from __future__ import annotations

import dataclasses
import re

import numpy as np

from ocpkit.cli.options import knot_count

# --- task-space targets: --target, --obstacle, --frame, --task (ocpkit.task.reach) --------------------------------

# The keys of a --task file beside target, frame and [[obstacle]]: reach()'s keyword arguments, all positive but
# margin (any finite number: the clearance kept, m).
_TASK_NUMBERS = ("margin", "position_weight", "terminal_weight", "link_radius", "obstacle_weight")
_TASK_KEYS = ("target", "frame", "obstacle") + _TASK_NUMBERS
# A value of --target or --obstacle that argparse would take for an option ("-0.3,0.5,0"): see _attach_values.
NUMBERS = re.compile(r"^-[0-9.][0-9.eE+-]*(,\s*[-+]?[0-9.][0-9.eE+-]*)*$")


@dataclasses.dataclass
class Reach:
    """A reach task from the command line: the target point, the frame (None: the problem's end effector), the
    obstacles (ocpkit.task.Sphere) and reach()'s other options; ``source`` names where target and frame came from."""

    target: np.ndarray
    frame: str | None
    obstacles: list
    options: dict
    source: dict


def _point(text, option: str, form: str = "'x,y,z'") -> np.ndarray:
    """x,y,z (m) from "x,y,z" or a list of three numbers."""
    try:
        values = [float(v) for v in (text.split(",") if isinstance(text, str) else text)]
    except (TypeError, ValueError):
        values = []
    if len(values) != 3 or not np.isfinite(values).all():
        raise ValueError(f"{option} is {form} (the end effector's target point in metres, world frame), got {text!r}")
    return np.array(values)


def _number(value, where: str, positive: bool) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or \
            (positive and value <= 0):
        raise ValueError(f"{where} must be a {'positive' if positive else 'finite'} number, got {value!r}")
    return float(value)


def read_task_file(path) -> dict:
    """A --task TOML file as {target, frame, obstacles, options}, every value checked (errors name the file)."""
    import tomllib

    from ocpkit.task import Sphere

    where = f"--task {path}"
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise ValueError(f"{where}: no such file") from None
    except IsADirectoryError:
        raise ValueError(f"{where}: is a folder; give a TOML file") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{where}: not valid TOML: {exc}") from None
    unknown = sorted(set(data) - set(_TASK_KEYS))
    if unknown:
        raise ValueError(f"{where}: unknown key {unknown[0]!r}; a task file has {', '.join(_TASK_KEYS)}")
    out = {"target": None, "frame": None, "obstacles": [], "options": {}}
    if "target" in data:
        out["target"] = _point(data["target"], f"{where}: target", "[x, y, z]")
    if "frame" in data:
        if not isinstance(data["frame"], str) or not data["frame"]:
            raise ValueError(f"{where}: frame must be a frame name (a string), got {data['frame']!r}")
        out["frame"] = data["frame"]
    obstacles = data.get("obstacle", [])
    if not isinstance(obstacles, list) or not all(isinstance(o, dict) for o in obstacles):
        raise ValueError(f"{where}: obstacles are [[obstacle]] tables with center = [x, y, z] and radius = r")
    for k, o in enumerate(obstacles, 1):
        if set(o) != {"center", "radius"}:
            raise ValueError(f"{where}: obstacle {k} has the keys {sorted(o)}; it needs exactly center = [x, y, z] "
                             f"and radius = r (m)")
        center = o["center"]
        if not isinstance(center, list) or len(center) != 3 or not all(
                isinstance(c, (int, float)) and not isinstance(c, bool) for c in center):
            raise ValueError(f"{where}: obstacle {k}: center must be [x, y, z] (m), got {center!r}")
        radius = _number(o["radius"], f"{where}: obstacle {k}: radius", positive=True)
        try:
            out["obstacles"].append(Sphere(tuple(float(c) for c in center), radius))
        except ValueError as exc:
            raise ValueError(f"{where}: obstacle {k}: {exc}") from None
    for key in _TASK_NUMBERS:
        if key in data:
            out["options"][key] = _number(data[key], f"{where}: {key}", positive=key != "margin")
    return out


def reach_task(args) -> Reach | None:
    """The reach task that --target, --obstacle, --frame and --task ask for (None: none, the seeded joint goal)."""
    from ocpkit.task import Sphere

    file = read_task_file(args.task) if args.task else {"target": None, "frame": None, "obstacles": [],
                                                              "options": {}}
    source = {"target": "--target", "frame": "--frame"}
    target = None
    if args.target is not None:
        target = _point(args.target, "--target")
    elif file["target"] is not None:
        target, source["target"] = file["target"], f"--task {args.task}"
    if target is None:
        given = [o for o, v in (("--obstacle", args.obstacle), ("--frame", args.frame)) if v]
        if given:
            raise ValueError(f"{given[0]} needs --target x,y,z (or a --task file with target = [x, y, z]): it "
                             f"belongs to a reach task")
        if args.task:
            raise ValueError(f"--task {args.task}: no target = [x, y, z] in the file (nor --target)")
        return None
    obstacles = list(file["obstacles"])
    for text in args.obstacle or ():
        try:
            obstacles.append(Sphere.parse(text))
        except ValueError as exc:
            raise ValueError(f"--obstacle {text}: {exc}") from None
    frame = args.frame
    if frame is None and file["frame"] is not None:
        frame, source["frame"] = file["frame"], f"--task {args.task}: frame"
    return Reach(target, frame, obstacles, file["options"], source)


def reach_ocp(problem, args, task: Reach, **options):
    """ocpkit.task.reach for the command line's task, after the checks that name its options."""
    from ocpkit.task import reach

    kinematics = getattr(problem, "kinematics", None)
    if kinematics is None:
        raise ValueError(f"{task.source['target']}: {args.problem} has no kinematics (no frames to bring to a "
                         f"point); a reach task needs a robot problem: nlink:N, puma560, baxter, panda, urdf:FILE")
    if task.frame is None:
        task.frame = getattr(problem, "end_effector", None)
        if task.frame is None:
            raise ValueError(f"{args.problem} names no end effector; give --frame NAME, one of its frames: "
                             f"{', '.join(kinematics.frames)}")
    else:
        try:
            kinematics.function(task.frame)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{task.source['frame']} {task.frame!r}: {exc}") from None
    return reach(problem, task.obstacles, frame=task.frame, knots=knot_count(problem, args), horizon=args.horizon,
                 parameterization=args.parameterization, integrator=args.integrator, **task.options, **options)


def reach_panels(problem, ocp, task: Reach, xs) -> dict:
    """The figure's task panel: the frame's distance to the target and (with obstacles) the smallest clearance, at
    every state of ``xs``."""
    positions, clearance = _reach_series(problem, ocp, task, xs)
    panels = {f"{task.frame} to target": np.linalg.norm(positions - task.target, axis=1)}
    if clearance is not None:
        panels["min clearance"] = clearance
    return panels


def _reach_series(problem, ocp, task: Reach, xs):
    """The frame's positions (N, 3) along the states ``xs`` (N, nx) and the smallest clearance at each (None without
    obstacles): distance from a robot sphere's surface to an obstacle's."""
    from ocpkit.task import clearances

    xs = np.atleast_2d(np.asarray(xs, dtype=float))
    kin = problem.kinematics
    positions = kin.positions(task.frame, xs[:, :kin.n])
    if not task.obstacles:
        return positions, None
    return positions, clearances(ocp.task.kinematics, ocp.task.robot, ocp.task.obstacles, xs[:, :kin.n])


def reach_report(problem, ocp, task: Reach, xs, dt: float | None = None,
                 success_while_colliding: int | None = None) -> dict:
    """How the states ``xs`` (N, nx) did on the task: the frame's distance to the target at the last state, and the
    smallest clearance — distance from a robot sphere's surface to an obstacle's — over all states (negative: they
    overlap, a collision); for a closed loop, ``success_while_colliding``: the steps reported "success" whose next
    state collides."""
    positions, closest = _reach_series(problem, ocp, task, xs)
    report = {"frame": task.frame, "target": task.target.tolist(), "final_position": positions[-1].tolist(),
              "final_distance": float(np.linalg.norm(positions[-1] - task.target)),
              "obstacles": [[*map(float, o.center), float(o.radius)] for o in task.obstacles],
              "margin": ocp.task.margin,
              "min_clearance": None, "collisions": 0, "first_collision": None, "states": len(positions)}
    if closest is not None:
        hit = np.flatnonzero(closest < 0)
        report.update(min_clearance=float(closest.min()), collisions=int(hit.size),
                      first_collision=None if not hit.size else int(hit[0]) if dt is None else float(hit[0] * dt))
    if success_while_colliding is not None:
        report["success_while_colliding"] = int(success_while_colliding)
    return report


def reach_line(report: dict, what: str) -> str:
    """The report as one line of text."""
    line = (f"reach: {report['frame']} {report['final_distance']:.4f} m from the target "
            f"{point_text(report['target'])} {what}")
    n = len(report["obstacles"])
    if not n:
        return line + "; no obstacles"
    first = report["first_collision"]
    when = "" if first is None else f", first at t = {first:.2f} s" if isinstance(first, float) else \
        f", first at step {first}"
    collided = (f"COLLIDED in {report['collisions']} of {report['states']} states{when}" if report["collisions"]
                else f"no collision in {report['states']} states")
    if report["collisions"] and "success_while_colliding" in report:
        collided += f", {report['success_while_colliding']} steps reported success while colliding"
    return (line + f"; min clearance {report['min_clearance']:.4f} m to {n} obstacle{'s' * (n > 1)} "
                   f"(margin {report['margin']:g} m); {collided}")


def point_text(v) -> str:
    return "(" + ", ".join(f"{a:g}" for a in v) + ")"

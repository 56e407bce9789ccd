"""Task-space targets on the command line: --target, --obstacle, --frame and --task
(:func:`ocpkit.model.task.reach`); how a run did on them: :mod:`ocpkit.cli.task_report`."""

from __future__ import annotations

from pathlib import Path

import dataclasses
import re

import numpy as np

from ocpkit.cli.options import knot_count

# --- task-space targets: --target, --obstacle, --frame, --task (ocpkit.model.task.reach) -----------------------------

# The keys of a --task file beside target, frame, orientation, joint_limits and the [[obstacle]] and [[frame_target]]
# tables: numbers, reach()'s keyword arguments and the weights of the orientation and joint-limit terms, all positive
# but margin (the clearance kept, m, of either sign); link_radius and margin are lengths within
# ocpkit.model.task.MAX_LENGTH.
_TASK_NUMBERS = (
    "margin",
    "position_weight",
    "terminal_weight",
    "link_radius",
    "obstacle_weight",
    "orientation_weight",
    "joint_limit_weight",
)
_REACH_OPTIONS = _TASK_NUMBERS[:5]
_TASK_KEYS = ("target", "frame", "orientation", "joint_limits", "obstacle", "frame_target") + _TASK_NUMBERS
# the motion files a --task file may name (paths relative to the file), as simulate's --reference and --obstacle-path
_MOTION_KEYS = {"reference": "--reference", "obstacle_path": "--obstacle-path"}
# The orientation term's default weight: position_weight / 100, so an orientation 0.1 rad off costs what a position
# 1 cm off does (the residual is sin θ, the position's metres).
ORIENTATION_PER_POSITION = 1e-2
# A value of --target, --obstacle or --orientation that argparse would take for an option ("-0.3,0.5,0"): see
# _attach_values.
NUMBERS = re.compile(r"^-[0-9.][0-9.eE+-]*(,\s*[-+]?[0-9.][0-9.eE+-]*)*$")


@dataclasses.dataclass
class Reach:
    """A reach task from the command line: the target point, the frame (None: the problem's end effector), the
    obstacles (ocpkit.model.task.Sphere) and reach()'s other options; the frame's orientation target (a rotation, 9
    entries row by row, or None) and its term's weight (None: the default), more frames' targets
    (:class:`FrameTarget`), the joint-limit term's weight (None: no such term); ``source`` names where each came
    from."""

    target: np.ndarray
    frame: str | None
    obstacles: list
    options: dict
    source: dict
    orientation: np.ndarray | None = None
    orientation_weight: float | None = None
    frame_targets: list = dataclasses.field(default_factory=list)
    joint_limits: float | None = None

    def goal(self, ocp, x_goal) -> np.ndarray:
        """The OCP's goal vector: ``x_goal`` and every target, by its term's name."""
        targets = {"position": self.target, **{t.term: t.target for t in self.frame_targets}}
        if self.orientation is not None:
            targets["orientation"] = self.orientation
        return ocp.goal(x_goal, **targets)


@dataclasses.dataclass
class FrameTarget:
    """Another frame brought to a point (a --frame-target or a [[frame_target]] table), by the term ``term``."""

    frame: str
    target: np.ndarray
    weight: float | None
    source: str

    @property
    def term(self) -> str:
        return "position_" + re.sub(r"\W", "_", self.frame)


def _numbers(value, count: int) -> list | None:
    """``value`` as ``count`` finite floats ("a,b,c" or a list of numbers, where booleans and strings are not
    numbers), else None."""
    if isinstance(value, str):
        items = value.split(",")
    elif isinstance(value, list) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        items = value
    else:
        return None
    try:
        values = [float(v) for v in items]
    except ValueError:
        return None
    return values if len(values) == count and np.isfinite(values).all() else None


def _point(text, option: str, form: str = "'x,y,z'") -> np.ndarray:
    """x,y,z (m) from "x,y,z" or a list of three numbers."""
    values = _numbers(text, 3)
    if values is None:
        raise ValueError(f"{option} is {form} (the end effector's target point in metres, world frame), got {text!r}")
    return np.array(values)


def _rotation(value, option: str) -> np.ndarray:
    """A rotation target (9 entries row by row) from roll, pitch, yaw (rad; R = Rz(yaw) Ry(pitch) Rx(roll), URDF's
    rpy) as "r,p,y" or [r, p, y], or from a 3 × 3 matrix [[…], […], […]] (ocpkit.model.task.check_rotation checks
    it)."""
    import pinocchio as pin

    from ocpkit.model.task import check_rotation

    if isinstance(value, list) and len(value) == 3 and all(isinstance(row, list) for row in value):
        rows = [_numbers(row, 3) for row in value]
        R = None if None in rows else np.array(rows)
    else:
        rpy = _numbers(value, 3)
        R = None if rpy is None else pin.rpy.rpyToMatrix(*rpy)
    if R is None:
        raise ValueError(
            f"{option} is roll, pitch, yaw (rad, about the world's x, y, z: R = Rz(yaw) Ry(pitch) "
            f"Rx(roll)) or a 3 × 3 rotation matrix, got {value!r}"
        )
    return check_rotation(R, option)


def _frame_target(text: str) -> tuple[str, np.ndarray]:
    """(frame, point) from --frame-target "NAME=x,y,z"."""
    frame, sep, point = text.partition("=")
    if not (sep and frame.strip()):
        raise ValueError(f"--frame-target is NAME=x,y,z (a frame and its target point in metres), got {text!r}")
    return frame.strip(), _point(point, f"--frame-target {text}")


def _number(value, where: str, positive: bool) -> float:
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float))
        or not np.isfinite(value)
        or (positive and value <= 0)
    ):
        raise ValueError(f"{where} must be a {'positive' if positive else 'finite'} number, got {value!r}")
    return float(value)


def _frame_name(value, where: str) -> str:
    if not isinstance(value, str) or not value:
        raise ValueError(f"{where} must be a frame name (a string), got {value!r}")
    return value


def _tables(data, key: str, where: str, form: str) -> list:
    tables = data.get(key, [])
    if not isinstance(tables, list) or not all(isinstance(t, dict) for t in tables):
        raise ValueError(f"{where}: {key} entries are [[{key}]] tables with {form}")
    return tables


def _no_task() -> dict:
    """What a --task file gives when it gives nothing (read_task_file's keys, empty)."""
    return {
        "target": None,
        "frame": None,
        "orientation": None,
        "joint_limits": False,
        "obstacles": [],
        "frame_targets": [],
        "options": {},
    }


def read_task_file(path) -> dict:
    """A --task TOML file as {target, frame, orientation, joint_limits, obstacles, frame_targets, options}, every
    value checked (errors name the file and the key)."""
    import tomllib

    from ocpkit.model.task import Sphere, length

    where = f"--task {path}"
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise ValueError(f"{where}: no such file") from None
    except IsADirectoryError:
        raise ValueError(f"{where}: is a folder; give a TOML file") from None
    except UnicodeDecodeError as exc:
        raise ValueError(f"{where}: not UTF-8 text (byte {exc.start}); a TOML file is UTF-8") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{where}: not valid TOML: {exc}") from None
    unknown = sorted(set(data) - set(_TASK_KEYS) - set(_MOTION_KEYS))
    if unknown:
        raise ValueError(
            f"{where}: unknown key {unknown[0]!r}; a task file has {', '.join(_TASK_KEYS + tuple(_MOTION_KEYS))}"
        )
    out = _no_task()
    if "target" in data:
        out["target"] = _point(data["target"], f"{where}: target", "[x, y, z]")
    if "frame" in data:
        out["frame"] = _frame_name(data["frame"], f"{where}: frame")
    if "orientation" in data:
        out["orientation"] = _rotation(data["orientation"], f"{where}: orientation")
    if "joint_limits" in data:
        if not isinstance(data["joint_limits"], bool):
            raise ValueError(f"{where}: joint_limits must be true or false, got {data['joint_limits']!r}")
        out["joint_limits"] = data["joint_limits"]
    for k, o in enumerate(_tables(data, "obstacle", where, "center = [x, y, z] and radius = r"), 1):
        if set(o) != {"center", "radius"}:
            raise ValueError(
                f"{where}: obstacle {k} has the keys {sorted(o)}; it needs exactly center = [x, y, z] "
                f"and radius = r (m)"
            )
        center = _point(o["center"], f"{where}: obstacle {k}: center", "[x, y, z]")
        radius = _number(o["radius"], f"{where}: obstacle {k}: radius", positive=True)
        out["obstacles"].append(Sphere(tuple(center), radius))
    form = 'frame = "NAME", target = [x, y, z] and optionally weight = w'
    for k, t in enumerate(_tables(data, "frame_target", where, form), 1):
        at = f"{where}: frame_target {k}"
        if not {"frame", "target"} <= set(t) <= {"frame", "target", "weight"}:
            raise ValueError(f"{at} has the keys {sorted(t)}; it takes {form}")
        weight = _number(t["weight"], f"{at}: weight", positive=True) if "weight" in t else None
        out["frame_targets"].append(
            FrameTarget(
                _frame_name(t["frame"], f"{at}: frame"), _point(t["target"], f"{at}: target", "[x, y, z]"), weight, at
            )
        )
    for key in _MOTION_KEYS:
        if key in data:
            if not isinstance(data[key], str):
                raise ValueError(f"{where}: {key} must be a file name (a string), got {data[key]!r}")
            out[key] = _motion_file(Path(path).parent / data[key], f"{where}: {key}")
    for key in _TASK_NUMBERS:
        if key in data:
            value = _number(data[key], f"{where}: {key}", positive=key != "margin")
            if key in ("link_radius", "margin"):
                value = length(value, f"{where}: {key}", signed=key == "margin")
            out["options"][key] = value
    return out


def _motion_file(path, where: str) -> Path:
    """A reference or obstacle path file that exists, a .csv or .npz."""
    path = Path(path)
    if path.suffix not in (".csv", ".npz"):
        raise ValueError(f"{where}: a .csv or .npz file, got {path.name}")
    if not path.is_file():
        raise ValueError(f"{where}: no such file {path}")
    return path


def motion_files(args) -> dict:
    """{"reference": path or None, "obstacle_path": path or None}: simulate's --reference and --obstacle-path, else
    the --task file's reference and obstacle_path."""
    file = read_task_file(args.task) if getattr(args, "task", None) else {}
    out = {}
    for key, flag in _MOTION_KEYS.items():
        given = getattr(args, key, None)
        out[key] = _motion_file(given, flag) if given is not None else file.get(key)
    return out


def reach_task(args) -> Reach | None:
    """The reach task that --target, --obstacle, --frame, --orientation, --frame-target, --joint-limits and --task ask
    for (None: none, the seeded joint goal)."""
    from ocpkit.model.task import Sphere

    file = read_task_file(args.task) if args.task else _no_task()
    source = {"target": "--target", "frame": "--frame"}
    target = None
    if args.target is not None:
        target = _point(args.target, "--target")
    elif file["target"] is not None:
        target, source["target"] = file["target"], f"--task {args.task}: target"
    if target is None:
        given = [
            o
            for o, v in (
                ("--obstacle", args.obstacle),
                ("--frame", args.frame),
                ("--orientation", args.orientation),
                ("--frame-target", args.frame_target),
                ("--joint-limits", args.joint_limits),
            )
            if v
        ]
        if given:
            raise ValueError(
                f"{given[0]} needs --target x,y,z (or a --task file with target = [x, y, z]): it "
                f"belongs to a reach task"
            )
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
    orientation = file["orientation"] if args.orientation is None else _rotation(args.orientation, "--orientation")
    frame_targets = list(file["frame_targets"])
    for text in args.frame_target or ():
        name, point = _frame_target(text)
        frame_targets.append(FrameTarget(name, point, None, f"--frame-target {text}"))
    options = {k: v for k, v in file["options"].items() if k in _REACH_OPTIONS}
    joint_limits = None
    if args.joint_limits or file["joint_limits"]:
        joint_limits = file["options"].get("joint_limit_weight", 1e3)  # JointLimitBarrier's default
        source["joint_limits"] = "--joint-limits" if args.joint_limits else f"--task {args.task}: joint_limits"
    return Reach(
        target,
        frame,
        obstacles,
        options,
        source,
        orientation,
        file["options"].get("orientation_weight"),
        frame_targets,
        joint_limits,
    )


def _joint_limits(problem, where: str) -> tuple[np.ndarray, np.ndarray]:
    """The robot's joint limits (q_min, q_max; ±inf: none), from its ``q_min``/``q_max`` or its pinocchio model
    (whose ±1.8e308 means none); a ValueError naming ``where`` if no joint has one."""
    n = problem.kinematics.n
    if getattr(problem, "q_min", None) is not None:
        lo, hi = (np.asarray(v, dtype=float) for v in (problem.q_min, problem.q_max))
    else:
        model = problem.pin_model
        lo, hi = (np.asarray(v, dtype=float) for v in (model.lowerPositionLimit, model.upperPositionLimit))
        lo, hi = np.where(lo > -1e300, lo, -np.inf), np.where(hi < 1e300, hi, np.inf)
    if lo.size != n or not (np.isfinite(lo) & np.isfinite(hi)).any():
        raise ValueError(f"{where}: {problem.name} has no joint limits to keep away from")
    return lo, hi


def reach_ocp(problem, args, task: Reach, **options):
    """ocpkit.model.task.reach for the command line's task, after the checks that name its options: frames, targets
    within the robot's workspace, and the orientation, other frames and joint-limit terms (ocpkit.model.task)."""
    from ocpkit.model.task import (
        FixedFrameError,
        FrameOrientation,
        FramePosition,
        JointLimitBarrier,
        check_frame,
        check_point,
        reach,
        workspace_radius,
    )

    kinematics = getattr(problem, "kinematics", None)
    if kinematics is None:
        raise ValueError(
            f"{task.source['target']}: {args.problem} has no kinematics (no frames to bring to a "
            f"point); a reach task needs a robot problem: nlink:N, puma560, baxter, panda, urdf:FILE"
        )
    if task.frame is None:
        task.frame = getattr(problem, "end_effector", None)
        if task.frame is None:
            raise ValueError(
                f"{args.problem} names no end effector; give --frame NAME, one of its frames: "
                f"{', '.join(kinematics.frames)}"
            )
    radius = workspace_radius(kinematics)
    for frame, point, where, named in [
        (task.frame, task.target, task.source["target"], f"{task.source['frame']} {task.frame!r}"),
        *((t.frame, t.target, t.source, t.source) for t in task.frame_targets),
    ]:
        try:
            check_frame(kinematics, frame)
        except FixedFrameError as exc:  # named already names the frame
            raise ValueError(f"{named}: {exc.reason}") from None
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{named}: {exc}") from None
        check_point(point, radius, where)
    terms = []
    weight = task.options.get("position_weight", 1e3)  # reach()'s default
    if task.orientation is not None:
        terms.append(
            FrameOrientation(kinematics, task.frame, task.orientation_weight or ORIENTATION_PER_POSITION * weight)
        )
    names = [task.frame]
    for t in task.frame_targets:
        if t.frame in names:
            raise ValueError(f"{t.source}: frame {t.frame!r} already has a target")
        names.append(t.frame)
        terms.append(FramePosition(kinematics, t.frame, weight if t.weight is None else t.weight, name=t.term))
    if task.joint_limits is not None:
        terms.append(JointLimitBarrier(*_joint_limits(problem, task.source["joint_limits"]), task.joint_limits))
    return reach(
        problem,
        task.obstacles,
        frame=task.frame,
        knots=knot_count(problem, args),
        horizon=args.horizon,
        parameterization=args.parameterization,
        integrator=args.integrator,
        terms=terms,
        **task.options,
        **options,
    )

"""The `ocpkit` command line: solve, simulate, demo, study, reproduce, export, build and bench.

Wherever a problem is named, a problem spec is accepted: a registered name (``pendulum``, ``nlink:7``, …),
``package.module:Name`` or ``path/to/file.py:Name`` (see :mod:`ocpkit.problems`).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import sys
import tempfile
from pathlib import Path

import numpy as np

from ocpkit import __version__, problems, solvers, studies
from ocpkit.controller import LINEARIZATIONS, TRAJECTORY, Controller
from ocpkit.model import INTEGRATORS


_SPEC_HELP = ("problem spec: a registered name (pendulum, pendulum:linear, nlink:N with N = 1…13, puma560, baxter, "
              "panda, urdf:FILE), package.module:Name or path/to/file.py:Name (a Problem subclass, instance or factory; "
              "':arg' passes through)")
# Knot points p of solve, simulate and export unless --knots or --parameterization identity says otherwise: the
# README's examples and the C step's size (traditional MPC, p = T, makes EMPC compile for minutes).
DEFAULT_KNOTS = 5
# The solvers' own choices, written out so that `ocpkit --help` does not import every solver (half a second);
# tests/test_cli.py checks them against solvers.nlp.METHODS/DYNAMICS, solvers.qp.QP_SOLVERS, solvers.sampling.VARIANTS.
NLP_METHODS = ("ipopt", "sqp", "fatrop", "rti")
DYNAMICS = ("nonlinear", "affine")
QP_BACKENDS = ("proxqp", "osqp", "daqp", "hpipm")
VARIANTS = ("preconditioned", "paper")
SAMPLING = ("empc", "cem", "mppi")
# Studies that take --problem, and benchmarks that take --problem (their `problems` argument).
_PROBLEM_STUDIES = ("knots", "horizon", "robustness")
_PROBLEM_BENCHMARKS = ("qp", "export", "nlp", "task", "startup")

# `ocpkit bench NAME`: module in ocpkit.benchmarks, function, keyword arguments of --quick.
_BENCHMARKS = {
    "qp": ("qp", "bench_qp", {"problems": ("pendulum:linear", "pendulum", "nlink:3"), "samples": 10}),
    "empc": ("empc", "bench_empc", {"links": (1, 7, 13), "populations": (256, 1024), "horizons": (100,)}),
    "export": ("export", "bench_export", {"problems": ["pendulum", "nlink:2", "nlink:3"]}),
    "model": ("model", "bench_model", {"links": (1, 7, 13), "states": 5}),
    "nlp": ("nlp", "bench_nlp", {"problems": ["pendulum", "nlink:2", "nlink:3"], "samples": 1, "steps": 5}),
    "faults": ("faults", "bench_faults", {}),
    "step": ("step", "bench_step", {"links": (1, 7, 13), "steps": 10}),
    "task": ("task", "bench_task", {"problems": ("panda",), "steps": 100, "seeds": 1}),
    "sensitivities": ("sensitivities", "bench_sensitivities", {"problems": ("puma560", "nlink:7"), "repeats": 50}),
    "startup": ("startup", "bench_startup", {"problems": ("nlink:13",), "controllers": ("linear", "rti", "empc")}),
}


class _Parser(argparse.ArgumentParser):
    """argparse with our one-line errors (exit code 2)."""

    def error(self, message):
        self.exit(2, f"ocpkit: error: {message}\n")


def _add_problem_args(p):
    """The problem and its OCP, the same in solve, simulate and export."""
    p.add_argument("problem", help=_SPEC_HELP)
    p.add_argument("--knots", type=int, default=None,
                   help=f"knot points p (default {DEFAULT_KNOTS}, or T when the horizon is shorter); traditional MPC "
                        f"(one knot per step, p = T) is --parameterization identity")
    p.add_argument("--parameterization", default="linear", choices=("linear", "zoh", "identity"),
                   help="input between the knots: linear (default, the paper's piecewise-linear), zoh (move blocking) "
                        "or identity (traditional MPC, p = T; takes no --knots)")
    p.add_argument("--horizon", type=int, default=None, help="horizon T in steps (default: the problem's)")
    p.add_argument("--integrator", default="rk4", choices=INTEGRATORS,
                   help="how the controller predicts a step of a nonlinear model: rk4 (default) or euler "
                        "(semi-implicit for x = [q, q̇]; one model and Jacobian evaluation instead of four; the plant "
                        "stays RK4)")


def _add_controller_args(p):
    _add_problem_args(p)
    p.add_argument("--solver", default="qp", help=f"solver: {', '.join(solvers.names())} (default qp)")
    p.add_argument("--form", choices=("sparse", "condensed"),
                   help="qp, ipopt --method rti: QP transcription (default condensed)")
    p.add_argument("--qp", choices=QP_BACKENDS,
                   help="qp, ipopt --method rti: QP backend (default daqp for condensed, proxqp for sparse; hpipm: "
                        "sparse traditional)")
    p.add_argument("--method", choices=NLP_METHODS,
                   help="ipopt: how the NLP is solved: ipopt (interior point, default), sqp (CasADi's SQP), fatrop "
                        "(interior point with a Riccati recursion over the stages) or rti (real-time iteration: "
                        "--iterations Gauss-Newton SQP steps per control step on the knot QP)")
    p.add_argument("--iterations", type=int,
                   help="ipopt --method rti: SQP iterations per control step (default 1, the real-time iteration)")
    p.add_argument("--dynamics", choices=DYNAMICS,
                   help="ipopt --method ipopt|sqp: the prediction model (default nonlinear); empc/cem/mppi: the "
                        "rollout model (default affine, re-linearized every step)")
    p.add_argument("--linearization", choices=LINEARIZATIONS + (TRAJECTORY,),
                   help="the affine model's expansion point: goal (default: about the goal's input), plan (the "
                        "input the previous plan expects now) or, qp only, trajectory (stage by stage along the "
                        "shifted plan); qp, ipopt --dynamics affine, empc/cem/mppi")
    p.add_argument("--population", type=int, help="empc/cem/mppi: rollouts per generation")
    p.add_argument("--generations", type=int, help="empc/cem/mppi: generations per control step")
    p.add_argument("--arch", choices=("auto", "cpu", "cuda"), help="empc/cem/mppi: Taichi arch (default auto)")
    p.add_argument("--variant", choices=VARIANTS,
                   help="empc/cem/mppi: preconditioned by the knot QP (default) or the paper's plain algorithm")
    p.add_argument("--error", type=float, default=1.0, help="model error multiplier of the controller's model")
    p.add_argument("--compiled", action="store_true", default=None,
                   help="compile the affine model to C before the first step (default: large models start on "
                        "CasADi's VM and switch once a background compile, cached, has finished)")
    p.add_argument("--no-compiled", dest="compiled", action="store_false",
                   help="stay on CasADi's VM (no C compile)")
    p.add_argument("--seed", type=int, default=0, help="seed of the random start and goal")


def _add_task_args(p):
    """A task-space target (ocpkit.task.reach) instead of the seeded joint-space goal: solve and simulate."""
    p.add_argument("--target", metavar="X,Y,Z",
                   help="bring the end effector (or --frame) to this point (m, world frame) from the seeded start "
                        "instead of the seeded joint goal (ocpkit.task.reach; a robot problem with kinematics)")
    p.add_argument("--obstacle", action="append", metavar="X,Y,Z,R",
                   help="with a target: a sphere (centre and radius, m, world frame) the robot keeps clear of "
                        "(repeatable)")
    p.add_argument("--frame", metavar="NAME", help="with a target: the frame brought to it (default: the "
                                                    "problem's end effector)")
    p.add_argument("--task", metavar="FILE",
                   help="a TOML reach task: target = [x, y, z], optional frame, margin, position_weight, "
                        "terminal_weight, link_radius, obstacle_weight and [[obstacle]] tables (center = [x, y, z], "
                        "radius = r); --target and --frame override its values, --obstacle adds to its obstacles")


def _add_study_args(p, size=True):
    if size:
        p.add_argument("--size", default="quick", choices=("quick", "full"))
    p.add_argument("--out", default="results/reproduce", help="results folder (store, figures, report)")
    p.add_argument("--workers", type=int, default=None, help="local worker processes (default: CPU count)")
    p.add_argument("--scheduler", default=None, help="Dask scheduler address tcp://HOST:PORT")
    p.add_argument("--trial-timeout", type=float, default=None, metavar="SECONDS",
                   help="stop a trial that runs longer and store it as failed (default: no limit)")
    p.add_argument("--retry-failed", action="store_true", help="run the stored failed trials again")
    stale = p.add_mutually_exclusive_group()
    stale.add_argument("--reuse-stale", dest="stale", action="store_const", const="reuse",
                       help="keep stored trials computed by another ocpkit version or other study code")
    stale.add_argument("--rerun-stale", dest="stale", action="store_const", const="rerun",
                       help="compute such trials again (default: refuse to resume over them)")
    p.set_defaults(stale="refuse")
    p.add_argument("--export", default=None, metavar="FILE",
                   help="also write the results database as one self-contained SQLite file")


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="ocpkit", description="Parameterized and GPU-parallelized real-time MPC.")
    parser.add_argument("--debug", action="store_true",
                        help="on an error, print its full traceback (anywhere on the command line)")
    parser.add_argument("--version", action="version", version=f"ocpkit {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    solve = sub.add_parser("solve", help="one MPC solve from a seeded random state and goal")
    _add_controller_args(solve)
    _add_task_args(solve)
    solve.add_argument("--json", action="store_true", help="print one JSON object")
    sim = sub.add_parser("simulate", help="closed loop: actual cost, solve times, a figure")
    _add_controller_args(sim)
    sim.add_argument("--duration", type=float, default=None, help="seconds (default: the problem's)")
    sim.add_argument("--out", default="results/simulate.png", help="figure path")
    sim.add_argument("--plant", default="ocpkit", choices=("ocpkit", "mujoco"),
                     help="the simulated robot: ocpkit's model integrated by RK4 (default), or MuJoCo's (pip install "
                          "\"ocpkit[mujoco]\"; RK4 at the same sub-step) from the problem's robot or --mjcf")
    sim.add_argument("--mjcf", metavar="FILE", help="--plant mujoco: simulate this MJCF instead of the problem's robot")
    sim.add_argument("--joint-map", metavar="J1,J2,…|NAME=J,…",
                     help="--mjcf: the file's joints for the problem's, in q's order or as problem=mjcf name pairs "
                          "(default: the problem's joint names)")
    sim.add_argument("--animate", metavar="FILE.gif", help="also write the robot's motion as an animated GIF (stick "
                                                           "figure; goal pose, or target and obstacles)")
    _add_task_args(sim)
    sim.add_argument("--json", action="store_true", help="print one JSON object")
    demo = sub.add_parser("demo", help="closed-loop pendulum with every available controller")
    demo.add_argument("--problem", default="pendulum")
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--out", default="results/demo", help="folder for the figure")
    st = sub.add_parser("study", help="run one of the paper's studies (resumable) and write its report")
    st.add_argument("name", choices=studies.NAMES, metavar="NAME", help=f"the study: {', '.join(studies.NAMES)}")
    st.add_argument("--problem", action="append", metavar="SPEC",
                    help=f"{', '.join(_PROBLEM_STUDIES)}: run on this problem instead of the paper's (repeatable; "
                         f"quick size: a test-sized grid). {_SPEC_HELP}")
    st.add_argument("--plant", default="ocpkit", choices=("ocpkit", "mujoco"),
                    help="robustness: mujoco runs LinearMPC, RTI and EMPC against MuJoCo with unmodelled joint "
                         "friction and armature (pip install \"ocpkit[mujoco]\"), as study robustness_mujoco")
    _add_study_args(st)
    rep = sub.add_parser("reproduce", help=f"run every study ({', '.join(studies.NAMES)}) and write report.md")
    size = rep.add_mutually_exclusive_group()
    size.add_argument("--quick", dest="size", action="store_const", const="quick", help="minutes (default)")
    size.add_argument("--full", dest="size", action="store_const", const="full", help="paper scale")
    rep.set_defaults(size="quick")
    _add_study_args(rep, size=False)
    exp = sub.add_parser("export", help="generate, build and check a C MPC step")
    _add_problem_args(exp)
    exp.add_argument("--form", default="condensed", choices=("sparse", "condensed"),
                     help="QP transcription (default condensed, the one exported)")
    exp.add_argument("--qp", default="daqp", choices=("daqp", "qrqp", "osqp", "hpipm"),
                     help="QP backend (default daqp)")
    exp.add_argument("--linearization", default="goal", choices=LINEARIZATIONS + (TRAJECTORY,),
                     help="the affine model's expansion point, as solve's: goal (default), plan, or trajectory (the "
                          "real-time iteration: per stage along the shifted plan)")
    exp.add_argument("--iterations", type=int, default=1,
                     help="--linearization trajectory: Gauss-Newton iterations per control step (default 1)")
    exp.add_argument("--seed", type=int, default=0, help="seed of the example closed loop's start and goal")
    exp.add_argument("--out", default="export", help="output folder (absent or empty unless --force)")
    exp.add_argument("--force", action="store_true", help="export into a non-empty --out, overwriting its files")
    pre = sub.add_parser("build", help="fill the cache ahead of deployment with what a controller loads: the default "
                                       "LinearMPC's C step and compiled model, or with --solver and its options "
                                       "(as simulate takes them) that controller's C step or Taichi kernels (a "
                                       "read-only cache is then used as it is)")
    _add_controller_args(pre)
    bench = sub.add_parser("bench", help="benchmarks that print medians and ratios")
    bench.add_argument("what", choices=tuple(_BENCHMARKS))
    bench.add_argument("--quick", action="store_true", help="a smaller grid (minutes instead of tens)")
    bench.add_argument("--arch", choices=("auto", "cpu", "cuda"), help="empc: Taichi arch (default auto)")
    bench.add_argument("--precision", choices=("float64", "float32"), help="empc: float type (default float64)")
    bench.add_argument("--problem", action="append", metavar="SPEC",
                       help=f"{'/'.join(_PROBLEM_BENCHMARKS)}: benchmark this problem (repeatable). {_SPEC_HELP}")
    bench.add_argument("--integrator", choices=INTEGRATORS,
                       help="nlp: every controller's prediction (default rk4; euler: semi-implicit; the plant: RK4)")
    bench.add_argument("--seed", type=int, help="nlp: the first of the seeded starts and goals; startup: the seeded "
                                                "start and goal (default 0)")
    bench.add_argument("--busy", type=int, help="step: busy processes for the quiet-vs-loaded comparison (default 2; "
                                                "0 skips it)")
    bench.add_argument("--controller", action="append", metavar="NAME",
                       help="nlp: a controller column (repeatable; default ipopt fatrop rti1 rti3 lti ltv); crocoddyl "
                            "adds Crocoddyl's FDDP and its per-solve table (pip install \"ocpkit[peers]\"); startup: "
                            "a controller row (repeatable; default linear linear-python rti ipopt fatrop empc cem mppi "
                            "exported)")
    return parser


# Solver-specific options: where each applies, as (test of the configuration, where it applies in words). A given
# option that does not apply is an error naming it and the solver, never silently dropped.
_SOLVER_OPTIONS = {
    "form": (lambda c: c.solver == "qp" or c.method == "rti", "solver qp, and solver ipopt with --method rti"),
    "qp": (lambda c: c.solver == "qp" or c.method == "rti", "solver qp, and solver ipopt with --method rti"),
    "method": (lambda c: c.solver == "ipopt", "solver ipopt"),
    "iterations": (lambda c: c.method == "rti", "solver ipopt with --method rti"),
    "dynamics": (lambda c: c.method in ("ipopt", "sqp") or c.solver in SAMPLING,
                 f"solver ipopt with --method ipopt or sqp, and solvers {', '.join(SAMPLING)}"),
    "linearization": (lambda c: c.solver == "qp" or c.dynamics == "affine" or c.variant == "preconditioned",
                      f"solver qp, solver ipopt with --method ipopt or sqp and --dynamics affine, and solvers "
                      f"{', '.join(SAMPLING)} unless --dynamics nonlinear --variant paper (they linearize nothing)"),
    **{name: (lambda c: c.solver in SAMPLING, f"solvers {', '.join(SAMPLING)}")
       for name in ("population", "generations", "arch", "variant")},
}


class _Config:
    """The solver configuration the command line asks for, with the solvers' defaults filled in (None: not
    this solver's setting)."""

    def __init__(self, args):
        self.solver = args.solver
        self.method = (args.method or "ipopt") if args.solver == "ipopt" else None
        self.dynamics = self.variant = None
        if self.method in ("ipopt", "sqp"):
            self.dynamics = args.dynamics or "nonlinear"
        elif args.solver in SAMPLING:
            self.dynamics, self.variant = args.dynamics or "affine", args.variant or "preconditioned"

    def describe(self, option: str) -> str:
        """The configuration in the words of the command line, with what decides whether ``option`` applies."""
        settings = [f"--method {self.method}"] if self.method else []
        if option == "linearization":
            settings += [f"--{k} {v}" for k, v in (("dynamics", self.dynamics), ("variant", self.variant)) if v]
        return f"solver {self.solver!r}" + (f" with {' '.join(settings)}" if settings else "")


def _solver_options(args) -> dict:
    """The solver's keyword arguments from the command line; an option that does not apply to the chosen solver
    (and method, dynamics, variant) is a ValueError naming both."""
    if args.solver not in solvers.names():
        raise ValueError(f"unknown solver {args.solver!r}; known: {', '.join(solvers.names())}")
    config = _Config(args)
    given = {k: getattr(args, k) for k in _SOLVER_OPTIONS if getattr(args, k) is not None}
    for option in given:
        applies, where = _SOLVER_OPTIONS[option]
        if not applies(config):
            why = " (--method rti always linearizes along its iterate)" if option == "linearization" and \
                config.method == "rti" else ""
            raise ValueError(f"--{option} does not apply to {config.describe(option)}{why}: it applies to {where}")
    if given.get("linearization") == TRAJECTORY and args.solver != "qp":
        raise ValueError(f"--linearization trajectory applies to solver qp only; {config.describe('')} takes "
                         f"{' or '.join(LINEARIZATIONS)}")
    return given


def _knots(problem, args) -> int | None:
    """The knot count p of the OCP (None: traditional MPC, p = T): --knots, or DEFAULT_KNOTS capped at the horizon."""
    if args.parameterization == "identity":
        if args.knots is not None:
            raise ValueError(f"--knots {args.knots} does not apply to --parameterization identity (traditional MPC "
                             f"has one knot per step, p = T); give one of them")
        return None
    if args.knots is not None:
        return args.knots
    T = problem.horizon if args.horizon is None else args.horizon
    return min(DEFAULT_KNOTS, T) if T >= 1 else DEFAULT_KNOTS  # a bad horizon: the OCP's own check names it


def _ocp(problem, args, **options):
    return problem.ocp(knots=_knots(problem, args), horizon=args.horizon, parameterization=args.parameterization,
                       integrator=args.integrator, **options)


# --- task-space targets: --target, --obstacle, --frame, --task (ocpkit.task.reach) --------------------------------

# The keys of a --task file beside target, frame and [[obstacle]]: reach()'s keyword arguments, all positive but
# margin (any finite number: the clearance kept, m).
_TASK_NUMBERS = ("margin", "position_weight", "terminal_weight", "link_radius", "obstacle_weight")
_TASK_KEYS = ("target", "frame", "obstacle") + _TASK_NUMBERS
# A value of --target or --obstacle that argparse would take for an option ("-0.3,0.5,0"): see _attach_values.
_NUMBERS = re.compile(r"^-[0-9.][0-9.eE+-]*(,\s*[-+]?[0-9.][0-9.eE+-]*)*$")


@dataclasses.dataclass
class _Reach:
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


def _read_task_file(path) -> dict:
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


def _reach_task(args) -> _Reach | None:
    """The reach task that --target, --obstacle, --frame and --task ask for (None: none, the seeded joint goal)."""
    from ocpkit.task import Sphere

    file = _read_task_file(args.task) if args.task else {"target": None, "frame": None, "obstacles": [],
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
    return _Reach(target, frame, obstacles, file["options"], source)


def _reach_ocp(problem, args, task: _Reach, **options):
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
    return reach(problem, task.obstacles, frame=task.frame, knots=_knots(problem, args), horizon=args.horizon,
                 parameterization=args.parameterization, integrator=args.integrator, **task.options, **options)


def _reach_panels(problem, ocp, task: _Reach, xs) -> dict:
    """The figure's task panel: the frame's distance to the target and (with obstacles) the smallest clearance, at
    every state of ``xs``."""
    positions, clearance = _reach_series(problem, ocp, task, xs)
    panels = {f"{task.frame} to target": np.linalg.norm(positions - task.target, axis=1)}
    if clearance is not None:
        panels["min clearance"] = clearance
    return panels


def _reach_series(problem, ocp, task: _Reach, xs):
    """The frame's positions (N, 3) along the states ``xs`` (N, nx) and the smallest clearance at each (None without
    obstacles): distance from a robot sphere's surface to an obstacle's."""
    from ocpkit.task import clearances

    xs = np.atleast_2d(np.asarray(xs, dtype=float))
    kin = problem.kinematics
    positions = kin.positions(task.frame, xs[:, :kin.n])
    if not task.obstacles:
        return positions, None
    return positions, clearances(ocp.task.kinematics, ocp.task.robot, ocp.task.obstacles, xs[:, :kin.n])


def _reach_report(problem, ocp, task: _Reach, xs, dt: float | None = None) -> dict:
    """How the states ``xs`` (N, nx) did on the task: the frame's distance to the target at the last state, and the
    smallest clearance — distance from a robot sphere's surface to an obstacle's — over all states (negative: they
    overlap, a collision)."""
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
    return report


def _reach_line(report: dict, what: str) -> str:
    """The report as one line of text."""
    line = (f"reach: {report['frame']} {report['final_distance']:.4f} m from the target "
            f"{_fmt(report['target'])} {what}")
    n = len(report["obstacles"])
    if not n:
        return line + "; no obstacles"
    first = report["first_collision"]
    when = "" if first is None else f", first at t = {first:.2f} s" if isinstance(first, float) else \
        f", first at step {first}"
    collided = (f"COLLIDED in {report['collisions']} of {report['states']} states{when}" if report["collisions"]
                else f"no collision in {report['states']} states")
    return (line + f"; min clearance {report['min_clearance']:.4f} m to {n} obstacle{'s' * (n > 1)} "
                   f"(margin {report['margin']:g} m); {collided}")


def _fmt(v) -> str:
    return "(" + ", ".join(f"{a:g}" for a in v) + ")"


def _controller(args, task: _Reach | None = None) -> tuple:
    options = _solver_options(args)
    problem = problems.make(args.problem)
    _check_size(problem, args)
    if task is None:
        ocp = _ocp(problem, args, error=args.error, compiled=args.compiled)
    else:
        ocp = _reach_ocp(problem, args, task, error=args.error, compiled=args.compiled)
    return problem, ocp, solvers.make(args.solver, ocp, **options)


def _start(problem, ocp, seed: int, task: _Reach | None) -> tuple:
    """The seeded start and goal; with a reach task the goal is the target, at rest (joint velocities zero)."""
    x0, goal = problem.sample(seed)
    return (x0, goal) if task is None else (x0, ocp.goal(x0, position=task.target))


def _solve(args):
    task = _reach_task(args)
    problem, ocp, ctrl = _controller(args, task)
    x0, goal = _start(problem, ocp, args.seed, task)
    sol = ctrl.solve(x0, goal)
    extra = {}
    if task is not None:  # the plan: the OCP's model from x0 under the solved knots, x_0 … x_T
        extra["reach"] = _reach_report(problem, ocp, task, ctrl.rollout(x0, ocp.parameterization.inputs(sol.knots)))
    if args.json:
        print(json.dumps({"problem": args.problem, "solver": args.solver, "controller": repr(ctrl),
                          "x0": x0.tolist(), "goal": goal.tolist(), **sol.to_dict(), **extra}))
    else:
        print(f"{ctrl!r}\nx0 = {x0}, goal = {goal}\nu = {sol.u}  status = {sol.status} ({sol.raw_status}), "
              f"{sol.iterations} iterations, total {1e3 * sol.times['total']:.3f} ms")
        if task is not None:
            print(_reach_line(extra["reach"], f"at the plan's end (x_T, T = {ocp.horizon}, the OCP's model)"))
    return 0 if sol.ok else 1


def _run_closed_loop(problem, ctrl: Controller, seed: int, duration: float | None = None, start=None, plant=None):
    """The closed loop from the seeded start (or ``start``, (x0, goal)) against ``plant`` (default the problem's),
    after one untimed solve that compiles what the controller needs (Taichi kernels take seconds): said on stderr
    when it takes over a second, never counted in the step times."""
    import time

    from ocpkit.metrics import actual_cost
    from ocpkit.simulate import simulate

    x0, goal = problem.sample(seed) if start is None else start
    start = time.perf_counter()
    ctrl.solve(x0, goal)  # simulate() resets the controller: this solve only compiles and warms up
    first = time.perf_counter() - start
    if first > 1.0:
        print(f"  ({ctrl!r}: first solve, compiling, took {first:.1f} s; not in the step times)", file=sys.stderr)
    traj = simulate(plant or problem.plant(), ctrl, x0, goal, duration or problem.duration)
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
    effort = [("N·m" if r else "N") if name.startswith("tau") else p
              for r, name, p in zip(revolute, plant.input_names, position)]
    return {"state_names": [f"{s} [{u}]" for s, u in zip(plant.state_names, position + rate)],
            "input_names": [f"{s} [{u}]" for s, u in zip(plant.input_names, effort)]}


def _time_summary(traj) -> dict:
    t = traj.times("total")
    return {"median_ms": 1e3 * float(np.median(t)), "p90_ms": 1e3 * float(np.percentile(t, 90)),
            "max_ms": 1e3 * float(t.max())}


def _plant(problem, args):
    """The plant of --plant: None for the problem's own, else a MuJoCoPlant of its robot or of --mjcf."""
    if args.plant == "ocpkit":
        return None
    from ocpkit.mujoco_plant import MuJoCoPlant

    joint_map = None
    if args.joint_map:
        items = [item.strip() for item in args.joint_map.split(",")]
        pairs = [item.partition("=") for item in items]
        if any(sep for _, sep, _ in pairs) and not all(sep and a and b for a, sep, b in pairs):
            raise ValueError(f"--joint-map must be MJCF joint names J1,J2,… or pairs NAME=J,…, got {args.joint_map!r}")
        joint_map = {a: b for a, _, b in pairs} if pairs[0][1] else items
    return MuJoCoPlant(problem, mjcf=args.mjcf, joint_map=joint_map)


def _simulate(args):
    from ocpkit import plots

    _check_output_file(args.out, "--out")
    if args.animate is not None:
        from ocpkit import animation

        _check_output_file(animation.check_path(args.animate, "--animate"), "--animate")
    task = _reach_task(args)
    if args.plant != "mujoco" and (args.mjcf or args.joint_map):
        raise ValueError(f"{'--mjcf' if args.mjcf else '--joint-map'} applies to --plant mujoco only")
    if args.joint_map and not args.mjcf:
        raise ValueError("--joint-map names the joints of an MJCF file: give --mjcf too")
    problem, ocp, ctrl = _controller(args, task)
    plant = _plant(problem, args)
    if args.animate is not None:
        animation.Skeleton(problem, None if task is None else task.frame)  # a robot it cannot draw fails before the run
    traj, cost = _run_closed_loop(problem, ctrl, args.seed, args.duration, start=_start(problem, ocp, args.seed, task),
                                  plant=plant)
    shown, title = traj, f"{args.problem}, seed {args.seed}" + (", MuJoCo plant" if args.plant == "mujoco" else "")
    if task is not None:
        # the joint angles have no goal in a reach task (x_goal's angles are the start's, weighted zero): none drawn
        goal = traj.goal.copy()
        goal[:problem.kinematics.n] = np.nan
        shown = dataclasses.replace(traj, goal=goal)
        title += f", {task.frame} to {_fmt(task.target)}"
    panels = None if task is None else _reach_panels(problem, ocp, task, traj.x)
    fig = plots.closed_loop({repr(ctrl): shown}, args.out, title=title, task=panels, **_labels(problem))
    summary = {"problem": args.problem, "solver": args.solver, "controller": repr(ctrl), "actual_cost": cost,
               "fallbacks": traj.fallbacks, "fallback_causes": traj.fallback_causes(), "steps": len(traj.solutions),
               "total_time": _time_summary(traj),
               "figure": str(fig), "plant": "ocpkit" if plant is None else repr(plant)}
    if task is not None:
        summary["reach"] = _reach_report(problem, ocp, task, traj.x, dt=float(traj.t[1] - traj.t[0]))
    if args.animate is not None:  # a reach task's target and obstacles drawn, else the joint goal's pose
        scene = {} if task is None else {"target": task.target, "obstacles": task.obstacles, "frame": task.frame}
        summary["animation"] = str(animation.animate(traj, args.animate, problem, title=title, **scene))
    if args.json:
        print(json.dumps(summary))
    else:
        causes = f" ({summary['fallback_causes']})" if traj.fallbacks else ""
        print(f"{ctrl!r}: actual cost {cost:.4f}, {traj.fallbacks} fallbacks{causes} in {len(traj.solutions)} steps, "
              f"total solve time median {summary['total_time']['median_ms']:.3f} ms "
              f"(p90 {summary['total_time']['p90_ms']:.3f}, max {summary['total_time']['max_ms']:.3f})\n"
              f"figure: {fig}" + ("" if plant is None else f"\nplant: {plant!r}"))
        if task is not None:
            print(_reach_line(summary["reach"], f"after {traj.t[-1]:g} s"))
        if args.animate is not None:
            print(f"animation: {summary['animation']}")
    return 0


def _demo(args):
    """Every registered controller configuration on one seeded pendulum swing, side by side."""
    from ocpkit import plots
    from ocpkit.solvers.qp import LinearMPC

    _check_output_folder(args.out, "--out")
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
    print(f"{args.problem}: x0 = {np.round(x0, 3)}, goal = {np.round(goal, 3)}, {problem.duration} s at "
          f"{1 / problem.dt:.0f} Hz, horizon {problem.horizon}")
    print(f"{'controller':36} {'actual cost':>12} {'ratio':>8} {'median ms':>10} {'p90 ms':>8} {'fallbacks':>9}")
    trajs, base = {}, None
    for label, ctrl in configs.items():
        traj, cost = _run_closed_loop(problem, ctrl, args.seed)
        base = cost if base is None else base
        t = _time_summary(traj)
        print(f"{label:36} {cost:12.4f} {cost / base:8.4f} {t['median_ms']:10.3f} {t['p90_ms']:8.3f} "
              f"{traj.fallbacks:9d}")
        trajs[label] = traj
    fig = plots.closed_loop(trajs, Path(args.out) / f"{args.problem}.png",
                            title=f"{args.problem}: closed loop, seed {args.seed}", **_labels(problem))
    print(f"ratio = actual cost / first row's; figure: {fig}")
    return 0


def _study_options(args) -> dict:
    """The study runner's options from the command line, with the output paths and the scheduler checked first."""
    from ocpkit.study import check_scheduler

    _check_output_folder(args.out, "--out")
    if args.export is not None:
        _check_output_file(args.export, "--export")
    if args.trial_timeout is not None and not args.trial_timeout > 0:
        raise ValueError(f"--trial-timeout must be a positive number of seconds, got {args.trial_timeout}")
    if args.scheduler is not None:
        check_scheduler(args.scheduler)
    return {"trial_timeout": args.trial_timeout, "retry_failed": args.retry_failed, "stale": args.stale}


def _export_store(args) -> None:
    if args.export is not None:
        from ocpkit.store import Store

        with Store(args.out) as store:
            print(f"results database: {store.export(args.export)}")


def _study(args):
    from ocpkit.studies.reproduce import run_study

    options = _study_options(args)
    if args.plant != "ocpkit" and args.name != "robustness":
        raise ValueError(f"--plant applies to the robustness study only, not {args.name!r}")
    if args.problem:
        section = _study_problems(args, options)
    else:
        section = run_study(args.name, args.size, args.out, workers=args.workers, scheduler=args.scheduler,
                            plant=args.plant, **options)
    path = Path(args.out) / f"{args.name}{'' if args.plant == 'ocpkit' else '_' + args.plant}.md"
    path.write_text(section)
    print(section + f"\nreport: {path}")
    _export_store(args)
    return 0


def _study_problems(args, options) -> str:
    """A closed-loop study on the problems of --problem: its table (CSV), figures and report section."""
    from ocpkit import study as study_runner
    from ocpkit.studies import get

    if args.name not in _PROBLEM_STUDIES:
        raise ValueError(f"--problem applies to the studies {', '.join(_PROBLEM_STUDIES)}, not {args.name!r}")
    module = get(args.name)
    out = Path(args.out)
    study = module.study(args.size, problems=args.problem, **({} if args.plant == "ocpkit" else {"plant": args.plant}))
    df = study_runner.run(study, out, workers=args.workers, scheduler=args.scheduler, **options)
    df.to_csv(out / f"{study.name}.csv", index=False)
    failed = df[df["status"] == "failed"]
    if len(failed) == len(df):
        raise ValueError(f"every trial of {args.name} failed; first error: {failed['error'].iloc[0].splitlines()[0]}")
    return module.report(df, out) + study_runner.failure_summary(df) + study_runner.cluster_summary(df)


def _reproduce(args):
    from ocpkit.studies.reproduce import reproduce

    options = _study_options(args)
    report = reproduce(args.size, args.out, workers=args.workers, scheduler=args.scheduler, **options)
    print(f"report: {report}")
    _export_store(args)
    return 0


def _bench(args):
    import importlib

    module, function, quick = _BENCHMARKS[args.what]
    options = {k: getattr(args, k) for k in ("arch", "precision") if getattr(args, k) is not None}
    if options and args.what != "empc":
        raise ValueError(f"--{next(iter(options))} applies to `ocpkit bench empc` only")
    if args.busy is not None:
        if args.what != "step":
            raise ValueError("--busy applies to `ocpkit bench step` only")
        if args.busy < 0:
            raise ValueError(f"--busy must be >= 0, got {args.busy}")
        options["busy"] = args.busy
    # option: {benchmark: (its keyword, type)}
    chosen = {"controller": {"nlp": ("controllers", tuple), "startup": ("controllers", tuple)},
              "integrator": {"nlp": ("integrator", str)},
              "seed": {"nlp": ("first_seed", int), "startup": ("seed", int)}}
    for option, where in chosen.items():
        value = getattr(args, option)
        if value is not None:
            if args.what not in where:
                raise ValueError(f"--{option} applies to `ocpkit bench {'|'.join(where)}` only")
            keyword, kind = where[args.what]
            options[keyword] = kind(value)
    kwargs = dict(quick) if args.quick else {}
    if args.problem:
        if args.what not in _PROBLEM_BENCHMARKS:
            raise ValueError(f"--problem applies to `ocpkit bench {'|'.join(_PROBLEM_BENCHMARKS)}` only")
        for spec in args.problem:
            problems.make(spec)  # a bad spec fails before any benchmark starts
        kwargs["problems"] = list(args.problem)
    bench = getattr(importlib.import_module(f"ocpkit.benchmarks.{module}"), function)
    bench(**kwargs, **options)
    return 0


def _prebuild(args):
    """`ocpkit build`: what the default LinearMPC of the problem's OCP loads from the cache — its C step and the
    compiled affine model of its Python step — built into the cache unless there (and loading), paths printed; with
    another solver or options, :func:`_prebuild_controller`."""
    import time

    from ocpkit import compiled, native
    from ocpkit.cache import cache_root
    from ocpkit.ocp import BACKGROUND_MIN_INSTRUCTIONS
    from ocpkit.solvers.qp import LinearMPC

    print(f"cache: {cache_root()} (set OCPKIT_CACHE_DIR to fill another)")
    if args.solver != "qp" or _solver_options(args):
        return _prebuild_controller(args)
    problem = problems.make(args.problem)
    ocp = _ocp(problem, args, error=args.error, compiled=args.compiled)
    size = ocp.model.jacobian.n_instructions()
    start = time.time()
    if native.wanted(ocp):
        LinearMPC(ocp, native=True)  # builds the C step here and now (or finds it), and loads it
        for folder in native.built(ocp):
            library = folder / f"lib{native.NAME}.so"
            print(f"C step (LinearMPC: condensed, daqp, linearization goal): {library} ({_how(library, start)})")
    else:
        why = ("a linear model" if ocp.model.linear else
               f"a model of {size} VM instructions, below {BACKGROUND_MIN_INSTRUCTIONS}"
               if size < BACKGROUND_MIN_INSTRUCTIONS else
               f"a knot QP of {ocp.knots * ocp.nu} variables, over ocpkit.native.MAX_VARIABLES = {native.MAX_VARIABLES}")
        print(f"C step: none (the default LinearMPC keeps its Python step here: {why})")
    if size >= BACKGROUND_MIN_INSTRUCTIONS:
        start = time.time()
        library = compiled.prebuild(ocp.model.affine(ocp.dt, ocp.substeps, ocp.integrator))
        print(f"compiled affine model (the Python step's): {library} ({_how(library, start)})")
    else:
        print(f"compiled affine model: none (a model of {size} VM instructions, below {BACKGROUND_MIN_INSTRUCTIONS}, "
              f"stays on CasADi's VM)")
    return 0


def _prebuild_controller(args):
    """`ocpkit build --solver …`: the controller as `simulate` constructs it, one step from the seeded start (a
    Taichi kernel compiles at its first launch, into the cache) and its background builds waited for."""
    import time

    start = time.perf_counter()
    problem, ocp, ctrl = _controller(args)
    x0, goal = problem.sample(args.seed)
    sol = ctrl.solve(x0, goal)
    ctrl.wait_compiled()
    print(f"{ctrl!r}: first step {sol.status} by {sol.path}; ready in {time.perf_counter() - start:.1f} s, now "
          f"answering by {ctrl.path}")
    return 0


def _how(library: Path, start: float) -> str:
    return "built now" if library.stat().st_mtime >= start - 0.05 else "already in the cache"


def _export(args):
    from ocpkit.export import BuildError, build, check_tools, export

    try:
        check_tools()  # before any work: a missing cc or make is one line
        problem = problems.make(args.problem)
        ocp = _ocp(problem, args)
        x0, goal = problem.sample(args.seed)
        exported = export(ocp, args.out, form=args.form, qp=args.qp, linearization=args.linearization, x0=x0,
                          goal=goal, force=args.force, iterations=args.iterations)
        build(args.out)
    except BuildError as exc:
        print(f"ocpkit: error: {exc}", file=sys.stderr)
        return 2
    du, steps, failures = _round_trip(problem, ocp, args, exported)
    ok = failures == 0 and du <= 1e-6
    print(f"exported and built {args.problem} ({args.form}, {ocp.parameterization.kind} with {ocp.knots} knots over "
          f"T = {ocp.horizon}, {args.qp}, linearization {args.linearization}) in {exported.out_dir}; "
          f"see {Path(args.out) / 'README.md'}\nround trip: the compiled step vs the same step in Python over {steps} "
          f"closed-loop steps from seed {args.seed}: max |du| = {du:.2e}, {failures} non-successes — "
          f"{'agree' if ok else 'DISAGREE'}")
    return 0 if ok else 1


def _round_trip(problem, ocp, args, exported, steps: int = 20):
    """The compiled step (through ctypes) and LinearMPC in Python on the same closed loop (the discrete model,
    driven by LinearMPC's input): their largest first-input difference and the steps where either failed."""
    from ocpkit.export import ExportedMPC
    from ocpkit.problem import check_dynamics
    from ocpkit.solvers.nlp import RealTimeIteration
    from ocpkit.solvers.qp import LinearMPC

    c = ExportedMPC(ocp, exported.out_dir, name=exported.name)
    if exported.linearization == "trajectory":
        py = RealTimeIteration(ocp, iterations=args.iterations, eps=1e-10, native=False)
    else:
        py = LinearMPC(ocp, form="condensed", eps=1e-10, linearization=exported.linearization, native=False)
    F = ocp.discrete()
    x, goal = problem.sample(args.seed)
    du, failures = 0.0, 0
    for k in range(steps):
        a, b = py.solve(x, goal), c.solve(x, goal)
        failures += (not a.ok) + (not b.ok)
        du = max(du, float(np.abs(a.u - b.u).max()))
        x_next = np.asarray(F(x, a.u)).ravel()
        if not np.isfinite(x_next).all():  # NaN dynamics are named as such (DynamicsError), else the step diverged
            check_dynamics(ocp.model, x, a.u, dt=ocp.dt, substeps=ocp.substeps,
                           context=f"the round trip's closed loop, step {k + 1}")
            raise ValueError(f"the round trip's closed loop diverged at step {k + 1}: the discrete model "
                             f"from x = {x.tolist()}, u = {a.u.tolist()} is not finite")
        x = x_next
    return du, steps, failures


# Output paths and sizes are checked before any work starts, so a run is not lost to a bad path at its end.

def _check_output_folder(path, option: str) -> None:
    """``path`` is (or can be created as) a folder this process can write into."""
    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{option} {path}: is a file; give a folder")
    existing = next((p for p in (folder, *folder.parents) if p.exists()), None)
    if existing is not None and not existing.is_dir():
        raise ValueError(f"{option} {path}: {existing} is a file, so the folder cannot be created")
    _probe(folder if folder.exists() else existing, option, path, folder.exists())


def _check_output_file(path, option: str) -> None:
    """``path`` names a file this process can create or replace."""
    target = Path(path)
    if target.is_dir():
        raise ValueError(f"{option} {path}: is a folder; give a file name")
    if target.exists() and not os.access(target, os.W_OK):
        raise ValueError(f"{option} {path}: the file cannot be written; choose another path")
    existing = next((p for p in target.parents if p.exists()), None)
    if existing is not None and not existing.is_dir():
        raise ValueError(f"{option} {path}: {existing} is a file, so no file can be created below it")
    _probe(existing, option, path, False)


def _probe(folder, option, path, is_target) -> None:
    """Create and delete a scratch file in ``folder`` (file modes alone do not tell: root, /proc, read-only mounts)."""
    folder = Path(folder) if folder is not None else Path(".")
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".ocpkit-probe-"):
            pass
    except OSError as exc:
        where = "" if is_target else f" (nothing can be created in {folder})"
        raise ValueError(f"{option} {path}: not writable{where}: {exc.strerror or exc}; choose another path") from None


def _available_memory() -> float | None:
    """Bytes of memory available now (Linux /proc/meminfo), or None where unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return 1024.0 * int(line.split()[1])
    except OSError:
        return None
    return None


def _check_size(problem, args) -> None:
    """Refuse an MPC problem whose dense matrices cannot fit in memory; warn when one solve will take long (solve and
    simulate, whose arguments were checked by _solver_options).

    Dense storage (8-byte floats): the T×p basis, and for the condensed QP the (T·nx)×(p·nu) prediction matrix
    and the (p·nu)² Hessian. Time (condensed, the default): about 2 ns × ((p·nu)³ + T·nx·(p·nu)²), fitted to
    pendulum solves at T = 250…3000 here (one-off build included), so an order of magnitude only."""
    T = problem.horizon if args.horizon is None else args.horizon
    if T < 1:
        return  # the OCP's own check names the bad value
    model = problem.model()
    nx, nu = model.nx, model.nu
    knots = _knots(problem, args)
    p = T if knots is None else max(1, knots)
    qp_based = args.solver == "qp" or args.method == "rti"
    condensed = qp_based and (args.form or "condensed") == "condensed"
    entries = T * p + (T * nx * p * nu + (p * nu) ** 2 if condensed or not qp_based else 0)
    need = 8.0 * entries
    have = _available_memory()
    size = f"horizon T = {T}, p = {p} knots, nx = {nx}, nu = {nu}"
    if have is not None and need > 0.5 * have:
        raise ValueError(f"{size} needs about {_gib(need)} for its dense matrices, more than half the "
                         f"{_gib(have)} available: shorten --horizon or give --knots")
    if condensed:
        seconds = 2e-9 * ((p * nu) ** 3 + T * nx * (p * nu) ** 2)
        if seconds > 30:
            print(f"ocpkit: warning: {size}: one solve may take around {seconds:.0f} s "
                  f"(memory about {_gib(need)}); --knots makes it smaller", file=sys.stderr)
    elif qp_based and (args.qp or "proxqp") == "proxqp" and p < T:
        # Sparse ProxQP with knots: its factorization fills in along the knots' columns, about 2.5 ns × (T·nx)³ a
        # solve (pendulum, 5 knots: 1.9 s at T = 600, 168 s at T = 2000; traditional MPC 0.1 and 1.8 s; OSQP 0.3 s).
        seconds = 2.5e-9 * (T * nx) ** 3
        if seconds > 30:
            from ocpkit.solvers.qp import LinearMPC

            ceiling = max(LinearMPC.CEILING_MIN, LinearMPC.CEILING_PER_VARIABLE * ((T + 1) * nx + p * nu))
            print(f"ocpkit: warning: {size}: sparse ProxQP with knots may take around {seconds:.3g} s a solve "
                  f"(a step stops at LinearMPC's default budget, {ceiling:.0f} s here); --qp osqp or --form "
                  f"condensed is far faster", file=sys.stderr)


def _gib(n: float) -> str:
    return f"{n / 2**30:.1f} GiB" if n >= 2**30 else f"{n / 2**20:.0f} MiB"


def _one_line_error(exc: BaseException) -> bool:
    """Errors of the user's input or environment, shown as one line (anything else keeps its traceback)."""
    if isinstance(exc, (ValueError, TypeError, OSError, ImportError)):  # ImportError: an optional package, with pip's line
        return True
    kinds = [getattr(sys.modules.get(module), name, None) for module, name in (
        ("ocpkit.store", "StoreError"), ("ocpkit.kernels.runtime", "ArchUnavailable"),
        ("ocpkit.compiled", "CompileError"))]
    return any(kind is not None and isinstance(exc, kind) for kind in kinds)


def _debug_first(argv) -> list[str]:
    """The arguments with ``--debug`` moved to the front, where the top-level parser takes it, so that it may be
    written anywhere (``ocpkit solve X --debug``); arguments after ``--`` are left alone."""
    argv = list(sys.argv[1:] if argv is None else argv)
    end = argv.index("--") if "--" in argv else len(argv)
    if "--debug" in argv[:end]:
        argv = ["--debug", *(a for a in argv[:end] if a != "--debug"), *argv[end:]]
    return argv


def _error_line(exc: BaseException, debug: bool) -> str:
    """The one line an error is shown as; a failure inside the user's own code points at --debug."""
    from ocpkit.problem import ProblemError

    hint = isinstance(exc, ProblemError) and exc.__cause__ is not None and not debug
    return f"ocpkit: error: {exc}" + (" (--debug prints its traceback)" if hint else "")


def _attach_values(argv) -> list[str]:
    """``--target -0.3,0.5,0`` as ``--target=-0.3,0.5,0`` (and so --obstacle): argparse takes a value that starts
    with '-' and is not one plain number for an option ("expected one argument")."""
    out = []
    for k, a in enumerate(argv):
        if a == "--":
            return out + list(argv[k:])
        if out and out[-1] in ("--target", "--obstacle") and _NUMBERS.match(a):
            out[-1] = f"{out[-1]}={a}"
        else:
            out.append(a)
    return out


def main(argv=None) -> int:
    args = _parser().parse_args(_attach_values(_debug_first(argv)))
    try:
        commands = {"solve": _solve, "simulate": _simulate, "demo": _demo, "study": _study,
                    "reproduce": _reproduce, "export": _export, "bench": _bench,
                    "build": _prebuild}
        return commands[args.command](args)
    except Exception as exc:
        if not _one_line_error(exc):
            raise
        if args.debug:
            import traceback

            traceback.print_exception(exc, file=sys.stderr)
        print(_error_line(exc, args.debug), file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

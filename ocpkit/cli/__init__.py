"""The `ocpkit` command line: solve, simulate, demo, study, reproduce, export, build and bench.

Wherever a problem is named, a problem spec is accepted: a registered name (``pendulum``, ``nlink:7``, …),
``package.module:Name`` or ``path/to/file.py:Name`` (see :mod:`ocpkit.problems`).
"""

from __future__ import annotations

import argparse
import sys

from ocpkit import __version__, solvers, studies
from ocpkit.cli import commands
from ocpkit.cli.arguments import add_controller_args, add_problem_args, add_study_args, add_task_args
from ocpkit.cli.bench import BENCHMARKS, PROBLEM_BENCHMARKS, bench_command
from ocpkit.cli.bench import HELP as BENCH_HELP
from ocpkit.cli.build import build_command
from ocpkit.cli.export import export_command
from ocpkit.cli.options import (
    DEFAULT_KNOTS,
    DYNAMICS,
    EXPORT_FORMS,
    EXPORT_QPS,
    NLP_METHODS,
    QP_BACKENDS,
    SAMPLING,
    SPEC_HELP,
    VARIANTS,
    default,
)
from ocpkit.cli.study import PROBLEM_STUDIES, reproduce_command, study_command
from ocpkit.cli.task import NUMBERS
from ocpkit.controller import LINEARIZATIONS, TRAJECTORY
from ocpkit.model.dynamics import INTEGRATORS

MUJOCO_INTEGRATORS = ("rk4", "implicit", "implicitfast", "euler")  # ocpkit.sim.mujoco_plant.INTEGRATORS
COMMANDS = {
    **commands.COMMANDS,
    "study": study_command,
    "reproduce": reproduce_command,
    "bench": bench_command,
    "build": build_command,
    "export": export_command,
}

__all__ = ["main", "DEFAULT_KNOTS", "DYNAMICS", "NLP_METHODS", "QP_BACKENDS", "SAMPLING", "VARIANTS"]


class _Parser(argparse.ArgumentParser):
    """argparse with our one-line errors (exit code 2)."""

    def error(self, message):
        self.exit(2, f"ocpkit: error: {message}\n")


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="ocpkit", description="Parameterized and GPU-parallelized real-time MPC.")
    parser.add_argument(
        "--debug", action="store_true", help="on an error, print its full traceback (anywhere on the command line)"
    )
    parser.add_argument("--version", action="version", version=f"ocpkit {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    solve = sub.add_parser("solve", help="one MPC solve from a seeded random state and goal")
    add_controller_args(solve)
    add_task_args(solve)
    solve.add_argument("--json", action="store_true", help="print one JSON object")
    sim = sub.add_parser("simulate", help="closed loop: actual cost, solve times, a figure with --out")
    add_controller_args(sim)
    sim.add_argument("--duration", type=float, default=None, help="seconds (default: the problem's)")
    sim.add_argument("--out", metavar="FIG.png", help="write the closed loop's figure to this file (default: none)")
    sim.add_argument(
        "--plant",
        default="ocpkit",
        choices=("ocpkit", "mujoco"),
        help="the simulated robot: ocpkit's model integrated by RK4 (default), or MuJoCo's (pip install "
        '"ocpkit[mujoco]"; RK4 at the same sub-step) from the problem\'s robot or --mjcf',
    )
    sim.add_argument("--mjcf", metavar="FILE", help="--plant mujoco: simulate this MJCF instead of the problem's robot")
    sim.add_argument(
        "--joint-map",
        metavar="J1,J2,…|NAME=J,…",
        help="--mjcf: the file's joints for the problem's, in q's order or as problem=mjcf name pairs "
        "(default: the problem's joint names)",
    )
    # MuJoCoPlant's options for what ocpkit's model leaves out, with its defaults (ocpkit.sim.mujoco_plant)
    sim.add_argument(
        "--frictionloss",
        type=float,
        default=0.0,
        metavar="N·m",
        help="--plant mujoco: dry joint friction added at every joint (default 0)",
    )
    sim.add_argument(
        "--armature",
        type=float,
        default=0.0,
        metavar="KG·M²",
        help="--plant mujoco: rotor inertia added at every joint (default 0)",
    )
    sim.add_argument(
        "--floor",
        type=float,
        default=None,
        metavar="Z",
        help="--plant mujoco: a floor plane at height Z (m) that the links touch (default none)",
    )
    sim.add_argument(
        "--limits",
        action="store_true",
        default=None,
        help="--plant mujoco: the joint ranges as constraints (default: off for a generated or URDF "
        "robot, an MJCF's own)",
    )
    sim.add_argument(
        "--mujoco-integrator",
        default="rk4",
        choices=MUJOCO_INTEGRATORS,
        help="--plant mujoco: MuJoCo's integrator at the plant's 1 ms sub-step (default rk4)",
    )
    sim.add_argument(
        "--animate",
        metavar="FILE.gif",
        help="also write the robot's motion as an animated GIF (stick figure; goal pose, or target and obstacles)",
    )
    sim.add_argument(
        "--reference",
        metavar="FILE.csv|FILE.npz",
        help="follow this reference: a column t (s) and the goal's entries by name (the state names, a target's "
        "entries as position[0] …; missing ones as the goal) — each step previews it over the horizon; without a "
        "task the run starts at the reference's state at t = 0",
    )
    sim.add_argument(
        "--no-preview",
        action="store_true",
        help="--reference: hold the reference's present value as the goal instead (a loop without preview)",
    )
    sim.add_argument(
        "--obstacle-path",
        metavar="FILE.csv|FILE.npz",
        help="move the task's obstacles: a column t (s) and obstacle<i>_x, _y, _z, _radius per obstacle i (as "
        "--obstacle gives them, in order), predicted over the horizon at constant velocity",
    )
    add_task_args(sim)
    sim.add_argument("--json", action="store_true", help="print one JSON object")
    demo = sub.add_parser("demo", help="closed-loop pendulum with every available controller")
    demo.add_argument("--problem", default="pendulum")
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--out", default="results/demo", help="folder for the figure")
    st = sub.add_parser("study", help="run one of the paper's studies (resumable) and write its report")
    st.add_argument("name", choices=studies.NAMES, metavar="NAME", help=f"the study: {', '.join(studies.NAMES)}")
    st.add_argument(
        "--problem",
        action="append",
        metavar="SPEC",
        help=f"{', '.join(PROBLEM_STUDIES)}: run on this problem instead of the paper's (repeatable; "
        f"quick size: a test-sized grid). {SPEC_HELP}",
    )
    st.add_argument(
        "--plant",
        default="ocpkit",
        choices=("ocpkit", "mujoco"),
        help="robustness: mujoco runs LinearMPC, RTI and EMPC against MuJoCo with unmodelled joint "
        'friction and armature (pip install "ocpkit[mujoco]"), as study robustness_mujoco',
    )
    add_study_args(st)
    rep = sub.add_parser("reproduce", help=f"run every study ({', '.join(studies.NAMES)}) and write report.md")
    size = rep.add_mutually_exclusive_group()
    size.add_argument("--quick", dest="size", action="store_const", const="quick", help="minutes (default)")
    size.add_argument("--full", dest="size", action="store_const", const="full", help="paper scale")
    rep.set_defaults(size="quick")
    rep.add_argument(
        "--only",
        action="append",
        choices=(*studies.NAMES, "paper"),
        metavar="NAME",
        help=f"run and report this study only (repeatable): {', '.join(studies.NAMES)}, or paper for the paper's "
        f"own ({', '.join(studies.PAPER)}) (default: every study)",
    )
    add_study_args(rep, size=False)
    exp = sub.add_parser("export", help="generate, build and check a C MPC step")
    add_problem_args(exp)
    exp.add_argument(
        "--form",
        default=EXPORT_FORMS[0],
        choices=EXPORT_FORMS,
        help="QP transcription: condensed, the one exported (the sparse form is solved in Python only)",
    )
    exp.add_argument(
        "--qp",
        default=EXPORT_QPS[0],
        choices=EXPORT_QPS,
        help="QP backend generated into the C: daqp (default), qrqp or osqp (hpipm needs a stage-wise "
        "QP, which the knot QP is not)",
    )
    exp.add_argument(
        "--linearization",
        default=default("qp", "linearization"),
        choices=LINEARIZATIONS + (TRAJECTORY,),
        help="the affine model's expansion point, as solve's: goal, plan, or trajectory (the real-time "
        "iteration: per stage along the shifted plan) (default %(default)s)",
    )
    exp.add_argument(
        "--iterations",
        type=int,
        default=default("rti", "iterations"),
        help="--linearization trajectory: Gauss-Newton iterations per control step (default %(default)s)",
    )
    exp.add_argument("--seed", type=int, default=0, help="seed of the example closed loop's start and goal")
    exp.add_argument(
        "--reference-window",
        metavar="FILE",
        help="the example follows this reference (CSV or NPZ: column t and the goal's entries by name, as simulate's "
        "--reference): its rows written to reference.csv, each step's window passed to <name>_step_window",
    )
    exp.add_argument("--out", default="export", help="output folder (absent or empty unless --force)")
    exp.add_argument("--force", action="store_true", help="export into a non-empty --out, overwriting its files")
    add_task_args(exp)
    pre = sub.add_parser(
        "build",
        help="fill the cache ahead of deployment with what a controller loads: the default "
        "LinearMPC's C step and compiled model, or with --solver and its options "
        "(as simulate takes them) that controller's C step or Taichi kernels (a "
        "read-only cache is then used as it is)",
    )
    add_controller_args(pre)
    bench = sub.add_parser("bench", help="benchmarks that print medians and ratios")
    bench.add_argument("what", choices=tuple(BENCHMARKS), help=BENCH_HELP)
    bench.add_argument("--quick", action="store_true", help="a smaller grid (minutes instead of tens)")
    bench.add_argument("--arch", choices=("auto", "cpu", "cuda"), help="empc: Taichi arch (default auto)")
    bench.add_argument("--precision", choices=("float64", "float32"), help="empc: float type (default float64)")
    bench.add_argument(
        "--problem",
        action="append",
        metavar="SPEC",
        help=f"{'/'.join(PROBLEM_BENCHMARKS)}: benchmark this problem (repeatable). {SPEC_HELP}",
    )
    bench.add_argument(
        "--integrator",
        choices=INTEGRATORS,
        help="nlp: every controller's prediction (default rk4; euler: semi-implicit; the plant: RK4); peers: this "
        "integrator only (default both)",
    )
    bench.add_argument(
        "--seed",
        type=int,
        help="nlp, peers: the first of the seeded starts and goals (default 0; peers: 100); startup: the seeded start "
        "and goal (default 0)",
    )
    bench.add_argument(
        "--busy", type=int, help="step: busy processes for the quiet-vs-loaded comparison (default 2; 0 skips it)"
    )
    columns, rows = (" ".join(solvers.BENCHMARKED[what]) for what in ("nlp", "startup"))
    bench.add_argument(
        "--controller",
        action="append",
        metavar="NAME",
        help=f"nlp: a controller column (repeatable; default {columns}); crocoddyl adds Crocoddyl's "
        f'FDDP and its per-solve table (pip install "ocpkit[peers]"); '
        "acados prints acados' SQP-RTI tables beside "
        f"ocpkit's RTI C step (p = T and knots; python -m ocpkit.benchmarks.acados_install); startup: a controller row "
        f"(repeatable; default {rows}); the names: the solvers ({', '.join(solvers.names())}) and "
        f"{', '.join(c for c in solvers.CONTROLLERS if c not in solvers.names())}",
    )
    return parser


def _one_line_error(exc: BaseException) -> bool:
    """Errors of the user's input or environment, shown as one line (anything else keeps its traceback)."""
    # ImportError: an optional package missing, said with the pip command that installs it
    if isinstance(exc, (ValueError, TypeError, OSError, ImportError)):
        return True
    kinds = [
        getattr(sys.modules.get(module), name, None)
        for module, name in (
            ("ocpkit.runs.store", "StoreError"),
            ("ocpkit.codegen.kernels.runtime", "ArchUnavailable"),
            ("ocpkit.codegen.compiled", "CompileError"),
        )
    ]
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
    from ocpkit.model.problem import ProblemError

    hint = isinstance(exc, ProblemError) and exc.__cause__ is not None and not debug
    return f"ocpkit: error: {exc}" + (" (--debug prints its traceback)" if hint else "")


def _attach_values(argv) -> list[str]:
    """``--target -0.3,0.5,0`` as ``--target=-0.3,0.5,0`` (and so --obstacle and --orientation): argparse takes a
    value that starts with '-' and is not one plain number for an option ("expected one argument")."""
    out = []
    for k, a in enumerate(argv):
        if a == "--":
            return out + list(argv[k:])
        if out and out[-1] in ("--target", "--obstacle", "--orientation") and NUMBERS.match(a):
            out[-1] = f"{out[-1]}={a}"
        else:
            out.append(a)
    return out


def main(argv=None) -> int:
    args = _parser().parse_args(_attach_values(_debug_first(argv)))
    try:
        return COMMANDS[args.command](args)
    except Exception as exc:
        if not _one_line_error(exc):
            raise
        if args.debug:
            import traceback

            traceback.print_exception(exc, file=sys.stderr)
        print(_error_line(exc, args.debug), file=sys.stderr)
        return 2

"""The command-line options several commands share: the problem and its OCP, the controller, the task-space
targets and a study's run (the commands' parser: :mod:`ocpkit.cli`)."""

from __future__ import annotations

from ocpkit import solvers
from ocpkit.cli.options import (
    DEFAULT_KNOTS,
    DYNAMICS,
    NLP_METHODS,
    QP_BACKENDS,
    SPEC_HELP,
    VARIANTS,
    default,
)
from ocpkit.solvers.methods import QP_BY_FORM
from ocpkit.controller import LINEARIZATIONS, TRAJECTORY
from ocpkit.model.dynamics import INTEGRATORS


def add_problem_args(p):
    """The problem and its OCP, the same in solve, simulate and export."""
    p.add_argument("problem", help=SPEC_HELP)
    p.add_argument(
        "--knots",
        type=int,
        default=None,
        help=f"knot points p (default {DEFAULT_KNOTS}, or T when the horizon is shorter; the Python API's "
        f"Problem.ocp(knots=None) is traditional MPC instead); traditional MPC (one knot per step, "
        f"p = T) is --parameterization identity",
    )
    p.add_argument(
        "--parameterization",
        default="linear",
        choices=("linear", "zoh", "bspline", "identity"),
        help="input between the knots: linear (default, the paper's piecewise-linear), zoh (move blocking), "
        "bspline (clamped cubic B-spline, 4 knots or more) or identity (traditional MPC, p = T; takes no --knots)",
    )
    p.add_argument("--horizon", type=int, default=None, help="horizon T in steps (default: the problem's)")
    p.add_argument(
        "--integrator",
        default="rk4",
        choices=INTEGRATORS,
        help="how the controller predicts a step of a nonlinear model: rk4 (default) or euler "
        "(semi-implicit for x = [q, q̇]; one model and Jacobian evaluation instead of four; the plant "
        "stays RK4)",
    )


def add_controller_args(p):
    add_problem_args(p)
    # The solvers' options default to None, "not given" (one that does not apply to the solver is refused); the
    # solver then takes its own default, the one its help names from the table (ocpkit.solvers.methods).
    p.add_argument("--solver", default="qp", help=f"solver: {', '.join(solvers.names())} (default qp)")
    p.add_argument(
        "--form",
        choices=("sparse", "condensed"),
        help=f"qp, rti: QP transcription (default {default('qp', 'form')}; sparse is faster in the median for rti at "
        "p = T, with a heavier tail)",
    )
    p.add_argument(
        "--qp",
        choices=QP_BACKENDS,
        help=f"qp, rti: QP backend (default {' and '.join(f'{q} for {f}' for f, q in QP_BY_FORM.items())}; "
        f"hpipm: sparse traditional)",
    )
    p.add_argument(
        "--method",
        choices=NLP_METHODS,
        help=f"ipopt: how the NLP is solved: ipopt (interior point), sqp (CasADi's SQP), fatrop (interior "
        f"point with a Riccati recursion over the stages) (default {default('ipopt', 'method')}); "
        f"real-time iteration is --solver rti",
    )
    p.add_argument(
        "--iterations",
        type=int,
        help=f"rti: Gauss-Newton SQP iterations per control step on the knot QP (default "
        f"{default('rti', 'iterations')}, the real-time iteration)",
    )
    p.add_argument(
        "--dynamics",
        choices=DYNAMICS,
        help=f"ipopt --method ipopt|sqp: the prediction model (default {default('ipopt', 'dynamics')}); "
        f"empc/cem/mppi: the rollout model (default {default('empc', 'dynamics')}, re-linearized "
        f"every step)",
    )
    p.add_argument(
        "--linearization",
        choices=LINEARIZATIONS + (TRAJECTORY,),
        help=f"the affine model's expansion point: goal (about the goal's input), plan (the input the "
        f"previous plan expects now) or, qp only, trajectory (stage by stage along the shifted plan) "
        f"(default {default('qp', 'linearization')}); qp, ipopt --dynamics affine, empc/cem/mppi",
    )
    p.add_argument(
        "--population",
        type=int,
        help=f"empc/cem/mppi: rollouts per generation (default {default('empc', 'population')})",
    )
    p.add_argument(
        "--generations",
        type=int,
        help=f"empc/cem/mppi: generations per control step (default {default('empc', 'generations')})",
    )
    p.add_argument(
        "--arch",
        choices=("auto", "cpu", "cuda"),
        help=f"empc/cem/mppi: Taichi arch (default {default('empc', 'arch')})",
    )
    p.add_argument(
        "--variant",
        choices=VARIANTS,
        help=f"empc/cem/mppi: preconditioned by the knot QP or the paper's plain algorithm (default "
        f"{default('empc', 'variant')})",
    )
    p.add_argument("--error", type=float, default=1.0, help="model error multiplier of the controller's model")
    p.add_argument(
        "--compiled",
        action="store_true",
        default=None,
        help="compile the affine model to C before the first step (default: large models start on "
        "CasADi's VM and switch once a background compile, cached, has finished)",
    )
    p.add_argument("--no-compiled", dest="compiled", action="store_false", help="stay on CasADi's VM (no C compile)")
    p.add_argument("--seed", type=int, default=0, help="seed of the random start and goal")


def add_task_args(p):
    """A task-space target (ocpkit.model.task.reach) instead of the seeded joint-space goal: solve, simulate and
    export."""
    p.add_argument(
        "--target",
        metavar="X,Y,Z",
        help="bring the end effector (or --frame) to this point (m, world frame) from the seeded start "
        "instead of the seeded joint goal (ocpkit.model.task.reach; a robot problem with kinematics)",
    )
    p.add_argument(
        "--obstacle",
        action="append",
        metavar="X,Y,Z,R",
        help="with a target: a sphere (centre and radius, m, world frame) the robot keeps clear of (repeatable)",
    )
    p.add_argument(
        "--frame", metavar="NAME", help="with a target: the frame brought to it (default: the problem's end effector)"
    )
    p.add_argument(
        "--orientation",
        metavar="R,P,Y",
        help="with a target: the frame's orientation too, as roll, pitch, yaw (rad, about the world's x, "
        "y, z: R = Rz(yaw) Ry(pitch) Rx(roll), as a URDF's rpy; ocpkit.model.task.FrameOrientation)",
    )
    p.add_argument(
        "--frame-target",
        action="append",
        metavar="NAME=X,Y,Z",
        help="with a target: another frame brought to a point as well (m, world frame; "
        "ocpkit.model.task.FramePosition; repeatable)",
    )
    p.add_argument(
        "--joint-limits",
        action="store_true",
        help="with a target: keep the joints off their limits (ocpkit.model.task.JointLimitBarrier at the "
        "robot's limits, 0.05 rad inside)",
    )
    p.add_argument(
        "--task",
        metavar="FILE",
        help="a TOML reach task: target = [x, y, z], optional frame, orientation = [roll, pitch, yaw] "
        "(or a 3 × 3 matrix), joint_limits = true, margin, position_weight, terminal_weight, "
        "orientation_weight, joint_limit_weight, link_radius, obstacle_weight, [[obstacle]] tables "
        "(center = [x, y, z], radius = r) and [[frame_target]] tables (frame = NAME, target = "
        "[x, y, z], optional weight); the flags override its values, --obstacle and --frame-target "
        "add to its lists",
    )


def add_study_args(p, size=True):
    if size:
        p.add_argument(
            "--size",
            default="quick",
            choices=("quick", "full"),
            help="quick (minutes, the default) or full (the paper's scale)",
        )
    p.add_argument(
        "--out", default="results/reproduce", help="results folder: store, figures, report (default: results/reproduce)"
    )
    p.add_argument("--workers", type=int, default=None, help="local worker processes (default: CPU count)")
    p.add_argument("--scheduler", default=None, help="Dask scheduler address tcp://HOST:PORT")
    p.add_argument(
        "--trial-timeout",
        type=float,
        default=None,
        metavar="SECONDS",
        help="stop a trial that runs longer and store it as failed (default: no limit)",
    )
    p.add_argument("--retry-failed", action="store_true", help="run the stored failed trials again")
    stale = p.add_mutually_exclusive_group()
    stale.add_argument(
        "--reuse-stale",
        dest="stale",
        action="store_const",
        const="reuse",
        help="keep stored trials computed by another ocpkit version or other study code",
    )
    stale.add_argument(
        "--rerun-stale",
        dest="stale",
        action="store_const",
        const="rerun",
        help="compute such trials again (default: refuse to resume over them)",
    )
    p.set_defaults(stale="refuse")
    p.add_argument(
        "--export",
        default=None,
        metavar="FILE",
        help="also write the results database as one self-contained SQLite file",
    )

"""The non-convex suite's controllers and trials (:mod:`ocpkit.studies.nonconvex`): one closed-loop reach of a drawn
case (:mod:`ocpkit.studies.nonconvex_cases`) by one controller, at its default or at an equal time budget per step.

Every controller gets the same task OCP as in the reach study (:func:`ocpkit.model.task.reach`, margin 1 cm; the
limits case adds the joint limits to its state bounds, beside the velocity limits). Defaults: IPOPT (:data:`ITERATIONS`
a step, ten times the reach study's), IPOPT multi-start (:data:`STARTS` guesses per cold solve,
:mod:`ocpkit.studies.nonconvex_multistart`), RTI with 1 and 3 iterations, LinearMPC linearized along the plan
("trajectory"), MPPI, CEM and EMPC (population as the size says, one generation, the affine model re-linearized about
the plan). At an equal budget (``budget`` seconds a step, the whole step: ``time_limit``): IPOPT with 1 000
iterations, multi-start at every step, RTI with up to :data:`MANY` iterations, and the sampling planners with up to
:data:`MANY` generations — each runs what fits. A budget makes the outcome depend on the machine's speed and load:
the trial records the load; the default controllers' outcomes do not depend on it.

Bases at an equal decision-variable count (issue 49 item 4): the rows of :data:`BSPLINE` run the same controller with
a cubic B-spline basis (``Parameterization.bspline``) of the same knot count as the piecewise-linear rows.

The swing-up (:data:`~ocpkit.studies.nonconvex_cases.SWINGUP`) is the problem's own OCP (its Q, R and terminal
weight) towards the upright state, with the case's torque limit as the input bounds and :data:`SWING_KNOTS` knots; it
succeeds when every state of the last :data:`HOLD` s is within :data:`ANGLE_TOLERANCE` rad of upright (each joint,
modulo 2π) and :data:`SPEED_TOLERANCE` rad/s of rest, every applied torque within the limit. The cart-pole's cart
counts as a joint in metres, not wrapped: within ANGLE_TOLERANCE m of the track's centre and SPEED_TOLERANCE m/s of
rest over the last HOLD s, and no state more than :data:`LIMIT_TOLERANCE` m beyond the track's ends.
"""

from __future__ import annotations

import numpy as np

from ocpkit import problems, solvers
from ocpkit._checks import choice
from ocpkit.codegen.kernels.runtime import current_arch
from ocpkit.model.task import reach
from ocpkit.sim.metrics import actual_cost
from ocpkit.sim.simulate import REACHED, simulate
from ocpkit.studies.nonconvex_cases import SEED_OFFSET
from ocpkit.studies.nonconvex_cases import case as draw
from ocpkit.studies.nonconvex_multistart import MultiStartNLP
from ocpkit.studies.reach_trials import KNOTS, MARGIN, SAMPLING, TOLERANCE, _times

# IPOPT's iterations a step. The reach study's 50 keep its steps short, but here a cold solve around the sphere took
# 87 and 242 (nlink:3, two draws): at 50 no step of those runs converged and every one fell back to holding still.
ITERATIONS = {"max_iter": 500}
STARTS = 8  # IPOPT multi-start's guesses per cold solve (its own cold start and 7 random plans)
MANY = 1000  # iterations or generations a budgeted controller may run: the budget, not this, stops it
LIMIT_TOLERANCE = 0.01  # rad beyond a joint limit a success may go (the limits case; m beyond the cart-pole's track)
BUDGET = ", budget"  # the suffix of a controller at the equal budget
HOLD, ANGLE_TOLERANCE, SPEED_TOLERANCE = 0.2, 0.1, 0.5  # the swing-up's success: s held, rad, rad/s
# The swing-up's knots: a pump alternates every ~0.7 s. Over a 3 s horizon 5 knots (0.75 s apart) cannot say it: 24
# IPOPT starts on development draw 0 all converged to pushing against gravity, at 20 knots all to a swing-up.
SWING_KNOTS = 20
IPOPT, MULTI, RTI, RTI3, LTV, MPPI, CEM, EMPC = (
    "IPOPT",
    f"IPOPT ×{STARTS}",
    "RTI",
    "RTI ×3",
    "LinearMPC (trajectory)",
    "MPPI",
    "CEM",
    "EMPC",
)
DEFAULTS = {
    IPOPT: ("ipopt", ITERATIONS),
    MULTI: ("multistart", {**ITERATIONS, "starts": STARTS}),
    RTI: ("rti", {}),
    RTI3: ("rti", {"iterations": 3}),
    LTV: ("qp", {"linearization": "trajectory"}),
    MPPI: ("mppi", SAMPLING),
    CEM: ("cem", SAMPLING),
    EMPC: ("empc", SAMPLING),
}
BUDGETED = {
    IPOPT + BUDGET: ("ipopt", {"max_iter": MANY}),
    MULTI + BUDGET: ("multistart", {"max_iter": MANY, "starts": STARTS, "every_step": True}),
    RTI + BUDGET: ("rti", {"iterations": MANY}),
    MPPI + BUDGET: ("mppi", {**SAMPLING, "generations": MANY}),
    CEM + BUDGET: ("cem", {**SAMPLING, "generations": MANY}),
    EMPC + BUDGET: ("empc", {**SAMPLING, "generations": MANY}),
}
LTV_BSPLINE, EMPC_BSPLINE = "LinearMPC (trajectory, B-spline)", "EMPC (B-spline)"
BSPLINE = {LTV_BSPLINE: DEFAULTS[LTV], EMPC_BSPLINE: DEFAULTS[EMPC]}  # the same controllers on a cubic B-spline
# The ablation (issue 49: what each of EMPC's choices contributes): EMPC with one choice changed — the paper's GA
# (a uniform cold start and N(0, σ) mutation: no Newton seed, no whitened mutation), rollouts and their violations on
# the nonlinear model instead of the affine one about the plan, three generations a step instead of one.
EMPC_PAPER, EMPC_NONLINEAR, EMPC_GENERATIONS = "EMPC (paper's GA)", "EMPC (nonlinear rollouts)", "EMPC ×3 generations"
ABLATION = {
    EMPC_PAPER: ("empc", {**SAMPLING, "variant": "paper"}),
    EMPC_NONLINEAR: ("empc", {**SAMPLING, "dynamics": "nonlinear"}),
    EMPC_GENERATIONS: ("empc", {**SAMPLING, "generations": 3}),
}
CONTROLLERS = {**DEFAULTS, **BUDGETED, **BSPLINE, **ABLATION}
GRADIENT = (IPOPT, MULTI, RTI, RTI3, LTV, LTV_BSPLINE, IPOPT + BUDGET, MULTI + BUDGET, RTI + BUDGET)
SAMPLERS = ("empc", "cem", "mppi")


def make_controller(name: str, ocp, *, population: int, arch: str, seed: int, budget: float):
    """The suite's controller ``name`` for ``ocp``: a sampling planner keyed by ``seed``, a budgeted one with
    ``time_limit`` = ``budget``."""
    choice(name, tuple(CONTROLLERS), "controller")
    solver, options = CONTROLLERS[name]
    options = dict(options)
    if solver in SAMPLERS:
        options.update(population=population, arch=arch, seed=seed)
    if name in BUDGETED:
        options["time_limit"] = budget
    if solver == "multistart":
        return MultiStartNLP(ocp, seed=seed, **options)
    return solvers.make(solver, ocp, **options)


def basis(controller: str) -> str:
    """The parameterization kind of controller ``controller``'s OCP: "bspline" for the :data:`BSPLINE` rows."""
    return "bspline" if controller in BSPLINE else "linear"


def task_ocp(robot: str, drawn: dict, horizon: int, parameterization: str = "linear"):
    """The OCP of a drawn case: the reach, the limits case's joint limits joining the velocity limits as state bounds;
    for the swing-up, the problem's OCP under the case's input limit (and the cart-pole's track as state bounds).
    ``parameterization``: a kind's name, the same knot count either way."""
    pb = problems.make(robot)
    options = {"knots": KNOTS.get(robot, 5), "horizon": horizon, "parameterization": parameterization}
    if drawn["limits"] is not None:
        n, defaults = pb.model().nx // 2, pb.defaults()
        x_min = np.array(defaults.get("x_min", np.full(2 * n, -np.inf)), dtype=float)
        x_max = np.array(defaults.get("x_max", np.full(2 * n, np.inf)), dtype=float)
        velocity = getattr(pb, "velocity_limit", None)
        velocity = np.full(n, np.inf) if velocity is None else np.asarray(velocity, dtype=float)
        x_min[:n], x_max[:n] = drawn["limits"]
        x_min[n:], x_max[n:] = np.maximum(x_min[n:], -velocity), np.minimum(x_max[n:], velocity)
        options.update(x_min=x_min, x_max=x_max)
    if "x_goal" in drawn:
        options["knots"] = min(SWING_KNOTS, horizon)  # a test's short horizon: a knot a step
        limit = np.full(pb.model().nu, drawn["tau_max"])
        return pb.ocp(u_min=-limit, u_max=limit, **options)
    return reach(pb, drawn["obstacles"], margin=MARGIN, **options)


def trial(
    robot: str,
    case: str,
    controller: str,
    horizon: int,
    duration: float,
    population: int,
    arch: str,
    budget: float,
    seed: int,
) -> dict:
    """One closed-loop run of case ``case`` drawn from SEED_OFFSET + ``seed`` on ``robot``."""
    drawn = draw(robot, case, SEED_OFFSET + seed)
    options = {"horizon": horizon, "duration": duration, "population": population, "arch": arch, "budget": budget}
    return {**closed_loop(robot, drawn, controller, seed=seed, **options), "case_seed": SEED_OFFSET + seed}


def closed_loop(
    robot: str,
    drawn: dict,
    controller: str,
    *,
    horizon: int,
    duration: float,
    population: int,
    arch: str,
    budget: float,
    seed: int,
) -> dict:
    """One closed-loop run of the drawn case ``drawn`` (:func:`~ocpkit.studies.nonconvex_cases.case`) by
    ``controller``, its sampling planners keyed by ``seed``: the trial's metrics."""
    pb = problems.make(robot)
    ocp = task_ocp(robot, drawn, horizon, basis(controller))
    swing = "x_goal" in drawn
    goal = ocp.goal(drawn["x_goal"]) if swing else ocp.goal(drawn["x0"], position=drawn["target"])
    ctrl = make_controller(controller, ocp, population=population, arch=arch, seed=seed, budget=budget)
    # compiles kernels and functions and measures the steps' stages outside the timed run (simulate resets ctrl)
    ctrl.warm_up(drawn["x0"], goal)
    traj = simulate(pb.plant(), ctrl, drawn["x0"], goal, duration)
    return {
        **(_swung(traj, ocp, drawn) if swing else _reached(traj, ocp, pb, drawn)),
        "successes": traj.successes,
        "soft_steps": traj.soft_steps,
        "steps": len(traj.solutions),
        "first_fallback": next((s.raw_status for s in traj.solutions if s.fallback), ""),
        "actual_cost": actual_cost(traj, ocp),
        **_times(traj, ctrl),
        "random_win_rate": float(getattr(ctrl, "random_win_rate", float("nan"))),
        "rejected": drawn["rejected"],
        "device": current_arch() if CONTROLLERS[controller][0] in SAMPLERS else "cpu",
    }


def _reached(traj, ocp, pb, drawn) -> dict:
    """A reach's verdict: within TOLERANCE of the target at the end, no collision, no joint beyond its limit."""
    n = pb.kinematics.n
    d = traj.clearances(ocp)
    progress = traj.progress(pb.kinematics, pb.end_effector, drawn["target"], tolerance=TOLERANCE)
    collisions = int((d < 0).sum())
    beyond = _beyond(traj.x[:, :n], drawn["limits"])
    return {
        "success": bool(progress.verdict == REACHED and collisions == 0 and beyond <= LIMIT_TOLERANCE),
        "reached": progress.verdict == REACHED,
        "verdict": progress.verdict,
        "collision_steps": collisions,
        "beyond_limit": beyond,
        "min_clearance": float(d.min()),
        "final_distance": progress.final,
        "start_distance": float(progress.error[0]),
        "ee": pb.kinematics.positions(pb.end_effector, traj.x[:, :n]),
        "target": drawn["target"],
        "obstacles": np.array([[*o.center, o.radius] for o in drawn["obstacles"]]),
    }


def _beyond(q: np.ndarray, limits) -> float:
    """How far [rad or m] the configurations ``q`` (rows) go beyond ``limits`` (q_min, q_max) at most; 0 for None."""
    if limits is None:
        return 0.0
    return float(max(0.0, (limits[0] - q).max(), (q - limits[1]).max()))


def swing_errors(x: np.ndarray, x_goal: np.ndarray, angles=None) -> tuple[np.ndarray, np.ndarray]:
    """Per state (rows of ``x``): the largest configuration error to ``x_goal``'s — modulo 2π where ``angles`` (a mask
    over the configuration; None: all) says the coordinate is an angle, as is, in metres, where not (the cart) — and
    the largest speed."""
    n = x.shape[1] // 2
    error = x[:, :n] - x_goal[:n]
    wrapped = (error + np.pi) % (2 * np.pi) - np.pi
    error = wrapped if angles is None else np.where(angles, wrapped, error)
    return np.abs(error).max(axis=1), np.abs(x[:, n:]).max(axis=1)


def _swung(traj, ocp, drawn) -> dict:
    """A swing-up's verdict (see the module docstring)."""
    angle, speed = swing_errors(traj.x, drawn["x_goal"], drawn["angles"])
    held = traj.t >= traj.t[-1] - HOLD - 1e-9
    upright = bool((angle[held] <= ANGLE_TOLERANCE).all() and (speed[held] <= SPEED_TOLERANCE).all())
    torque = float(np.abs(traj.u).max())
    beyond = _beyond(traj.x[:, : traj.x.shape[1] // 2], drawn["limits"])
    return {
        "success": bool(upright and torque <= drawn["tau_max"] * (1 + 1e-9) and beyond <= LIMIT_TOLERANCE),
        "reached": upright,
        "verdict": "upright" if upright else "not upright",
        "collision_steps": 0,
        "beyond_limit": beyond,
        "final_angle_error": float(angle[-1]),
        "final_speed": float(speed[-1]),
        "torque_max": torque,
        "tau_max": drawn["tau_max"],
    }

"""ocpkit.safety and the controller's use of it: the task certificate of a plan, the brake, the safe fallback and the
divergence warning, each against a computation by hand."""

from __future__ import annotations

import warnings

import casadi as ca
import numpy as np
import pytest

from ocpkit.status import INFEASIBLE, LIMITED, SOFT, Reason
from ocpkit.model.dynamics import Model
from ocpkit.model.ocp import OCP
from ocpkit.problems import make
from ocpkit.safety import CLEARANCE_TOL, Brake, PlanCheck
from ocpkit.solvers.qp import LinearMPC
from ocpkit.model.task import Sphere, clearances, reach

PENDULUM = make("pendulum")


def _oscillator(dt: float, substeps: int) -> OCP:
    """q̈ = −10⁴ sin q − 10 q̇ + u (nonlinear: RK4, not the exact discretization of a linear model): eigenvalues
    ≈ −5 ± 100i about q = 0, beyond RK4's stability region at 50 ms, inside at 2.5 ms."""
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u")
    model = Model("stiff", x, u, ca.vertcat(x[1], -1e4 * ca.sin(x[0]) - 10 * x[1] + u))
    return OCP(model, dt, 10, np.eye(2), np.eye(1), u_min=[-1.0], u_max=[1.0], substeps=substeps)


def test_plan_check_names_the_worst_state_bound_by_hand():
    ocp = PENDULUM.ocp(knots=3, x_min=[-np.inf, -1.0], x_max=[np.inf, 1.0])
    check = PlanCheck(ocp)
    xs = np.zeros((ocp.horizon + 1, 2))
    assert check.needed and check.violation(xs) is None
    xs[7, 1] = 1.0 + 0.5e-3  # within STATE_TOL of the bound: certified
    assert check.violation(xs) is None
    xs[7, 1], xs[9, 1] = 1.2, -1.5
    v = check.violation(xs)
    assert (v.kind, v.stage, v.which) == ("state bound", 9, "x[1]") and v.amount == pytest.approx(0.5)
    xs[0, 1] = 50.0  # x_0 is the state the step starts from, not the plan's to keep
    assert check.violation(xs).stage == 9
    xs[4, 0] = np.nan
    assert check.violation(xs).kind == "non-finite" and check.violation(xs).stage == 4


def test_plan_check_clearance_matches_numpy():
    """The clearance the certificate reads equals ocpkit.model.task.clearances (numpy) minus the margin, and it
    certifies a plan down to margin − CLEARANCE_TOL, never into a collision."""
    arm = make("nlink:3")
    x = np.r_[0.3, 0.4, 0.3, 0.0, 0.0, 0.0]
    tip = np.asarray(arm.kinematics.function(arm.end_effector)(x[:3])[0]).ravel()
    ocp = reach(arm, [Sphere((tip[0] + 0.2, tip[1], 0.0), 0.05)], knots=3, horizon=10)
    check = PlanCheck(ocp)
    true = clearances(ocp.task.kinematics, ocp.task.robot, ocp.task.obstacles, x[None, :3])[0]
    for radius in (
        0.05,
        0.05 + true - ocp.task.margin + 0.5 * CLEARANCE_TOL,
        0.05 + true - ocp.task.margin + 2 * CLEARANCE_TOL,
    ):
        ocp_r = reach(arm, [Sphere((tip[0] + 0.2, tip[1], 0.0), radius)], knots=3, horizon=10)
        v = PlanCheck(ocp_r).violation(np.tile(x, (11, 1)))
        gap = true - (radius - 0.05) - ocp.task.margin  # d − margin with this radius
        assert (v is None) == (gap >= -CLEARANCE_TOL), (radius, gap, v)
        if v is not None:
            assert v.kind == "clearance" and v.amount == pytest.approx(-gap, abs=1e-9)
    assert check.violation(np.tile(x, (11, 1))) is None


def test_brake_is_the_box_constrained_least_squares_by_hand():
    """From q̇ ≠ 0 the brake minimizes |q̇⁺| within |τ| ≤ τ_max; at rest it holds the pendulum against gravity."""
    ocp = PENDULUM.ocp(knots=3)
    brake = Brake(ocp)
    Ad, Bd, wd = (np.asarray(v, dtype=float) for v in ocp.affine()(np.array([0.5, 0.0]), np.zeros(1)))
    u = -(Ad[1] @ [0.5, 0.0] + wd.ravel()[1]) / Bd[1, 0]  # q̇⁺ = 0 (the model is affine in u about any ū)
    assert brake(np.array([0.5, 0.0]), np.zeros(1)) == pytest.approx([u], rel=1e-6)
    assert brake(np.array([0.0, 30.0]), np.zeros(1)) == pytest.approx(ocp.u_min)  # full torque against q̇ > 0
    assert brake(np.array([0.0, -30.0]), np.zeros(1)) == pytest.approx(ocp.u_max)


def test_fallback_replays_a_safe_plan_then_brakes():
    """A refused step replays the shifted plan while it is safe and for at most stale_steps steps in a row, then
    brakes; a success resets the count."""
    ocp = PENDULUM.ocp(knots=3)
    ctrl = LinearMPC(ocp)
    ctrl.stale_steps = 2
    x, goal = np.array([0.3, 0.0]), np.array([1.0, 0.0])
    assert ctrl.solve(x, goal).ok
    paths = []
    for _ in range(4):
        ctrl._x = x
        sol = ctrl.fallback(LIMITED, "test")
        paths.append(sol.path)
        ctrl._refused += 1
        ctrl.plan = sol.knots
    assert paths == ["fallback (plan)"] * 2 + ["fallback (brake)"] * 2
    assert ctrl.solve(x, goal).ok and ctrl._refused == 0


def test_refused_replay_of_an_unsafe_plan_brakes():
    """The shifted plan from a state where it would break a state bound is not replayed."""
    ocp = PENDULUM.ocp(knots=3, x_min=[-np.inf, -3.0], x_max=[np.inf, 3.0])
    ctrl = LinearMPC(ocp)
    goal = np.array([0.5, 0.0])
    assert ctrl.solve([0.0, 0.0], goal).ok
    ctrl._x = np.array([0.0, 3.5])
    assert ctrl.fallback(INFEASIBLE, "test").path == "fallback (brake)"
    ctrl._x = np.array([0.0, 0.0])
    assert ctrl.fallback(INFEASIBLE, "test").path == "fallback (plan)"


def test_soft_step_is_applied_not_a_fallback():
    ocp = PENDULUM.ocp(knots=3, x_min=[-np.inf, -1.0], x_max=[np.inf, 1.0])
    sol = LinearMPC(ocp).solve([0.0, 1.3], [1.0, 0.0])
    assert sol.status == SOFT and sol.applied and not sol.fallback and not sol.ok
    assert (sol.violation.kind, sol.violation.stage, sol.violation.which) == ("state bound", 1, "x[1]")
    assert sol.reason is sol.violation.kind is Reason.STATE_BOUND  # the kind is a reason, said as its words
    assert "soft: state bound x[1] violated by" in sol.raw_status and "at x_1 " in sol.raw_status


def test_divergence_warning_names_substeps():
    x0, goal = np.array([0.01, 0.0]), np.zeros(2)
    with pytest.warns(RuntimeWarning, match=r"diverges at the start.*substeps=2"):
        LinearMPC(_oscillator(0.05, 1)).solve(x0, goal)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        LinearMPC(_oscillator(0.05, 20)).solve(x0, goal)  # 2.5 ms RK4 sub-steps: stable, no warning
        LinearMPC(PENDULUM.ocp(knots=3)).solve([np.pi, 0.0], [np.pi, 0.0])  # unstable upright, physically: none


def test_a_collision_within_the_first_steps_is_refused_a_deeper_start_is_not():
    """violation(xs, ahead=k): a plan whose x_1 … x_k enter an obstacle is a "collision" (refused); one that starts
    inside and moves out is a clearance violation (soft), not a collision."""
    arm = make("nlink:3")
    x_out = np.r_[0.3, 0.4, 0.3, 0.0, 0.0, 0.0]
    x_in = x_out + np.r_[0.4, 0.0, 0.0, 0.0, 0.0, 0.0]  # the arm swung: its tip on the ball's centre
    tip = np.asarray(arm.kinematics.function(arm.end_effector)(x_in[:3])[0]).ravel()
    ocp = reach(arm, [Sphere(tuple(tip), 0.03)], knots=3, horizon=10)
    d = clearances(ocp.task.kinematics, ocp.task.robot, ocp.task.obstacles, np.vstack([x_in[:3], x_out[:3]]))
    assert d[0] < 0 < d[1] - ocp.task.margin
    check = PlanCheck(ocp)
    into = np.vstack([x_out, x_out, x_in] + [x_in] * 8)
    v = check.violation(into, ahead=5)
    assert v.kind is Reason.COLLISION and v.stage == 2
    assert check.violation(into, ahead=1).kind == "clearance"  # beyond the look-ahead: soft
    out = np.vstack([x_in] + [x_out] * 10)
    assert check.violation(out, ahead=5) is None

"""Sampling planners around obstacles (issue 43, item 2): feasibility first.

The set-up: nlink:3 reaching for a point past a ball that sits on the path the planners take without it (tip at
(0.0, 0.45) about 0.4 s into the unobstructed reach), with obstacle_weight 10 — a penalty so light that, ranked by
penalized cost alone, every planner drove the arm through the ball (down to −0.09 m, 57–64 of 101 states inside).
"""

import numpy as np
import pytest

from ocpkit import problems, solvers
from ocpkit.qp.boxqp import solve_box_qp
from ocpkit.codegen.kernels.rollout import Rollout
from ocpkit.sim.simulate import simulate
from ocpkit.model.task import Sphere, clearances, reach

pytestmark = pytest.mark.usefixtures("taichi_arch")

PLANNERS = ("empc", "cem", "mppi")
VARIANTS = ("preconditioned", "paper")
X0 = np.r_[0.3, 0.4, 0.3, 0.0, 0.0, 0.0]
BALL = Sphere((0.0, 0.45, 0.0), 0.04)


@pytest.fixture(scope="module")
def case():
    """(problem, ocp, goal, target, x near the ball): x is 0.25 s into LinearMPC's reach that ignores the ball,
    moving towards it."""
    problem = problems.make("nlink:3")
    tip = problem.kinematics.function(problem.end_effector)
    target = np.asarray(tip([1.7, 0.3, 0.2])[0]).ravel()
    ocp = reach(problem, [BALL], knots=3, horizon=20, obstacle_weight=10)
    free = reach(problem, [], knots=3, horizon=20)
    blind = simulate(problem.plant(), solvers.make("qp", free), X0, free.goal(X0, position=target), 0.25)
    return problem, ocp, ocp.goal(X0, position=target), target, blind.x[-1]


def _affine(ocp, x, goal):
    """The sampling planners' affine model at x (about the input goal, their default linearization)."""
    Ad, Bd, wd = (np.asarray(M, dtype=float) for M in ocp.affine()(x, ocp.input_goal(goal[: ocp.nx])))
    return Ad, Bd, wd.ravel()


def _reference_violation(ocp, xs):
    """Σ_{k≥1} max(0, margin − clearance(x_k)) + the state bounds' excess, by ocpkit.model.task.clearances and numpy."""
    task = ocp.task
    c = clearances(task.kinematics, task.robot, task.obstacles, xs[1:, : task.kinematics.n])
    bounds = np.maximum(0.0, xs[1:] - ocp.x_max) + np.maximum(0.0, ocp.x_min - xs[1:])
    return float(np.maximum(0.0, task.margin - c).sum() + bounds.sum())


@pytest.mark.parametrize("dynamics", ["affine", "nonlinear"])
def test_kernel_violation_equals_an_independent_rollout(case, dynamics):
    """(a) Each candidate's violation — clearances below the margin and state bounds exceeded, summed over x_1 … x_T
    — is what a numpy rollout of the same knots and ocpkit.model.task.clearances give; some candidates collide, some
    not."""
    problem, _, goal, target, x = case
    vmax = np.full(3, 6.0)
    ocp = reach(
        problem,
        [BALL],
        knots=3,
        horizon=20,
        obstacle_weight=10,
        x_min=np.r_[np.full(3, -np.inf), -vmax],
        x_max=np.r_[np.full(3, np.inf), vmax],
    )
    scale = np.linspace(0.0, 1.0, 12)[:, None, None]  # from coasting to torques anywhere within the bounds
    U = scale * np.random.default_rng(0).uniform(ocp.u_min, ocp.u_max, size=(12, ocp.knots, ocp.nu))
    engine = Rollout(ocp, len(U), dynamics=dynamics)
    if dynamics == "affine":
        Ad, Bd, wd = _affine(ocp, x, goal)
        engine.load(x, goal, (Ad, Bd, wd))
        step = lambda x, u: Ad @ x + Bd @ u + wd  # noqa: E731
    else:
        F = ocp.discrete()
        engine.load(x, goal)
        step = lambda x, u: np.asarray(F(x, u)).ravel()  # noqa: E731
    _, violation = engine.evaluate(U)
    expected = []
    for knots in U:
        xs = [x]
        for u in ocp.parameterization.inputs(knots):
            xs.append(step(xs[-1], u))
        expected.append(_reference_violation(ocp, np.array(xs)))
    np.testing.assert_allclose(violation, expected, rtol=1e-9, atol=1e-12)
    assert engine.constrained and (violation == 0).any() and (violation > 0.01).any(), violation


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("name", PLANNERS)
def test_a_feasible_candidate_beats_a_cheaper_colliding_one(case, name, variant, monkeypatch):
    """(b) A population of three plans from x near the ball — the unobstructed reach's plan (cheapest: it goes
    through the ball), LinearMPC's plan around it and coasting (zero torque), both clear — every planner returns the
    cheaper clear one: EMPC's pick, CEM's elites and MPPI's weights rank feasibility first."""
    problem, ocp, goal, target, x = case
    free = reach(problem, [], knots=3, horizon=20)
    through = solvers.make("qp", free).solve(x, free.goal(X0, position=target)).knots
    around = solvers.make("qp", ocp).solve(x, goal).knots
    coast = np.zeros_like(through)
    population = np.stack([through, around, coast] * 3 + [through])  # 10 candidates, the colliding one first
    options = {"num_parents": 2} if name == "empc" else {"num_elites": 2} if name == "cem" else {}
    ctrl = solvers.make(name, ocp, variant=variant, population=len(population), seed=0, **options)
    generation = ctrl._generation_kernel if name == "empc" else ctrl._gaussian_kernel
    launch, seen = ctrl._launch, []

    def constructed(kernel, *args):
        """The planner's own generation, its population then replaced by ours, rolled out by its engine."""
        launch(kernel, *args)
        if kernel is generation:
            args[-1][:, 0], args[-1][:, 1] = ctrl.engine.evaluate(population)
            seen.append(args[-1].copy())

    monkeypatch.setattr(ctrl, "_launch", constructed)
    sol = ctrl.solve(x, goal)
    cost, violation = seen[-1].T
    assert violation[0] > 0.01 and violation[1] == violation[2] == 0, violation
    assert cost[0] < cost[1] < cost[2], cost  # the colliding plan is the cheapest: a penalty alone picks it
    assert sol.ok or sol.status == "soft", sol.raw_status
    np.testing.assert_allclose(sol.knots, np.clip(around, ocp.u_min, ocp.u_max), atol=1e-9)


@pytest.mark.parametrize("name", PLANNERS)
def test_closed_loop_stays_clear_of_the_ball(case, name):
    """(c) One second of the reach, preconditioned: the arm never touches the ball (true clearance, no margin) and
    still gets around it towards the target."""
    problem, ocp, goal, target, _ = case
    traj = simulate(problem.plant(), solvers.make(name, ocp, population=256, seed=0), X0, goal, 1.0)
    task = ocp.task
    clear = clearances(task.kinematics, task.robot, task.obstacles, traj.x[:, :3])
    tip = problem.kinematics.function(problem.end_effector)
    distance = np.linalg.norm(np.asarray(tip(traj.x[-1, :3])[0]).ravel() - target)
    assert clear.min() >= 0.0, (clear.min(), int((clear < 0).sum()))
    assert distance < 0.15, distance


def test_newton_seed_keeps_the_linearized_clearance_rows(case):
    """The preconditioned planners' QP seed holds the clearance rows linearized about the warm start (DAQP): near
    the ball, where the box-constrained optimum of the same knot QP runs into it, the seed stays clear on the
    affine prediction up to the linearization's error (1 mm)."""
    problem, ocp, goal, target, x = case
    ctrl = solvers.make("empc", ocp, population=16, num_parents=2, seed=0)
    ctrl.solve(x, goal)
    pre = ctrl.preconditioner
    assert pre.seed_status.startswith("DAQP") and "optimal" in pre.seed_status, pre.seed_status
    box = solve_box_qp(pre.P, pre.q, pre.lo, pre.hi).z.reshape(pre.newton.shape)
    engine = Rollout(ocp, 2)
    engine.load(x, goal, _affine(ocp, x, goal))
    _, violation = engine.evaluate(np.stack([pre.newton, box]))
    assert violation[1] > 0.01 and violation[0] <= 1e-3 * ocp.horizon, violation

"""The cost as named terms (ocpkit.model.cost), built once: each term against its definition computed another way,
and the same cost read by the NLP and the closed-loop measures."""

import casadi as ca
import numpy as np
import pinocchio as pin
import pytest

from ocpkit import problems
from ocpkit.model.task import FrameOrientation, JointLimitBarrier, reach
from ocpkit.sim.metrics import actual_cost, cost_by_term
from ocpkit.sim.simulate import Trajectory
from ocpkit.solvers.nlp import NonlinearMPC


@pytest.fixture(scope="module")
def panda_reach():
    panda = problems.make("panda")
    nq = panda.kinematics.n
    terms = [
        FrameOrientation(panda.kinematics, panda.end_effector, 3.0, terminal=False),
        JointLimitBarrier(-np.ones(nq), np.ones(nq), 50.0),
    ]
    return panda, reach(panda, ["0.5,0,0.4,0.05"], knots=5, horizon=10, terms=terms)


def test_the_cost_is_the_sum_of_its_named_terms(panda_reach):
    _, ocp = panda_reach
    cost = ocp.cost
    assert cost.names == ocp.terms == ["state", "input", "position", "orientation", "joint_limits"]
    rng = np.random.default_rng(0)
    for _ in range(5):
        x, u, g = rng.uniform(-1, 1, ocp.nx), rng.uniform(-20, 20, ocp.nu), rng.uniform(-1, 1, ocp.ng)
        stage, terminal = np.asarray(cost.stage_terms(x, u, g)).ravel(), np.asarray(cost.terminal_terms(x, g)).ravel()
        assert float(cost.stage(x, u, g)) == pytest.approx(stage.sum(), rel=1e-13)
        assert float(cost.terminal(x, g)) == pytest.approx(terminal.sum(), rel=1e-13)
        assert terminal[1] == 0 and terminal[3] == 0  # "input" and this "orientation" have no terminal part


def test_each_term_equals_its_definition_computed_with_pinocchio(panda_reach):
    panda, ocp = panda_reach
    model = panda.pin_model
    data = model.createData()
    frame = model.getFrameId(panda.end_effector)
    n, nq = ocp.nx, model.nq
    rng = np.random.default_rng(1)
    x, u = rng.uniform(-1, 1, n), rng.uniform(-20, 20, ocp.nu)
    R_target = pin.rpy.rpyToMatrix(0.3, -0.2, 1.0)
    p_target = np.array([0.4, 0.1, 0.5])
    goal = ocp.goal(rng.uniform(-1, 1, n), position=p_target, orientation=R_target)
    pin.framesForwardKinematics(model, data, x[:nq])
    placement = data.oMf[frame]
    xg = goal[:n]
    ug = ocp.input_goal(xg)
    position_weight = 1e3  # reach()'s default
    R_err = R_target.T @ placement.rotation
    orientation = 0.5 * np.array([R_err[2, 1] - R_err[1, 2], R_err[0, 2] - R_err[2, 0], R_err[1, 0] - R_err[0, 1]])
    expected = {
        "state": (x - xg) @ ocp.Q @ (x - xg),
        "input": (u - ug) @ ocp.R @ (u - ug),
        "position": position_weight * np.sum((placement.translation - p_target) ** 2),
        "orientation": 3.0 * orientation @ orientation,
    }
    terms = dict(zip(ocp.cost.names, np.asarray(ocp.cost.stage_terms(x, u, goal)).ravel()))
    for name, value in expected.items():
        assert terms[name] == pytest.approx(value, rel=1e-9, abs=1e-12), name


def test_the_nlp_objective_is_the_cost_summed_over_its_plan():
    """NonlinearMPC's objective at a plan (x_1 … x_T rolled out, the knots) equals Σ_k ℓ(x_k, u_k) + ℓ_T(x_T)
    summed in numpy from the cost's per-term Functions."""
    n3 = problems.make("nlink:3")
    ocp = reach(n3, [], knots=4, horizon=8, terms=[JointLimitBarrier(-0.3 * np.ones(3), 0.3 * np.ones(3))])
    mpc = NonlinearMPC(ocp)
    _, nlp, _ = mpc._nlp
    objective = ca.Function("f", [nlp["x"], nlp["p"]], [nlp["f"]])
    rng = np.random.default_rng(2)
    x0 = rng.uniform(-0.5, 0.5, ocp.nx)
    goal = ocp.goal(np.zeros(ocp.nx), position=[0.3, 0.2, 0.0])
    knots = rng.uniform(-1, 1, (ocp.knots, ocp.nu))
    inputs = ocp.parameterization.inputs(knots)
    F, xs = ocp.discrete(), [x0]
    for k in range(ocp.horizon):
        xs.append(np.asarray(F(xs[-1], inputs[k]), dtype=float).ravel())
    xs = np.array(xs)
    expected = sum(np.asarray(ocp.cost.stage_terms(xs[k], inputs[k], goal)).sum() for k in range(ocp.horizon))
    expected += np.asarray(ocp.cost.terminal_terms(xs[-1], goal)).sum()
    w = np.r_[xs[1:].ravel(), knots.ravel()]
    assert float(objective(w, np.r_[x0, np.tile(goal, ocp.horizon + 1)])) == pytest.approx(expected, rel=1e-12)


def test_the_actual_cost_by_term_equals_the_papers_sum():
    """Paper eq. actual_cost, Σ_{i=0}^{H} (x_i − x_g)ᵀQ(x_i − x_g) + Σ_{i<H} (u_i − u_g)ᵀR(u_i − u_g), in numpy."""
    pb = problems.make("puma560")
    ocp = pb.ocp(knots=5)
    rng = np.random.default_rng(3)
    H = 7
    traj = Trajectory(
        t=np.arange(H + 1) * ocp.dt,
        x=rng.normal(size=(H + 1, ocp.nx)),
        u=rng.normal(size=(H, ocp.nu)),
        goal=rng.normal(size=ocp.nx),
    )
    ex, eu = traj.x - traj.goal, traj.u - ocp.input_goal(traj.goal)
    terms = cost_by_term(traj, ocp)
    assert terms["state"] == pytest.approx(np.einsum("ij,jk,ik->", ex, ocp.Q, ex), rel=1e-13)
    assert terms["input"] == pytest.approx(np.einsum("ij,jk,ik->", eu, ocp.R, eu), rel=1e-13)
    assert actual_cost(traj, ocp) == pytest.approx(sum(terms.values()), rel=1e-15)

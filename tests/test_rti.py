"""Real-time iteration and fatrop against IPOPT on the same nonlinear OCP."""

import numpy as np
import pytest

from ocpkit import solvers
from ocpkit.benchmarks.crocoddyl_peer import undamped
from ocpkit.status import LIMITED
from ocpkit.problems import make
from ocpkit.sim.simulate import simulate
from ocpkit.solvers.nlp import NonlinearMPC
from ocpkit.solvers.qp import LinearMPC
from ocpkit.solvers.rti import RealTimeIteration


def _ipopt(ocp, x0, goal):
    sol = NonlinearMPC(ocp, options={"tol": 1e-11}).solve(x0, goal)
    assert sol.ok
    return sol


@pytest.mark.parametrize("form", ["condensed", "sparse"])
@pytest.mark.parametrize("knots", [None, 5])
def test_iterated_rti_converges_to_ipopts_optimum(form, knots):
    """Gauss–Newton SQP on the LTV knot QP, iterated from a cold start, reaches the NLP's KKT point."""
    prob = make("nlink:3")
    ocp = prob.ocp(knots=knots)
    x0, goal = prob.sample(0)
    ref = _ipopt(ocp, x0, goal)
    rti = RealTimeIteration(ocp, form=form, iterations=60, tol=1e-11)
    sol = rti.solve(x0, goal)
    assert sol.ok and sol.iterations > 0
    np.testing.assert_allclose(sol.knots, ref.knots, atol=1e-6)
    np.testing.assert_allclose(sol.x_pred, ref.x_pred, atol=1e-6)


def test_one_rti_step_moves_towards_the_optimum_and_stays_a_plan():
    prob = make("nlink:3")
    ocp = prob.ocp(knots=5)
    x0, goal = prob.sample(1)
    ref = _ipopt(ocp, x0, goal)
    errors = []
    for k in (1, 2, 4):
        sol = RealTimeIteration(ocp, iterations=k).solve(x0, goal)
        assert sol.ok
        errors.append(np.abs(sol.knots - ref.knots).max())
    assert errors[2] < errors[0]


def test_rti_is_the_trajectory_linear_mpc_with_one_iteration():
    """One iteration per step is LinearMPC linearized along the shifted plan, step for step."""
    prob = make("nlink:2")
    ocp = prob.ocp(knots=4)
    x0, goal = prob.sample(0)
    a = simulate(prob.plant(), RealTimeIteration(ocp), x0, goal, 0.2)
    b = simulate(prob.plant(), LinearMPC(ocp, linearization="trajectory"), x0, goal, 0.2)
    np.testing.assert_allclose(a.u, b.u, atol=1e-9)


def test_rti_on_the_compiled_model_is_the_rti_on_the_sx_model(tmp_path, monkeypatch):
    """compiled=True changes where the per-stage models are evaluated (C, not the SX virtual machine), not
    the controller: the same inputs to 1e-10 in closed loop, with 2 SQP iterations a step."""
    monkeypatch.setenv("OCPKIT_CACHE_DIR", str(tmp_path))
    prob = make("nlink:2")
    x0, goal = prob.sample(1)
    trajs = [
        simulate(prob.plant(), RealTimeIteration(prob.ocp(knots=4, compiled=compiled), iterations=2), x0, goal, 0.1)
        for compiled in (False, True)
    ]
    assert all(t.fallbacks == 0 for t in trajs)
    np.testing.assert_allclose(trajs[1].u, trajs[0].u, rtol=0, atol=1e-10)


def test_cold_rti_step_linearizes_at_x_held_not_along_a_diverging_rollout():
    """A cold step linearizes at x held (as IPOPT and acados start), not along the input goal's rollout: the
    undamped Panda's (|eig A_d| 1.11 a step at dt 0.01) ran 16-64 from x within T = 50 steps, and the first input
    was 0.95-1.84 of max |u_0| away from IPOPT's (seeds 100-102); held, 0.06-0.16, acados' SQP-RTI to 1e-8."""
    prob = undamped("panda")
    ocp = prob.ocp(knots=None, horizon=50)
    for seed in (100, 101, 102):
        x0, goal = prob.sample(seed)
        ref = _ipopt(ocp, x0, goal)
        rti = RealTimeIteration(ocp, native=False)
        np.testing.assert_array_equal(rti.shifted_plan(x0, goal)[0], np.tile(x0, (ocp.horizon, 1)))
        sol = rti.solve(x0, goal)
        assert sol.ok
        assert np.abs(sol.u - ref.u).max() <= 0.2 * np.abs(ref.u).max()


def test_rti_options_are_checked():
    ocp = make("nlink:2").ocp(knots=3)
    with pytest.raises(ValueError, match="iterations"):
        RealTimeIteration(ocp, iterations=0)
    with pytest.raises(ValueError, match="tol"):
        RealTimeIteration(ocp, tol=-1.0)
    with pytest.raises(ValueError, match="takes no linearization"):
        RealTimeIteration(ocp, linearization="goal")
    with pytest.raises(ValueError, match="form"):
        RealTimeIteration(ocp, form="dense")


def test_rti_is_its_own_solver():
    """Issue 45: real-time iteration is the registered solver "rti", no longer a method of NonlinearMPC, which refuses
    method "rti" in one line naming the new way; its options apply (native: the C step; max_iter: each QP's)."""
    prob = make("nlink:2")
    ocp = prob.ocp(horizon=20, knots=3)
    x0, goal = prob.sample(0)
    assert "rti" in solvers.names() and type(solvers.make("rti", ocp)) is RealTimeIteration
    with pytest.raises(ValueError, match=r"solvers.make\('rti'") as error:
        NonlinearMPC(ocp, method="rti")
    assert "\n" not in str(error.value)
    assert RealTimeIteration(ocp, native=False).solve(x0, goal).path != "C step"
    assert solvers.make("rti", ocp, native=True).solve(x0, goal).path == "C step"
    assert RealTimeIteration(ocp, max_iter=1, native=False).solve(x0, goal).status == LIMITED


def test_rti_solves_traditional_mpc_in_the_sparse_form():
    """Issue 48: at p = T the sparse QP (ProxQP's sparse backend) gives the condensed QP's closed loop (the default)
    to the backends' tolerance."""
    prob = make("nlink:3")
    ocp = prob.ocp(horizon=20, knots=None)
    rti = RealTimeIteration(ocp, form="sparse")
    assert (rti.form, rti.qp_name) == ("sparse", "proxqp") and RealTimeIteration(ocp).form == "condensed"
    x0, goal = prob.sample(0)
    sparse, dense = (simulate(prob.plant(), c, x0, goal, 0.2) for c in (rti, RealTimeIteration(ocp)))
    assert sparse.fallbacks == dense.fallbacks == 0
    np.testing.assert_allclose(sparse.u, dense.u, rtol=0, atol=1e-7)


def test_rti_time_budget_falls_back():
    """A budget no iteration fits in: the fallback input, finite, no exception."""
    prob = make("nlink:3")
    ocp = prob.ocp(knots=5)
    x0, goal = prob.sample(0)
    rti = RealTimeIteration(ocp, iterations=3)
    rti.solve(x0, goal)  # calibrates the measured costs
    rti.time_limit = 1e-9
    sol = rti.solve(x0, goal)
    assert not sol.ok and sol.fallback and np.isfinite(sol.u).all()


@pytest.mark.parametrize("knots", [None, 5])
def test_fatrop_reaches_ipopts_optimum(knots):
    prob = make("nlink:3")
    ocp = prob.ocp(knots=knots)
    x0, goal = prob.sample(0)
    ref = _ipopt(ocp, x0, goal)
    ctrl = NonlinearMPC(ocp, method="fatrop", options={"tol": 1e-10})
    sol = ctrl.solve(x0, goal)
    assert sol.ok, sol.raw_status
    np.testing.assert_allclose(sol.knots, ref.knots, atol=1e-6)
    np.testing.assert_allclose(sol.x_pred, ref.x_pred, atol=1e-6)
    again = ctrl.solve(x0, goal)  # warm start in fatrop's stage order
    assert again.ok
    np.testing.assert_allclose(again.knots, ref.knots, atol=1e-6)


def test_fatrop_takes_no_time_limit():
    with pytest.raises(ValueError, match="time_limit"):
        NonlinearMPC(make("nlink:2").ocp(knots=3), method="fatrop", time_limit=0.01)


@pytest.mark.slow
def test_fatrop_reaches_ipopts_optimum_on_the_puma():
    prob = make("puma560")
    ocp = prob.ocp(knots=5, horizon=50)
    x0, goal = prob.sample(0)
    ref = _ipopt(ocp, x0, goal)
    sol = NonlinearMPC(ocp, method="fatrop", options={"tol": 1e-10}).solve(x0, goal)
    assert sol.ok, sol.raw_status
    np.testing.assert_allclose(sol.knots, ref.knots, atol=1e-6 * max(1.0, np.abs(ref.knots).max()))


def test_rti_swings_the_cartpole_up(cartpole):
    x0, goal = np.r_[0.0, np.pi, 0.0, 0.0], np.zeros(4)
    ocp = cartpole.ocp(knots=10)
    traj = simulate(cartpole.plant(), RealTimeIteration(ocp), x0, goal, 3.0)
    assert traj.fallbacks == 0
    assert np.abs(traj.x[-1] - goal).max() <= 0.05

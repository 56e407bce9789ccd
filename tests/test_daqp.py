"""LinearMPC(qp="daqp"): DAQP's dense active-set solve of the condensed knot QP against ProxQP's."""

import numpy as np
import pytest

from ocpkit.status import INFEASIBLE, LIMITED, NAN, SUCCESS
from ocpkit.problems import make
from ocpkit.sim.simulate import simulate
from ocpkit.solvers.qp import LinearMPC

pytest.importorskip("daqp")


@pytest.mark.parametrize("seed", range(3))
def test_daqp_gives_proxqps_optimum_with_active_bounds(seed):
    problem = make("nlink:4")
    ocp = problem.ocp(horizon=60, knots=5, compiled=False)
    x, goal = problem.sample(seed)
    daqp, proxqp = LinearMPC(ocp, qp="daqp"), LinearMPC(ocp)
    plant = ocp.discrete()
    active = False
    for _ in range(8):  # the first step cold, the rest warm-started from the previous active set
        a, b = daqp.solve(x, goal), proxqp.solve(x, goal)
        assert a.status == SUCCESS and b.status == SUCCESS, (a.raw_status, b.raw_status)
        np.testing.assert_allclose(a.knots, b.knots, atol=1e-6, rtol=0)
        active |= bool(np.isclose(np.abs(b.knots), problem.tau_max, atol=1e-6).any())
        x = np.asarray(plant(x, b.u)).ravel()
    assert active


def test_daqp_with_state_bounds_soft_and_hard():
    problem = make("pendulum")
    x0, goal = problem.sample(0)
    for bounds in ("soft", "hard"):
        ocp = problem.ocp(knots=4, x_min=[-np.inf, -1.0], x_max=[np.inf, 1.0])
        a, b = (LinearMPC(ocp, qp=qp, state_bounds=bounds).solve(x0, goal) for qp in ("daqp", "proxqp"))
        assert a.ok and b.ok
        np.testing.assert_allclose(a.knots, b.knots, atol=1e-6, rtol=0)


def test_daqp_infeasible_hard_bounds_fall_back():
    problem = make("pendulum:linear")
    ocp = problem.ocp(knots=4, x_min=[-np.inf, 1.0], x_max=[np.inf, 2.0])
    traj = simulate(problem.plant(), LinearMPC(ocp, qp="daqp", state_bounds="hard"), [0.0, 0.0], [1.0, 0.0], 0.05)
    assert traj.fallbacks == len(traj.solutions) == 5
    assert all(s.status in (INFEASIBLE, LIMITED) for s in traj.solutions)
    assert np.isfinite(traj.u).all() and (np.abs(traj.u) <= problem.tau_max).all()


def test_daqp_budget_and_absurd_state():
    problem = make("pendulum")
    x0, goal = problem.sample(0)
    ctrl = LinearMPC(problem.ocp(horizon=100, knots=5), qp="daqp")
    assert ctrl.solve(x0, goal).ok  # calibration
    ctrl.time_limit = 1e-6
    sol = ctrl.solve(x0, goal)
    assert sol.status == LIMITED and sol.fallback and "budget" in sol.raw_status
    ctrl.time_limit = None
    assert ctrl.solve(x0, goal).ok
    assert ctrl.solve([1e20, 0.0], goal).status == NAN
    assert ctrl.solve(x0, goal).ok


def test_daqp_closed_loop_matches_proxqp():
    problem = make("pendulum")
    x0, goal = problem.sample(1)
    ocp = problem.ocp(knots=5)
    a, b = (simulate(problem.plant(), LinearMPC(ocp, qp=qp), x0, goal, 0.5) for qp in ("daqp", "proxqp"))
    assert a.fallbacks == b.fallbacks == 0
    np.testing.assert_allclose(a.u, b.u, atol=1e-6)


def test_daqp_needs_the_condensed_form():
    with pytest.raises(ValueError, match="daqp.*condensed"):
        LinearMPC(make("pendulum").ocp(knots=3), form="sparse", qp="daqp")


def _many_active_rows(n=40, rows=400, seed=0):
    """A dense QP whose solution has many active rows: DAQP needs dozens of iterations from a cold start."""
    from ocpkit.qp.quadratic_program import QP

    rng = np.random.default_rng(seed)
    M = rng.normal(size=(n, n))
    C = rng.normal(size=(rows, n))
    return QP(
        M @ M.T + n * np.eye(n),
        100 * rng.normal(size=n),
        np.zeros((0, n)),
        np.zeros(0),
        C,
        -np.ones(rows),
        np.ones(rows),
    )


def test_daqp_deadline_becomes_an_iteration_limit():
    """With a deadline the backend gives DAQP the iterations that fit: the time left after its measured set-up over
    its measured time per iteration (here set to 1 ms: 10.5 ms left allow 10), and refuses a solve where none fits."""
    import time

    from ocpkit.status import OperationCosts
    from ocpkit.qp.daqp import DAQP

    qp = _many_active_rows()
    backend = DAQP(max_iter=10_000, eps=1e-9)
    full = backend.solve(qp, None, None)
    assert full.status == SUCCESS and full.iterations > 20
    per_row = 1e-3 / (qp.n + qp.l.size)  # DAQP's times are measured per row of the data (n + rows)
    backend.costs = OperationCosts()
    backend.costs.add(f"set-up n={qp.n}", 0.0)
    backend.costs.add(f"iteration n={qp.n}", per_row)
    capped = backend.solve(qp, None, time.perf_counter() + 10.5e-3)
    assert capped.status == LIMITED and 1 <= capped.iterations <= 10, (capped.iterations, capped.raw_status)
    assert "time budget" in capped.raw_status
    backend.costs.add(f"iteration n={qp.n}", per_row)  # the median again 1 ms a step, whatever the solve measured
    backend.costs.add(f"iteration n={qp.n}", per_row)
    none = backend.solve(qp, None, time.perf_counter() + 0.5e-3)
    assert none.status == LIMITED and none.iterations == 0 and "time budget" in none.raw_status
    assert backend.solve(qp, capped.duals, None).status == SUCCESS  # the limited iterate warm-starts the next solve

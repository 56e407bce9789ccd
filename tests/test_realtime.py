"""Real-time behaviour: bounded steps, verified successes, absurd states, threads, soft state bounds."""

import time

import numpy as np
import pytest
from threadpoolctl import threadpool_info

from ocpkit import problems
from ocpkit.benchmarks.faults_realtime import beyond_bounds_rows, huge_state_rows, realtime_rows, two_threads_rows
from ocpkit.controller import Controller
from ocpkit.status import LIMITED, NAN, SOFT, SUCCESS, OperationCosts, Solution
from ocpkit.solvers.nlp import NonlinearMPC
from ocpkit.solvers.qp import LinearMPC

PENDULUM = problems.make("pendulum")
X0, GOAL = PENDULUM.sample(0)


@pytest.mark.parametrize("form", ["sparse", "condensed"])
@pytest.mark.parametrize("qp", ["proxqp", "osqp"])
def test_absurd_state_is_nan_before_any_solver(form, qp):
    ctrl = LinearMPC(PENDULUM.ocp(knots=3), form=form, qp=qp)
    t0 = time.perf_counter()
    sol = ctrl.solve([1e20, 0.0], GOAL)
    assert time.perf_counter() - t0 < 1.0  # generous: the check runs before the model and the QP
    assert sol.status == NAN and sol.fallback and sol.iterations == 0 and "state_limit" in sol.raw_status
    assert np.isfinite(sol.u).all() and abs(sol.u[0]) <= PENDULUM.tau_max
    assert ctrl.solve(X0, GOAL).ok  # and the controller still works


def test_every_solver_answers_huge_state_with_non_success():
    rows = huge_state_rows(("qp condensed proxqp", "qp sparse osqp", "ipopt"))
    assert all(r.acceptable for r in rows), [(r.solver, r.statuses, r.seconds) for r in rows]


@pytest.mark.parametrize("form", ["sparse", "condensed"])
def test_proxqp_total_inner_iterations_capped(form):
    # With the state check lifted, x = 1e20 reaches ProxQP, which once ran 15 M inner iterations (54 s) here.
    ctrl = LinearMPC(PENDULUM.ocp(knots=3), form=form, qp="proxqp", max_iter=200)
    ctrl.state_limit = 1e300
    t0 = time.perf_counter()
    sol = ctrl.solve([1e20, 0.0], GOAL)
    assert time.perf_counter() - t0 < 10.0
    assert sol.status != SUCCESS and sol.iterations <= 200 + 1
    assert np.isfinite(sol.u).all() and abs(sol.u[0]) <= PENDULUM.tau_max


@pytest.mark.parametrize("form", ["sparse", "condensed"])
@pytest.mark.parametrize("qp", ["proxqp", "osqp"])
def test_budget_after_calibration_is_limited_and_keeps_workspace(form, qp):
    ctrl = LinearMPC(PENDULUM.ocp(horizon=100, knots=5), form=form, qp=qp)
    assert ctrl.solve(X0, GOAL).ok  # calibration
    backend = ctrl._backend.solver
    ctrl.time_limit = 1e-6
    t0 = time.perf_counter()
    sol = ctrl.solve(X0, GOAL)
    assert time.perf_counter() - t0 < 0.5
    assert sol.status == LIMITED and sol.fallback and "budget" in sol.raw_status
    assert ctrl._backend.solver is backend  # "limited" keeps the workspace
    ctrl.time_limit = None
    assert ctrl.solve(X0, GOAL).ok


def test_ipopt_budget_smaller_than_an_iteration_is_not_started():
    ctrl = NonlinearMPC(PENDULUM.ocp(knots=3))
    assert ctrl.solve(X0, GOAL).ok
    ctrl.time_limit = 1e-6
    sol = ctrl.solve(X0, GOAL)
    assert sol.status == LIMITED and "IPOPT iteration" in sol.raw_status


class _Fixed(Controller):
    """Reports success with a given input: the base class must verify it."""

    def __init__(self, ocp, u, **kw):
        self.fixed = np.asarray(u, dtype=float)
        super().__init__(ocp, **kw)

    def _solve(self, x, goal):
        knots = np.tile(self.fixed, (self.ocp.knots, 1))
        self.seen_threads = [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]
        return Solution(u=self.fixed.copy(), knots=knots, status=SUCCESS, raw_status="claimed")


def test_success_outside_input_bounds_is_rejected():
    ocp = PENDULUM.ocp(knots=3)
    sol = _Fixed(ocp, [-4.7e8]).solve(X0, GOAL)
    assert sol.status == LIMITED and sol.fallback and abs(sol.u[0]) <= PENDULUM.tau_max
    sol = _Fixed(ocp, [PENDULUM.tau_max + 1e-9]).solve(X0, GOAL)  # within the tolerance: clipped
    assert sol.ok and sol.u[0] == PENDULUM.tau_max and (sol.knots <= PENDULUM.tau_max).all()
    assert _Fixed(ocp, [np.nan]).solve(X0, GOAL).status == NAN


def test_blas_threads_limited_inside_a_step():
    ocp = PENDULUM.ocp(knots=3)
    one = _Fixed(ocp, [0.0])
    one.solve(X0, GOAL)
    assert one.seen_threads and set(one.seen_threads) == {1}
    free = _Fixed(ocp, [0.0], threads=None)
    free.solve(X0, GOAL)
    outside = [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]
    assert free.seen_threads == outside  # None leaves the pools alone, and the limit was restored
    with pytest.raises(ValueError, match="threads"):
        _Fixed(ocp, [0.0], threads=0)


def test_osqp_update_error_is_not_success():
    ctrl = LinearMPC(PENDULUM.ocp(knots=3), form="sparse", qp="osqp")
    assert ctrl.solve(X0, GOAL).ok
    raw = ctrl._backend.solver._solver

    class Failing:
        def __getattr__(self, name):
            return getattr(raw, name)

        def update_data_vec(self, **kw):
            return 1  # OSQP's "data validation" error code

    ctrl._backend.solver._solver = Failing()
    sol = ctrl.solve(X0 + 0.1, GOAL)
    assert sol.status != SUCCESS and "update failed" in sol.raw_status and sol.fallback
    assert ctrl.solve(X0, GOAL).ok  # a fresh workspace afterwards


def test_two_threads_share_one_controller_safely():
    rows = two_threads_rows(per_thread=40)
    assert all(r.acceptable for r in rows), [r.detail for r in rows]


@pytest.mark.parametrize("label", ["qp condensed proxqp", "qp sparse proxqp"])
def test_goal_beyond_state_bound_drives_to_the_bound(label):
    # Sparse ProxQP stalled from its warm start here (25/100 steps, 10,000 iterations each) before the cold retry.
    (row,) = beyond_bounds_rows((label,))
    assert row.acceptable, row.detail


@pytest.mark.parametrize("form", ["sparse", "condensed"])
def test_soft_bounds_equal_hard_ones_when_feasible(form):
    ocp = PENDULUM.ocp(knots=3, x_min=[-np.inf, -1.0], x_max=[np.inf, 1.0])
    soft = LinearMPC(ocp, form=form).solve([0.5, 0.0], GOAL)
    hard = LinearMPC(ocp, form=form, state_bounds="hard").solve([0.5, 0.0], GOAL)
    assert soft.ok and hard.ok
    np.testing.assert_allclose(soft.u, hard.u, atol=1e-6)
    np.testing.assert_allclose(soft.x_pred, hard.x_pred, atol=1e-5)


def test_soft_bounds_recover_a_start_outside_them():
    ocp = PENDULUM.ocp(knots=3, x_min=[-np.inf, -1.0], x_max=[np.inf, 1.0])
    sol = LinearMPC(ocp).solve([0.0, 1.4], GOAL)
    # it brakes as hard as it can; its plan starts beyond the bound, so it is "soft", not a success
    assert sol.status == SOFT and "state bound x[1]" in sol.raw_status and sol.u[0] == -PENDULUM.tau_max
    assert LinearMPC(ocp, state_bounds="hard").solve([0.0, 1.4], GOAL).status != SUCCESS


def test_a_state_outside_the_trust_region_brakes_without_a_solve():
    """q̇ = 3 with |q̇| ≤ 1: beyond Controller.TRUST_REGION (1.5) times the bound no solver runs; the brake answers."""
    ocp = PENDULUM.ocp(knots=3, x_min=[-np.inf, -1.0], x_max=[np.inf, 1.0])
    ctrl = LinearMPC(ocp)
    ctrl.solve([0.0, 0.5], GOAL)
    sol = ctrl.solve([0.0, 3.0], GOAL)
    assert sol.status == "infeasible" and "trust region" in sol.raw_status and sol.path == "fallback (brake)"
    assert sol.u[0] == -PENDULUM.tau_max and sol.iterations == 0
    assert ctrl.solve([0.0, 0.5], GOAL).applied  # the solver answers again


@pytest.mark.parametrize("x0", [[0.5, 0.0], [0.0, 1.4]], ids=["hard QP feasible", "hard QP infeasible"])
def test_daqp_hard_first_equals_the_soft_qp(x0):
    """DAQP solves the hard QP and the soft one only where that is infeasible: ProxQP's soft QP, the same answer."""
    ocp = PENDULUM.ocp(knots=3, x_min=[-np.inf, -1.0], x_max=[np.inf, 1.0])
    daqp, proxqp = LinearMPC(ocp, qp="daqp"), LinearMPC(ocp, qp="proxqp", eps=1e-10)
    assert len(daqp._transcriptions) == 2 and len(proxqp._transcriptions) == 1
    a, b = daqp.solve(x0, GOAL), proxqp.solve(x0, GOAL)
    assert a.status == b.status == (SUCCESS if x0[1] <= 1.0 else SOFT)  # a start past a bound: "soft"
    np.testing.assert_allclose(a.knots, b.knots, atol=1e-6)
    np.testing.assert_allclose(a.x_pred, b.x_pred, atol=1e-5)


def test_hpipm_takes_hard_state_bounds_only():
    ocp = PENDULUM.ocp(x_min=[-np.inf, -1.0], x_max=[np.inf, 1.0])
    with pytest.raises(ValueError, match="hard"):
        LinearMPC(ocp, form="sparse", qp="hpipm", state_bounds="soft")
    assert LinearMPC(ocp, form="sparse", qp="hpipm").state_bounds == "hard"


@pytest.mark.slow
def test_every_realtime_row_acceptable():
    rows = realtime_rows()
    bad = [(r.case, r.solver, r.detail) for r in rows if not r.acceptable]
    assert not bad, bad


@pytest.mark.parametrize("qp", ["proxqp", "osqp"])
def test_warm_up_makes_the_first_budgeted_step_bounded(qp):
    ctrl = LinearMPC(PENDULUM.ocp(horizon=100, knots=5), qp=qp, time_limit=1e-6)
    assert ctrl.warm_up(X0, GOAL).ok and ctrl.time_limit == 1e-6  # outside the budget, which is restored
    t0 = time.perf_counter()
    sol = ctrl.solve(X0, GOAL)
    assert time.perf_counter() - t0 < 0.5 and sol.status == LIMITED and "budget" in sol.raw_status


def test_one_slow_measurement_does_not_lock_an_operation_out():
    costs = OperationCosts()
    costs.add("build", 5.2e-3)  # a slow first call
    refused = 0
    while not costs.fits("build", 5e-3):
        refused += 1
        assert refused < 100
    assert refused == 4  # 5.2 ms × 0.99^4 ≤ 5 ms: tried again, and measured again
    costs.add("build", 1.5e-3)
    assert costs.predict("build") == pytest.approx(np.median([5.2e-3, 1.5e-3]))
    # Never below half the measured time: an operation more than twice the time left is never retried.
    assert not any(costs.fits("build", 0.49 * costs.predict("build")) for _ in range(1000))


def test_default_ceiling_stops_an_unbudgeted_step():
    """No time_limit: the step still stops at LinearMPC's ceiling (sparse ProxQP at x = 9e5 on nlink:3 ran 30-75 s
    before). The ceiling is lowered for the test; time_limit=inf removes it."""
    problem = problems.make("nlink:3")
    ocp = problem.ocp(knots=5)
    ctrl = LinearMPC(ocp, form="sparse", native=False)
    assert ctrl.ceiling == LinearMPC.CEILING_MIN  # a small QP: the floor
    ctrl.CEILING_MIN = 0.5
    x = np.zeros(ocp.nx)
    x[0] = 9e5
    t0 = time.perf_counter()
    sol = ctrl.solve(x, np.zeros(ocp.nx))
    wall = time.perf_counter() - t0
    assert sol.status == LIMITED and "time budget" in sol.raw_status, sol.raw_status
    assert wall < 0.5 + 1.0  # the budget and at most one uninterruptible chunk beyond it
    ctrl.time_limit = float("inf")
    assert ctrl._deadline() is None


def test_ceiling_grows_with_the_qp():
    ctrl = LinearMPC(problems.make("pendulum").ocp(knots=5, horizon=200), form="sparse", native=False)
    assert ctrl.ceiling == LinearMPC.CEILING_MIN
    ctrl.CEILING_MIN = 0.0  # the floor lowered: what is left is the per-variable part
    assert ctrl.ceiling == pytest.approx(LinearMPC.CEILING_PER_VARIABLE * (201 * 2 + 5))


def test_proxqp_chunks_converge_where_a_solve_needs_many_outer_iterations():
    """Chunks of a fixed 5 outer iterations restarted ProxQP's BCL tolerances every time and never converged on the
    pendulum against an active hard state bound (10,000 iterations, where one solve takes 13)."""
    ocp = PENDULUM.ocp(knots=3, horizon=10, x_min=[-np.inf, -1.0], x_max=[np.inf, 1.0])
    sol = LinearMPC(ocp, qp="proxqp", state_bounds="hard", native=False).solve([0.0, 0.0], [np.pi, 0.0])
    assert sol.ok and sol.iterations < 100, (sol.raw_status, sol.iterations)

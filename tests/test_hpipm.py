"""HPIPM (through CasADi's conic interface) on the sparse traditional QP: its interface is built once and its answers
hold the certificate solve after solve."""

from __future__ import annotations

import numpy as np

from ocpkit.problems import make
from ocpkit.sim.simulate import simulate
from ocpkit.solvers.qp import LinearMPC
from ocpkit.solvers.rti import RealTimeIteration


def _controller():
    ocp = make("pendulum").ocp(knots=10, horizon=10, x_min=[-np.inf, -1.0], x_max=[np.inf, 1.0])
    return LinearMPC(ocp, form="sparse", qp="hpipm", native=False)


def test_hpipm_keeps_its_interface_across_reset_and_answers_each_qp_afresh():
    """Building CasADi's HPIPM interface costs 30 ms at nlink:13, T = 50, a solve 10: a reset keeps it (there is no
    warm start to forget). Each solve's answer is a fresh controller's on the same QP, certified; a new iteration
    limit rebuilds it."""
    c = _controller()
    goal = np.array([2.0, 0.0])
    assert c.solve(np.array([0.0, 0.5]), goal).ok
    made = c._backend.solver
    for x in ([0.3, -0.2], [-0.5, 0.9], [1.0, 0.0]):
        c.reset()
        sol, fresh = c.solve(np.array(x), goal), _controller().solve(np.array(x), goal)
        assert c._backend.solver is made
        assert sol.ok and sol.certificate.holds, sol.raw_status
        np.testing.assert_allclose(sol.u, fresh.u, rtol=0, atol=1e-12)
        np.testing.assert_allclose(sol.x_pred, fresh.x_pred, rtol=0, atol=1e-12)
    c.max_iter = 30
    assert c.solve(np.array([0.0, 0.5]), goal).ok and c._backend.solver is not made


def test_hpipm_starts_from_the_warm_start_moved_inside_its_bounds():
    """HPIPM starts from the previous answer, each bounded variable moved a tenth of its range inside its bounds:
    fewer iterations than from zero (nlink:13, T = 50: a median 7-8 against 10), every step certified."""
    problem = make("pendulum")
    ocp = problem.ocp(knots=20, horizon=20)
    x0, goal = problem.sample(0)
    iterations = {}
    for warm in (True, False):
        c = RealTimeIteration(ocp, form="sparse", qp="hpipm", warm_start=warm, native=False)
        steps = simulate(problem.plant(), c, x0, goal, 10 * ocp.dt).solutions
        assert all(s.ok and s.certificate.holds for s in steps)
        iterations[warm] = sum(s.iterations for s in steps)
    assert iterations[True] <= 0.8 * iterations[False], iterations

"""A step's initial guess as the QP's primal start (issue 46): ProxQP and OSQP start from the guess's knots (and, in
the sparse form, the states they imply) instead of the previous answer; the answer is the unguided one."""

import numpy as np
import pytest

from ocpkit import problems
from ocpkit.solvers.qp import LinearMPC
from ocpkit.solvers.rti import RealTimeIteration

N3 = problems.make("nlink:3")
OCP = N3.ocp(knots=5, compiled=False)
X0, GOAL = N3.sample(0)


@pytest.mark.parametrize("form, qp", [("condensed", "proxqp"), ("condensed", "osqp"), ("sparse", "osqp")])
def test_a_guess_at_the_optimum_takes_fewer_iterations_to_the_same_answer(form, qp):
    """The goal linearization builds the same QP with or without the guess: only the start differs. Measured
    (nlink:3, seed 0): ProxQP condensed 9 → 6 iterations, OSQP condensed 925 → 200, OSQP sparse 375 → 300."""
    cold = LinearMPC(OCP, form=form, qp=qp, native=False).solve(X0, GOAL)
    guided = LinearMPC(OCP, form=form, qp=qp, native=False).solve(X0, GOAL, initial_guess=cold.knots)
    assert cold.ok and guided.ok
    assert guided.iterations < cold.iterations, (guided.iterations, cold.iterations)
    scale = np.abs(OCP.u_max).max()
    np.testing.assert_allclose(guided.knots, cold.knots, rtol=0, atol=1e-6 * scale)


def test_the_sparse_start_holds_the_states_the_guess_implies():
    """SparseQP.primal: the optimum's knots give back the optimum's states (the QP's dynamics rows solved)."""
    ctrl = LinearMPC(OCP, form="sparse", qp="proxqp", native=False)
    starts, solve = [], ctrl._backend.solve
    ctrl._backend.solve = lambda qp, warm, deadline: (starts.append((qp, warm)), solve(qp, warm, deadline))[1]
    cold = ctrl.solve(X0, GOAL)
    guided = ctrl.solve(X0, GOAL, initial_guess=cold.knots)
    (qp, warm), tr = starts[1], ctrl.transcription
    assert len(warm) == 1  # the primal point alone, not the previous answer's multipliers
    np.testing.assert_allclose(tr.states(warm[0]), cold.x_pred, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(tr.knots(warm[0]), cold.knots)
    np.testing.assert_allclose(qp.A @ warm[0], qp.b, rtol=0, atol=1e-9)
    assert guided.iterations <= cold.iterations
    np.testing.assert_allclose(guided.knots, cold.knots, rtol=0, atol=1e-6 * np.abs(OCP.u_max).max())


def test_rti_from_its_converged_plan_converges_at_once_to_it():
    """RTI iterated to convergence, then again from its answer as the guess: the first QP starts from the guess, the
    later ones from the previous iteration's answer. Measured (Panda, seed 1): 35 QP iterations cold (from the state
    held at x; 441 from the input goal's rollout before 0.13.0), 13 from the guess (52 where the guess was only the
    linearization point and every QP started cold)."""
    panda = problems.make("panda")
    ocp = panda.ocp(knots=5, compiled=False)
    x0, goal = panda.sample(1)
    options = {"form": "sparse", "qp": "proxqp", "iterations": 20, "tol": 1e-10, "native": False}
    cold = RealTimeIteration(ocp, **options).solve(x0, goal)
    guided = RealTimeIteration(ocp, **options).solve(x0, goal, initial_guess=cold.knots)
    assert cold.ok and guided.ok and "converged" in guided.raw_status
    assert guided.iterations < cold.iterations / 2, (guided.iterations, cold.iterations)
    np.testing.assert_allclose(guided.knots, cold.knots, rtol=0, atol=1e-6 * np.abs(ocp.u_max).max())

"""The box-constrained QP of the sampling planners' Newton candidate against ProxQP, an independent solver."""

import numpy as np
import proxsuite
import pytest

from ocpkit import problems
from ocpkit.qp.boxqp import solve_box_qp
from ocpkit.qp.transcription import CondensedQP


def proxqp_box(P, q, lo, hi):
    qp = proxsuite.proxqp.dense.QP(q.size, 0, 0, box_constraints=True)
    qp.settings.eps_abs, qp.settings.eps_rel, qp.settings.max_iter = 1e-12, 0.0, 100_000
    qp.init(P, q, None, None, None, None, None, lo, hi)
    qp.solve()
    return np.array(qp.results.x)


@pytest.mark.parametrize("seed", range(4))
def test_matches_proxqp_on_ill_conditioned_problems(seed):
    rng = np.random.default_rng(seed)
    d = 30
    U, _ = np.linalg.qr(rng.normal(size=(d, d)))
    P = (U * np.logspace(-1, 6, d)) @ U.T  # condition 1e7, as the knot QPs of the N-link robots
    P = (P + P.T) / 2
    q = 100 * rng.normal(size=d)
    lo, hi = np.full(d, -2.0), np.full(d, 2.0)
    lo[:3] = -np.inf  # unbounded components too
    result = solve_box_qp(P, q, lo, hi)
    assert result.converged and np.all(result.z >= lo) and np.all(result.z <= hi)
    np.testing.assert_allclose(result.z, proxqp_box(P, q, lo, hi), atol=1e-6)
    assert np.sum((result.z == lo) | (result.z == hi)) > 0  # the bounds were really in play


@pytest.mark.parametrize("links", [3, 6])
def test_newton_candidate_is_the_knot_qp_optimum(links):
    """On the 3-knot QP of an N-link robot, from a cold and from a warm start."""
    problem = problems.make(f"nlink:{links}")
    ocp = problem.ocp(knots=3, horizon=100)
    x0, goal = problem.sample(5)

    Ad, Bd, wd = (np.asarray(v, dtype=float) for v in ocp.affine()(x0, np.zeros(links)))
    qp = CondensedQP(ocp).build(Ad, Bd, wd.ravel(), x0, goal)
    lo, hi = qp.l[: qp.n], qp.u[: qp.n]
    reference = proxqp_box(qp.P, qp.q, lo, hi)
    assert np.sum(np.isclose(reference, lo) | np.isclose(reference, hi)) > 0
    cold = solve_box_qp(qp.P, qp.q, lo, hi)
    warm = solve_box_qp(qp.P, qp.q, lo, hi, reference + 0.1)
    for result in (cold, warm):
        assert result.converged
        np.testing.assert_allclose(result.z, reference, atol=1e-6)
    assert warm.iterations <= cold.iterations


def test_unconstrained_optimum_in_one_iteration_and_bad_input():
    P, q = np.array([[2.0, 0.5], [0.5, 1.0]]), np.array([-1.0, 0.3])
    result = solve_box_qp(P, q, -10.0, 10.0)
    assert result.iterations == 1 and result.converged
    np.testing.assert_allclose(result.z, np.linalg.solve(P, -q), atol=1e-14)
    with pytest.raises(ValueError, match="lo must be <= hi"):
        solve_box_qp(P, q, 1.0, -1.0)
    with pytest.raises(ValueError, match="P must have shape"):
        solve_box_qp(np.eye(3), q, -1.0, 1.0)

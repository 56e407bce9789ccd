"""The two transcriptions against the paper's examples and against each other."""

import numpy as np
import pytest

from conftest import random_lti
from ocpkit.model.ocp import OCP
from ocpkit.model.parameterization import Parameterization
from ocpkit.problems import make
from ocpkit.solvers.qp import LinearMPC
from ocpkit.qp.sparse import SparseQP
from ocpkit.qp.transcription import CondensedQP


def _ocp(model, T=5, p=3, **kw):
    return OCP(
        model,
        0.01,
        T,
        np.eye(model.nx),
        0.1 * np.eye(model.nu),
        parameterization=Parameterization.make("linear", T, p),
        **kw,
    )


def _random_affine(n, m, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, n)), rng.normal(size=(n, m)), rng.normal(size=n), rng.normal(size=n)


def test_sparse_matches_paper_T5_p3_A():
    n, m = 2, 1
    ocp = _ocp(random_lti(0, n, m))
    Ad, Bd, wd, x0 = _random_affine(n, m)
    qp = SparseQP(ocp).build(Ad, Bd, wd, x0, np.zeros(n))
    I, Z, B, h = np.eye(n), np.zeros((n, n)), Bd, 0.5 * Bd
    zb = np.zeros((n, m))
    # The paper's A for T=5, p=3 without its last (w_d) column, which moves to the right-hand side.
    paper = np.block(
        [
            [-I, Z, Z, Z, Z, Z, zb, zb, zb],
            [Ad, -I, Z, Z, Z, Z, B, zb, zb],
            [Z, Ad, -I, Z, Z, Z, h, h, zb],
            [Z, Z, Ad, -I, Z, Z, zb, B, zb],
            [Z, Z, Z, Ad, -I, Z, zb, h, h],
            [Z, Z, Z, Z, Ad, -I, zb, zb, B],
        ]
    )
    np.testing.assert_array_equal(qp.A.toarray(), paper)
    np.testing.assert_array_equal(qp.b, np.r_[-x0, np.tile(-wd, 5)])


def test_condensed_matches_paper_T5_p3_S():
    n, m = 3, 2
    ocp = _ocp(random_lti(1, n, m))
    Ad, Bd, wd, x0 = _random_affine(n, m, 1)
    S, v = CondensedQP(ocp).prediction(Ad, Bd, wd, x0)
    A2, A3, A4, I = Ad @ Ad, Ad @ Ad @ Ad, np.linalg.matrix_power(Ad, 4), np.eye(n)
    Zb = np.zeros((n, m))
    paper = np.block(
        [
            [Bd, Zb, Zb],
            [(Ad + I / 2) @ Bd, Bd / 2, Zb],
            [(A2 + Ad / 2) @ Bd, (Ad / 2 + I) @ Bd, Zb],
            [(A3 + A2 / 2) @ Bd, (A2 / 2 + Ad + I / 2) @ Bd, Bd / 2],
            [(A4 + A3 / 2) @ Bd, (A3 / 2 + A2 + Ad / 2) @ Bd, (Ad / 2 + I) @ Bd],
        ]
    )
    np.testing.assert_allclose(S, paper, rtol=1e-13, atol=1e-13)
    # v does not depend on the parameterization: A_d^k x0 + Σ A_d^i w_d.
    xs, x = [], x0
    for _ in range(5):
        x = Ad @ x + wd
        xs.append(x)
    np.testing.assert_allclose(v, np.concatenate(xs), rtol=1e-13, atol=1e-12)


def _first_solution(ocp, form, x0, goal, qp="proxqp"):
    sol = LinearMPC(ocp, form=form, qp=qp).solve(x0, goal)
    assert sol.ok, sol.raw_status
    return sol


CASES = [("pendulum:linear", s) for s in range(3)] + [("pendulum", s) for s in range(3)]


@pytest.mark.parametrize("knots", [None, 2, 5, 17])
@pytest.mark.parametrize("name,seed", CASES)
def test_sparse_equals_condensed_pendulum(name, seed, knots):
    problem = make(name)
    ocp = problem.ocp(knots=knots)
    x0, goal = problem.sample(seed)
    s, c = _first_solution(ocp, "sparse", x0, goal), _first_solution(ocp, "condensed", x0, goal)
    scale = max(1.0, np.abs(c.knots).max())
    np.testing.assert_allclose(s.knots, c.knots, atol=1e-6 * scale)
    np.testing.assert_allclose(s.x_pred, c.x_pred, atol=1e-6 * max(1.0, np.abs(c.x_pred).max()))


@pytest.mark.parametrize("knots", [None, 3, 8])
@pytest.mark.parametrize("seed", range(4))
def test_sparse_equals_condensed_random_lti_active_bounds(seed, knots):
    model = random_lti(seed, 4, 2)
    T = 20
    ocp = OCP(
        model,
        0.05,
        T,
        np.eye(4) * 10,
        0.01 * np.eye(2),
        u_min=-0.5,
        u_max=0.5,
        parameterization=Parameterization.make("linear", T, knots),
    )
    rng = np.random.default_rng(100 + seed)
    x0, goal = rng.normal(size=4) * 3, rng.normal(size=4) * 3
    for qp in ("proxqp", "osqp"):
        s, c = _first_solution(ocp, "sparse", x0, goal, qp), _first_solution(ocp, "condensed", x0, goal, qp)
        assert np.isclose(np.abs(c.knots), 0.5, atol=1e-6).any(), "input bounds should be active"
        np.testing.assert_allclose(s.knots, c.knots, atol=1e-6)


@pytest.mark.parametrize("form", ["sparse", "condensed"])
def test_p_equal_T_reproduces_traditional(form):
    problem = make("pendulum")
    x0, goal = problem.sample(7)
    trad = _first_solution(problem.ocp(), form, x0, goal)
    full = _first_solution(problem.ocp(knots=problem.horizon), form, x0, goal)
    np.testing.assert_allclose(full.knots, trad.knots, atol=1e-9)


def test_state_bounds_respected_by_both_forms():
    problem = make("pendulum:linear")
    x0, goal = np.array([0.0, 0.0]), np.array([2.0, 0.0])
    ocp = problem.ocp(knots=5, x_min=[-np.inf, -3.0], x_max=[np.inf, 3.0])
    for form in ("sparse", "condensed"):
        sol = _first_solution(ocp, form, x0, goal)
        assert sol.x_pred[:, 1].max() <= 3.0 + 1e-6
    s, c = (_first_solution(ocp, f, x0, goal) for f in ("sparse", "condensed"))
    np.testing.assert_allclose(s.knots, c.knots, atol=1e-6)

"""Bases beyond piecewise linear (issue 49 item 4): the clamped cubic B-spline and a user-supplied basis, checked
against independent evaluations and used by every controller (QP forms, IPOPT, the sampling kernels, RTI, C step)."""

from __future__ import annotations

import numpy as np
import pytest

from ocpkit import solvers
from ocpkit.codegen.kernels.rollout import Rollout, SparseRows
from ocpkit.model.parameterization import Parameterization
from ocpkit.problems import make
from ocpkit.solvers.qp import LinearMPC

from conftest import smooth_basis


def _kinds(T, p):
    return {"bspline": Parameterization.bspline(T, p), "custom": Parameterization.custom(smooth_basis(T, p))}


@pytest.mark.parametrize("T, p, degree", [(50, 5, 3), (10, 4, 3), (30, 30, 3), (20, 7, 2), (13, 6, 1), (40, 12, 5)])
def test_bspline_basis_is_de_boor(T, p, degree):
    """Each column is the B-spline basis function of the clamped uniform knot vector, evaluated by SciPy's de Boor
    recursion at t_k = k/(T−1); rows sum to one, entries are ≥ 0 and the ends are the first and last knot."""
    BSpline = pytest.importorskip("scipy.interpolate").BSpline
    par = Parameterization.bspline(T, p, degree)
    t = np.r_[np.zeros(degree), np.linspace(0, 1, p - degree + 1), np.ones(degree)]
    s = np.linspace(0, 1, T)
    expected = np.column_stack([BSpline(t, np.eye(p)[j], degree, extrapolate=False)(s) for j in range(p)])
    expected[-1] = np.eye(p)[-1]  # SciPy's half-open last span leaves t = 1 at zero; the clamped end is U_{p−1}
    np.testing.assert_allclose(par.basis, expected, atol=1e-14)
    assert par.kind == "bspline" and par.convex and (par.horizon, par.knots) == (T, p)
    np.testing.assert_allclose(par.basis.sum(axis=1), 1.0, atol=1e-14)
    assert np.count_nonzero(par.basis, axis=1).max() <= degree + 1
    assert Parameterization.make("bspline", T, p).basis.tobytes() == Parameterization.bspline(T, p).basis.tobytes()


def test_bspline_and_custom_arguments_are_checked():
    with pytest.raises(ValueError, match="knots must be >= degree \\+ 1 = 4"):
        Parameterization.bspline(50, 3)
    with pytest.raises(ValueError, match="knots must be <= horizon"):
        Parameterization.bspline(5, 6)
    with pytest.raises(ValueError, match="degree must be >= 1"):
        Parameterization.bspline(50, 5, 0)
    with pytest.raises(TypeError, match="degree must be an integer"):
        Parameterization.bspline(50, 5, 2.5)
    with pytest.raises(ValueError, match="2-D T×p"):
        Parameterization.custom(np.ones(5))
    with pytest.raises(ValueError, match="2-D T×p"):
        Parameterization.custom(np.ones((4, 0)))
    with pytest.raises(ValueError, match="at most as many columns"):
        Parameterization.custom(np.ones((3, 4)))
    with pytest.raises(ValueError, match="finite"):
        Parameterization.custom(np.where(np.eye(4) > 0, np.nan, 0.0))
    with pytest.raises(ValueError, match="full column rank 3, got rank 2"):
        Parameterization.custom(np.c_[np.ones(6), np.arange(6.0), np.arange(6.0) + 1])
    with pytest.raises(TypeError, match="numeric"):
        Parameterization.custom([["a", "b"]])
    with pytest.raises(ValueError, match="parameterization must be one of"):
        Parameterization.make("custom", 10, 3)


def test_custom_basis_knots_inputs_and_shift():
    """u = φU; the warm-start shift is the least-squares fit (its pseudo-inverse) of the advanced inputs."""
    B = np.random.default_rng(0).normal(size=(12, 4))
    par = Parameterization.custom(B)
    assert par.kind == "custom" and not par.convex and Parameterization.custom(smooth_basis(12, 4)).convex
    U = np.random.default_rng(1).normal(size=(4, 2))
    np.testing.assert_allclose(par.inputs(U), B @ U, atol=1e-14)
    advanced = np.r_[(B @ U)[1:], (B @ U)[-1:]]
    np.testing.assert_allclose(par.shift(U), np.linalg.lstsq(B, advanced, rcond=None)[0], atol=1e-12)


def test_a_non_convex_basis_refuses_input_bounds_and_runs_without_them():
    """Knot bounds bound u = φU only for convex-combination rows: otherwise input bounds are refused, and without
    them LinearMPC's two forms agree with the basis."""
    problem = make("pendulum")
    T, p = 30, 4
    rng = np.random.default_rng(2)
    basis = Parameterization.custom(smooth_basis(T, p) + 0.3 * rng.normal(size=(T, p)))
    with pytest.raises(ValueError, match="input bounds need a parameterization whose rows are convex"):
        problem.ocp(parameterization=basis)
    ocp = problem.ocp(parameterization=basis, u_min=[-np.inf], u_max=[np.inf])
    x, goal = problem.sample(0)
    a = LinearMPC(ocp, form="condensed", native=False, eps=1e-12).solve(x, goal)
    b = LinearMPC(ocp, form="sparse", native=False, eps=1e-12).solve(x, goal)
    assert a.ok and b.ok
    np.testing.assert_allclose(b.knots, a.knots, atol=1e-6)


def test_problem_ocp_takes_a_parameterization():
    problem = make("pendulum")
    par = Parameterization.custom(smooth_basis(20, 4))
    ocp = problem.ocp(parameterization=par)
    assert ocp.parameterization is par and (ocp.horizon, ocp.knots) == (20, 4)
    with pytest.raises(ValueError, match="knots=5 differs from the parameterization's 4"):
        problem.ocp(parameterization=par, knots=5)
    with pytest.raises(ValueError, match="horizon=30 differs"):
        problem.ocp(parameterization=par, horizon=30)


@pytest.mark.parametrize("kind", ["bspline", "custom"])
@pytest.mark.parametrize("name", ["pendulum", "nlink:3"])
def test_sparse_and_condensed_qps_share_the_optimum(kind, name):
    """The large- and small-matrix transcriptions (different S, pieces of two steps for these bases) solve to the
    same knots, about the input goal and along the plan, with active input bounds."""
    problem = make(name)
    ocp = problem.ocp(parameterization=_kinds(50, 5)[kind])
    for seed in (0, 1):
        x, goal = problem.sample(seed)
        a = LinearMPC(ocp, form="condensed", native=False, eps=1e-12)
        b = LinearMPC(ocp, form="sparse", native=False, eps=1e-12)
        for _ in range(3):
            sa, sb = a.solve(x, goal), b.solve(x, goal)
            assert sa.ok and sb.ok, (sa.raw_status, sb.raw_status)
            np.testing.assert_allclose(sb.knots, sa.knots, atol=1e-5 * max(1.0, np.abs(sa.knots).max()))
            x = np.asarray(ocp.discrete()(x, sa.u)).ravel()


@pytest.mark.parametrize("kind", ["bspline", "custom"])
def test_ipopt_and_the_qp_agree_on_a_linear_problem(kind):
    """On a linear model the NLP is the QP: IPOPT (the OCP's basis substituted in CasADi) finds the QP's knots."""
    problem = make("pendulum:linear")
    ocp = problem.ocp(parameterization=_kinds(40, 5)[kind])
    x, goal = problem.sample(3)
    qp = LinearMPC(ocp, native=False, eps=1e-12).solve(x, goal)
    nlp = solvers.make("ipopt", ocp, options={"tol": 1e-10}).solve(x, goal)
    assert qp.ok and nlp.ok
    np.testing.assert_allclose(nlp.knots, qp.knots, atol=1e-6)


@pytest.mark.usefixtures("taichi_arch")
@pytest.mark.parametrize("kind", ["bspline", "custom"])
def test_taichi_rollout_of_the_basis_matches_numpy(kind):
    """The kernels read the basis as sparse rows: 4 nonzeros for the cubic B-spline, all p for the dense basis."""
    problem = make("nlink:2")
    ocp = problem.ocp(parameterization=_kinds(30, 6)[kind])
    rows = SparseRows(ocp.parameterization.basis)
    assert rows.width == (4 if kind == "bspline" else 6)
    rng = np.random.default_rng(4)
    x0, goal = problem.sample(4)
    U = rng.uniform(ocp.u_min, ocp.u_max, size=(16, ocp.knots, ocp.nu))
    F = ocp.discrete()
    engine = Rollout(ocp, 16, dynamics="nonlinear")
    engine.load(x0, goal)
    expected = []
    for knots in U:
        x, J = x0.copy(), 0.0
        for u in ocp.parameterization.basis @ knots:
            J += float(ocp.cost.stage(x, u, goal))
            x = np.asarray(F(x, u)).ravel()
        expected.append(J + float(ocp.cost.terminal(x, goal)))
    np.testing.assert_allclose(engine.evaluate(U)[0], expected, rtol=1e-10)

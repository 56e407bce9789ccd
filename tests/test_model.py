import casadi as ca
import control
import numpy as np
import pytest

from conftest import random_lti
from ocpkit.model import Model
from ocpkit.problems import make


def test_linear_model_uses_exact_zoh_matching_python_control():
    model = random_lti(3, 4, 2)
    assert model.linear
    A, B = (np.asarray(M) for M in ca.Function("j", [model.x, model.u], [ca.jacobian(model.xdot, model.x),
                                                                         ca.jacobian(model.xdot, model.u)])(0, 0))
    sysd = control.c2d(control.ss(A, B, np.eye(4), 0), 0.05, method="zoh")
    Ad, Bd, wd = (np.asarray(M) for M in model.affine(0.05)(np.zeros(4), np.zeros(2)))
    np.testing.assert_allclose(Ad, sysd.A, atol=1e-12)
    np.testing.assert_allclose(Bd, sysd.B, atol=1e-12)


def test_rk4_converges_to_exact_zoh_on_linear_model():
    model = random_lti(4, 3, 1)
    x, u = np.array([1.0, -2.0, 0.5]), np.array([0.3])
    exact = np.asarray(model.discrete(0.1)(x, u)).ravel()
    err = [np.abs(np.asarray(model.rk4(0.1, s)(x, u)).ravel() - exact).max() for s in (1, 2, 4)]
    assert err[0] < 1e-3 and err[1] < err[0] / 10 and err[2] < err[1] / 10  # fourth order: ÷16 per halving


def test_affine_model_is_first_order_expansion_of_discrete():
    model = make("pendulum").plant()
    F, aff = model.discrete(0.01), model.affine(0.01)
    xb, ub = np.array([0.7, -0.3]), np.array([1.2])
    Ad, Bd, wd = (np.asarray(M) for M in aff(xb, ub))
    np.testing.assert_allclose(Ad @ xb + Bd @ ub + wd.ravel(), np.asarray(F(xb, ub)).ravel(), atol=1e-14)
    dx, du = 1e-6 * np.array([1.0, -2.0]), np.array([1e-6])
    lin = Ad @ (xb + dx) + Bd @ (ub + du) + wd.ravel()
    np.testing.assert_allclose(lin, np.asarray(F(xb + dx, ub + du)).ravel(), atol=1e-11)


def test_pendulum_error_multiplier_only_in_controller_model():
    p = make("pendulum")
    assert p.plant() is p.model(1.0)
    x, u = np.array([0.4, 0.1]), np.array([0.5])
    f = lambda m: np.asarray(m.f(x, u)).ravel()
    np.testing.assert_array_equal(f(p.model(1.0)), f(p.plant()))
    assert not np.allclose(f(p.model(1.3)), f(p.plant()))
    # m l² q̈ + b q̇ + m g l sin q = τ with m, l scaled by 1.3.
    m, l = 1.3, 0.65
    assert f(p.model(1.3))[1] == pytest.approx((0.5 - 0.1 * 0.1 - m * 9.81 * l * np.sin(0.4)) / (m * l * l))


def test_model_validation():
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    with pytest.raises(ValueError, match="xdot must have the shape"):
        Model("m", x, u, x[0])
    with pytest.raises(ValueError, match="other than x and u"):
        Model("m", x, u, x + ca.SX.sym("k"))
    with pytest.raises(TypeError, match="x must be a casadi.SX"):
        Model("m", np.zeros(2), u, x)
    m = Model("m", x, u, ca.vertcat(x[1], u))
    for bad in (0, -0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="dt must be finite and > 0"):
            m.discrete(bad)
    with pytest.raises(ValueError, match="substeps must be an integer"):
        m.rk4(0.1, 0)


def test_compiled_affine_model_equals_casadi(tmp_path, monkeypatch):
    monkeypatch.setenv("OCPKIT_CACHE_DIR", str(tmp_path))
    problem = make("pendulum")
    plain, compiled = problem.ocp(knots=3), problem.ocp(knots=3, compiled=True)
    x, u = np.array([0.4, -1.0]), np.array([2.0])
    for a, b in zip(plain.affine()(x, u), compiled.affine()(x, u)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert len(list((tmp_path / "compiled").glob("*/*.so"))) == 1
    # A second OCP of the same model loads the cached library instead of compiling again.
    again = problem.ocp(knots=3, compiled=True).affine()
    assert len(list((tmp_path / "compiled").glob("*/*.so"))) == 1 and again.name() == compiled.affine().name()

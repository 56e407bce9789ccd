import casadi as ca
import control
import numpy as np
import pytest

from conftest import random_lti
from ocpkit.model.dynamics import Model
from ocpkit.problems import make


def test_linear_model_uses_exact_zoh_matching_python_control():
    model = random_lti(3, 4, 2)
    assert model.linear
    A, B = (
        np.asarray(M)
        for M in ca.Function(
            "j", [model.x, model.u], [ca.jacobian(model.xdot, model.x), ca.jacobian(model.xdot, model.u)]
        )(0, 0)
    )
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

    def f(m):
        return np.asarray(m.f(x, u)).ravel()

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


def test_second_order_state_is_read_from_the_expression():
    x, u = ca.SX.sym("x", 4), ca.SX.sym("u", 2)
    assert make("puma560").model().second_order == 6 and make("pendulum").plant().second_order == 1
    assert Model("m", x, u, ca.vertcat(x[2:], u - x[:2])).second_order == 2
    assert Model("m", x, u, ca.vertcat(2 * x[2:], u)).second_order is None  # ẋ[:2] is not q̇ itself
    assert Model("m", x, u, ca.vertcat(x[3], x[2], u)).second_order is None  # … nor in its order
    y = ca.SX.sym("y", 3)
    assert Model("m", y, u[:1], ca.vertcat(y[1:], u[0])).second_order is None  # odd state size


def test_euler_steps_by_hand():
    """Semi-implicit Euler for x = [q, q̇] (the new velocity moves the position), explicit Euler otherwise."""
    pendulum = make("pendulum").plant()
    x, u, h = np.array([0.7, -0.3]), np.array([1.2]), 0.01
    qdd = np.asarray(pendulum.f(x, u)).ravel()[1]
    qd = x[1] + h * qdd
    np.testing.assert_array_equal(np.asarray(pendulum.discrete(h, 1, "euler")(x, u)).ravel(), [x[0] + h * qd, qd])
    z, v = ca.SX.sym("z", 3), ca.SX.sym("v", 1)
    model = Model("m", z, v, ca.vertcat(ca.sin(z[1]), z[2] * z[0], v - z[0] ** 2))
    x, u = np.array([0.3, -1.0, 2.0]), np.array([0.5])
    np.testing.assert_array_equal(
        np.asarray(model.discrete(h, 1, "euler")(x, u)).ravel(), x + h * np.asarray(model.f(x, u)).ravel()
    )
    half = x + h / 2 * np.asarray(model.f(x, u)).ravel()  # two sub-steps of h/2
    np.testing.assert_allclose(
        np.asarray(model.discrete(h, 2, "euler")(x, u)).ravel(),
        half + h / 2 * np.asarray(model.f(half, u)).ravel(),
        rtol=1e-15,
    )


def test_euler_is_first_order_and_rk4_fourth():
    model = make("nlink:3").plant()
    x, u, dt = np.array([0.5, -1.0, 0.8, 2.0, -1.0, 0.5]), np.array([1.0, -0.5, 0.2]), 0.02
    exact = np.asarray(model.rk4(dt, 64)(x, u)).ravel()
    err = {
        i: [np.abs(np.asarray(model.discrete(dt, s, i)(x, u)).ravel() - exact).max() for s in (2, 4)]
        for i in ("euler", "rk4")
    }
    # over the step dt, s sub-steps of local error O(h²) (Euler) or O(h⁵) (RK4): ÷2 and ÷16 per halving of h
    assert 1.8 < err["euler"][0] / err["euler"][1] < 2.2
    assert 14 < err["rk4"][0] / err["rk4"][1] < 18


def test_linear_model_keeps_exact_zoh_whatever_the_integrator():
    model = random_lti(2, 3, 1)
    x, u = np.array([0.2, -1.0, 0.4]), np.array([0.7])
    for a, b in zip(model.affine(0.05, 1, "euler")(x, u), model.affine(0.05)(x, u)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(
        np.asarray(model.discrete(0.05, 3, "euler")(x, u)), np.asarray(model.discrete(0.05)(x, u))
    )


def test_integrator_option_of_model_ocp_and_problem():
    problem = make("pendulum")
    model = problem.model()
    for bad in ("rk45", "Euler", None, 4):
        with pytest.raises(ValueError, match="integrator must be one of"):
            model.discrete(0.01, 1, bad)
        with pytest.raises(ValueError, match="integrator must be one of"):
            model.affine(0.01, 1, bad)
        with pytest.raises(ValueError, match="integrator must be one of"):
            problem.ocp(knots=3, integrator=bad)
    rk4, euler = problem.ocp(knots=3), problem.ocp(knots=3, integrator="euler", substeps=2)
    assert rk4.integrator == "rk4" and "integrator" not in repr(rk4)
    assert euler.integrator == "euler" and "integrator='euler'" in repr(euler)
    assert euler.discrete() is model.discrete(0.01, 2, "euler") and rk4.discrete() is model.rk4(0.01, 1)
    assert euler.affine() is model.affine(0.01, 2, "euler")
    x, u = np.array([0.4, -1.0]), np.array([2.0])
    assert not np.allclose(np.asarray(euler.discrete()(x, u)), np.asarray(rk4.discrete()(x, u)))
    assert problem.plant().rk4(0.01, 10) is problem.model().rk4(0.01, 10)  # the plant: RK4, whatever the OCP

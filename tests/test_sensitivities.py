"""The affine model's derivatives against independent references: pinocchio's analytical ABA derivatives
(computeABADerivatives, C++) for the continuous Jacobians of :attr:`Model.jacobian`, and CasADi's own Jacobian of the
discrete step for the sensitivities that :meth:`Model.affine` propagates (RK4 and Euler)."""

from __future__ import annotations

import inspect

import casadi as ca
import numpy as np
import pinocchio as pin
import pytest

from ocpkit.model.dynamics import INTEGRATORS, Model
from ocpkit.model.problem import URDFRobot
from ocpkit.problems import make
from ocpkit.problems.panda import FINGERS, urdf_path as panda_urdf
from ocpkit.model.rigid_body import Chain

# forward_dynamics smooths Coulomb friction as f tanh(q̇ / v_f); the problems use its default v_f
FRICTION_VELOCITY = inspect.signature(Chain.forward_dynamics).parameters["friction_velocity"].default


def _problem(spec: str):
    # The Panda's URDF has no Coulomb friction: this one has, so that its q̇-derivative is checked too.
    if spec == "panda+friction":
        return URDFRobot(panda_urdf(), locked_joints=FINGERS, friction=0.4, name="panda")
    return make(spec)


def _state(problem, seed: int):
    """A sampled configuration with random velocities (so that Coriolis, damping and friction act) and inputs."""
    rng = np.random.default_rng(seed)
    x0, _ = problem.sample(seed)
    n = x0.size // 2
    return np.r_[x0[:n], rng.uniform(-1.0, 1.0, n)], rng.uniform(-5.0, 5.0, n)


def _close(ours, ref, what):
    np.testing.assert_allclose(ours, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max(), err_msg=what)


@pytest.mark.parametrize("spec", ["puma560", "nlink:3", "nlink:7", "panda", "panda+friction"])
def test_continuous_jacobians_equal_pinocchio_aba_derivatives(spec):
    """Our SX forward-mode Jacobian of the symbolic ABA equals pinocchio's analytical derivatives to 1e-9 relative.

    pinocchio's ABA has the armature but no damping or friction: ours is q̈ = ABA(q, q̇, τ') with
    τ' = τ − b q̇ − f tanh(q̇ / v_f), so pinocchio is evaluated at τ' and the chain rule through τ' is added exactly:
    ∂q̈/∂q̇ = ∂ABA/∂q̇ − M⁻¹ diag(b + f sech²(q̇ / v_f) / v_f); ∂q̈/∂q and ∂q̈/∂τ = M⁻¹ need nothing."""
    problem = _problem(spec)
    model, chain = problem.model(), problem.chain
    b = chain.coefficients(problem.damping, "damping")
    f = chain.coefficients(getattr(problem, "friction", 0.0), "friction")
    n = chain.n
    data = problem.pin_model.createData()
    for seed in range(3):
        x, tau = _state(problem, seed)
        q, qd = x[:n], x[n:]
        tau_p = tau - b * qd - f * np.tanh(qd / FRICTION_VELOCITY)
        dq, dv, minv = pin.computeABADerivatives(problem.pin_model, data, q, qd, tau_p)
        dv = dv - minv @ np.diag(b + f / FRICTION_VELOCITY / np.cosh(qd / FRICTION_VELOCITY) ** 2)
        xdot, fx, fu = (np.asarray(v, dtype=float) for v in model.jacobian(x, tau))
        _close(xdot[n:].ravel(), pin.aba(problem.pin_model, data, q, qd, tau_p), f"{spec} q̈")
        _close(fx[n:, :n], dq, f"{spec} ∂q̈/∂q")
        _close(fx[n:, n:], dv, f"{spec} ∂q̈/∂q̇")
        _close(fu[n:], minv, f"{spec} ∂q̈/∂τ")
        np.testing.assert_array_equal(fx[:n], np.hstack([np.zeros((n, n)), np.eye(n)]))
        np.testing.assert_array_equal(fu[:n], 0.0)


def _first_order_model() -> Model:
    """A nonlinear model that is not x = [q, q̇]: explicit Euler applies."""
    x, u = ca.SX.sym("x", 3), ca.SX.sym("u", 2)
    return Model(
        "tank",
        x,
        u,
        ca.vertcat(-ca.sqrt(1 + x[0] ** 2) + u[0], x[0] * x[2] - ca.sin(x[1]), u[1] * ca.cos(x[0]) - 0.3 * x[2]),
    )


@pytest.mark.parametrize("integrator", INTEGRATORS)
@pytest.mark.parametrize("spec", ["puma560", "nlink:3", "tank"])
def test_affine_model_is_the_jacobian_of_the_discrete_step(spec, integrator):
    """A_d, B_d from the propagated sensitivities equal CasADi's Jacobian of :meth:`Model.discrete` (AD through the
    step as a whole) to 1e-9 relative, and A_d x̄ + B_d ū + w_d = F(x̄, ū)."""
    if spec == "tank":
        model, dt, rng = _first_order_model(), 0.05, np.random.default_rng(0)
        points = [(rng.normal(size=3), rng.normal(size=2)) for _ in range(3)]
        assert model.second_order is None
    else:
        problem = make(spec)
        model, dt = problem.model(), problem.dt
        points = [_state(problem, seed) for seed in range(3)]
        assert model.second_order == model.nx // 2
    X, U = ca.MX.sym("x", model.nx), ca.MX.sym("u", model.nu)
    for substeps in (1, 2):
        F = model.discrete(dt, substeps, integrator)
        reference = ca.Function("step_jacobian", [X, U], [ca.jacobian(F(X, U), X), ca.jacobian(F(X, U), U)])
        affine = model.affine(dt, substeps, integrator)
        for x, u in points:
            Ad, Bd, wd = (np.asarray(v, dtype=float) for v in affine(x, u))
            A_ref, B_ref = (np.asarray(v, dtype=float) for v in reference(x, u))
            _close(Ad, A_ref, f"{spec} {integrator} A_d")
            _close(Bd, B_ref, f"{spec} {integrator} B_d")
            _close(Ad @ x + Bd @ u + wd.ravel(), np.asarray(F(x, u), dtype=float).ravel(), f"{spec} w_d")


def test_integrator_benchmark_closed_loops_agree(tmp_path, monkeypatch):
    """The benchmark's closed loops: RTI predicting with Euler steers the plant (RK4) about as well as with RK4."""
    from ocpkit.benchmarks.sensitivities import bench_integrators

    monkeypatch.setenv("OCPKIT_CACHE_DIR", str(tmp_path))
    (row,) = bench_integrators(["nlink:2"], seeds=(0,), steps=20, horizon=20, methods=("rti",), out=lambda *a: None)
    assert row["steps"] == 20 and row["rti rk4 fallbacks"] == row["rti euler fallbacks"] == 0
    assert 0.98 < row["rti e/r"] < 1.02

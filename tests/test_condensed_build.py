"""CondensedQP.build against a straightforward reference: S and v by stepping the model, P = SᵀQ̄S + φᵀφ⊗R."""

import numpy as np
import pytest

from conftest import random_lti
from ocpkit.model.ocp import OCP
from ocpkit.model.parameterization import Parameterization
from ocpkit.qp.transcription import CondensedQP


def _reference(ocp, Ad, Bd, wd, x0, goal):
    """P, q and [x_1 … x_T] = S z + v from a plain forward simulation, one column of S per knot entry."""
    n, m, T, p = ocp.nx, ocp.nu, ocp.horizon, ocp.knots
    phi = ocp.parameterization.basis
    per_stage = Ad.ndim == 3

    def rollout(x, U, affine):
        xs = []
        for k in range(T):
            A, B, w = (Ad[k], Bd[k], wd[k]) if per_stage else (Ad, Bd, wd)
            x = A @ x + B @ (phi[k] @ U) + (w if affine else 0.0)
            xs.append(x)
        return np.concatenate(xs)

    v = rollout(np.asarray(x0, float), np.zeros((p, m)), True)
    S = np.column_stack([rollout(np.zeros(n), np.eye(p * m)[i].reshape(p, m), False) for i in range(p * m)])
    Qbar = np.zeros((T * n, T * n))
    for k in range(T):
        Qbar[k * n : (k + 1) * n, k * n : (k + 1) * n] = ocp.Q if k < T - 1 else ocp.Q_terminal
    R_knots = np.kron(phi.T @ phi, ocp.R)
    ug = ocp.input_goal(goal)
    P = S.T @ Qbar @ S + R_knots
    q = S.T @ Qbar @ (v - np.tile(goal, T)) - np.kron(phi.sum(axis=0), ocp.R @ ug)
    return P, q, S, v


def _case(n, m, T, kind, p, Q, QT, seed, **kw):
    rng = np.random.default_rng(seed)
    ocp = OCP(
        random_lti(seed, n, m),
        0.01,
        T,
        Q,
        0.1 * np.eye(m),
        Q_terminal=QT,
        parameterization=Parameterization.make(kind, T, p),
        **kw,
    )
    scale = 1.0 / np.sqrt(n)  # a stable-ish A_d so long horizons stay finite
    Ad = np.eye(n) + scale * 0.3 * rng.normal(size=(n, n))
    return ocp, Ad, rng.normal(size=(n, m)), rng.normal(size=n), rng.normal(size=n), rng.normal(size=n)


def _weights(kind, n, rng):
    if kind == "diagonal":
        return np.diag(10.0 ** rng.uniform(-3, 3, n)), np.diag(10.0 ** rng.uniform(-3, 3, n))
    if kind == "zeros":  # Q ⪰ 0 with zero weights: no Q^½ change of coordinates
        d = rng.uniform(0.5, 2.0, n)
        d[::2] = 0.0
        return np.diag(d), 3 * np.diag(d)
    G = rng.normal(size=(n, n))
    return G @ G.T + np.eye(n), 2 * G @ G.T


@pytest.mark.parametrize("weights", ["diagonal", "zeros", "full"])
@pytest.mark.parametrize(
    "T,kind,p",
    [
        (20, "linear", 5),
        (23, "linear", 4),
        (17, "zoh", 5),
        (12, "identity", None),
        (30, "linear", 1),
        (9, "linear", 9),
        (40, "linear", 2),
    ],
)
def test_build_equals_reference(T, kind, p, weights):
    n, m = 5, 2
    rng = np.random.default_rng(T)
    Q, QT = _weights(weights, n, rng)
    ocp, Ad, Bd, wd, x0, goal = _case(n, m, T, kind, p, Q, QT, seed=T)
    tr = CondensedQP(ocp)
    P_ref, q_ref, S_ref, v_ref = _reference(ocp, Ad, Bd, wd, x0, goal)
    for _ in range(2):  # buffers reused from one build to the next
        qp = tr.build(Ad, Bd, wd, x0, goal)
        np.testing.assert_allclose(qp.P, P_ref, rtol=0, atol=1e-12 * np.abs(P_ref).max())
        np.testing.assert_allclose(qp.q, q_ref, rtol=0, atol=1e-12 * np.abs(q_ref).max())
        assert np.array_equal(qp.P, qp.P.T)
    z = rng.normal(size=tr.nz)
    X = tr.states(z, x0)
    np.testing.assert_allclose(X[0], x0)
    np.testing.assert_allclose(X[1:].ravel(), S_ref @ z + v_ref, rtol=0, atol=1e-12 * np.abs(v_ref).max())
    S, v = tr.prediction(Ad, Bd, wd, x0)
    np.testing.assert_allclose(S, S_ref, rtol=0, atol=1e-12 * np.abs(S_ref).max())
    np.testing.assert_allclose(v, v_ref, rtol=0, atol=1e-12 * np.abs(v_ref).max())


@pytest.mark.parametrize("soft", [False, True])
def test_state_bound_rows_equal_reference(soft):
    n, m, T = 4, 2, 25
    x_min, x_max = np.full(n, -np.inf), np.full(n, np.inf)
    x_min[1], x_max[1], x_max[3] = -1.0, 2.0, 0.5
    Q, QT = np.diag([1.0, 2.0, 0.5, 3.0]), np.diag([10.0, 2.0, 5.0, 3.0])
    ocp, Ad, Bd, wd, x0, goal = _case(n, m, T, "linear", 5, Q, QT, seed=3, x_min=x_min, x_max=x_max)
    tr = CondensedQP(ocp, soft=soft)
    qp = tr.build(Ad, Bd, wd, x0, goal)
    P_ref, q_ref, S_ref, v_ref = _reference(ocp, Ad, Bd, wd, x0, goal)
    nz = tr.nz
    np.testing.assert_allclose(qp.P[:nz, :nz], P_ref, rtol=0, atol=1e-12 * np.abs(P_ref).max())
    np.testing.assert_allclose(qp.q[:nz], q_ref, rtol=0, atol=1e-12 * np.abs(q_ref).max())
    rows = tr.x_rows
    k = len(tr.u_rows) + (tr.ns if soft else 0)  # box rows (and s ≥ 0) first
    np.testing.assert_allclose(qp.C[k:, :nz], S_ref[rows], rtol=0, atol=1e-12 * np.abs(S_ref).max())
    np.testing.assert_allclose(qp.l[k:], tr.x_lo - v_ref[rows], rtol=0, atol=1e-12 * np.abs(v_ref).max())
    np.testing.assert_allclose(qp.u[k:], tr.x_hi - v_ref[rows], rtol=0, atol=1e-12 * np.abs(v_ref).max())


def test_per_stage_models_equal_reference():
    n, m, T = 4, 2, 21
    Q, QT = np.diag([1.0, 2.0, 0.5, 3.0]), np.diag([10.0, 2.0, 5.0, 3.0])
    ocp, *_ = _case(n, m, T, "linear", 5, Q, QT, seed=5)
    rng = np.random.default_rng(5)
    Ad = np.eye(n) + 0.15 * rng.normal(size=(T, n, n))
    Bd, wd, x0, goal = rng.normal(size=(T, n, m)), rng.normal(size=(T, n)), rng.normal(size=n), rng.normal(size=n)
    qp = CondensedQP(ocp).build(Ad, Bd, wd, x0, goal)
    P_ref, q_ref, _, _ = _reference(ocp, Ad, Bd, wd, x0, goal)
    np.testing.assert_allclose(qp.P, P_ref, rtol=0, atol=1e-12 * np.abs(P_ref).max())
    np.testing.assert_allclose(qp.q, q_ref, rtol=0, atol=1e-12 * np.abs(q_ref).max())


def test_build_flops_counts_the_dominant_products():
    n, m, T, p = 5, 2, 20, 5
    Q = np.eye(n)
    ocp, *_ = _case(n, m, T, "linear", p, Q, Q, seed=1)
    tr = CondensedQP(ocp)
    K, L = n + 2 * m + 1, tr._lengths[-1]
    assert tr.build_flops() > 2 * n * K * K * (L - 1) + 2 * n * L * K * K  # doubling and Γ_L, then the pieces


def test_qp_check_names_the_problem_and_passes_large_finite_data():
    import copy

    Q = np.eye(5)
    ocp, Ad, Bd, wd, x0, goal = _case(5, 2, 20, "linear", 5, Q, Q, seed=2, u_min=-1.0, u_max=1.0)
    qp = CondensedQP(ocp).build(Ad, Bd, wd, x0, goal)
    assert qp.check() is None
    for field, value, message in [
        ("P", np.inf, "non-finite entries in P"),
        ("q", np.nan, "non-finite entries in q"),
        ("C", -np.inf, "non-finite entries in C"),
        ("l", np.nan, "NaN in the bounds"),
    ]:
        bad = copy.deepcopy(qp)
        getattr(bad, field).flat[1] = value
        assert message in bad.check()
    bad = copy.deepcopy(qp)
    bad.P[0, 1] += 1.0
    assert bad.check() == "P is not symmetric"
    big = copy.deepcopy(qp)  # finite entries whose sum overflows, and infinite bounds: nothing to report
    big.P[0, 1] = big.P[1, 0] = big.P[2, 2] = 1e308
    big.l, big.u = np.full_like(qp.l, -np.inf), np.full_like(qp.u, np.inf)
    with np.errstate(all="raise"):
        assert big.check() is None

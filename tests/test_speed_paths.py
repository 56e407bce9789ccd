"""The fast condensed build and the QP backends against a straightforward reference computation."""

import numpy as np
import pytest

from conftest import random_lti
from ocpkit.model.ocp import OCP
from ocpkit.model.parameterization import Parameterization
from ocpkit.problems import make
from ocpkit.solvers.qp import LinearMPC
from ocpkit.qp.transcription import CondensedQP


def _reference(tr, Ad, Bd, wd, x0, x_goal):
    """S by the plain recursion S_k = A S_{k−1} + φ_k ⊗ B, then P = SᵀQ̄S + φᵀφ⊗R, q = SᵀQ̄(v − x_goal) + q_knots."""
    T, n, p, m = tr.T, tr.n, tr.p, tr.m
    S, v = np.zeros((T, n, p * m)), np.zeros((T, n))
    phiB = np.einsum("kj,am->kajm", tr.phi, Bd).reshape(T, n, p * m)
    S[0], v[0] = phiB[0], Ad @ x0 + wd
    for k in range(1, T):
        S[k] = Ad @ S[k - 1] + phiB[k]
        v[k] = Ad @ v[k - 1] + wd
    QS = np.einsum("kab,kbc->kac", tr.Qs, S).reshape(T * n, -1)
    S = S.reshape(T * n, -1)
    return S.T @ QS + tr.R_knots, QS.T @ (v.ravel() - np.tile(x_goal, T)) + tr.q_knots(x_goal), S, v.ravel()


@pytest.mark.parametrize(
    "kind,T,p",
    [
        ("linear", 100, 5),
        ("linear", 50, 5),
        ("linear", 37, 4),
        ("zoh", 30, 7),
        ("identity", 12, None),
        ("linear", 1, 1),
        ("linear", 9, 9),
    ],
)
@pytest.mark.parametrize("seed", range(3))
def test_condensed_build_equals_reference(kind, T, p, seed):
    rng = np.random.default_rng(seed)
    n, m = 5, 3
    Q = np.diag(rng.uniform(0.5, 2, n)) if seed != 2 else (lambda M: M @ M.T)(rng.normal(size=(n, n)))
    ocp = OCP(
        random_lti(seed, n, m),
        0.05,
        T,
        Q,
        0.1 * np.eye(m),
        Q_terminal=10 * Q,
        u_min=-1,
        u_max=1,
        x_min=-5 * np.ones(n),
        x_max=5 * np.ones(n),
        parameterization=Parameterization.make(kind, T, p),
    )
    Ad, Bd = rng.normal(size=(n, n)) * 0.4 + np.eye(n), rng.normal(size=(n, m))
    wd, x0, xg = rng.normal(size=(3, n))
    tr = CondensedQP(ocp)
    qp = tr.build(Ad, Bd, wd, x0, xg)
    P, q, S, v = _reference(tr, Ad, Bd, wd, x0, xg)
    scale = np.abs(P).max()
    np.testing.assert_allclose(qp.P, P, atol=1e-12 * scale, rtol=0)
    np.testing.assert_allclose(qp.q, q, atol=1e-12 * max(scale, np.abs(q).max()), rtol=0)
    np.testing.assert_allclose(qp.C[len(qp.box) :], S[tr.x_rows], atol=1e-12 * np.abs(S).max(), rtol=0)
    np.testing.assert_allclose(qp.l[len(qp.box) :], tr.x_lo - v[tr.x_rows], atol=1e-12 * np.abs(v).max(), rtol=0)
    z = rng.normal(size=tr.nz)
    np.testing.assert_allclose(tr.states(z, x0)[1:].ravel(), S @ z + v, atol=1e-12 * np.abs(S @ z + v).max())


@pytest.mark.parametrize("seed", range(3))
def test_fast_step_same_optimum_as_reference_qp(seed):
    """nlink:4 with active input bounds: the ProxQP box path solves the reference QP's optimum."""
    import proxsuite

    problem = make("nlink:4")
    ocp = problem.ocp(horizon=60, knots=5)
    x0, goal = problem.sample(seed)
    ctrl = LinearMPC(ocp)
    sol = ctrl.solve(x0, goal)
    assert sol.ok and np.isclose(np.abs(sol.knots), problem.tau_max, atol=1e-6).any()
    P, q, _, _ = _reference(ctrl.transcription, *ctrl.affine_model(x0, goal, "goal"), x0, goal)
    s = proxsuite.proxqp.dense.QP(P.shape[0], 0, P.shape[0])
    s.settings.eps_abs, s.settings.verbose = 1e-10, False
    s.init(0.5 * (P + P.T), q, None, None, np.eye(P.shape[0]), np.full(P.shape[0], -2.0), np.full(P.shape[0], 2.0))
    s.solve()
    np.testing.assert_allclose(sol.knots.ravel(), s.results.x, atol=1e-6)


def test_proxqp_reuse_matches_fresh_solver_in_closed_loop():
    problem = make("nlink:3")
    ocp = problem.ocp(horizon=50, knots=5)
    x, goal = problem.sample(4)
    F = ocp.discrete()
    reused, fresh = LinearMPC(ocp), LinearMPC(ocp)
    for _ in range(15):
        a = reused.solve(x, goal)
        fresh._backend.reset()
        b = fresh.solve(x, goal)
        assert a.ok and b.ok
        np.testing.assert_allclose(a.knots, b.knots, atol=1e-6)
        x = np.asarray(F(x, a.u)).ravel()


@pytest.mark.parametrize("seed", range(3))
def test_hpipm_agrees_with_osqp_and_proxqp(seed):
    problem = make("nlink:2")
    ocp = problem.ocp(horizon=30)
    x0, goal = problem.sample(seed)
    sols = {qp: LinearMPC(ocp, form="sparse", qp=qp).solve(x0, goal) for qp in ("hpipm", "osqp", "proxqp")}
    assert all(s.ok for s in sols.values()), {k: s.raw_status for k, s in sols.items()}
    for qp in ("osqp", "proxqp"):
        np.testing.assert_allclose(sols["hpipm"].u, sols[qp].u, atol=1e-4)


def test_hpipm_needs_sparse_traditional():
    problem = make("nlink:2")
    with pytest.raises(ValueError, match="hpipm"):
        LinearMPC(problem.ocp(knots=5), form="sparse", qp="hpipm")
    with pytest.raises(ValueError, match="hpipm"):
        LinearMPC(problem.ocp(), form="condensed", qp="hpipm")


def test_bench_step_runs_every_solver_in_rounds():
    from ocpkit.benchmarks.step import BASE, PROXQP, PYTHON, VM, bench_step

    lines = []
    rows = bench_step(
        links=(1,), horizons=(10, 20), knots=3, steps=3, rounds=2, peers=False, busy=0, fresh=0, out=lines.append
    )
    assert {r["solver"] for r in rows} >= {
        BASE,
        PYTHON,
        PROXQP,
        VM,
        "ocpkit sparse traditional hpipm",
        "ocpkit sparse traditional osqp",
    }
    assert all(r["status"] == "success" and r["p25"] <= r["median"] <= r["p75"] for r in rows)
    assert [r["ratio"] for r in rows if r["solver"] == BASE] == [1.0, 1.0]
    parts = [r for r in rows if "flops" in r]  # the four condensed variants report their parts
    assert len(parts) == 8 and all(r["step"] == "Python" for r in parts)  # nlink:1: too small for the C step
    assert all(r["model"] + r["build"] + r["solve"] <= r["median"] * 1.5 for r in parts)
    assert all(0.0 <= r["rest"] < r["median"] for r in parts)  # the Python around the parts
    assert sum(" rest " in line for line in lines) == 8
    assert any("solve(T=20)/solve(T=10)" in line for line in lines)
    floors = [line for line in lines if line.startswith("  ") and "best step" in line]
    assert len(floors) == 2 and all("nlink:1" in line and "%" in line for line in floors)


def test_buffered_function_equals_casadi_call():
    import casadi as ca

    from ocpkit.numeric import BufferedFunction

    fn = make("nlink:3").ocp(knots=3).affine()  # A_d has structural zeros: its buffer holds nonzeros only
    assert not fn.sparsity_out(0).is_dense()
    call = BufferedFunction(fn)
    rng = np.random.default_rng(0)
    for _ in range(3):
        x, u = rng.normal(size=6), rng.normal(size=3)
        for got, expected in zip(call(x, u), fn(x, u)):
            np.testing.assert_array_equal(got, np.asarray(expected))
    a, b = call(x, u)[0], call(2 * x, u)[0]
    assert not np.array_equal(a, b)  # every call returns new arrays
    M = ca.SX.sym("M", 2, 2)
    matrix = ca.Function("f", [M], [M.T, ca.trace(M)])
    np.testing.assert_array_equal(BufferedFunction(matrix)(np.array([[1.0, 2.0], [3.0, 4.0]]))[0], [[1, 3], [2, 4]])
    with pytest.raises(TypeError, match="takes 2 arguments"):
        call(x)
    with pytest.raises(ValueError, match="'u'.*3 entries"):
        call(x, np.zeros(4))
    d = ca.SX.sym("d", ca.Sparsity.diag(2))
    sparse = ca.Function("s", [d], [ca.sum1(ca.sum2(d))])
    with pytest.raises(ValueError, match="sparse inputs"):
        BufferedFunction(sparse)

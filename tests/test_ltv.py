"""Linearization along the plan (LTV): per-stage affine models in both transcriptions and in LinearMPC."""

import numpy as np
import pytest
import scipy.sparse as sp

from conftest import random_lti
from ocpkit.model.ocp import OCP
from ocpkit.model.parameterization import Parameterization
from ocpkit.problems import make
from ocpkit.sim.simulate import simulate
from ocpkit.solvers.qp import LinearMPC
from ocpkit.qp.sparse import SparseQP
from ocpkit.qp.transcription import CondensedQP


def _ocp(model, T=7, p=3, kind="linear", dense_Q=False, bounds=True):
    n, m = model.nx, model.nu
    Q = np.eye(n)
    if dense_Q:
        M = np.random.default_rng(3).normal(size=(n, n))
        Q = M @ M.T + np.eye(n)
    kw = dict(x_min=-np.r_[2.0, np.full(n - 1, np.inf)], x_max=np.r_[2.0, np.full(n - 1, np.inf)]) if bounds else {}
    return OCP(
        model,
        0.01,
        T,
        Q,
        0.1 * np.eye(m),
        Q_terminal=3 * Q,
        u_min=-np.ones(m),
        u_max=np.ones(m),
        parameterization=Parameterization.make(kind, T, p),
        **kw,
    )


def _stages(n, m, T, seed):
    rng = np.random.default_rng(seed)
    return (np.eye(n) + 0.1 * rng.normal(size=(T, n, n)), rng.normal(size=(T, n, m)), 0.1 * rng.normal(size=(T, n)))


def _dense(qp):
    return [M.toarray() if sp.issparse(M) else np.asarray(M) for M in qp.stacked()]


@pytest.mark.parametrize("form", [SparseQP, CondensedQP])
@pytest.mark.parametrize("kind,p", [("linear", 3), ("zoh", 2), ("identity", 7)])
@pytest.mark.parametrize("soft", [False, True])
@pytest.mark.parametrize("dense_Q", [False, True])
def test_identical_stages_equal_the_lti_build(form, kind, p, soft, dense_Q):
    """Per-stage models that are all the same model give the one-model (LTI) QP: independent build paths."""
    n, m, T = 4, 2, 7
    ocp = _ocp(random_lti(0, n, m), T, p, kind, dense_Q)
    rng = np.random.default_rng(1)
    Ad, Bd, wd = np.eye(n) + 0.1 * rng.normal(size=(n, n)), rng.normal(size=(n, m)), rng.normal(size=n)
    x0, goal = rng.normal(size=n), rng.normal(size=n)
    tr = form(ocp, soft=soft)
    lti = _dense(tr.build(Ad, Bd, wd, x0, goal))
    ltv = _dense(tr.build(np.stack([Ad] * T), np.stack([Bd] * T), np.tile(wd, (T, 1)), x0, goal))
    for a, b in zip(lti, ltv):
        scale = max(1.0, np.abs(a[np.isfinite(a)]).max(initial=0.0))
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12 * scale)


@pytest.mark.parametrize("kind,p", [("linear", 3), ("identity", 7)])
def test_condensed_ltv_prediction_is_the_stage_by_stage_rollout(kind, p):
    n, m, T = 3, 2, 7
    ocp = _ocp(random_lti(1, n, m), T, p, kind)
    Ad, Bd, wd = _stages(n, m, T, 2)
    x0 = np.random.default_rng(4).normal(size=n)
    S, v = CondensedQP(ocp).prediction(Ad, Bd, wd, x0)
    for seed in range(3):
        U = np.random.default_rng(seed).normal(size=(p, m))
        us, x, xs = ocp.parameterization.inputs(U), x0, []
        for k in range(T):
            x = Ad[k] @ x + Bd[k] @ us[k] + wd[k]
            xs.append(x)
        np.testing.assert_allclose(S @ U.ravel() + v, np.concatenate(xs), rtol=1e-12, atol=1e-12)


def test_sparse_and_condensed_ltv_reach_the_same_optimum():
    """Random per-stage models: the two transcriptions' QPs (bounds active) have one minimizer."""
    import proxsuite

    n, m, T, p = 4, 2, 9, 4
    ocp = _ocp(random_lti(2, n, m), T, p)
    Ad, Bd, wd = _stages(n, m, T, 5)
    x0, goal = np.r_[1.5, 0.5, -0.3, 0.2], np.r_[-3.0, 1.0, 0.0, 0.0]  # goal beyond x_max: bounds bind
    knots = []
    for tr in (SparseQP(ocp), CondensedQP(ocp)):
        qp = tr.build(Ad, Bd, wd, x0, goal)
        H, g, A, b, C, l, u = (M.toarray() if sp.issparse(M) else M for M in (qp.P, qp.q, qp.A, qp.b, qp.C, qp.l, qp.u))
        solver = proxsuite.proxqp.dense.QP(qp.n, b.size, l.size)
        solver.settings.eps_abs, solver.settings.verbose = 1e-11, False
        solver.init(H, g, A if b.size else None, b if b.size else None, C, l, u)
        solver.solve()
        assert solver.results.info.status == proxsuite.proxqp.QPSolverOutput.PROXQP_SOLVED
        knots.append(tr.knots(np.array(solver.results.x)))
    assert np.abs(knots[0]).max() > 0.1 and np.isclose(np.abs(knots[0]).max(), 1.0)  # an input bound is active
    np.testing.assert_allclose(knots[0], knots[1], atol=1e-7)


def test_ltv_rejects_misshapen_stage_models():
    ocp = _ocp(random_lti(0, 4, 2), 7, 3)
    Ad, Bd, wd = _stages(4, 2, 6, 0)  # one stage short
    with pytest.raises(ValueError, match="per-stage affine model"):
        CondensedQP(ocp).build(Ad, Bd, wd, np.zeros(4), np.zeros(4))


def test_trajectory_linearization_of_a_linear_model_is_the_lti_controller():
    """A linear model has one affine model everywhere: along the plan or at x, the same steps."""
    prob = make("pendulum:linear")
    ocp = prob.ocp(knots=4)
    x0, goal = prob.sample(0)
    for form in ("condensed", "sparse"):
        lti = simulate(prob.plant(), LinearMPC(ocp, form=form), x0, goal, 0.3)
        ltv = simulate(prob.plant(), LinearMPC(ocp, form=form, linearization="trajectory"), x0, goal, 0.3)
        np.testing.assert_allclose(ltv.u, lti.u, atol=1e-6)


def test_affine_models_are_the_one_point_model_at_every_stage():
    prob = make("nlink:2")
    ocp = prob.ocp(knots=3)
    ctrl = LinearMPC(ocp, linearization="trajectory")
    rng = np.random.default_rng(0)
    xs, us = rng.normal(size=(ocp.horizon, ocp.nx)), rng.normal(size=(ocp.horizon, ocp.nu))
    A, B, w = ctrl.affine_models(xs, us)
    for k in (0, 7, ocp.horizon - 1):
        ref = [np.asarray(v, dtype=float) for v in ocp.affine()(xs[k], us[k])]
        np.testing.assert_allclose(A[k], ref[0], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(B[k], ref[1], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(w[k], ref[2].ravel(), rtol=1e-12, atol=1e-12)
    X = ctrl.rollout(xs[0], us)
    F = ocp.discrete()
    np.testing.assert_allclose(X[5], np.asarray(F(X[4], us[4])).ravel(), rtol=1e-12, atol=1e-12)


def test_compiled_and_threaded_per_stage_models_equal_the_sx_ones(tmp_path, monkeypatch):
    """The per-stage map of the compiled C affine model (ocp.compiled), serial or over threads, gives the SX
    model's (A_k, B_k, w_k), and the LTV controller built on it the same closed loop."""
    monkeypatch.setenv("OCPKIT_CACHE_DIR", str(tmp_path))
    prob = make("nlink:2")
    plain, compiled = prob.ocp(knots=3, compiled=False), prob.ocp(knots=3, compiled=True)
    rng = np.random.default_rng(3)
    xs, us = rng.normal(size=(plain.horizon, plain.nx)), rng.normal(size=(plain.horizon, plain.nu))
    ref = LinearMPC(plain, linearization="trajectory").affine_models(xs, us)
    fast = LinearMPC(compiled, linearization="trajectory")
    assert fast.ocp.affine().is_a("External")
    for threads in (1, 2, 1):  # serial, two threads, and back (the map is rebuilt when threads change)
        fast.threads = threads
        for a, b in zip(fast.affine_models(xs, us), ref):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-10)
    x0, goal = prob.sample(0)
    trajs = [
        simulate(prob.plant(), LinearMPC(ocp, linearization="trajectory"), x0, goal, 0.1) for ocp in (plain, compiled)
    ]
    np.testing.assert_allclose(trajs[1].u, trajs[0].u, rtol=0, atol=1e-10)


def test_default_per_stage_models_switch_to_the_compiled_map(tmp_path, monkeypatch):
    """The default OCP (compiled not given): the per-stage map runs on the VM until the background compile
    finishes, then on the compiled model by itself, with the SX model's numbers to 1e-10."""
    import ocpkit.model.ocp as ocp_module

    monkeypatch.setenv("OCPKIT_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(ocp_module, "BACKGROUND_MIN_INSTRUCTIONS", 0)
    prob = make("nlink:2")
    ocp = prob.ocp(knots=3)
    rng = np.random.default_rng(4)
    xs, us = rng.normal(size=(ocp.horizon, ocp.nx)), rng.normal(size=(ocp.horizon, ocp.nu))
    ref = LinearMPC(prob.ocp(knots=3, compiled=False), linearization="trajectory").affine_models(xs, us)
    ctrl = LinearMPC(ocp, linearization="trajectory")
    first = ctrl.affine_models(xs, us)  # on the VM or already switched: the same numbers either way
    assert ocp.affine() is not None and ocp._compiled_affine.wait(300) is not None
    for got in (first, ctrl.affine_models(xs, us)):
        for a, b in zip(got, ref):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-10)
    assert getattr(ctrl._affine_map[1]._buffer, "switched", True)  # a plain buffer: mapped after the compile


def test_sparse_and_condensed_ltv_controllers_agree_in_closed_loop():
    prob = make("nlink:2")
    ocp = prob.ocp(knots=4)
    x0, goal = prob.sample(1)
    trajs = [
        simulate(prob.plant(), LinearMPC(ocp, form=form, linearization="trajectory"), x0, goal, 0.2)
        for form in ("condensed", "sparse")
    ]
    assert all(t.fallbacks == 0 for t in trajs)
    np.testing.assert_allclose(trajs[0].u, trajs[1].u, atol=1e-5)


def test_cartpole_swing_up_needs_the_trajectory_linearization(cartpole):
    """From hanging (θ = π) to upright: linearized along the plan it swings up; linearized at x it cannot."""
    x0, goal = np.r_[0.0, np.pi, 0.0, 0.0], np.zeros(4)
    ocp = cartpole.ocp(knots=10)
    errors = {}
    for lin in ("goal", "trajectory"):
        traj = simulate(cartpole.plant(), LinearMPC(ocp, linearization=lin), x0, goal, 3.0)
        errors[lin] = np.abs(traj.x[-1] - goal).max()
    assert errors["trajectory"] <= 0.05
    assert errors["goal"] > 1.0

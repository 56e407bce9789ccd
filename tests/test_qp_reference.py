"""Issue 46 in LinearMPC and RTI: a goal window (stage k's terms towards row k), moving obstacles and a user's initial
guess in the condensed and sparse QPs (ocpkit.qp.transcription, sparse, task_rows), checked against a dense QP built
here from the per-stage goals, in closed loop against the held goal, and for no Function built as obstacles move."""

import casadi as ca
import numpy as np
import pytest

from ocpkit import problems
from ocpkit.codegen import compiled
from ocpkit.model.problem import GoalInputOCP
from ocpkit.model.reference import Reference
from ocpkit.model.task import reach
from ocpkit.qp.sparse import SparseQP
from ocpkit.qp.transcription import CondensedQP
from ocpkit.sim.simulate import simulate
from ocpkit.solvers.qp import LinearMPC
from ocpkit.solvers.rti import RealTimeIteration

N3 = problems.make("nlink:3")
X0 = np.array([0.1, -0.2, 0.3, 0.0, 0.1, 0.0])


def _ocp(**options):
    return N3.ocp(horizon=20, knots=5, compiled=False, **options)


def _moving(ocp, x0=X0, scale=0.3):
    """A goal window that moves: row k's joint angles x0 + scale·sin(k/4) per joint, rates its derivative."""
    k = np.arange(ocp.horizon + 1)[:, None]
    window = np.zeros((ocp.horizon + 1, ocp.ng))
    window[:, :3] = x0[:3] + scale * np.sin(k / 4 + np.arange(3))
    window[:, 3:6] = scale / 4 / ocp.dt * np.cos(k / 4 + np.arange(3))
    return window


def _controller(kind, ocp, **options):
    if kind == "rti":
        return RealTimeIteration(ocp, native=False, **options)
    form, qp = {"condensed": ("condensed", "daqp"), "sparse": ("sparse", "proxqp")}[kind]
    return LinearMPC(ocp, form=form, qp=qp, native=False, **options)


def _models(ocp, x0=X0, seed=0):
    """A one-model affine model about (x0, small u) and per-stage models along a rollout under random inputs."""
    rng = np.random.default_rng(seed)
    ctrl = LinearMPC(ocp, native=False, linearization="trajectory")
    us = 0.3 * rng.normal(size=(ocp.horizon, ocp.nu))
    xs = ctrl.rollout(x0, us)[:-1]
    lti = tuple(np.asarray(a) for a in ocp.affine()(x0, us[0]))
    return (lti[0], lti[1], lti[2].ravel()), ctrl.affine_models(xs, us)


def _prediction(ocp, Ad, Bd, wd, x0):
    """S (T·n, p·m), v (T·n) of x_{k+1} = A_k x_k + B_k u_k + w_k, u = (φ ⊗ I) z, by the plain recursion."""
    n, m, T = ocp.nx, ocp.nu, ocp.horizon
    stages = [(Ad, Bd, wd)] * T if np.ndim(Ad) == 2 else list(zip(Ad, Bd, wd))
    Phi = np.kron(ocp.parameterization.basis, np.eye(m))
    S, v = np.zeros((T * n, Phi.shape[1])), np.zeros(T * n)
    Sk, vk = np.zeros((n, Phi.shape[1])), np.asarray(x0, dtype=float)
    for k, (A, B, w) in enumerate(stages):
        Sk, vk = A @ Sk + B @ Phi[k * m : (k + 1) * m], A @ vk + w
        S[k * n : (k + 1) * n], v[k * n : (k + 1) * n] = Sk, vk
    return S, v, Phi


def _dense(ocp, model, x0, window):
    """The QP ½ zᵀPz + qᵀz of the cost with per-stage goals, built densely: Σ_{k=1}^{T} (x_k − g_k)ᵀQ_k(x_k − g_k)
    + Σ_{k=0}^{T−1} (u_k − u_g(g_k))ᵀR(u_k − u_g(g_k))."""
    n, T = ocp.nx, ocp.horizon
    S, v, Phi = _prediction(ocp, *model, x0)
    Qbar = np.kron(np.eye(T), ocp.Q)
    Qbar[-n:, -n:] = ocp.Q_terminal
    Rbar = np.kron(np.eye(T), ocp.R)
    Ug = np.concatenate([ocp.input_goal(window[k, :n]) for k in range(T)])
    P = S.T @ Qbar @ S + Phi.T @ Rbar @ Phi
    q = S.T @ Qbar @ (v - window[1:, :n].ravel()) - Phi.T @ Rbar @ Ug
    return P, q


@pytest.mark.parametrize("kind", ["condensed", "sparse", "rti"])
def test_a_window_of_the_held_goal_gives_the_held_solution(kind):
    ocp = _ocp()
    goal = _moving(ocp)[5]
    held, windowed = _controller(kind, ocp), _controller(kind, ocp)
    x = X0
    for _ in range(3):
        a = held.solve(x, goal)
        b = windowed.solve(x, np.tile(goal, (ocp.horizon + 1, 1)))
        assert a.ok and np.array_equal(a.u, b.u) and np.array_equal(a.knots, b.knots)
        x = a.x_pred[1]


@pytest.mark.parametrize("ltv", [False, True])
def test_the_build_with_equal_rows_is_the_held_qp(ltv):
    """The per-stage build itself (not only the controller's held path) gives the held QP for equal rows."""
    ocp = _ocp(x_min=-np.full(6, 3.0), x_max=np.full(6, 3.0))
    model = _models(ocp)[ltv]
    goal = _moving(ocp)[7]
    for tr in (CondensedQP(ocp), SparseQP(ocp)):
        held = tr.build(*model, X0, goal)
        rows = tr.build(*model, X0, np.tile(goal, (ocp.horizon + 1, 1)))
        P = held.P.toarray() if hasattr(held.P, "toarray") else held.P
        np.testing.assert_array_equal(P, rows.P.toarray() if hasattr(rows.P, "toarray") else rows.P)
        np.testing.assert_allclose(rows.q, held.q, rtol=0, atol=1e-12 * np.abs(held.q).max())
        np.testing.assert_array_equal(rows.l, held.l)


def _input_goal_ocp(kind):
    """nlink:3 with the input goal u_g = 0, u_g = K x_goal, or u_g = h(x_goal) (a GoalInputOCP)."""
    if kind == "zero":
        return _ocp()
    if kind == "gain":
        return _ocp(u_goal_gain=0.5 * np.ones((3, 6)))
    xg = ca.SX.sym("x_goal", 6)
    base = _ocp()
    return GoalInputOCP(
        base.model,
        base.dt,
        base.horizon,
        base.Q,
        base.R,
        Q_terminal=base.Q_terminal,
        parameterization=base.parameterization,
        compiled=False,
        goal_input=ca.Function("h", [xg], [ca.sin(xg[:3]) + xg[3:]]),
    )


@pytest.mark.parametrize("ltv", [False, True])
@pytest.mark.parametrize("input_goal", ["zero", "gain", "goal input"])
def test_a_moving_window_builds_the_dense_qp_of_the_per_stage_goals(ltv, input_goal):
    ocp = _input_goal_ocp(input_goal)
    model = _models(ocp)[ltv]
    window = _moving(ocp)
    P, q = _dense(ocp, model, X0, window)
    qp = CondensedQP(ocp).build(*model, X0, window[:, : ocp.nx])
    np.testing.assert_allclose(qp.P, P, rtol=0, atol=1e-10 * np.abs(P).max())
    np.testing.assert_allclose(qp.q, q, rtol=0, atol=1e-10 * np.abs(q).max())
    held = CondensedQP(ocp).build(*model, X0, window[0, : ocp.nx])
    assert np.abs(held.q - q).max() > 1e-3 * np.abs(q).max()  # the window matters
    # the same optimum from the sparse form (both unconstrained here: the KKT systems solved directly)
    sparse = SparseQP(ocp).build(*model, X0, window[:, : ocp.nx])
    Ps, A = sparse.P.toarray(), sparse.A.toarray()
    kkt = np.block([[Ps, A.T], [A, np.zeros((A.shape[0], A.shape[0]))]])
    zs = np.linalg.solve(kkt, np.r_[-sparse.q, sparse.b])[: sparse.q.size]
    zc = np.linalg.solve(qp.P, -qp.q)
    k0 = ocp.nx * (ocp.horizon + 1)  # z = [x_0 … x_T, knots]
    np.testing.assert_allclose(zc, zs[k0:], rtol=0, atol=1e-8 * max(1.0, np.abs(zc).max()))


def test_a_moving_target_enters_the_task_terms_stage_by_stage():
    """With a task, the condensed QP's gradient at the linearization knots is that of ½ J, J the cost with row k's
    goal at stage k (state, input and the frame-position term; ocp.cost), on the affine prediction."""
    ocp = reach(N3, [], horizon=12, knots=4, compiled=False)
    n, T = ocp.nx, ocp.horizon
    model = _models(ocp)[0]
    window = np.tile(ocp.goal(X0, position=[0.3, 0.4, 0.0]), (T + 1, 1))
    window[:, n : n + 2] += 0.1 * np.c_[np.sin(np.arange(T + 1) / 3), np.cos(np.arange(T + 1) / 3)]
    window[:, :n] = _moving(ocp)[:, :n]
    knots = 0.2 * np.random.default_rng(1).normal(size=(ocp.knots, ocp.nu))
    qp = CondensedQP(ocp).build(*model, X0, window[:, :n], targets=window[:, n:], knots=knots)
    S, v, Phi = _prediction(ocp, *model, X0)
    stage, terminal = ocp.cost.stage.map(T), ocp.cost.terminal

    def J(z):
        X = np.r_[X0, S @ z + v].reshape(T + 1, n)
        U = (Phi @ z).reshape(T, ocp.nu)
        return float(np.sum(np.asarray(stage(X[:-1].T, U.T, window[:-1].T)))) + float(terminal(X[-1], window[-1]))

    z, h = knots.ravel(), 1e-5
    grad = np.array([(J(z + h * e) - J(z - h * e)) / (2 * h) for e in np.eye(z.size)])
    np.testing.assert_allclose(qp.P @ z + qp.q, 0.5 * grad, rtol=0, atol=1e-6 * np.abs(grad).max())


def _sinusoid(ocp):
    """Joint angles 0.4 sin(2t + i) + 0.2 and their rates: a reference in joint space."""

    def goal(t):
        phase = 2 * t + np.arange(3)
        return np.r_[0.4 * np.sin(phase) + 0.2, 0.8 * np.cos(phase)]

    return Reference.from_function(goal, ocp.ng)


def test_the_preview_tracks_a_moving_reference_better_than_the_held_goal():
    ocp = N3.ocp(horizon=30, knots=6, compiled=False)
    reference, duration = _sinusoid(ocp), 2.0
    x0 = reference.at(0.0)
    preview = simulate(N3.plant(), LinearMPC(ocp, native=False), x0, reference, duration)
    ctrl, step = LinearMPC(ocp, native=False), N3.plant().rk4(ocp.dt, 10)
    xs = [x0]
    for t in preview.t[:-1]:  # the held goal updated each step, as a loop that cannot see ahead
        xs.append(np.asarray(step(xs[-1], ctrl.solve(xs[-1], reference.at(t)).u)).ravel())
    goals = preview.reference

    def rms(x):
        return float(np.sqrt(np.mean(np.sum((np.asarray(x)[:, :3] - goals[:, :3]) ** 2, axis=1))))

    with_preview, held = rms(preview.x), rms(xs)
    print(f"RMS joint tracking error: preview {with_preview:.4g} rad, held goal {held:.4g} rad")
    assert all(s.ok for s in preview.solutions)
    assert with_preview < 0.5 * held


def _spheres_ocp():
    return reach(N3, ["2.0,2.0,0,0.05"], horizon=12, knots=4, compiled=False)


def test_moving_obstacles_move_the_rows_and_the_certificate_without_building_a_function(monkeypatch):
    ocp = _spheres_ocp()
    ctrl = LinearMPC(ocp, native=False)
    goal = ocp.goal(X0, position=[0.2, 0.5, 0.0])
    rows, checked = [], []
    violation = ctrl._plan_check.violation
    for tr in ctrl._transcriptions:
        monkeypatch.setattr(tr.task, "add", lambda *a, _add=tr.task.add: rows.append(_add(*a)) or rows[-1])
    monkeypatch.setattr(
        ctrl._plan_check, "violation", lambda xs, **kw: checked.append(kw.get("obstacles")) or violation(xs, **kw)
    )
    sol = ctrl.solve(X0, goal)
    assert sol.ok and rows[-1] is None and checked[-1] is None  # the declared obstacle is far away
    # the obstacle moves into the plan's end-effector path, towards the robot
    tips = [np.asarray(ocp.task_functions.spheres(sol.x_pred[k])[0])[:, -1] for k in (0, ocp.horizon)]
    ahead = tips[1] - tips[0]
    built = []
    for name in ("__init__", "map", "mapaccum"):
        original = getattr(ca.Function, name)
        monkeypatch.setattr(
            ca.Function, name, lambda *a, _f=original, _n=name, **k: built.append(_n) or _f(*a, **k), raising=True
        )
    for fn in ("compile_function", "compile_in_background"):
        original = getattr(compiled, fn)
        monkeypatch.setattr(compiled, fn, lambda *a, _f=original, _n=fn, **k: built.append(_n) or _f(*a, **k))
    x = sol.x_pred[1]
    for step in range(4):
        window = np.tile([*(tips[1] + 0.5 * ahead), 0.03], (ocp.horizon + 1, 1, 1))
        window[:, 0, :3] -= 0.02 * np.multiply.outer(step + np.arange(ocp.horizon + 1) / ocp.horizon, ahead)
        sol = ctrl.solve(x, goal, obstacles=window)
        assert rows[-1] is not None and rows[-1][0].shape[0] > 0  # rows against the moved obstacle
        np.testing.assert_array_equal(checked[-1], window)  # the certificate's obstacles: the step's window
        assert sol.applied, sol.raw_status
        d = ocp.task_functions.pair_clearances(
            np.asarray(
                ocp.task_maps()["spheres"](ctrl.rollout(x, ocp.parameterization.inputs(sol.knots))[1:].T)[0]
            ).reshape(3, ocp.horizon, -1),
            window[1:],
        )
        assert d.min() > -0.005  # the plan keeps (within rounding of its linearization) 1 cm from it at each stage
        x = sol.x_pred[1]
    assert built == [], built


def test_an_initial_guess_is_the_trajectory_linearization_point(monkeypatch):
    ocp = _ocp()
    par, goal = ocp.parameterization, _moving(ocp)[3]
    guess = 0.5 * np.random.default_rng(2).normal(size=(ocp.knots, ocp.nu))
    for ctrl in (LinearMPC(ocp, native=False, linearization="trajectory"), RealTimeIteration(ocp, native=False)):
        seen = []
        models = ctrl.affine_models
        monkeypatch.setattr(ctrl, "affine_models", lambda xs, us, _m=models: seen.append((xs, us)) or _m(xs, us))
        ctrl.solve(X0, goal)
        start = len(seen)
        ctrl.solve(X0, goal, initial_guess=guess)
        xs, us = seen[start]  # the step's (RTI: first iteration's) linearization point: the guess's rollout
        np.testing.assert_array_equal(us, par.inputs(guess))
        np.testing.assert_array_equal(xs, ctrl.rollout(X0, par.inputs(guess))[:-1])
        start = len(seen)
        ctrl.solve(X0, goal)  # the next step without one: the previous plan, shifted
        assert np.abs(seen[start][1] - par.inputs(guess)).max() > 1e-3


def test_an_initial_guess_is_the_plan_linearization_point(monkeypatch):
    """linearization "plan": the model about the input the guess gives now (needs Controller.affine_model's ū)."""
    ocp = _ocp()
    ctrl = LinearMPC(ocp, native=False, linearization="plan")
    guess = 0.5 * np.random.default_rng(3).normal(size=(ocp.knots, ocp.nu))
    seen = []
    ctrl.solve(X0, _moving(ocp)[3])
    model = ctrl._affine_model
    monkeypatch.setattr(ctrl, "_affine_model", lambda x, u: seen.append(np.array(u)) or model(x, u))
    ctrl.solve(X0, _moving(ocp)[3], initial_guess=guess)
    np.testing.assert_array_equal(seen[-1], ocp.parameterization.u_at(guess, 0))


def test_an_initial_guess_is_the_task_terms_linearization_point(monkeypatch):
    ocp = reach(N3, [], horizon=12, knots=4, compiled=False)
    ctrl = LinearMPC(ocp, native=False)
    goal = ocp.goal(X0, position=[0.3, 0.4, 0.0])
    guess = 0.3 * np.ones((ocp.knots, ocp.nu))
    seen = []
    build = ctrl.transcription.build
    monkeypatch.setattr(ctrl.transcription, "build", lambda *a, **k: seen.append(k["knots"]) or build(*a, **k))
    ctrl.solve(X0, goal, initial_guess=guess)
    np.testing.assert_array_equal(seen[-1], guess)


def test_the_c_step_takes_a_moving_window_and_moved_obstacles_as_the_python_step_does():
    """LinearMPC's C step (<name>_step_window) answers a moving goal and a moved ball as the Python step does; a
    step with an initial guess runs in Python (the C step keeps its own plan)."""
    from ocpkit.export import BuildError, check_tools

    try:
        check_tools()
    except BuildError as exc:
        pytest.skip(str(exc))
    ocp = reach(N3, ["0.9,0.9,0,0.05"], horizon=12, knots=4)
    c, py = LinearMPC(ocp, native=True), LinearMPC(ocp, native=False)
    window = np.tile(ocp.goal(X0, position=[0.3, 0.4, 0.0]), (ocp.horizon + 1, 1))
    window[:, -3] += np.linspace(0.0, 0.1, ocp.horizon + 1)  # the target moves along x
    ball = [[0.45, 0.35, 0.0, 0.05]]
    a, b = c.solve(X0, window, obstacles=ball), py.solve(X0, window, obstacles=ball)
    assert a.path == "C step" and a.ok and b.ok, (a.path, a.raw_status, b.raw_status)
    np.testing.assert_allclose(a.knots, b.knots, atol=1e-8 * max(1.0, np.abs(b.knots).max()))
    guessed = c.solve(X0, window[0], initial_guess=a.knots)
    assert guessed.path == "Python step (initial guess)"

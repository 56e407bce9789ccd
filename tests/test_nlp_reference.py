"""NonlinearMPC follows what moves (issue 46): a goal window over the horizon, obstacles moved at run time and a user's
plan as the start of a step, each a parameter or the start of the NLP built once."""

import casadi as ca
import numpy as np
import pytest

import ocpkit.problems as problems
from ocpkit.model.reference import ObstaclePath, Reference
from ocpkit.model.task import Sphere, reach
from ocpkit.sim.simulate import simulate
from ocpkit.solvers.nlp import NonlinearMPC

N3 = problems.make("nlink:3")
CONFIGS = [
    ("ipopt", {}),
    ("ipopt", {"hessian": "exact"}),
    ("ipopt", {"dynamics": "affine"}),
    ("sqp", {}),
    ("fatrop", {}),
    ("fatrop", {"hessian": "exact"}),
]
IDS = [f"{method}-{'-'.join(kwargs.values()) or 'gauss-newton'}" for method, kwargs in CONFIGS]


def _reach(obstacles=()):
    return reach(N3, list(obstacles), knots=5, horizon=20, compiled=False)


def _tip(q):
    return np.asarray(N3.kinematics.function(N3.end_effector)(q)[0]).ravel()


def _moving_window(ocp, x0, seed=0):
    """A goal window whose rows all differ: x_goal and the tip's target drifting over the horizon."""
    rng = np.random.default_rng(seed)
    T = ocp.horizon
    start = ocp.goal(x0, position=[0.3, 0.45, 0.0])
    drift = np.r_[0.02 * rng.normal(size=ocp.nx), 0.01, -0.01, 0.0]
    return start + np.arange(T + 1)[:, None] * drift


@pytest.mark.parametrize("method, kwargs", CONFIGS, ids=IDS)
def test_a_window_of_equal_rows_gives_the_held_goals_solution(method, kwargs):
    """A held goal and the window repeating it are the same NLP parameters: the same plans, bit for bit, over a
    warm-started loop; a window that moves is taken and changes the plan."""
    ocp = _reach()
    x0 = np.r_[0.3, 0.4, 0.3, 0.0, 0.0, 0.0]
    goal = ocp.goal(x0, position=[0.3, 0.45, 0.0])
    held, window = NonlinearMPC(ocp, method=method, **kwargs), NonlinearMPC(ocp, method=method, **kwargs)
    F, x = ocp.discrete(), x0
    for _ in range(3):
        a, b = held.solve(x, goal), window.solve(x, np.tile(goal, (ocp.horizon + 1, 1)))
        assert a.ok and b.ok, (a.raw_status, b.raw_status)
        np.testing.assert_array_equal(a.knots, b.knots)
        np.testing.assert_array_equal(a.x_pred, b.x_pred)
        x = np.asarray(F(x, a.u)).ravel()
    moved = NonlinearMPC(ocp, method=method, **kwargs).solve(x0, _moving_window(ocp, x0))
    assert (
        moved.ok and np.abs(moved.knots - NonlinearMPC(ocp, method=method, **kwargs).solve(x0, goal).knots).max() > 1e-3
    )


@pytest.mark.parametrize("method, kwargs", [CONFIGS[0], CONFIGS[4], CONFIGS[5]], ids=[IDS[0], IDS[4], IDS[5]])
def test_the_nlp_objective_costs_each_stage_towards_its_row_of_the_window(method, kwargs):
    """The NLP's objective at any plan (states not consistent with the inputs) equals Σ_k ℓ(x_k, u_k, row k) + ℓ_T(x_T,
    row T) summed here stage by stage; fatrop's Gauss–Newton objective (the task's residuals frozen to first order)
    too, at the point it is taken about."""
    ocp = _reach()
    ctrl = NonlinearMPC(ocp, method=method, **kwargs)
    rng = np.random.default_rng(3)
    n, m, T, p = ocp.nx, ocp.nu, ocp.horizon, ocp.knots
    x0, states = rng.normal(size=n), rng.normal(size=(T, n))
    knots = rng.uniform(ocp.u_min, ocp.u_max, size=(p, m))
    window = _moving_window(ocp, x0, seed=1)
    w = np.r_[states.ravel(), knots.ravel()]
    if ctrl._order is not None:  # fatrop's stage order, the carried knot copies equal to the knots
        w = np.empty(ctrl._lbx.size)
        w[ctrl._order] = np.r_[states.ravel(), knots.ravel()]
        for start in ctrl._copies:
            w[start : start + p * m] = knots.ravel()
    nlp = ctrl._nlp[1]
    objective = float(ca.Function("f", [nlp["x"], nlp["p"]], [nlp["f"]])(w, np.r_[x0, window.ravel()]))
    xs, us = np.vstack([x0, states]), ocp.parameterization.inputs(knots)
    expected = sum(float(ocp.cost.stage(xs[k], us[k], window[k])) for k in range(T))
    expected += float(ocp.cost.terminal(xs[T], window[T]))
    assert objective == pytest.approx(expected, rel=1e-12)
    held = sum(float(ocp.cost.stage(xs[k], us[k], window[0])) for k in range(T)) + float(
        ocp.cost.terminal(xs[T], window[0])
    )
    assert abs(held - expected) > 1e-3 * abs(expected)  # the rows matter


def test_the_preview_of_a_joint_reference_tracks_it_better_than_the_held_goal():
    """nlink:3 following a joint-space sinusoid: the controller previewing the reference over the horizon against
        the same controller given the reference's value now as a held goal each step (RMS of the joint-angle error; the
    torques stay within their bounds: a faster or wider sinusoid saturates them and neither can follow it)."""
    ocp = N3.ocp(knots=5, horizon=20, compiled=False)
    amplitude, omega, phase = np.array([0.3, 0.2, 0.15]), 2 * np.pi * 0.5, np.array([0.0, 1.0, 2.0])

    def g(t):
        return np.r_[amplitude * np.sin(omega * t + phase), amplitude * omega * np.cos(omega * t + phase)]

    reference, duration = Reference.from_function(g, ocp.ng), 1.5
    x0 = g(0.0)
    preview = simulate(N3.plant(), NonlinearMPC(ocp), x0, reference, duration)
    ctrl, step = NonlinearMPC(ocp), N3.plant().rk4(ocp.dt, 10)
    xs = [x0]
    for t in preview.t[:-1]:
        sol = ctrl.solve(xs[-1], reference.at(t))
        assert sol.ok, sol.raw_status
        xs.append(np.asarray(step(xs[-1], sol.u)).ravel())
    assert preview.fallbacks == 0

    def rms(x):
        return float(np.sqrt(np.mean(np.sum((x[:, :3] - preview.reference[:, :3]) ** 2, axis=1))))

    errors = {"preview": rms(preview.x), "held": rms(np.array(xs))}
    print(f"RMS joint-angle error (rad): {errors}")
    assert errors["preview"] < 0.5 * errors["held"], errors


def _ball_on_the_path():
    """x_0, the goal (nlink:3's tip across its workspace) and the tip's place at stage 12 of the free plan."""
    x0 = np.r_[0.3, 0.4, 0.3, 0.0, 0.0, 0.0]
    free = _reach()
    goal = free.goal(x0, position=_tip([1.7, 0.3, 0.2]))
    return x0, goal, _tip(NonlinearMPC(free).solve(x0, goal).x_pred[12, :3])


@pytest.mark.parametrize("method, kwargs", CONFIGS[:2] + [CONFIGS[3]], ids=IDS[:2] + [IDS[3]])
def test_obstacles_given_at_run_time_are_the_task_declaring_them_there(method, kwargs):
    """The obstacle window is the clearances' parameter: a ball given to the step where the task declared another
    gives the plan of the task declaring the ball, bit for bit (the ball active: the plan bends around it)."""
    x0, goal, centre = _ball_on_the_path()
    declared = NonlinearMPC(
        reach(N3, [Sphere(tuple(centre), 0.03)], knots=5, horizon=20, compiled=False), method=method, **kwargs
    )
    moved = NonlinearMPC(_reach(["0.0,0.0,0.6,0.03"]), method=method, **kwargs)
    a, b = declared.solve(x0, goal), moved.solve(x0, goal, obstacles=[[*centre, 0.03]])
    assert a.ok and b.ok, (a.raw_status, b.raw_status)
    np.testing.assert_array_equal(a.knots, b.knots)
    assert not np.array_equal(b.knots, moved.solve(x0, goal).knots)


@pytest.mark.parametrize("hessian", ["gauss-newton", "exact"])
def test_moved_obstacles_are_kept_clear_without_a_rebuild(hessian, monkeypatch):
    """A ball moving across the path of nlink:3's tip (a constant-velocity window over the horizon): every plan keeps
    its clearance at every stage against the ball's place at that stage, the constraint active, and no NLP or NLP
    solver is built after the first step. (SQP's Gauss–Newton steps stall on this moving ball,
    "Search_Direction_Becomes_Too_Small", as they do on a ball the task declares at the free plan's stage 10: not the
    obstacle window's doing.)"""
    x0, goal, centre = _ball_on_the_path()
    ocp = _reach(["0.0,0.0,0.6,0.03"])  # declared far above the plane the arm moves in
    path = ObstaclePath(lambda t: [[*(centre + [0.0, 0.1 * t, 0.0]), 0.03]])
    ctrl = NonlinearMPC(ocp, hessian=hessian)
    tf, F, x, dt, T = ocp.task_functions, ocp.discrete(), x0, ocp.dt, ocp.horizon
    built, nlpsol = [], ca.nlpsol
    monkeypatch.setattr(ca, "nlpsol", lambda *args, **kwargs: (built.append(args[0]), nlpsol(*args, **kwargs))[1])
    monkeypatch.setattr(NonlinearMPC, "_build", lambda self, ocp: built.append("NLP"))
    closest = np.inf
    for k in range(6):
        window = path.window(k * dt, dt, T)
        sol = ctrl.solve(x, goal, obstacles=window)
        assert sol.ok, sol.raw_status
        clear = [np.min(np.asarray(tf.clearance_at(sol.x_pred[j], window[j].T)[0])) for j in range(1, T + 1)]
        assert min(clear) >= -1e-6, (k, min(clear))
        closest = min(closest, min(clear))
        x = np.asarray(F(x, sol.u)).ravel()
    assert closest < 1e-4  # the moved ball bent the plans: its clearance constraint active
    assert not built, built


@pytest.mark.parametrize("method", ["ipopt", "sqp", "fatrop"])
def test_an_initial_guess_is_the_first_iterate(method, monkeypatch):
    """The step given a user's plan starts from it: its knots and the states they roll out to on the OCP's discrete
    model, no multipliers (a cold start's); the step after is warm again."""
    ocp = _reach()
    x0 = np.r_[0.3, 0.4, 0.3, 0.0, 0.0, 0.0]
    goal = ocp.goal(x0, position=[0.3, 0.45, 0.0])
    ctrl = NonlinearMPC(ocp, method=method)
    assert ctrl.solve(x0, goal).ok
    calls, solver = [], ctrl._solver

    class Spy:
        def __call__(self, **args):
            calls.append(args)
            return solver(**args)

        def stats(self):
            return solver.stats()

    monkeypatch.setattr(ctrl, "_solver", Spy())
    guess = np.random.default_rng(5).uniform(0.5 * ocp.u_min, 0.5 * ocp.u_max, size=(ocp.knots, ocp.nu))
    assert ctrl.solve(x0, goal, initial_guess=guess).ok
    states = ctrl.rollout(x0, ocp.parameterization.inputs(guess))[1:]
    w0 = np.asarray(calls[0]["x0"], dtype=float)
    if ctrl._order is not None:
        w0 = w0[ctrl._order]
    np.testing.assert_array_equal(w0, np.r_[states.ravel(), guess.ravel()])
    assert "lam_x0" not in calls[0] and "lam_g0" not in calls[0]
    assert ctrl.solve(x0, goal).ok  # warm again: the guess step's solution shifted (with multipliers but fatrop)
    assert not np.array_equal(calls[1]["x0"], calls[0]["x0"]) and ("lam_x0" in calls[1]) == (method != "fatrop")

"""The sampling planners (EMPC, CEM, MPPI) follow a goal window and moving obstacles through their kernels' data,
nothing compiled again, and start from a user's plan (issue 46), on the arch of `pytest --arch`."""

import numpy as np
import pytest
from taichi.lang import kernel_impl

from ocpkit import problems
from ocpkit.codegen.kernels import rollout
from ocpkit.codegen.kernels.rollout import Rollout
from ocpkit.model.reference import Reference
from ocpkit.model.task import reach
from ocpkit.sim.simulate import simulate
from ocpkit.solvers.cem import CrossEntropyMPC
from ocpkit.solvers.empc import EvolutionaryMPC
from ocpkit.solvers.mppi import MPPI

pytestmark = pytest.mark.usefixtures("taichi_arch")

N3 = problems.make("nlink:3")
PLANNERS = [EvolutionaryMPC, CrossEntropyMPC, MPPI]


@pytest.fixture
def compiles(monkeypatch):
    """Counts of Taichi kernel compilations (a kernel's new instance) and of ocpkit's CasADi-to-Taichi translations,
    from the fixture's start: {"taichi": …, "translate": …}."""
    count = {"taichi": 0, "translate": 0}
    materialize, translate = kernel_impl.Kernel.materialize, rollout.translate

    def counted_materialize(self, *args, **kwargs):
        before = len(self.compiled_kernels)
        materialize(self, *args, **kwargs)
        count["taichi"] += len(self.compiled_kernels) - before

    def counted_translate(*args, **kwargs):
        count["translate"] += 1
        return translate(*args, **kwargs)

    monkeypatch.setattr(kernel_impl.Kernel, "materialize", counted_materialize)
    monkeypatch.setattr(rollout, "translate", counted_translate)
    return count


def _affine(ocp, x):
    Ad, Bd, wd = (np.asarray(M, dtype=float) for M in ocp.affine()(x, np.zeros(ocp.nu)))
    return Ad, Bd, wd.ravel()


def _python_rollout(ocp, U, x0, model, window, obstacles=None):
    """(J, V) of each candidate by a Python loop: Σ_k l(x_k, u_k, row k) + l_T(x_T, row T), with the obstacles'
    penalty at x_0 … x_T and their violation at x_1 … x_T against row k of ``obstacles`` (T+1, N, 4)."""
    Ad, Bd, wd = model
    tf = ocp.task_functions
    costs, violations = [], []
    for knots in U:
        x, J, V = x0.copy(), 0.0, 0.0
        for k, u in enumerate(ocp.parameterization.inputs(knots)):
            J += float(ocp.cost.stage(x, u, window[k]))
            if obstacles is not None:
                J += float(tf.penalty_at(x, obstacles[k].T))
                V += max(0.0, -float(np.min(np.asarray(tf.clearance_at(x, obstacles[k].T)[0])))) if k > 0 else 0.0
            x = Ad @ x + Bd @ u + wd
        J += float(ocp.cost.terminal(x, window[-1]))
        if obstacles is not None:
            J += float(tf.penalty_at(x, obstacles[-1].T))
            V += max(0.0, -float(np.min(np.asarray(tf.clearance_at(x, obstacles[-1].T)[0]))))
        costs.append(J)
        violations.append(V)
    return np.array(costs), np.array(violations)


def _moving_window(ocp, goal, rng):
    """A goal window whose every entry moves over the horizon."""
    return goal + 0.2 * np.cumsum(rng.normal(size=(ocp.horizon + 1, ocp.ng)), axis=0) / ocp.horizon


def test_a_window_of_equal_rows_is_the_held_goal_bit_for_bit():
    ocp = N3.ocp(knots=4)
    x0, goal = N3.sample(0)
    U = np.random.default_rng(0).uniform(ocp.u_min, ocp.u_max, size=(32, ocp.knots, ocp.nu))
    engine = Rollout(ocp, 32)
    engine.load(x0, goal, _affine(ocp, x0))
    held = engine.evaluate(U)
    engine.load(x0, np.tile(goal, (ocp.horizon + 1, 1)), _affine(ocp, x0))
    window = engine.evaluate(U)
    for a, b in zip(held, window):
        np.testing.assert_array_equal(a, b)


def test_the_rollout_cost_reads_row_k_of_a_moving_window_at_stage_k():
    """A task's targets move too: the reach term's position target, row by row."""
    ocp = reach(N3, [], knots=4, horizon=20, velocity_limits=False)
    rng = np.random.default_rng(1)
    x0 = np.r_[0.3, -0.2, 0.4, np.zeros(3)]
    window = _moving_window(ocp, ocp.goal(np.zeros(ocp.nx), position=[0.1, 0.4, 0.0]), rng)
    U = rng.uniform(ocp.u_min, ocp.u_max, size=(16, ocp.knots, ocp.nu))
    engine, model = Rollout(ocp, 16), _affine(ocp, x0)
    engine.load(x0, window, model)
    cost, violation = engine.evaluate(U)
    np.testing.assert_allclose(cost, _python_rollout(ocp, U, x0, model, window)[0], rtol=1e-9)
    assert np.array_equal(violation, np.zeros(len(U)))
    engine.load(x0, window[0], model)  # the held goal costs otherwise
    assert np.abs(engine.evaluate(U)[0] / cost - 1).min() > 1e-6


def test_moved_obstacles_change_the_penalty_and_nothing_is_compiled_again(compiles):
    ocp = reach(N3, ["0.3,0.3,0,0.05"], knots=4, horizon=12, velocity_limits=False)
    T, rng = ocp.horizon, np.random.default_rng(2)
    x0, goal = np.r_[0.5, 0.3, 0.2, np.zeros(3)], ocp.goal(np.zeros(ocp.nx), position=[0.0, 0.45, 0.0])
    U = rng.uniform(ocp.u_min, ocp.u_max, size=(16, ocp.knots, ocp.nu))
    engine, model = Rollout(ocp, 16), _affine(ocp, x0)
    engine.load(x0, goal, model)
    declared = engine.evaluate(U)
    assert compiles["taichi"] > 0 and compiles["translate"] == 2  # the counters see the first build
    before = dict(compiles)
    np.testing.assert_allclose(
        declared, _python_rollout(ocp, U, x0, model, np.tile(goal, (T + 1, 1)), ocp.obstacle_window()), rtol=1e-9
    )
    for step in range(3):  # a sphere that moves along the arm's reach, over the horizon and from step to step
        centre = np.array([0.2 + 0.05 * step, 0.25, 0.0]) + np.linspace(0, 0.1, T + 1)[:, None] * [1.0, 1.0, 0.0]
        obstacles = np.concatenate([centre, np.full((T + 1, 1), 0.08)], axis=1)[:, None, :]
        engine.load(x0, goal, model, obstacles)
        cost, violation = engine.evaluate(U)
        expected = _python_rollout(ocp, U, x0, model, np.tile(goal, (T + 1, 1)), obstacles)
        np.testing.assert_allclose(cost, expected[0], rtol=1e-9)
        np.testing.assert_allclose(violation, expected[1], rtol=1e-9, atol=1e-12)
        assert (violation > 0).any() and not np.allclose(cost, declared[0])
    assert compiles == before
    ctrl = EvolutionaryMPC(ocp, population=32, seed=0)
    ctrl.solve(x0, goal)
    first = dict(compiles)
    assert first["taichi"] > before["taichi"]
    for step in range(3):
        window = np.tile(goal, (T + 1, 1))
        window[:, -3:] += 0.01 * step * np.arange(T + 1)[:, None]
        ctrl.solve(x0, window, obstacles=[[0.2 + 0.05 * step, 0.25, 0.0, 0.08]])
    assert compiles == first


@pytest.mark.parametrize("cls", PLANNERS)
def test_the_initial_guess_is_the_incumbent(cls):
    ocp = N3.ocp(knots=4)
    x0, goal = N3.sample(0)
    options = {"variant": "paper"} if cls is not EvolutionaryMPC else {}
    ctrl = cls(ocp, population=32, generations=1, seed=0, **options)
    ctrl.solve(x0, goal)  # a warm step: without the guess the next would start from its shifted plan
    guess = np.random.default_rng(3).uniform(1.2 * ocp.u_min, 1.2 * ocp.u_max, size=(ocp.knots, ocp.nu))
    incumbent = np.clip(guess, ocp.u_min, ocp.u_max)
    if cls is EvolutionaryMPC:
        ctrl.solve(x0, goal, initial_guess=guess)
        population = ctrl.engine.knots.to_numpy()  # the parents are carried over unchanged: the first places
        np.testing.assert_array_equal(
            population[: ctrl.num_parents], np.broadcast_to(incumbent, (ctrl.num_parents,) + incumbent.shape)
        )
        return
    means = []
    sample = ctrl._sample
    ctrl._sample = lambda mean: (means.append(mean.copy()), sample(mean))
    ctrl.solve(x0, goal, initial_guess=guess)
    np.testing.assert_array_equal(means[0], incumbent)


def test_a_preconditioned_step_rolls_the_guess_out_first():
    ocp = N3.ocp(knots=4)
    x0, goal = N3.sample(0)
    ctrl = CrossEntropyMPC(ocp, population=32, generations=1, seed=0)
    ctrl.solve(x0, goal)
    guess = ctrl.plan + 0.1
    evaluated = []
    evaluate = ctrl._evaluate
    ctrl._evaluate = lambda candidates: (evaluated.append(np.array(candidates)), evaluate(candidates))[1]
    ctrl.solve(x0, goal, initial_guess=guess)
    np.testing.assert_array_equal(evaluated[0][0], np.clip(guess, ocp.u_min, ocp.u_max))


def _tracking_error(cls, reference, duration):
    ocp = N3.ocp(knots=4)
    ctrl = cls(ocp, population=128, seed=0)
    x0 = reference.at(0.0)
    traj = simulate(N3.plant(), ctrl, x0, reference, duration)
    q = slice(0, 3)
    return float(np.sqrt(np.mean(np.sum((traj.x[:, q] - traj.reference[:, q]) ** 2, axis=1)))), traj


@pytest.mark.parametrize("cls", PLANNERS)
def test_the_preview_tracks_a_moving_reference_closer_than_the_held_goal(cls):
    """nlink:3 following q(t) = q_0 + 0.4 sin(2t) (and its velocity) for 2 s: with the reference's window over the
    horizon vs its present value held over it at each step."""
    amplitude, omega, base = 0.4, 2.0, np.array([0.3, -0.4, 0.5])

    def goal(t):
        return np.r_[base + amplitude * np.sin(omega * t), amplitude * omega * np.cos(omega * t) * np.ones(3)]

    reference = Reference.from_function(goal, 6)
    preview, traj = _tracking_error(cls, reference, 2.0)
    held, _ = _tracking_error(cls, reference.without_preview(), 2.0)
    print(f"{cls.__name__}: RMS joint error {preview:.4f} rad with the preview, {held:.4f} rad held")
    assert traj.fallbacks == 0
    assert preview < 0.8 * held

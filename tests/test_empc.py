"""EvolutionaryMPC (Algorithm 1) and its siblings CEM and MPPI in closed loop, on the arch of `pytest --arch` (default cpu)."""
import casadi as ca
import numpy as np
import pytest

from ocpkit import problems
from ocpkit.controller import LIMITED, NAN, SUCCESS
from ocpkit.metrics import actual_cost
from ocpkit.simulate import simulate
from ocpkit.solvers.cem import CrossEntropyMPC
from ocpkit.solvers.empc import EvolutionaryMPC
from ocpkit.solvers.mppi import MPPI


pytestmark = pytest.mark.usefixtures("taichi_arch")


def test_linear_pendulum_reaches_goal():
    problem = problems.make("pendulum:linear")
    ocp = problem.ocp(knots=3)
    x0, goal = problem.sample(0)
    ctrl = EvolutionaryMPC(ocp, population=256, seed=0)
    traj = simulate(problem.plant(), ctrl, x0, goal, 2.0)
    assert traj.fallbacks == 0 and set(traj.statuses) == {SUCCESS}
    np.testing.assert_allclose(traj.x[-1], goal, atol=0.02)
    sol = traj.solutions[-1]
    assert sol.iterations == 1 and sol.times["solve"] > 0 and sol.times["build"] == 0
    assert sol.knots.shape == (3, 1) and np.all(np.abs(sol.knots) <= ocp.u_max)


def test_nlink2_reaches_goal_and_generations_help():
    problem = problems.make("nlink:2")
    ocp = problem.ocp(knots=3)
    costs = {}
    for generations in (1, 3):
        ctrl = EvolutionaryMPC(ocp, population=256, generations=generations, shrink_distance=1.0,
                               sigma_min=0.01, seed=0)
        costs[generations] = []
        for trial in range(3):
            x0, goal = problem.sample(trial)
            traj = simulate(problem.plant(), ctrl, x0, goal, 5.0)
            costs[generations].append(actual_cost(traj, ocp))
            if generations == 3:
                # A sampling optimizer settles near, not exactly at, the goal: 0.007–0.032 measured.
                np.testing.assert_allclose(traj.x[-1], goal, atol=0.05)
    assert np.mean(costs[3]) <= np.mean(costs[1])


def test_same_seed_same_run():
    problem = problems.make("pendulum")
    ocp = problem.ocp(knots=3)
    x0, goal = problem.sample(1)
    runs = []
    for seed in (5, 5, 6):
        ctrl = EvolutionaryMPC(ocp, population=128, generations=2, seed=seed)
        runs.append(simulate(problem.plant(), ctrl, x0, goal, 0.3))
    np.testing.assert_array_equal(runs[0].u, runs[1].u)
    np.testing.assert_array_equal(runs[0].x, runs[1].x)
    assert not np.array_equal(runs[0].u, runs[2].u)
    # reset() restarts the random stream: the same controller repeats itself too.
    ctrl = EvolutionaryMPC(ocp, population=128, generations=2, seed=5)
    first = [ctrl.solve(x0, goal).u for _ in range(3)]
    ctrl.reset()
    np.testing.assert_array_equal(first, [ctrl.solve(x0, goal).u for _ in range(3)])


def test_non_smooth_cost_dead_zone_and_speed_penalty():
    """A dead-zone on the angle and a hard speed penalty: neither fits a QP; EMPC keeps |q̇| ≤ 2."""
    problem = problems.make("pendulum:linear")
    ocp = problem.ocp(knots=3)
    x0, goal = np.array([0.0, 0.0]), np.array([1.5, 0.0])
    x, u, g = ca.SX.sym("x", 2), ca.SX.sym("u"), ca.SX.sym("x_goal", 2)
    angle = 10 * ca.fmax(ca.fabs(x[0] - g[0]) - 0.02, 0)
    too_fast = ca.if_else(ca.fabs(x[1]) > 2.0, 1e3, 0.0)
    stage = ca.Function("l", [x, u, g], [angle + too_fast + 0.01 * u ** 2])
    terminal = ca.Function("l_T", [x, g], [angle + too_fast])
    plain = simulate(problem.plant(), EvolutionaryMPC(ocp, population=256, generations=2),
                     x0, goal, 2.0)
    shaped = simulate(problem.plant(), EvolutionaryMPC(ocp, population=256, generations=2, stage_cost=stage,
                                                       terminal_cost=terminal), x0, goal, 2.0)
    assert np.abs(plain.x[:, 1]).max() > 3.0  # the quadratic cost alone moves faster
    assert np.abs(shaped.x[:, 1]).max() <= 2.0
    assert abs(shaped.x[-1, 0] - goal[0]) < 0.05


def test_nonlinear_dynamics_mode():
    problem = problems.make("pendulum")
    ocp = problem.ocp(knots=3)
    x0, goal = problem.sample(2)
    ctrl = EvolutionaryMPC(ocp, population=256, generations=2, dynamics="nonlinear")
    traj = simulate(problem.plant(), ctrl, x0, goal, 2.0)
    np.testing.assert_allclose(traj.x[-1], goal, atol=0.02)
    assert traj.solutions[0].times["model"] == 0.0


@pytest.mark.parametrize("cls, options", [(CrossEntropyMPC, {"generations": 3}),
                                          (MPPI, {"generations": 3, "temperature": 1.0})])
def test_cem_and_mppi_reach_goal(cls, options):
    problem = problems.make("pendulum:linear")
    ocp = problem.ocp(knots=3)
    x0, goal = problem.sample(0)
    traj = simulate(problem.plant(), cls(ocp, population=256, seed=0, **options), x0, goal, 2.0)
    assert traj.fallbacks == 0
    np.testing.assert_allclose(traj.x[-1], goal, atol=0.05)


def test_nan_cost_falls_back():
    ocp = problems.make("pendulum:linear").ocp(knots=3)
    x, u, g = ca.SX.sym("x", 2), ca.SX.sym("u"), ca.SX.sym("x_goal", 2)
    broken = ca.Function("l", [x, u, g], [ca.sqrt(-1 - ca.sumsqr(x))])
    ctrl = EvolutionaryMPC(ocp, population=16, num_parents=4, stage_cost=broken)
    sol = ctrl.solve(np.zeros(2), np.ones(2))
    assert sol.status == NAN and sol.fallback and np.isfinite(sol.u).all()


def test_solvers_are_registered():
    from ocpkit.solvers import cem, empc, mppi

    assert empc.SOLVERS == {"empc": EvolutionaryMPC}
    assert cem.SOLVERS == {"cem": CrossEntropyMPC} and mppi.SOLVERS == {"mppi": MPPI}


def test_bad_arguments():
    problem = problems.make("pendulum:linear")
    ocp = problem.ocp(knots=3)
    with pytest.raises(ValueError, match="num_parents"):
        EvolutionaryMPC(ocp, population=8, num_parents=8)
    with pytest.raises(ValueError, match="population"):
        EvolutionaryMPC(ocp, population=1)
    with pytest.raises(ValueError, match="sigma"):
        EvolutionaryMPC(ocp, population=8, num_parents=2, sigma=-1.0)
    with pytest.raises(ValueError, match="seed"):
        EvolutionaryMPC(ocp, population=8, num_parents=2, seed=-3)
    with pytest.raises(ValueError, match="arch"):
        EvolutionaryMPC(ocp, population=8, num_parents=2, arch="tpu")
    with pytest.raises(ValueError, match="u_min"):
        EvolutionaryMPC(problem.ocp(knots=3, u_min=None, u_max=None), population=8, num_parents=2)
    with pytest.raises(ValueError, match="temperature"):
        MPPI(ocp, population=8, temperature=0.0)
    with pytest.raises(ValueError, match="num_elites"):
        CrossEntropyMPC(ocp, population=8, num_elites=9)
    with pytest.raises(ValueError, match="x"):
        EvolutionaryMPC(ocp, population=8, num_parents=2).solve(np.zeros(3), np.zeros(2))


def test_parents_shift_is_not_lost_when_a_step_runs_no_generation():
    problem = problems.make("nlink:2")
    ocp = problem.ocp(knots=4, horizon=30)
    x0, goal = problem.sample(0)
    ctrl = EvolutionaryMPC(ocp, population=32, num_parents=4, seed=0)
    ctrl.solve(x0, goal)
    parents = ctrl.engine.picked.to_numpy()
    ctrl.time_limit = 1e-12  # out of time before the first generation: the fallback input, no breeding
    assert ctrl.solve(x0, goal).status == LIMITED
    ctrl.time_limit = None
    ctrl._start(x0, goal, cold=False)  # the next step: the skipped step's shift is applied now, its own in the kernel
    np.testing.assert_allclose(ctrl.engine.picked.to_numpy(), ctrl._shifted(parents))
    ctrl._generation(cold=False)  # the elites survive unchanged: shifted twice, as two steps have passed
    np.testing.assert_allclose(ctrl.engine.knots.to_numpy()[:4], ctrl._shifted(ctrl._shifted(parents)), atol=1e-15)

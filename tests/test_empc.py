"""EvolutionaryMPC (Algorithm 1, preconditioned and as printed) and its siblings CEM and MPPI in closed loop, on
the arch of `pytest --arch` (default cpu)."""

import casadi as ca
import numpy as np
import pytest

from ocpkit import problems
from ocpkit.status import LIMITED, NAN, SUCCESS
from ocpkit.sim.metrics import actual_cost
from ocpkit.sim.simulate import simulate
from ocpkit.solvers.cem import CrossEntropyMPC
from ocpkit.solvers.empc import EvolutionaryMPC
from ocpkit.solvers.mppi import MPPI
from ocpkit.solvers.sampling import SEEDS


pytestmark = pytest.mark.usefixtures("taichi_arch")


@pytest.mark.parametrize("variant", ["preconditioned", "paper"])
def test_linear_pendulum_reaches_goal(variant):
    problem = problems.make("pendulum:linear")
    ocp = problem.ocp(knots=3)
    x0, goal = problem.sample(0)
    ctrl = EvolutionaryMPC(ocp, population=256, seed=0, variant=variant)
    traj = simulate(problem.plant(), ctrl, x0, goal, 2.0)
    assert traj.fallbacks == 0 and set(traj.statuses) == {SUCCESS}
    np.testing.assert_allclose(traj.x[-1], goal, atol=0.02)
    sol = traj.solutions[-1]
    assert sol.iterations == 1 and sol.times["solve"] > 0 and sol.times["generations"] > 0
    # The paper's variant assembles nothing; the preconditioned one builds the knot QP.
    assert (sol.times["build"] > 0) == (variant == "preconditioned")
    assert sol.knots.shape == (3, 1) and np.all(np.abs(sol.knots) <= ocp.u_max)
    # On a linear model with a quadratic cost the Newton seed is the rollout cost's minimizer, so a bred child
    # cannot beat it: the preconditioned variant's plan is the seed's (child win rate ~0); the paper's variant
    # has no seed and its children win (its cold start is all children).
    assert ctrl.generations_run == len(traj.solutions)
    assert ctrl.child_win_rate < 0.05 if variant == "preconditioned" else ctrl.child_win_rate > 0.3
    ctrl.reset()
    assert ctrl.generations_run == 0 and np.isnan(ctrl.child_win_rate)


@pytest.mark.parametrize("cls", [EvolutionaryMPC, CrossEntropyMPC, MPPI])
def test_reaches_goal_at_three_links(cls):
    """The preconditioned planners bring the 3-link robot to its goal (the paper's Algorithm 1 does not)."""
    problem = problems.make("nlink:3")
    ocp = problem.ocp(knots=3)
    x0, goal = problem.sample(11)
    traj = simulate(problem.plant(), cls(ocp, population=256, seed=3), x0, goal, 5.0)
    assert traj.fallbacks == 0
    assert np.abs(traj.x[-1] - goal).max() < 0.05


@pytest.mark.parametrize("cls", [EvolutionaryMPC, CrossEntropyMPC, MPPI])
def test_whitened_draws_have_covariance_proportional_to_inverse_hessian(cls):
    """At rest on the goal (no gravity) every seed and the mean are zero, so each candidate is its whitened
    draw alone: Lᵀz must have covariance E[s²]·I (EMPC: s log-uniform; CEM and MPPI: s = sigma)."""
    problem = problems.make("nlink:2")
    ocp = problem.ocp(knots=3, horizon=20, u_min=np.full(2, -1e9), u_max=np.full(2, 1e9))
    x = np.r_[0.3, -0.2, 0.0, 0.0]
    if cls is EvolutionaryMPC:
        lo, hi = 0.5, 2.0
        ctrl, second_moment = cls(ocp, population=40_000, scales=(lo, hi)), (hi**2 - lo**2) / (2 * np.log(hi / lo))
    else:
        ctrl, second_moment = cls(ocp, population=40_000, sigma=0.7), 0.49
    ctrl.solve(x, x)
    pre = ctrl.preconditioner
    np.testing.assert_allclose(pre.newton, 0.0, atol=1e-12)
    first_child = ctrl.num_parents + SEEDS if cls is EvolutionaryMPC else 1 + SEEDS
    knots = ctrl.engine.knots.to_numpy()[first_child:]
    w = pre.whitened(knots, np.zeros(knots.shape[1:]))
    cov = w.T @ w / len(w)
    d = cov.shape[0]
    # Sample covariance of 40k draws: entries within ~4 standard errors of E[s²]·I.
    np.testing.assert_allclose(cov / second_moment, np.eye(d), atol=0.06)


def test_holding_input_compensates_gravity():
    problem = problems.make("puma560")
    ocp = problem.ocp(knots=3)
    ctrl = EvolutionaryMPC(ocp, population=16, num_parents=4)
    _, goal = problem.sample(0)
    hold = ctrl.preconditioner.holding_input(goal)
    xdot = np.asarray(ocp.model.f(goal, hold)).ravel()
    assert np.abs(hold).max() > 1.0  # gravity needs real torque
    np.testing.assert_allclose(xdot, 0.0, atol=1e-9)


def test_paper_variant_nlink2_reaches_goal_and_generations_help():
    problem = problems.make("nlink:2")
    ocp = problem.ocp(knots=3)
    costs = {}
    for generations in (1, 3):
        ctrl = EvolutionaryMPC(
            ocp, population=256, generations=generations, shrink_distance=1.0, sigma_min=0.01, seed=0, variant="paper"
        )
        costs[generations] = []
        for trial in range(3):
            x0, goal = problem.sample(trial)
            traj = simulate(problem.plant(), ctrl, x0, goal, 5.0)
            costs[generations].append(actual_cost(traj, ocp))
            if generations == 3:
                # A sampling optimizer settles near, not exactly at, the goal: 0.007–0.032 measured.
                np.testing.assert_allclose(traj.x[-1], goal, atol=0.05)
    assert np.mean(costs[3]) <= np.mean(costs[1])


@pytest.mark.parametrize("variant", ["preconditioned", "paper"])
def test_same_seed_same_run(variant):
    # Nonlinear rollouts: the Newton candidate of the linearized QP is then improvable, so the seed matters.
    problem = problems.make("pendulum")
    ocp = problem.ocp(knots=3)
    x0, goal = problem.sample(1)
    options = {"population": 128, "generations": 2, "variant": variant, "dynamics": "nonlinear"}
    runs = []
    for seed in (5, 5, 6):
        ctrl = EvolutionaryMPC(ocp, seed=seed, **options)
        runs.append(simulate(problem.plant(), ctrl, x0, goal, 0.3))
    np.testing.assert_array_equal(runs[0].u, runs[1].u)
    np.testing.assert_array_equal(runs[0].x, runs[1].x)
    knots = [np.array([s.knots for s in run.solutions]) for run in runs]
    np.testing.assert_array_equal(knots[0], knots[1])
    assert not np.array_equal(knots[0], knots[2])
    # reset() restarts the random stream: the same controller repeats itself too.
    ctrl = EvolutionaryMPC(ocp, seed=5, **options)
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
    stage = ca.Function("l", [x, u, g], [angle + too_fast + 0.01 * u**2])
    terminal = ca.Function("l_T", [x, g], [angle + too_fast])
    plain = simulate(problem.plant(), EvolutionaryMPC(ocp, population=256, generations=2), x0, goal, 2.0)
    shaped = simulate(
        problem.plant(),
        EvolutionaryMPC(ocp, population=256, generations=2, stage_cost=stage, terminal_cost=terminal),
        x0,
        goal,
        2.0,
    )
    assert np.abs(plain.x[:, 1]).max() > 3.0  # the quadratic cost alone moves faster
    assert np.abs(shaped.x[:, 1]).max() <= 2.0
    assert abs(shaped.x[-1, 0] - goal[0]) < 0.05


@pytest.mark.parametrize("variant", ["preconditioned", "paper"])
def test_nonlinear_dynamics_mode(variant):
    problem = problems.make("pendulum")
    ocp = problem.ocp(knots=3)
    x0, goal = problem.sample(2)
    ctrl = EvolutionaryMPC(ocp, population=256, generations=2, dynamics="nonlinear", variant=variant)
    traj = simulate(problem.plant(), ctrl, x0, goal, 2.0)
    np.testing.assert_allclose(traj.x[-1], goal, atol=0.02)
    # Only the preconditioner needs the affine model when the kernel rolls out the nonlinear one.
    assert (traj.solutions[0].times["model"] > 0) == (variant == "preconditioned")


@pytest.mark.parametrize(
    "cls, options", [(CrossEntropyMPC, {"generations": 3}), (MPPI, {"generations": 3, "temperature": 1.0})]
)
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
    traj = simulate(problems.make("pendulum:linear").plant(), ctrl, np.zeros(2), np.ones(2), 0.03)
    assert traj.fallbacks == 3 and traj.fallback_causes() == "nan 3"


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
        EvolutionaryMPC(ocp, population=8, num_parents=2, sigma=-1.0, variant="paper")
    with pytest.raises(ValueError, match="variant='paper' only"):
        EvolutionaryMPC(ocp, population=8, num_parents=2, sigma=0.1)
    with pytest.raises(ValueError, match="scales"):
        EvolutionaryMPC(ocp, population=8, num_parents=2, scales=(1.0, 0.1))
    with pytest.raises(ValueError, match="variant"):
        CrossEntropyMPC(ocp, population=8, num_elites=4, variant="isotropic")
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


def test_puma560_with_gravity_reaches_goal():
    """The preconditioned EMPC holds the 6-DoF arm against gravity at its goal (the holding input seeds it)."""
    problem = problems.make("puma560")
    ocp = problem.ocp(knots=3)
    ctrl = EvolutionaryMPC(ocp, population=1024, seed=0)
    errors = []
    for seed in range(5):
        x0, goal = problem.sample(seed)
        traj = simulate(problem.plant(), ctrl, x0, goal, problem.duration)
        assert traj.fallbacks == 0
        errors.append(np.abs(traj.x[-1, :6] - goal[:6]).max())
    assert max(errors) <= 0.05, errors  # 0.0024–0.0151 rad measured


def test_bench_reports_the_step_cpu_time():
    """`ocpkit bench empc` prints the step's CPU time beside its wall time: on a machine other processes share, the
    CPU time (one Taichi thread) is what an idle machine would take."""
    from ocpkit.benchmarks.empc import bench_empc

    lines = []
    (row,) = bench_empc((1,), (8,), (10,), variants=("preconditioned",), steps=2, arch="auto", out=lines.append)
    assert "step cpu" in lines[0] and 0 < row["step_cpu"] < 10 * row["step"] + 1.0

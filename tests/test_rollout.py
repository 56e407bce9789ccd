"""Population rollouts: the kernel's costs (and violations) equal a plain numpy/CasADi rollout of the same knots."""

import casadi as ca
import numpy as np
import pytest

from ocpkit import problems
from ocpkit.codegen.kernels import runtime
from ocpkit.codegen.kernels.rollout import Rollout


pytestmark = pytest.mark.usefixtures("taichi_arch")


def reference_costs(ocp, knots, x0, goal, step, stage=None, terminal=None):
    """Σ_{k<T} l(x_k, u_k) + l_T(x_T) by a Python loop over candidates and steps (CasADi costs)."""
    stage = ocp.cost.stage if stage is None else stage
    terminal = ocp.cost.terminal if terminal is None else terminal
    costs = []
    for U in knots:
        x, J = x0.copy(), 0.0
        for u in ocp.parameterization.inputs(U):
            J += float(stage(x, u, goal))
            x = step(x, u)
        costs.append(J + float(terminal(x, goal)))
    return np.array(costs)


def _costs(engine, U):
    """The kernel's costs of U; without obstacles or state bounds every violation is exactly 0."""
    cost, violation = engine.evaluate(U)
    assert not engine.constrained and np.array_equal(violation, np.zeros(len(U)))
    return cost


def _setup(name, population, seed, knots=3, horizon=None):
    problem = problems.make(name)
    ocp = problem.ocp(knots=knots, horizon=horizon)
    rng = np.random.default_rng(seed)
    x0, goal = problem.sample(seed)
    U = rng.uniform(ocp.u_min, ocp.u_max, size=(population, ocp.knots, ocp.nu))
    return ocp, x0, goal, U


@pytest.mark.parametrize("name", ["pendulum", "nlink:2"])
def test_affine_rollout_matches_numpy(name):
    ocp, x0, goal, U = _setup(name, 32, seed=0)
    Ad, Bd, wd = (np.asarray(M, dtype=float) for M in ocp.affine()(x0, np.zeros(ocp.nu)))
    engine = Rollout(ocp, 32)
    engine.load(x0, goal, (Ad, Bd, wd.ravel()))
    expected = reference_costs(ocp, U, x0, goal, lambda x, u: Ad @ x + Bd @ u + wd.ravel())
    np.testing.assert_allclose(_costs(engine, U), expected, rtol=1e-10)


@pytest.mark.parametrize("name, parameterization", [("pendulum", "linear"), ("nlink:2", "zoh")])
def test_nonlinear_rollout_matches_casadi_loop(name, parameterization):
    problem = problems.make(name)
    ocp = problem.ocp(knots=4, parameterization=parameterization, horizon=30)
    rng = np.random.default_rng(1)
    x0, goal = problem.sample(1)
    U = rng.uniform(ocp.u_min, ocp.u_max, size=(16, ocp.knots, ocp.nu))
    F = ocp.discrete()
    engine = Rollout(ocp, 16, dynamics="nonlinear")
    engine.load(x0, goal)
    expected = reference_costs(ocp, U, x0, goal, lambda x, u: np.asarray(F(x, u)).ravel())
    np.testing.assert_allclose(_costs(engine, U), expected, rtol=1e-10)


def test_non_smooth_cost_rollout():
    ocp, x0, goal, U = _setup("pendulum:linear", 24, seed=2)
    x, u, g = ca.SX.sym("x", 2), ca.SX.sym("u"), ca.SX.sym("x_goal", 2)
    stage = ca.Function(
        "l",
        [x, u, g],
        [10 * ca.fmax(ca.fabs(x[0] - g[0]) - 0.1, 0) + ca.if_else(ca.fabs(x[1]) > 1.0, 100.0, 0.0) + 0.01 * u**2],
    )
    terminal = ca.Function("lT", [x, g], [ca.norm_1(x - g)])
    F = ocp.discrete()
    engine = Rollout(ocp, 24, dynamics="nonlinear", stage_cost=stage, terminal_cost=terminal)
    engine.load(x0, goal)
    expected = reference_costs(ocp, U, x0, goal, lambda x, u: np.asarray(F(x, u)).ravel(), stage, terminal)
    np.testing.assert_allclose(_costs(engine, U), expected, rtol=1e-10)


def test_float32_rollout_is_close():
    ocp, x0, goal, U = _setup("pendulum", 8, seed=3)
    F = ocp.discrete()
    engine = Rollout(ocp, 8, dynamics="nonlinear", precision="float32")
    engine.load(x0, goal)
    expected = reference_costs(ocp, U, x0, goal, lambda x, u: np.asarray(F(x, u)).ravel())
    np.testing.assert_allclose(_costs(engine, U), expected, rtol=1e-4)


def test_pick_gathers_candidates():
    ocp, x0, goal, U = _setup("pendulum:linear", 10, seed=4)
    engine = Rollout(ocp, 10, num_picked=3)
    engine.knots.from_numpy(U)
    np.testing.assert_array_equal(engine.pick([7, 2]), U[[7, 2]])
    np.testing.assert_array_equal(engine.picked.to_numpy()[:2], U[[7, 2]])
    with pytest.raises(ValueError, match="indices"):
        engine.pick([10])


def test_step_sections_travel_with_load():
    """A step section sits before the basis and reaches the device with the next load, in its one launch, and with
    every later load until staged again; write() refuses it (load would overwrite it) and stage() any other."""
    ocp = problems.make("pendulum").ocp(knots=3)
    engine = Rollout(ocp, 4, dynamics="nonlinear", sections={"once": 2}, step_sections={"each": 3})
    layout = engine.layout
    assert layout["each"] < layout["basis"] < layout["once"]
    engine.write("once", [7.0, 8.0])
    engine.stage("each", [1.0, 2.0, 3.0])
    data = engine.data.to_numpy()
    np.testing.assert_array_equal(data[layout["each"] : layout["each"] + 3], 0.0)  # staged, not yet sent
    x0, goal = np.array([0.1, 0.2]), np.zeros(2)
    for _ in range(2):
        engine.load(x0, goal)
        data = engine.data.to_numpy()
        np.testing.assert_array_equal(data[layout["each"] : layout["each"] + 3], [1.0, 2.0, 3.0])
        np.testing.assert_array_equal(data[layout["x0"] : layout["x0"] + 2], x0)
        np.testing.assert_array_equal(data[layout["once"] : layout["once"] + 2], [7.0, 8.0])
    with pytest.raises(ValueError, match="stage"):
        engine.write("each", [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="not a step section"):
        engine.stage("once", [0.0, 0.0])
    with pytest.raises(ValueError, match="takes 3 values"):
        engine.stage("each", [0.0])


def test_bad_arguments():
    ocp = problems.make("pendulum").ocp(knots=3)
    x = ca.SX.sym("x", 2)
    with pytest.raises(ValueError, match="num_sims"):
        Rollout(ocp, 0)
    with pytest.raises(ValueError, match="dynamics"):
        Rollout(ocp, 4, dynamics="exact")
    with pytest.raises(TypeError, match="stage_cost"):
        Rollout(ocp, 4, stage_cost=lambda x, u, g: 0.0)
    with pytest.raises(ValueError, match="terminal_cost"):
        Rollout(ocp, 4, terminal_cost=ca.Function("t", [x], [ca.sumsqr(x)]))
    with pytest.raises(ValueError, match="precision"):
        Rollout(ocp, 4, precision="half")
    engine = Rollout(ocp, 4, dynamics="nonlinear")
    with pytest.raises(ValueError, match="affine"):
        engine.load(np.zeros(2), np.zeros(2), (np.eye(2), np.ones((2, 1)), np.zeros(2)))
    with pytest.raises(ValueError, match="affine"):
        Rollout(ocp, 4).load(np.zeros(2), np.zeros(2))
    with pytest.raises(ValueError, match="knots"):
        engine.evaluate(np.zeros((4, 2, 1)))
    with pytest.raises(ValueError, match="x0"):
        engine.load(np.zeros(3), np.zeros(2))


def test_cpu_thread_setting_is_checked(monkeypatch):
    monkeypatch.setenv("OCPKIT_CPU_THREADS", "3")
    assert runtime._cpu_threads() == 3
    for bad in ("0", "two", "-1"):
        monkeypatch.setenv("OCPKIT_CPU_THREADS", bad)
        with pytest.raises(ValueError, match="OCPKIT_CPU_THREADS must be a positive integer"):
            runtime._cpu_threads()


def test_starting_taichi_keeps_the_process_floating_point(pytestconfig):
    """ti.init turns flush-to-zero on in its thread; ocpkit.codegen.kernels.runtime.init restores the environment,
    so CasADi, IPOPT and numpy keep subnormal numbers (with it on, an SQP step on nlink:3 took 10-13 s instead of
    0.1 s). On the arch the run asked for (`pytest --arch`): Taichi starts once a process."""
    from ocpkit.codegen.kernels import runtime

    runtime.init(pytestconfig.getoption("arch"))
    assert (np.array([1e-310]) * 1.0)[0] != 0.0

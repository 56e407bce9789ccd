"""The safety contract, beside the optimality contract of test_contract.py: every registered configuration
(``ocpkit.solvers.configurations()``, and the exported C step: test_contract.EXPORTED) on obstacle cases

* never reports "success" on a step whose plan, rolled out on the controller's model, or whose actual next state
  (the plant's) collides — true clearance below zero, :func:`ocpkit.model.task.clearances`, computed here in numpy from
  the robot's sphere centres, not by the controller's CasADi rows;
* keeps the step contract: statuses from STATUSES, a fallback exactly when the step was refused (a "soft" step
  applies the solver's own input), finite inputs within the bounds;
* never takes longer a step than its ceiling (LinearMPC's and NonlinearMPC's ``ceiling``, 10 s; 10 s for the others)
  and one uninterruptible iteration. (It found that starting Taichi turned flush-to-zero on process-wide: SQP steps
  from a start inside a ball then ran to the ceiling, 10-13 s, instead of 0.1 s; ocpkit.codegen.kernels.runtime now
  keeps the floating-point environment.)

The cases, on the planar 3-link arm: the target behind a ball, a ball over a link of the start pose, a ball on the
tip, a sphere so large it contains the whole arm, and 100 spheres around it. A configuration that cannot take
obstacles says so at construction (test_contract.TASK_REFUSALS). The default run takes each configuration on two
cases by rotation (the sampling planners not on the 100 spheres) and the README's Panda example for the QP and RTI
configurations; ``pytest -m slow`` the whole grid, the Panda for every configuration included.
"""

from __future__ import annotations

import numpy as np
import pytest

from ocpkit import solvers
from ocpkit.status import SOFT, STATUSES, SUCCESS
from ocpkit.problems import make
from ocpkit.sim.simulate import simulate
from ocpkit.model.task import Sphere, clearances, reach

from test_contract import EXPORTED, SAMPLING, TASK_REFUSALS, exported_builds  # noqa: F401 - the builds' fixture

CONFIGS = solvers.configurations() + EXPORTED
CASES = ("behind", "over_start", "on_tip", "containing", "hundred")
HORIZON, KNOTS, STEPS = 20, 3, 5
DEFAULT_CEILING = 10.0


def _case(problem, case: str):
    """(x0, target, obstacles) of a named case on ``problem`` (nlink:3: the plane z = 0)."""
    tip = problem.kinematics.function(problem.end_effector)
    x0 = np.r_[0.3, 0.4, 0.3, 0.0, 0.0, 0.0]
    start = np.asarray(tip(x0[:3])[0]).ravel()
    target = np.asarray(tip([1.7, 0.3, 0.2])[0]).ravel()
    if case == "behind":
        return x0, target, [Sphere(tuple(0.5 * (start + target)), 0.04)]
    if case == "over_start":  # over the middle of the second link
        ends = [np.asarray(problem.kinematics.positions(j, x0[None, :3])).ravel() for j in ("joint2", "joint3")]
        return x0, target, [Sphere(tuple(0.5 * (ends[0] + ends[1])), 0.05)]
    if case == "on_tip":
        return x0, target, [Sphere(tuple(start), 0.03)]
    if case == "containing":
        return x0, target, [Sphere((0.0, 0.0, 0.0), 5.0)]
    rng = np.random.default_rng(11)
    centres = np.c_[rng.uniform(-1.5, 1.5, (100, 2)), np.zeros(100)]
    return x0, target, [Sphere(tuple(c), 0.02) for c in centres]


def _check_safe_steps(controller, problem, traj, obstacles):
    ocp = controller.ocp
    kin, robot = ocp.task.kinematics, ocp.task.robot
    nq = kin.n
    actual = clearances(kin, robot, obstacles, traj.x[:, :nq])
    ceiling = getattr(controller, "ceiling", DEFAULT_CEILING)
    for k, sol in enumerate(traj.solutions):
        assert sol.status in STATUSES, sol.status
        assert sol.fallback == (sol.status not in (SUCCESS, SOFT)), (sol.status, sol.path)
        assert sol.path.startswith("fallback") == sol.fallback, sol.path
        assert sol.u.shape == (ocp.nu,) and np.isfinite(sol.u).all(), sol.u
        assert np.all(sol.u >= ocp.u_min - 1e-9) and np.all(sol.u <= ocp.u_max + 1e-9), sol.u
        assert sol.times["total"] <= ceiling + 2.5, (k, sol.times)  # the ceiling, and one uninterruptible iteration
        if sol.ok:
            assert actual[k + 1] >= 0.0, f"step {k}: success, but the next state collides ({actual[k + 1]:.4f} m)"
            xs = controller.rollout(traj.x[k], ocp.parameterization.inputs(sol.knots))
            planned = clearances(kin, robot, obstacles, xs[1:, :nq])
            assert planned.min() >= 0.0, f"step {k}: success with a colliding plan ({planned.min():.4f} m)"


def _run(config, problem, x0, target, obstacles, steps=STEPS):
    ocp = reach(problem, obstacles, knots=HORIZON if config.knots == "horizon" else KNOTS, horizon=HORIZON)
    try:
        controller = config.make(ocp)
    except ValueError as exc:
        assert any(why in str(exc) for why in TASK_REFUSALS), str(exc)
        return None
    traj = simulate(problem.plant(), controller, x0, ocp.goal(x0, position=target), duration=steps * ocp.dt)
    _check_safe_steps(controller, problem, traj, obstacles)
    return traj


def _grid(slow: bool):
    """(configuration, case) pairs: every case for the slow run; two by rotation by default, where the sampling
    planners skip the 100 spheres (their Taichi kernel with 900 clearances per state compiles for many minutes), and
    so does IPOPT (~18 s on that NLP; the QP configurations keep the case in the default run)."""
    pairs = []
    for i, config in enumerate(CONFIGS):
        cases = CASES if slow else (CASES[i % len(CASES)], CASES[(i + 2) % len(CASES)])
        if not slow and (config.solver in SAMPLING or config.solver == "ipopt"):
            cases = tuple(CASES[(CASES.index(c) + 1) % len(CASES)] if c == "hundred" else c for c in cases)
        pairs += [pytest.param(config, case, id=f"{config.label}-{case}") for case in cases]
    return pairs


@pytest.fixture(scope="module")
def nlink3():
    return make("nlink:3")


@pytest.mark.parametrize("config, case", _grid(slow=False))
def test_safety_contract(config, case, nlink3):
    _run(config, nlink3, *_case(nlink3, case))


@pytest.mark.slow
@pytest.mark.parametrize("config, case", _grid(slow=True))
def test_safety_contract_whole_grid(config, case, nlink3):
    _run(config, nlink3, *_case(nlink3, case), steps=20)


def test_no_success_inside_an_obstacle_that_contains_the_arm(nlink3):
    """A sphere containing the whole arm: no plan can clear it, so no step may be a success — the steps are "soft"
    (the QP's softened rows, the clearance named in the raw status) or refused."""
    config = solvers.Configuration("qp", {"linearization": "trajectory"})
    traj = _run(config, nlink3, *_case(nlink3, "containing"))
    assert not any(sol.ok for sol in traj.solutions)
    soft = [sol for sol in traj.solutions if sol.status == SOFT]
    assert soft and all("clearance" in sol.raw_status for sol in soft), [s.raw_status for s in traj.solutions]


PANDA_CONFIGS = [
    c
    for c in CONFIGS
    if c.solver == "qp"
    and c.options.get("form") == "condensed"
    and c.options.get("qp") == "daqp"
    and not c.options.get("native")
] + [c for c in CONFIGS if c.solver == "rti" and "iterations" not in c.options]


def _panda_readme_case():
    arm = make("panda")
    x0, _ = arm.sample(seed=0)
    return arm, x0, np.array([0.4, 0.0, 0.3]), [Sphere((0.4, -0.25, 0.35), 0.08)]


@pytest.mark.parametrize("config", [pytest.param(c, id=c.label) for c in PANDA_CONFIGS])
def test_safety_contract_panda_readme_case(config):
    """The README's Panda example (the hand to (0.4, 0, 0.3) past a ball): 30 steps within the safety contract."""
    _run(config, *_panda_readme_case(), steps=30)


@pytest.mark.slow
@pytest.mark.parametrize("config", [pytest.param(c, id=c.label) for c in CONFIGS])
def test_safety_contract_panda_readme_case_every_configuration(config):
    _run(config, *_panda_readme_case(), steps=100)

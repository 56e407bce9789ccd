"""One contract for every registered controller (``ocpkit.solvers.configurations()``: each solver × variant × form
and backend × linearization), on shipped problems (nlink:3, the cart-pole), a user-declared one (the tutorial's
cart-pole) and a URDF arm:

* it constructs and steps; every status is one of STATUSES, ``fallback`` is set exactly when it is not a success,
  u is finite and within the input bounds;
* a QP step's success carries a KKT certificate that holds (:mod:`ocpkit.qp.certificate`);
* in closed loop on the pendulum it reaches the goal, with the piecewise-linear inputs and, where it takes knots,
  with a cubic B-spline and a user-supplied basis;
* where two configurations claim the same optimum they agree: every QP backend and form, the C step and IPOPT over
  the affine model on the knot QP about the input goal; IPOPT, SQP, fatrop and iterated RTI on the NLP.

A solver or variant joins by being listed in ``ocpkit.solvers.CONFIGURATIONS``; the exported C step loaded back
(:class:`ocpkit.export.ExportedMPC`, not a registered solver) joins as :data:`EXPORTED`, each distinct OCP exported
and built once a module (``exported_builds``). The default run takes every configuration on the pendulum (closed
loop) and on one other problem each (a few steps); ``pytest -m slow`` the whole grid.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from ocpkit import solvers
from ocpkit.status import SOFT, STATUSES, SUCCESS
from ocpkit.export import BuildError, ExportedMPC, build, check_tools, export
from ocpkit.export.digest import ocp_entries
from ocpkit.model.parameterization import Parameterization
from ocpkit.model.problem import Problem
from ocpkit.problems import make
from ocpkit.sim.simulate import simulate
from ocpkit.solvers.qp import LinearMPC
from ocpkit.problems.panda import urdf_path as panda_urdf

from conftest import EXAMPLES, smooth_basis


class _Exports:
    """The exported configurations' builds: each distinct OCP and linearization exported and built once, in the
    folder the module fixture :func:`exported_builds` gives (``root``)."""

    def __init__(self):
        self.root: Path | None = None
        self.built: dict[tuple, Path] = {}

    def folder(self, ocp, linearization: str) -> Path:
        key = (linearization, *ocp_entries(ocp))
        if key not in self.built:
            try:
                check_tools()
            except BuildError as exc:
                pytest.skip(str(exc))
            out = self.root / f"export{len(self.built)}"
            build(export(ocp, out, linearization=linearization).out_dir)
            self.built[key] = out
        return self.built[key]


EXPORTS = _Exports()


@dataclass(frozen=True)
class ExportedConfiguration(solvers.Configuration):
    """The exported C step, built and loaded back as an :class:`ocpkit.export.ExportedMPC`."""

    def make(self, ocp):
        return ExportedMPC(ocp, EXPORTS.folder(ocp, self.options["linearization"]))


# The C step about the input goal (the condensed knot QP LinearMPC solves) and the real-time iteration
EXPORTED = [
    ExportedConfiguration("export", {"linearization": "goal"}, optimum="convex"),
    ExportedConfiguration("export", {"linearization": "trajectory"}),
]
CONFIGS = solvers.configurations() + EXPORTED
OTHERS = ("nlink:3", "cartpole", "user:cartpole", "arm")  # user:cartpole: the tutorial's declared problem
HORIZON, KNOTS = 20, 3
SAMPLING = ("empc", "cem", "mppi")


def _arm():
    """The shipped Panda URDF with its fingers locked: a 7-DoF URDF arm."""
    urdf = panda_urdf()
    return Problem.from_urdf(urdf, locked_joints=["panda_finger_joint1", "panda_finger_joint2"])


@pytest.fixture(scope="module", autouse=True)
def exported_builds(tmp_path_factory):
    """The folder the exported configurations build in, each distinct OCP once a module (a build takes 1-5 s)."""
    EXPORTS.root, EXPORTS.built = tmp_path_factory.mktemp("exported"), {}
    yield EXPORTS
    EXPORTS.root, EXPORTS.built = None, {}


@pytest.fixture(scope="module")
def problems(tmp_path_factory):
    cartpole = tmp_path_factory.mktemp("contract") / "cartpole.py"
    shutil.copy(EXAMPLES / "cartpole.py", cartpole)
    cache = {}

    def get(name):
        if name not in cache:
            cache[name] = (
                make(f"{cartpole}:CartPole") if name == "user:cartpole" else _arm() if name == "arm" else make(name)
            )
        return cache[name]

    return get


def _ocp(problem, config, horizon=HORIZON):
    return problem.ocp(knots=horizon if config.knots == "horizon" else KNOTS, horizon=horizon)


def _check_step(controller, sol):
    ocp = controller.ocp
    assert sol.status in STATUSES, sol.status
    assert sol.fallback == (sol.status not in (SUCCESS, SOFT)), (sol.status, sol.fallback)  # "soft": its own input
    assert sol.path.startswith("fallback") == sol.fallback and sol.path, sol.path  # what answered, named
    assert sol.u.shape == (ocp.nu,) and np.isfinite(sol.u).all(), sol.u
    assert np.all(sol.u >= ocp.u_min - 1e-9) and np.all(sol.u <= ocp.u_max + 1e-9), sol.u
    if sol.ok and isinstance(controller, LinearMPC):  # every QP step (RTI included): a proven success
        assert sol.certificate is not None and sol.certificate.holds, (sol.raw_status, sol.certificate)
    if not sol.ok:
        assert sol.raw_status, "a failure names its reason"


def _grid(slow: bool):
    """(configuration, problem) pairs: the pendulum for all, and one other problem each by rotation (the sampling
    planners' Taichi kernels of the 7-DoF arm take minutes to compile: the slow grid only)."""
    pairs = []
    for i, config in enumerate(CONFIGS):
        others = OTHERS if slow else (OTHERS[i % len(OTHERS)],)
        for name in others:
            if config.solver in SAMPLING and name == "arm" and not slow:
                name = "nlink:3"
            pairs.append(pytest.param(config, name, id=f"{config.label}-{name}"))
    return pairs


def test_every_registered_solver_has_configurations():
    assert set(solvers.names()) == set(solvers.CONFIGURATIONS), "register a solver's configurations with it"
    assert all(c.solver in solvers.names() for c in CONFIGS if c not in EXPORTED)


def test_the_benchmarks_name_controllers_from_the_registry():
    """Issue 45: one list of controller names (solvers.CONTROLLERS: every solver by its name, and variants), which
    `ocpkit bench nlp` and `startup` take; real-time iteration is the solver "rti", no longer "rti1" of bench nlp."""
    from ocpkit.benchmarks import nlp, startup
    from ocpkit.solvers.rti import RealTimeIteration

    assert set(solvers.names()) <= set(solvers.CONTROLLERS)
    assert set(nlp.CONTROLLERS) | set(startup.CONTROLLERS) - {"exported"} <= set(solvers.CONTROLLERS)
    ocp = make("nlink:2").ocp(knots=3, horizon=10)
    rti3 = nlp.controller("rti3", ocp)
    assert type(rti3) is RealTimeIteration and rti3.iterations == 3
    with pytest.raises(ValueError, match="unknown controller 'rti1'"):
        nlp.controller("rti1", ocp)


def _pendulum_loop(controller, problem):
    """Two seconds on the pendulum to a goal it can hold: every step within the contract, 90 % of them successes,
    the goal reached."""
    controller.wait_compiled()
    x0, goal = np.array([0.0, 0.0]), np.array([1.0, 0.0])
    traj = simulate(problem.plant(), controller, x0, goal, duration=2.0)
    for sol in traj.solutions:
        _check_step(controller, sol)
    oks = sum(sol.ok for sol in traj.solutions)
    assert oks >= 0.9 * len(traj.solutions), (oks, {s.raw_status for s in traj.solutions if not s.ok})
    assert abs(traj.x[-1, 0] - goal[0]) < 0.05, traj.x[-1]


@pytest.mark.parametrize("config", [pytest.param(c, id=c.label) for c in CONFIGS])
def test_contract_closed_loop_on_the_pendulum(config, problems):
    """Every configuration brings the pendulum to a goal it can hold, every step within the contract."""
    problem = problems("pendulum")
    _pendulum_loop(config.make(_ocp(problem, config, horizon=40)), problem)


BASES = {
    "bspline": lambda T, p: Parameterization.bspline(T, p),
    "custom": lambda T, p: Parameterization.custom(smooth_basis(T, p)),
}


@pytest.mark.usefixtures("taichi_arch")
@pytest.mark.parametrize("basis", BASES)
@pytest.mark.parametrize("config", [pytest.param(c, id=c.label) for c in CONFIGS if c.knots != "horizon"])
def test_contract_closed_loop_with_other_bases(config, basis, problems):
    """Issue 49: every configuration that takes knots does the same with the inputs a clamped cubic B-spline or a
    user's basis (normalized Gaussian bumps, dense) of 5 knots over 40 steps."""
    problem = problems("pendulum")
    _pendulum_loop(config.make(problem.ocp(parameterization=BASES[basis](40, 5))), problem)


def _steps(config, name, problems, steps=3):
    """``steps`` closed-loop steps from the problem's seed-0 start, each within the contract."""
    problem = problems(name)
    ocp = _ocp(problem, config)
    controller = config.make(ocp)
    controller.wait_compiled()
    x, goal = problem.sample(0)
    traj = simulate(problem.plant(), controller, x, goal, duration=steps * ocp.dt)
    assert len(traj.solutions) == steps
    for sol in traj.solutions:
        _check_step(controller, sol)


@pytest.mark.parametrize("config, name", _grid(slow=False))
def test_contract_steps(config, name, problems):
    _steps(config, name, problems)


@pytest.mark.slow
@pytest.mark.parametrize("config, name", _grid(slow=True))
def test_contract_steps_whole_grid(config, name, problems):
    _steps(config, name, problems, steps=10)


# Configurations that cannot take a task say so at construction (the sparse QP, HPIPM's traditional form, the C step
# and fatrop with obstacles, the exported real-time iteration); every other one steps within the contract on a reach
# task with an obstacle.
TASK_REFUSALS = ("form='condensed'", "no C step: a task", "not its obstacles", "cannot be exported with linearization")


@pytest.mark.parametrize("config", [pytest.param(c, id=c.label) for c in CONFIGS])
def test_contract_with_a_task(config, problems):
    """Every configuration takes the same task — the tip of nlink:3 to a point, a ball on the way — or refuses it at
    construction with an error that says why; its steps keep the contract and never report success in collision
    at the plan it returns."""
    from ocpkit.model.task import Sphere, reach

    problem = problems("nlink:3")
    x0 = np.r_[0.3, 0.4, 0.3, 0.0, 0.0, 0.0]
    tip = problem.kinematics.function(problem.end_effector)
    target = np.asarray(tip([1.7, 0.3, 0.2])[0]).ravel()
    start = np.asarray(tip(x0[:3])[0]).ravel()
    ocp = reach(
        problem,
        [Sphere(tuple(0.5 * (start + target)), 0.04)],
        knots=HORIZON if config.knots == "horizon" else KNOTS,
        horizon=HORIZON,
    )
    try:
        controller = config.make(ocp)
    except ValueError as exc:
        assert any(why in str(exc) for why in TASK_REFUSALS), str(exc)
        return
    traj = simulate(problem.plant(), controller, x0, ocp.goal(x0, position=target), duration=3 * ocp.dt)
    for sol in traj.solutions:
        _check_step(controller, sol)
    assert sum(sol.ok for sol in traj.solutions) >= 2, [sol.raw_status for sol in traj.solutions]


def _reference(problem, config, optimum):
    """The reference knots for a configuration's claimed optimum at the problem's seed-0 start (cold)."""
    ocp = _ocp(problem, config)
    x, goal = problem.sample(0)
    if optimum == "convex":
        ref = LinearMPC(ocp, native=False, eps=1e-12).solve(x, goal)
    else:
        ref = solvers.make("ipopt", ocp, options={"tol": 1e-10}).solve(x, goal)
    assert ref.ok, ref.raw_status
    return ref.knots


@pytest.mark.parametrize(
    "name, optimum",
    [(name, "convex") for name in ("pendulum", "nlink:3", "cartpole", "user:cartpole", "arm")]
    + [(name, "nlp") for name in ("pendulum", "nlink:3", "cartpole", "user:cartpole", "arm")],
)
def test_contract_configurations_agree_on_their_optimum(name, optimum, problems):
    """From a cold start, every configuration that claims an optimum finds the same knots as the reference
    (the condensed knot QP solved by DAQP to 1e-12; IPOPT to 1e-10 on the NLP)."""
    problem = problems(name)
    x, goal = problem.sample(0)
    refs, bad = {}, []
    for config in (c for c in CONFIGS if c.optimum == optimum):
        key = (config.optimum, config.knots)
        if key not in refs:
            refs[key] = _reference(problem, config, config.optimum)
        controller = config.make(_ocp(problem, config))
        controller.wait_compiled()
        sol = controller.solve(x, goal)
        scale = max(1.0, float(np.abs(refs[key]).max()))
        # HPIPM stops at residuals of 1e-6 (solvers/qp.py), the NLP solvers at their own tolerances: 1e-3
        tol = (1e-5 if config.optimum == "convex" and config.options.get("qp") != "hpipm" else 1e-3) * scale
        if not sol.ok or np.abs(sol.knots - refs[key]).max() > tol:
            bad.append(
                (
                    config.label,
                    sol.status,
                    sol.raw_status[:80],
                    float(np.abs(sol.knots - refs[key]).max()) if sol.ok else None,
                )
            )
    assert not bad, bad


@pytest.mark.parametrize("config", [pytest.param(c, id=c.label) for c in CONFIGS])
def test_contract_against_mujoco(config, problems):
    """Every configuration steps nlink:3 against MuJoCo (:class:`ocpkit.sim.mujoco_plant.MuJoCoPlant`) within the
    contract, and as it does against ocpkit's plant: the two plants agree to about 1e-12 for the same inputs, so
    the states agree to 1e-6 and the inputs to the solvers' tolerances (1e-4 of the torque limit)."""
    pytest.importorskip("mujoco")
    from ocpkit.sim.mujoco_plant import MuJoCoPlant

    problem = problems("nlink:3")
    ocp = _ocp(problem, config)
    controller = config.make(ocp)
    controller.wait_compiled()
    x, goal = problem.sample(0)
    ours, theirs = (
        simulate(plant, controller, x, goal, duration=3 * ocp.dt) for plant in (problem.plant(), MuJoCoPlant(problem))
    )
    for sol in theirs.solutions:
        _check_step(controller, sol)
    np.testing.assert_allclose(theirs.x, ours.x, rtol=0, atol=1e-6)
    np.testing.assert_allclose(theirs.u, ours.u, rtol=0, atol=1e-4 * np.abs(ocp.u_max).max())


def _tracking_error(traj, reference) -> np.ndarray:
    """max_i |q_i − q_ref,i| at every recorded state."""
    n = traj.x.shape[1] // 2
    return np.abs(traj.x[:, :n] - np.array([reference.at(t)[:n] for t in traj.t])).max(axis=1)


# Preconditioned CEM tracked worse with the preview than held (RMS 0.167 vs 0.126 rad) while its draws were clipped
# to the input bounds: the tracking plan holds joint 1's torque at its bound (tests/test_cem_bounds.py).
@pytest.mark.parametrize("config", [pytest.param(c, id=c.label) for c in CONFIGS])
def test_contract_tracks_a_reference(config, problems):
    """Issue 46: every configuration follows a moving joint-space reference on nlink:3 — a 0.3 rad sinusoid of the
    three joints at 0.5 Hz with its rates, previewed over the horizon — each step within the contract, most of them
    successes, and stays closer to it than holding its start would (half its RMS at most). The preview is what a
    held goal lacks: it must not do worse than the same controller holding the reference's present value."""
    from ocpkit.model.reference import Reference

    problem = problems("nlink:3")
    ocp = _ocp(problem, config)
    t = np.linspace(0.0, 2.0, 201)
    w, phase = 2 * np.pi / 2.0, np.array([0.0, 1.0, 2.0])
    q = 0.3 * np.sin(w * t[:, None] + phase) - 0.3 * np.sin(phase)
    rates = 0.3 * w * np.cos(w * t[:, None] + phase)
    reference = Reference(t, np.hstack([q, rates]))
    x0 = reference.at(0.0)
    runs = {}
    for mode, goal in (("preview", reference), ("held", reference.without_preview())):
        controller = config.make(ocp)
        controller.wait_compiled()
        runs[mode] = simulate(problem.plant(), controller, x0, goal, duration=0.5)
    for sol in runs["preview"].solutions:
        _check_step(controller, sol)
    oks = sum(sol.ok for sol in runs["preview"].solutions)
    assert oks >= 0.8 * len(runs["preview"].solutions), (oks, {s.raw_status for s in runs["preview"].solutions})
    if config.options.get("variant") == "paper":
        return  # the paper's Algorithm 1 as printed does not control the N-link robots (docs: Choose a controller)
    rms = {mode: float(np.sqrt(np.mean(_tracking_error(traj, reference) ** 2))) for mode, traj in runs.items()}
    still = float(np.sqrt(np.mean(np.abs(q[:51] - q[0]).max(axis=1) ** 2)))  # holding the start, 0.5 s
    assert rms["preview"] <= 0.5 * still, (rms, still)
    assert rms["preview"] <= 1.05 * rms["held"], rms

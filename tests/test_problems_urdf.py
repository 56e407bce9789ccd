"""Robots from a URDF (Problem.from_urdf): the Franka Panda with its prismatic fingers, against pinocchio."""

from __future__ import annotations

import re
from pathlib import Path

import casadi as ca
import numpy as np
import pinocchio as pin
import pytest

from ocpkit import Problem, URDFRobot
from ocpkit.problems import make
from ocpkit.sim.simulate import simulate
from ocpkit.solvers.qp import LinearMPC
from ocpkit.problems.panda import urdf_path as panda_urdf

PANDA = panda_urdf()
WHEEL_ARM = Path(__file__).parent / "data" / "wheel_arm.urdf"  # continuous joints "shoulder" (z) and "spin" (tilted)
FINGERS = ["panda_finger_joint1", "panda_finger_joint2"]
TOL = 1e-9


@pytest.fixture(scope="module")
def panda():
    return Problem.from_urdf(PANDA)


@pytest.fixture(scope="module")
def arm():
    return Problem.from_urdf(PANDA, locked_joints=FINGERS)


def _states(problem, rng, count=5):
    n = problem.chain.n
    lo, hi = problem.q_min, problem.q_max
    return [(rng.uniform(lo, hi), rng.normal(size=n), rng.normal(size=n) * 5) for _ in range(count)]


def test_urdf_is_read_with_prismatic_fingers_damping_and_limits(panda):
    assert isinstance(panda, URDFRobot) and panda.chain.n == 9 and not panda.chain.serial
    assert panda.chain.revolute == [True] * 7 + [False, False]
    np.testing.assert_array_equal(panda.damping, [0.003] * 7 + [0.3, 0.3])  # <dynamics damping>
    ocp = panda.ocp(knots=3)
    np.testing.assert_array_equal(ocp.u_max, [87, 87, 87, 87, 12, 12, 12, 100, 100])  # <limit effort>
    np.testing.assert_array_equal(ocp.u_min, -ocp.u_max)
    assert panda.plant().input_names[7] == "tau_panda_finger_joint1"


def test_plant_equals_pinocchio_aba_with_damping(panda):
    """ẋ = [q̇, ABA(q, q̇, τ − b q̇)] against pinocchio's ABA on the full URDF (fingers as prismatic joints)."""
    model = pin.buildModelFromUrdf(PANDA)
    data = model.createData()
    f = panda.plant().f
    worst = 0.0
    for q, qd, tau in _states(panda, np.random.default_rng(1)):
        ours = np.asarray(f(np.r_[q, qd], tau)).ravel()
        ref = pin.aba(model, data, q, qd, tau - model.damping * qd)
        np.testing.assert_array_equal(ours[:9], qd)
        err = np.abs(ours[9:] - ref).max() / max(1.0, np.abs(ref).max())
        worst = max(worst, err)
    assert worst < TOL, worst


def test_locked_fingers_equal_pinocchios_reduced_model(arm):
    full = pin.buildModelFromUrdf(PANDA)
    ids = [full.getJointId(name) for name in FINGERS]
    reduced = pin.buildReducedModel(full, ids, pin.neutral(full))
    data = reduced.createData()
    assert arm.chain.n == 7 and arm.chain.serial and arm.joint_names == [f"panda_joint{i}" for i in range(1, 8)]
    f = arm.plant().f
    for q, qd, tau in _states(arm, np.random.default_rng(2)):
        ref = pin.aba(reduced, data, q, qd, tau - reduced.damping * qd)
        np.testing.assert_allclose(
            np.asarray(f(np.r_[q, qd], tau)).ravel()[7:], ref, rtol=0, atol=TOL * max(1.0, np.abs(ref).max())
        )


def test_locked_position_moves_the_fingers_mass(arm):
    """Fingers locked open (4 cm each) vs closed: same masses, different inertia about the wrist axes."""
    wide = Problem.from_urdf(PANDA, locked_joints=FINGERS, locked_positions={f: 0.04 for f in FINGERS})
    q = ca.SX.sym("q", 7)
    M = [ca.Function("M", [q], [p.chain.crba(q)]) for p in (arm, wide)]
    q0 = np.array([0.0, -0.3, 0.0, -2.0, 0.0, 1.6, 0.8])
    assert float(M[1](q0)[6, 6] - M[0](q0)[6, 6]) > 1e-5


def test_gravity_compensation_is_the_input_goal(arm):
    """u_g(goal) = g(q_goal) (pinocchio's generalized gravity), and it holds the goal at rest in the plant."""
    reduced = pin.buildReducedModel(pin.buildModelFromUrdf(PANDA), [8, 9], np.zeros(9))
    data = reduced.createData()
    ocp = arm.ocp(knots=5)
    _, goal = arm.sample(0)
    ug = ocp.input_goal(goal)
    np.testing.assert_allclose(ug, pin.computeGeneralizedGravity(reduced, data, goal[:7]), atol=1e-9)
    np.testing.assert_allclose(np.asarray(arm.plant().f(goal, ug)).ravel(), 0, atol=1e-9)
    # The stage cost (IPOPT's, EMPC's) is zero at the goal with that input.
    assert float(ocp.cost.stage(goal, ug, goal)) == pytest.approx(0, abs=1e-20)
    off = Problem.from_urdf(PANDA, locked_joints=FINGERS, gravity_compensation=False).ocp(knots=5)
    np.testing.assert_array_equal(off.input_goal(goal), 0)


def test_arm_reaches_its_goal_with_linear_mpc(arm):
    """The 7-DoF arm (fingers locked) from rest to a goal up to 0.5 rad away per joint, condensed 5-knot QP."""
    ctrl = LinearMPC(arm.ocp(knots=5))
    x0, goal = arm.sample(0)
    assert np.abs(goal - x0).max() > 0.3
    traj = simulate(arm.plant(), ctrl, x0, goal, arm.duration)
    assert traj.fallbacks == 0
    assert np.abs(traj.x[-1, :7] - goal[:7]).max() <= 0.02


def test_arm_with_fingers_reaches_its_goal(panda):
    """All 9 joints, the prismatic fingers included."""
    ctrl = LinearMPC(panda.ocp(knots=5))
    x0, goal = panda.sample(1)
    traj = simulate(panda.plant(), ctrl, x0, goal, panda.duration)
    assert traj.fallbacks == 0
    assert np.abs(traj.x[-1, :7] - goal[:7]).max() <= 0.02  # rad
    assert np.abs(traj.x[-1, 7:9] - goal[7:9]).max() <= 1e-3  # m


def test_model_error_half_still_solves(panda):
    """Error multiplier 0.5 halves the fingers' mass: QP gradients near 1e8, where an absolute 1e-9 tolerance
    alone was never met (every step 10,000 iterations and the fallback; a robustness study looked hung)."""
    ctrl = LinearMPC(panda.ocp(knots=2, error=0.5))
    x0, goal = panda.sample(0)
    traj = simulate(panda.plant(), ctrl, x0, goal, 0.3)
    assert traj.fallbacks == 0 and max(s.iterations for s in traj.solutions) < 10_000


def _pin_configuration(model, q):
    """pinocchio's configuration of one angle (or offset) per joint: a continuous joint's angle as (cos, sin)."""
    return np.concatenate([[np.cos(a), np.sin(a)] if model.joints[i + 1].nq == 2 else [a] for i, a in enumerate(q)])


def test_continuous_joints_equal_pinocchio():
    """A URDF with two continuous joints (about z and about a tilted axis), a revolute and a prismatic joint: one
    unbounded angle per continuous joint, and M(q), h(q, q̇), ẋ and the tool frame equal pinocchio's own model of
    the file (cos/sin configuration) at random states, angles beyond ±π included."""
    robot = Problem.from_urdf(WHEEL_ARM)
    model = pin.buildModelFromUrdf(str(WHEEL_ARM))
    data = model.createData()
    assert (model.nq, model.nv, robot.chain.n) == (6, 4, 4)
    assert robot.joint_names == ["shoulder", "elbow", "extend", "spin"]
    np.testing.assert_array_equal(robot.q_min, [-np.inf, -2, 0, -np.inf])
    np.testing.assert_array_equal(robot.q_max, [np.inf, 2, 0.1, np.inf])
    np.testing.assert_array_equal(robot.tau_max, [40, 20, 50, 5])
    q, qd = ca.SX.sym("q", 4), ca.SX.sym("qd", 4)
    M, h = ca.Function("M", [q], [robot.chain.crba(q)]), ca.Function("h", [q, qd], [robot.chain.bias(q, qd)])
    f, tool = robot.plant().f, model.getFrameId("tool")
    rng = np.random.default_rng(5)
    for _ in range(5):
        angles = rng.uniform([-7, -2, 0, -7], [7, 2, 0.1, 7])
        v, tau = rng.normal(size=4) * 2, rng.normal(size=4) * 5
        qp = _pin_configuration(model, angles)
        pin.framesForwardKinematics(model, data, qp)
        placement = data.oMf[tool]
        pairs = (
            (M(angles), np.triu(pin.crba(model, data, qp)) + np.triu(data.M, 1).T),
            (h(angles, v), pin.nonLinearEffects(model, data, qp, v)),
            (np.asarray(f(np.r_[angles, v], tau))[4:], pin.aba(model, data, qp, v, tau - model.damping * v)),
            (robot.kinematics.position(angles, "tool"), placement.translation),
            (robot.kinematics.placement(angles, "tool")[0], placement.rotation),
        )
        for ours, ref in pairs:
            np.testing.assert_allclose(
                np.asarray(ours).reshape(np.shape(ref)), ref, rtol=0, atol=TOL * max(1.0, np.abs(ref).max())
            )
    bounded = Problem.from_urdf(WHEEL_ARM, position_bounds=True)
    np.testing.assert_array_equal(bounded.defaults()["x_min"][:4], [-np.inf, -2, 0, -np.inf])
    x0, goal = robot.sample(0)
    assert LinearMPC(robot.ocp(knots=3)).solve(x0, goal).status == "success"


def test_locked_continuous_joint_equals_pinocchios_reduced_model():
    """A continuous joint locked at 0.7 rad: pinocchio's reduced model at (cos 0.7, sin 0.7)."""
    robot = Problem.from_urdf(WHEEL_ARM, locked_joints=["spin"], locked_positions={"spin": 0.7})
    full = pin.buildModelFromUrdf(str(WHEEL_ARM))
    reduced = pin.buildReducedModel(full, [full.getJointId("spin")], _pin_configuration(full, [0.0, 0.0, 0.0, 0.7]))
    data = reduced.createData()
    f = robot.plant().f
    rng = np.random.default_rng(3)
    states = rng.uniform([-7, -2, 0], [7, 2, 0.1], (5, 3)), rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    for q, qd, tau in zip(*states):
        ref = pin.aba(reduced, data, _pin_configuration(reduced, q), qd, tau - reduced.damping * qd)
        np.testing.assert_allclose(
            np.asarray(f(np.r_[q, qd], tau)).ravel()[3:], ref, rtol=0, atol=TOL * max(1.0, np.abs(ref).max())
        )


def test_bad_urdf_options_name_the_argument(tmp_path):
    with pytest.raises(ValueError, match=re.escape("has no joint 'panda_finger3'; its joints: panda_joint1")):
        Problem.from_urdf(PANDA, locked_joints=["panda_finger3"])
    with pytest.raises(ValueError, match="not in locked_joints"):
        Problem.from_urdf(PANDA, locked_positions={"panda_finger_joint1": 0.01})
    with pytest.raises(ValueError, match="damping"):
        Problem.from_urdf(PANDA, damping=[0.1, 0.2])
    with pytest.raises(ValueError, match="URDF file not found"):
        Problem.from_urdf(tmp_path / "missing.urdf")
    (tmp_path / "bad.urdf").write_text("<robot name='x'><link name='a'/><joint/></robot>")
    with pytest.raises(ValueError, match="not a URDF"):
        Problem.from_urdf(tmp_path / "bad.urdf")


def test_urdf_spec_and_export_with_gravity_compensation(tmp_path):
    p = make(f"urdf:{PANDA}")
    assert isinstance(p, URDFRobot) and p.chain.n == 9 and p.name == "urdf:panda"
    from ocpkit.export import export_problem

    spec = tmp_path / "arm.py"
    spec.write_text(
        f"from ocpkit import Problem\n\ndef Arm():\n    return Problem.from_urdf({PANDA!r}, "
        f"locked_joints={FINGERS!r})\n"
    )
    arm = make(f"{spec}:Arm")
    assert arm.chain.n == 7
    info = export_problem(f"{spec}:Arm", out_dir=tmp_path / "out", horizon=30, steps=5)
    assert "HAS_GOAL_INPUT 1" in (info.out_dir / "mpc.c").read_text()  # g(q_goal) generated into the C


def test_urdf_tutorial_runs_as_written(capsys):
    """The tutorial "Your own robot from a URDF" (examples/urdf_robot.py) brings the Panda to its joint goal."""
    from conftest import run_example

    run_example("urdf_robot.py")
    assert float(capsys.readouterr().out) <= 0.02

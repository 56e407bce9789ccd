"""Forward kinematics of named frames against pinocchio, and the spheres that approximate a robot."""

from __future__ import annotations

from functools import lru_cache

import casadi as ca
import numpy as np
import pinocchio as pin
import pytest

from ocpkit import Problem
from ocpkit.model.kinematics import Kinematics, RobotSphere, collision_spheres, sphere_centers, spheres_along_links
from ocpkit.problems import make
from ocpkit.problems.panda import urdf_path as panda_urdf

PANDA = panda_urdf()
TOL = 1e-9
ROBOTS = {
    "panda": lambda: Problem.from_urdf(PANDA),
    "puma560": lambda: make("puma560"),
    "baxter": lambda: make("baxter"),
    "nlink3": lambda: make("nlink:3"),
    "nlink7": lambda: make("nlink:7"),
}


@lru_cache(maxsize=None)
def _robot(name):
    return ROBOTS[name]()


def _random_q(model, rng):
    """Uniform within the joint limits clipped to [−π, π] (nlink's are ±DBL_MAX)."""
    lo, hi = np.array(model.lowerPositionLimit), np.array(model.upperPositionLimit)
    return rng.uniform(np.clip(lo, -np.pi, np.pi), np.clip(hi, -np.pi, np.pi))


def _frame_id(model, name):
    """pinocchio's frame of this name as Kinematics reads it: the BODY frame, else the first."""
    ids = [k for k, f in enumerate(model.frames) if f.name == name]
    return next((k for k in ids if model.frames[k].type == pin.FrameType.BODY), ids[0])


def _all_frames(kin):
    q = ca.SX.sym("q", kin.n)
    out = []
    for frame in kin.frames:
        out.extend(kin.placement(q, frame))
    return ca.Function("frames", [q], out)


@pytest.mark.parametrize("name", ROBOTS)
def test_every_frame_equals_pinocchio(name):
    problem = _robot(name)
    kin, model = problem.kinematics, problem.pin_model
    assert kin is problem.kinematics and kin.n == model.nq == model.nv
    assert len(set(kin.frames)) == len(kin.frames) and set(kin.frames) == {f.name for f in model.frames}
    data = model.createData()
    f = _all_frames(kin)
    ids = [_frame_id(model, frame) for frame in kin.frames]
    rng = np.random.default_rng(7)
    worst = 0.0
    for _ in range(5):
        q = _random_q(model, rng)
        pin.framesForwardKinematics(model, data, q)
        values = f(q)
        for k, i in enumerate(ids):
            R, p = np.asarray(values[2 * k]), np.asarray(values[2 * k + 1]).ravel()
            worst = max(worst, np.abs(R - data.oMf[i].rotation).max(), np.abs(p - data.oMf[i].translation).max())
    assert worst < TOL, worst


def test_placement_of_mx_and_numbers_and_the_cached_function():
    kin = _robot("panda").kinematics
    q = np.random.default_rng(1).uniform(-1, 1, kin.n)
    R, p = kin.placement(ca.SX(q), "panda_hand")
    qm = ca.MX.sym("q", kin.n)
    Rm, pm = kin.placement(qm, "panda_hand")
    assert isinstance(pm, ca.MX)
    Rn, pn = ca.Function("g", [qm], [Rm, pm])(q)
    np.testing.assert_allclose(np.asarray(ca.evalf(R)), np.asarray(Rn), atol=TOL)
    np.testing.assert_allclose(np.asarray(kin.position(q, "panda_hand")), np.asarray(pn), atol=TOL)
    fk = kin.function("panda_hand")
    assert fk is kin.function("panda_hand") and fk.name() == "fk_panda_hand"
    assert fk.name_out() == ["p", "R"]
    with pytest.raises(ValueError, match="column of 9"):
        kin.placement(ca.SX.sym("q", 3), "panda_hand")


def test_unknown_frame_names_it_and_the_close_ones():
    kin = _robot("panda").kinematics
    with pytest.raises(ValueError, match=r"unknown frame 'panda_hnd'.*did you mean 'panda_hand'.*panda_link0"):
        kin.position(ca.SX.sym("q", kin.n), "panda_hnd")
    with pytest.raises(TypeError, match="frame name"):
        kin.function(3)


def test_a_model_without_frames_gets_one_per_joint_and_a_tree_with_prismatic_unaligned_joints():
    """Joints built with addJoint alone (no frames), unaligned revolute and prismatic axes, a branch."""
    rng = np.random.default_rng(3)
    model = pin.Model()
    joints = [
        pin.JointModelRevoluteUnaligned(np.array([1.0, 2.0, 2.0]) / 3),
        pin.JointModelPX(),
        pin.JointModelPrismaticUnaligned(np.array([0.0, 0.6, 0.8])),
        pin.JointModelRY(),
    ]
    for i, (joint, parent) in enumerate(zip(joints, (0, 1, 2, 1))):
        placement = pin.SE3(pin.rpy.rpyToMatrix(*rng.uniform(-np.pi, np.pi, 3)), rng.uniform(-0.3, 0.3, 3))
        model.addJoint(parent, joint, placement, f"j{i}")
        model.appendBodyToJoint(i + 1, pin.Inertia.Random(), pin.SE3.Identity())
    kin = Kinematics(model)
    assert kin.frames == ["universe", "j0", "j1", "j2", "j3"]
    assert kin.segments() == [("j0", "j1"), ("j0", "j3"), ("j1", "j2")]
    data = model.createData()
    f = _all_frames(kin)
    for _ in range(5):
        q = rng.uniform(-1, 1, 4)
        pin.forwardKinematics(model, data, q)
        values = f(q)
        for k, frame in enumerate(kin.frames):
            i = model.getJointId(frame) if frame != "universe" else 0
            np.testing.assert_allclose(np.asarray(values[2 * k]), data.oMi[i].rotation, atol=TOL)
            np.testing.assert_allclose(np.asarray(values[2 * k + 1]).ravel(), data.oMi[i].translation, atol=TOL)


def test_a_name_shared_by_a_joint_and_a_link_means_the_link():
    model = pin.Model()
    jid = model.addJoint(0, pin.JointModelRZ(), pin.SE3.Identity(), "arm")
    joint_frame = model.addJointFrame(jid, 0)
    offset = pin.SE3(np.eye(3), np.array([0.3, 0.0, 0.1]))
    model.addBodyFrame("arm", jid, offset, joint_frame)
    kin = Kinematics(model)
    assert kin.frames.count("arm") == 1
    np.testing.assert_allclose(np.asarray(kin.position([np.pi / 2], "arm")).ravel(), [0.0, 0.3, 0.1], atol=TOL)


# --- spheres along links ------------------------------------------------------------------------------


def _segment_ends(problem, q):
    """World start and end points of every segment at q (a prismatic end at its q = 0 origin)."""
    kin = problem.kinematics
    out = []
    for a, b in kin.segments():
        q_end = q.copy()
        if b in kin.joints and not kin.chain.revolute[kin.joints.index(b)]:
            q_end[kin.joints.index(b)] = 0.0
        out.append((a, np.asarray(kin.position(q, a)).ravel(), np.asarray(kin.position(q_end, b)).ravel()))
    return out


@pytest.mark.parametrize("name", ROBOTS)
def test_spheres_along_links_cover_every_segment(name):
    problem = _robot(name)
    kin, r = problem.kinematics, problem.link_radius
    spheres = spheres_along_links(kin, r)
    assert spheres and all(s.radius == r for s in spheres)
    assert len(set(spheres)) == len(spheres)
    centers = sphere_centers(kin, spheres)
    rng = np.random.default_rng(2)
    t = np.linspace(0.0, 1.0, 41)
    for _ in range(3):
        q = _random_q(problem.pin_model, rng)
        C = np.asarray(centers(q))
        for a, start, end in _segment_ends(problem, q):
            points = start[:, None] + (end - start)[:, None] * t
            mine = C[:, [s.frame == a for s in spheres]]
            if np.linalg.norm(end - start) < 1e-12:
                continue
            gaps = np.linalg.norm(points[:, :, None] - mine[:, None, :], axis=0).min(axis=1)
            assert gaps.max() <= r + 1e-9, (a, gaps.max())


def test_spheres_along_links_options():
    kin = _robot("puma560").kinematics
    spheres = spheres_along_links(kin, 0.1, spacing=0.2)
    # The forearm (joint 4 to the wrist centre, 0.4318 m) takes ⌈0.4318 / 0.2⌉ + 1 = 4 spheres; the wrist's
    # zero-length segments (joint 5 to 6, joint 6 to the tool) none.
    assert sum(s.frame == "joint4" for s in spheres) == 4
    assert not any(s.frame in ("joint5", "joint6") for s in spheres)
    only = spheres_along_links(kin, 0.1, frames=["joint2"])
    assert only and {s.frame for s in only} == {"joint2"}
    np.testing.assert_allclose(only[-1].offset, [0.4318, 0.0, 0.0], atol=TOL)  # the end stays: joint3 is left out
    with pytest.raises(ValueError, match="spacing must be <= 2"):
        spheres_along_links(kin, 0.1, spacing=0.25)
    with pytest.raises(ValueError, match="'joint6' starts no segment"):
        spheres_along_links(kin, 0.1, frames="joint6")
    with pytest.raises(ValueError, match="unknown frame 'elbow'"):
        spheres_along_links(kin, 0.1, frames=["elbow"])
    with pytest.raises(ValueError, match="radius must be finite and > 0"):
        spheres_along_links(kin, 0.0)


def test_sphere_centers_match_placements():
    kin = _robot("baxter").kinematics
    spheres = [
        RobotSphere("right_gripper", (0.0, 0.0, 0.0), 0.05),
        RobotSphere("right_e1", (0.1, -0.2, 0.3), 0.1),
        RobotSphere("base", (1.0, 2.0, 3.0), 0.2),
    ]
    f = sphere_centers(kin, spheres)
    assert f.name() == "sphere_centers" and f.size_out(0) == (3, 3)
    q = np.random.default_rng(5).uniform(-1, 1, kin.n)
    C = np.asarray(f(q))
    for k, s in enumerate(spheres):
        R, p = (np.asarray(v) for v in kin.placement(q, s.frame))
        np.testing.assert_allclose(C[:, k], p.ravel() + R @ np.array(s.offset), atol=TOL)
    with pytest.raises(ValueError, match="unknown frame 'hand'"):
        sphere_centers(kin, [RobotSphere("hand", (0, 0, 0), 0.1)])
    with pytest.raises(ValueError, match="non-empty"):
        sphere_centers(kin, [])
    with pytest.raises(ValueError, match="offset must be 3"):
        RobotSphere("base", (0, 0), 0.1)


# --- spheres from the URDF's collision geometry ---------------------------------------------------------

ARM_URDF = """<robot name="two_link">
  <link name="base"/>
  <link name="upper">
    <collision><origin xyz="0 0 0.2"/><geometry><cylinder radius="0.05" length="0.4"/></geometry></collision>
  </link>
  <link name="fore">
    <collision><origin xyz="0.1 0 0" rpy="0 1.5707963267948966 0"/>
      <geometry><cylinder radius="0.04" length="0.2"/></geometry></collision>
    <collision><origin xyz="0.25 0 0"/><geometry><sphere radius="0.06"/></geometry></collision>
    <collision><origin xyz="0.1 0.05 0" rpy="0.3 0.2 0.1"/><geometry><box size="0.1 0.05 0.3"/></geometry></collision>
  </link>
  <joint name="shoulder" type="revolute"><parent link="base"/><child link="upper"/><axis xyz="0 1 0"/>
    <limit lower="-3" upper="3" effort="10" velocity="1"/></joint>
  <joint name="elbow" type="revolute"><parent link="upper"/><child link="fore"/><origin xyz="0 0 0.4"/>
    <axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="10" velocity="1"/></joint>
</robot>
"""


def _rpy(r, p, y):
    return pin.rpy.rpyToMatrix(r, p, y)


def _samples(shape, rng, count=400):
    """Points inside and on the surface of a primitive in its own frame."""
    kind, dims = shape
    u = rng.uniform(-1, 1, (count, 3))
    if kind == "box":
        u[: count // 2] = np.sign(u[: count // 2])  # corners and edges too
        return u * np.asarray(dims) / 2
    r, length = dims
    angle = rng.uniform(0, 2 * np.pi, count)
    rho = np.where(np.arange(count) % 2, r, r * np.sqrt(rng.uniform(0, 1, count)))  # rim and interior
    z = np.where(np.arange(count) % 3 == 0, np.sign(u[:, 2]) * length / 2, u[:, 2] * length / 2)
    return np.c_[rho * np.cos(angle), rho * np.sin(angle), z]


@pytest.mark.parametrize("radius", [None, 0.03, 0.09])
def test_collision_spheres_cover_cylinders_boxes_and_spheres(tmp_path, radius):
    path = tmp_path / "arm.urdf"
    path.write_text(ARM_URDF)
    kin = Kinematics(pin.buildModelFromUrdf(str(path)))
    spheres = collision_spheres(path, kin, radius=radius)
    assert {s.frame for s in spheres} == {"upper", "fore"}
    assert RobotSphere("fore", (0.25, 0.0, 0.0), 0.06) in spheres  # a <sphere> is itself
    if radius is None:  # √2·r, spaced 2r along the axis
        upper = [s for s in spheres if s.frame == "upper"]
        np.testing.assert_allclose([s.offset for s in upper], [[0, 0, z] for z in (0.05, 0.15, 0.25, 0.35)], atol=TOL)
        np.testing.assert_allclose([s.radius for s in upper], np.hypot(0.05, 0.05))
    primitives = [
        ("upper", ("cylinder", (0.05, 0.4)), np.eye(3), [0, 0, 0.2]),
        ("fore", ("cylinder", (0.04, 0.2)), _rpy(0, np.pi / 2, 0), [0.1, 0, 0]),
        ("fore", ("box", (0.1, 0.05, 0.3)), _rpy(0.3, 0.2, 0.1), [0.1, 0.05, 0]),
    ]
    rng = np.random.default_rng(0)
    for link, shape, R, t in primitives:
        points = _samples(shape, rng) @ R.T + np.asarray(t)
        mine = [s for s in spheres if s.frame == link]
        centers = np.array([s.offset for s in mine])
        radii = np.array([s.radius for s in mine])
        inside = np.linalg.norm(points[:, None, :] - centers[None], axis=2) <= radii + 1e-9
        assert inside.any(axis=1).all(), (link, shape)
    # The spheres' world centres follow the links.
    q = np.array([0.4, -0.7])
    C = np.asarray(sphere_centers(kin, spheres)(q))
    R, p = (np.asarray(v) for v in kin.placement(q, "fore"))
    k = spheres.index(RobotSphere("fore", (0.25, 0.0, 0.0), 0.06))
    np.testing.assert_allclose(C[:, k], p.ravel() + R @ [0.25, 0, 0], atol=TOL)


def test_collision_spheres_refuse_meshes_and_urdfs_without_collisions(tmp_path):
    mesh = ARM_URDF.replace('<sphere radius="0.06"/>', '<mesh filename="hand.stl"/>')
    (tmp_path / "mesh.urdf").write_text(mesh)
    kin = Kinematics(pin.buildModelFromUrdf(str(tmp_path / "mesh.urdf")))
    with pytest.raises(ValueError, match=r"link 'fore': a <mesh> .*cannot be turned into spheres.*spheres_along_links"):
        collision_spheres(tmp_path / "mesh.urdf", kin)
    panda = _robot("panda")
    with pytest.raises(ValueError, match=r"no <collision> element.*spheres_along_links"):
        collision_spheres(PANDA, panda.kinematics)
    with pytest.raises(ValueError, match="not found"):
        collision_spheres(tmp_path / "missing.urdf", kin)


# --- the robots' end effectors ----------------------------------------------------------------------------


@pytest.mark.parametrize("name", ROBOTS)
def test_every_robot_has_an_end_effector_frame_and_a_link_radius(name):
    problem = _robot(name)
    assert problem.end_effector in problem.kinematics.frames
    assert 0 < problem.link_radius < 0.2


def test_end_effectors_where_expected():
    assert _robot("panda").end_effector == "panda_hand_tcp"
    assert _robot("baxter").end_effector == "right_gripper"
    nlink = _robot("nlink3")
    np.testing.assert_allclose(
        np.asarray(nlink.kinematics.position(np.zeros(3), "tip")).ravel(), [0.75, 0, 0], atol=TOL
    )
    puma = _robot("puma560").kinematics  # a spherical wrist: the tool's origin ignores q4 … q6
    q = np.random.default_rng(4).uniform(-1, 1, 6)
    q2 = q.copy()
    q2[3:] += 0.5
    np.testing.assert_allclose(np.asarray(puma.position(q, "tool")), np.asarray(puma.position(q2, "tool")), atol=TOL)
    arm = Problem.from_urdf(
        PANDA, end_effector="panda_link8", locked_joints=["panda_finger_joint1", "panda_finger_joint2"]
    )
    assert arm.end_effector == "panda_link8"
    assert (
        Problem.from_urdf(PANDA, locked_joints=["panda_finger_joint1", "panda_finger_joint2"]).end_effector
        == "panda_hand_tcp"
    )
    with pytest.raises(ValueError, match="end_effector 'hand' is not a frame"):
        Problem.from_urdf(PANDA, end_effector="hand")

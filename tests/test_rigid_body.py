"""CasADi rigid-body dynamics against pinocchio, energy conservation, the error multiplier, robot problems."""

from __future__ import annotations


import casadi as ca
import numpy as np
import pinocchio as pin
import pytest

from ocpkit.problems.baxter import Baxter, baxter_arm_model
from ocpkit.problems.nlink import NLink, planar_chain
from ocpkit.problems.puma560 import Puma560, puma560_model
from ocpkit.model.rigid_body import Chain
from ocpkit.problems.panda import urdf_path as panda_urdf

TOL = 1e-9
PANDA_URDF = panda_urdf()


def _random_chain(n=5, seed=3):
    """A seeded 3-D chain with unaligned revolute axes, random placements, inertias and armature."""
    rng = np.random.default_rng(seed)
    model = pin.Model()
    parent = 0
    for i in range(n):
        axis = rng.normal(size=3)
        placement = pin.SE3(pin.rpy.rpyToMatrix(*rng.uniform(-np.pi, np.pi, 3)), rng.uniform(-0.3, 0.3, 3))
        parent = model.addJoint(
            parent, pin.JointModelRevoluteUnaligned(axis / np.linalg.norm(axis)), placement, f"j{i}"
        )
        L = rng.normal(size=(3, 3))
        model.appendBodyToJoint(
            parent,
            pin.Inertia(rng.uniform(0.5, 3), rng.uniform(-0.2, 0.2, 3), L @ L.T * 0.05 + 0.01 * np.eye(3)),
            pin.SE3.Identity(),
        )
    model.armature = rng.uniform(0, 0.2, n)
    return model


def _random_tree(n=7, seed=4):
    """A seeded 3-D tree mixing revolute and prismatic joints on aligned and unaligned axes, with random
    placements, inertias, armature and gravity. Each joint branches off the last one added or one of its
    ancestors (depth-first order, which pinocchio's algorithms assume)."""
    rng = np.random.default_rng(seed)
    model = pin.Model()
    kinds = [pin.JointModelRZ, pin.JointModelPX, pin.JointModelPY, pin.JointModelRY, pin.JointModelPZ]
    path = [0]  # the base, then the last joint's ancestors
    for i in range(n):
        parent = path[int(rng.integers(0, len(path)))]
        path = path[: path.index(parent) + 1]
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        if i % 3 == 2:
            joint = pin.JointModelPrismaticUnaligned(axis) if i % 2 else pin.JointModelRevoluteUnaligned(axis)
        else:
            joint = kinds[i % len(kinds)]()
        placement = pin.SE3(pin.rpy.rpyToMatrix(*rng.uniform(-np.pi, np.pi, 3)), rng.uniform(-0.3, 0.3, 3))
        jid = model.addJoint(parent, joint, placement, f"j{i}")
        path.append(jid)
        L = rng.normal(size=(3, 3))
        model.appendBodyToJoint(
            jid,
            pin.Inertia(rng.uniform(0.5, 3), rng.uniform(-0.2, 0.2, 3), L @ L.T * 0.05 + 0.01 * np.eye(3)),
            pin.SE3.Identity(),
        )
    model.armature = rng.uniform(0, 0.2, n)
    model.gravity = pin.Motion(rng.normal(size=3) * 5, np.zeros(3))
    return model


def _panda():
    """The Franka Panda from its shipped URDF: 7 revolute joints and two prismatic fingers, the
    second one on an unaligned (−y) axis, both children of the hand: a tree."""
    return pin.buildModelFromUrdf(PANDA_URDF)


MODELS = {
    "nlink1": lambda: planar_chain(1),
    "nlink2": lambda: planar_chain(2),
    "nlink7": lambda: planar_chain(7),
    "nlink13": lambda: planar_chain(13),
    "puma560": puma560_model,
    "baxter": baxter_arm_model,
    "unaligned": _random_chain,
    "tree_prismatic": _random_tree,
    "panda_fingers": _panda,
}


def _sym_functions(chain):
    n = chain.n
    q, qd, tau, qdd = (ca.SX.sym(s, n) for s in ("q", "qd", "tau", "qdd"))
    return (
        ca.Function("aba", [q, qd, tau], [chain.aba(q, qd, tau)]),
        ca.Function("M", [q], [chain.crba(q)]),
        ca.Function("h", [q, qd], [chain.bias(q, qd)]),
        ca.Function("rnea", [q, qd, qdd], [chain.rnea(q, qd, qdd)]),
    )


def _full(M):
    return np.triu(M) + np.triu(M, 1).T


@pytest.mark.parametrize("name", list(MODELS))
def test_matches_pinocchio(name):
    model = MODELS[name]()
    data = model.createData()
    chain = Chain(model)
    aba, crba, bias, rnea = _sym_functions(chain)
    rng = np.random.default_rng(7)
    n = chain.n
    for _ in range(5):
        q, qd = rng.uniform(-np.pi, np.pi, n), rng.normal(size=n) * 2
        tau, qdd = rng.normal(size=n) * 5, rng.normal(size=n)
        pairs = (
            (aba(q, qd, tau), pin.aba(model, data, q, qd, tau)),
            (crba(q), _full(pin.crba(model, data, q))),
            (bias(q, qd), pin.nonLinearEffects(model, data, q, qd)),
            (rnea(q, qd, qdd), pin.rnea(model, data, q, qd, qdd)),
        )
        for ours, ref in pairs:
            ours = np.array(ours).reshape(np.shape(ref))
            # 1e-9 relative to the magnitude (Baxter's light wrist reaches q̈ ~ 1e2 rad/s²; its URDF angles
            # 1.57079632679 are snapped to π/2 in Chain, a 1e-11 relative change).
            np.testing.assert_allclose(ours, ref, rtol=0, atol=TOL * max(1.0, np.abs(ref).max()))


def test_puma560_matches_published_values():
    """Corke's toolbox values for its mdl_puma560 (gravload at qz and qs, inertia at qn): an independent check
    of the DH-to-pinocchio conversion and the parameters."""
    chain = Chain(puma560_model())
    q = ca.SX.sym("q", 6)
    g = ca.Function("g", [q], [chain.bias(q, ca.SX.zeros(6))])
    M = ca.Function("M", [q], [chain.crba(q)])
    np.testing.assert_allclose(np.array(g([0, 0, 0, 0, 0, 0])).ravel(), [0, 37.4837, 0.2489, 0, 0, 0], atol=1e-4)
    np.testing.assert_allclose(
        np.array(g([0, 0, -np.pi / 2, 0, 0, 0])).ravel(), [0, 46.0069, 8.7722, 0, 0.0283, 0], atol=1e-4
    )
    Mqn = np.array(M([0, np.pi / 4, np.pi, 0, np.pi / 4, 0]))
    np.testing.assert_allclose(np.diag(Mqn), [3.6594, 4.4137, 0.9378, 0.1925, 0.1713, 0.1941], atol=1e-4)
    np.testing.assert_allclose(Mqn[0, 1:3], [-0.4044, 0.1006], atol=1e-4)


@pytest.mark.parametrize(
    "problem, tau_of",
    [
        (NLink(7), lambda p, q, qd, u: u - p.damping * qd),
        (NLink(2, gravity=9.81), lambda p, q, qd, u: u - p.damping * qd),  # the vertical double pendulum
        (Puma560(), lambda p, q, qd, u: u - p.damping * qd),
    ],
)
def test_problem_model_is_forward_dynamics_with_damping(problem, tau_of):
    model = problem.pin_model if hasattr(problem, "pin_model") else planar_chain(problem.links)
    data = model.createData()
    f = problem.plant().f
    n = model.nv
    rng = np.random.default_rng(11)
    for _ in range(3):
        q, qd, u = rng.uniform(-2, 2, n), rng.normal(size=n), rng.normal(size=n) * 3
        xdot = np.array(f(np.r_[q, qd], u)).ravel()
        np.testing.assert_allclose(xdot[:n], qd, rtol=0, atol=0)
        np.testing.assert_allclose(xdot[n:], pin.aba(model, data, q, qd, tau_of(problem, q, qd, u)), atol=TOL)


def test_nlink_gravity_variant_hangs_at_zero():
    """The variant "nlink:2:gravity": gravity in the arm's plane along q = 0, so q = 0 hangs and holding the
    straight arm horizontal takes m g (l/2 + 3l/2) at joint 1 and m g l/2 at joint 2 (pinocchio's g(q))."""
    from ocpkit import problems

    p = problems.make("nlink:2:gravity")
    assert p.name == "nlink:2:gravity" and p.gravity == 9.81 and problems.make("nlink:2").gravity == 0.0
    data = p.pin_model.createData()
    g = pin.computeGeneralizedGravity(p.pin_model, data, np.array([np.pi / 2, 0.0]))
    np.testing.assert_allclose(g, [9.81 * 0.5, 9.81 * 0.125], atol=1e-12)
    xdot = np.array(p.plant().f([0.1, 0.0, 0.0, 0.0], [0.0, 0.0])).ravel()
    assert xdot[2] < 0  # pulled back towards q = 0
    with pytest.raises(ValueError, match="variant"):
        problems.make("nlink:2:moon")


def test_baxter_model_is_the_pd_servo_without_gravity():
    p = Baxter()
    model = baxter_arm_model()
    model.gravity = pin.Motion.Zero()
    data = model.createData()
    rng = np.random.default_rng(5)
    for _ in range(3):
        q, qd, qdes = rng.uniform(-1, 1, 7), rng.normal(size=7), rng.uniform(-1, 1, 7)
        xdot = np.array(p.model().f(np.r_[q, qd], qdes)).ravel()
        tau = p.kp * (qdes - q) - p.kd * qd
        np.testing.assert_allclose(xdot[7:], pin.aba(model, data, q, qd, tau), atol=TOL)


def test_kinetic_energy_is_conserved_without_damping_input_or_gravity():
    """N-link plant with b = 0, τ = 0, g = 0 over 1 s: ½ q̇ᵀM q̇ (pinocchio's) constant to RK4 tolerance."""
    p = NLink(7, damping=0.0)
    pin_model = planar_chain(7)
    data = pin_model.createData()
    F = p.plant().rk4(0.01, 10)
    rng = np.random.default_rng(2)
    x = np.r_[rng.uniform(-np.pi, np.pi, 7), rng.normal(size=7)]
    energy = [pin.computeKineticEnergy(pin_model, data, x[:7], x[7:])]
    for _ in range(100):
        x = np.array(F(x, np.zeros(7))).ravel()
        energy.append(pin.computeKineticEnergy(pin_model, data, x[:7], x[7:]))
    energy = np.array(energy)
    assert energy[0] > 0.1
    assert np.abs(energy - energy[0]).max() < 1e-8 * energy[0]
    # With the paper's damping the energy decays monotonically instead.
    F_damped = NLink(7).plant().rk4(0.01, 10)
    x = np.r_[x[:7], x[7:]]
    e0 = pin.computeKineticEnergy(pin_model, data, x[:7], x[7:])
    x = np.array(F_damped(x, np.zeros(7))).ravel()
    assert pin.computeKineticEnergy(pin_model, data, x[:7], x[7:]) < e0


@pytest.mark.parametrize("make", [lambda: NLink(3), Puma560, Baxter])
def test_error_multiplier_scales_only_the_controllers_inertia(make):
    p = make()
    n = p.plant().nu
    rng = np.random.default_rng(4)
    x, u = np.r_[rng.uniform(-1, 1, n), rng.normal(size=n)], rng.normal(size=n)
    before = np.array(p.plant().f(x, u)).ravel()
    wrong = p.model(error=1.3)
    # The plant is untouched by building a wrong model, and error = 1 is the plant's model exactly.
    np.testing.assert_array_equal(np.array(p.plant().f(x, u)).ravel(), before)
    # error = 1 on a fresh problem gives bit-identical dynamics and affine matrices to the plant's.
    # (Baxter's plant samples its servo at 500 Hz, so there the comparison is with the continuous f.)
    fresh = make().model(error=1.0)
    np.testing.assert_array_equal(np.array(fresh.f(x, u)).ravel(), before)
    if not isinstance(p, Baxter):
        assert p.model(1.0) is p.plant()
        for a, b in zip(fresh.affine(0.01)(x, u), p.plant().affine(0.01)(x, u)):
            np.testing.assert_array_equal(np.array(a), np.array(b))
    # e·M(q) q̈_e = τ − h − b q̇  ⇔  q̈_e = q̈ / e, with M and h from pinocchio for the torque robots.
    qdd_true = before[n:]
    qdd_wrong = np.array(wrong.f(x, u)).ravel()[n:]
    np.testing.assert_allclose(qdd_wrong, qdd_true / 1.3, rtol=1e-12, atol=1e-12)
    if isinstance(p, Puma560):
        model = p.pin_model
        data = model.createData()
        q, qd = x[:n], x[n:]
        lhs = 1.3 * _full(pin.crba(model, data, q)) @ qdd_wrong + pin.nonLinearEffects(model, data, q, qd)
        np.testing.assert_allclose(lhs, u - p.damping * qd, atol=1e-9)


def test_baxter_plant_samples_its_servo():
    p = Baxter()
    x0, goal = p.sample(0)
    qdes = goal[:7]
    sampled = np.array(p.plant().rk4(0.01, 10)(x0, qdes)).ravel()
    continuous = np.array(p.model().rk4(0.01, 10)(x0, qdes)).ravel()
    assert 0 < np.abs(sampled - continuous).max() < 1e-2 * np.abs(continuous - x0).max()
    # A faster servo tends to the continuous one.
    from ocpkit.problems.baxter import SampledServo

    plant = p.plant()
    fast = SampledServo("fast", plant.x, plant.u, plant.xdot, arm_f=plant.arm_f, kp=p.kp, kd=p.kd, rate=20000)
    fast_x = np.array(fast.rk4(0.01, 10)(x0, qdes)).ravel()
    assert np.abs(fast_x - continuous).max() < 0.05 * np.abs(sampled - continuous).max()
    with pytest.raises(ValueError, match="dt"):
        p.plant().rk4(0.003)


def test_bad_inputs_raise_naming_the_argument():
    with pytest.raises(TypeError, match="model"):
        Chain("not a model")
    spherical = pin.Model()
    spherical.addJoint(0, pin.JointModelSpherical(), pin.SE3.Identity(), "ball")
    with pytest.raises(ValueError, match="1-DoF"):
        Chain(spherical)
    floating = pin.Model()
    floating.addJoint(0, pin.JointModelRZ(), pin.SE3.Identity(), "a")
    floating.addJoint(1, pin.JointModelPlanar(), pin.SE3.Identity(), "b")
    with pytest.raises(ValueError, match="1-DoF"):
        Chain(floating)
    chain = Chain(planar_chain(2))
    q = ca.SX.sym("q", 2)
    with pytest.raises(ValueError, match="inertia_scale"):
        chain.forward_dynamics(q, q, q, inertia_scale=0.0)
    with pytest.raises(ValueError, match="damping"):
        chain.forward_dynamics(q, q, q, damping=[0.1, 0.1, 0.1])
    with pytest.raises(ValueError, match="qd"):
        chain.aba(q, ca.SX.sym("v", 3), q)
    with pytest.raises(ValueError, match="links"):
        NLink(0)
    with pytest.raises(ValueError, match="error"):
        NLink(2).model(error=-1.0)


def test_registries_and_sampling():
    from ocpkit.problems import baxter, nlink, puma560

    p = nlink.REGISTRY["nlink"]("7")
    assert isinstance(p, NLink) and p.links == 7 and p.name == "nlink:7"
    with pytest.raises(ValueError, match="links"):
        nlink.REGISTRY["nlink"]("seven")
    with pytest.raises(ValueError, match="nlink"):
        nlink.REGISTRY["nlink"](None)
    assert isinstance(puma560.REGISTRY["puma560"](None), Puma560)
    with pytest.raises(ValueError, match="argument"):
        baxter.REGISTRY["baxter"]("2")
    for prob in (p, Puma560(), Baxter()):
        x0, goal = prob.sample(3)
        again = prob.sample(3)
        n = prob.plant().nu
        assert np.array_equal(x0, again[0]) and np.array_equal(goal, again[1])
        assert not np.array_equal(x0, prob.sample(4)[0])
        assert np.all(x0[n:] == 0) and np.all(goal[n:] == 0)
        ocp = prob.ocp(knots=3)
        assert np.all(ocp.u_min <= ocp.u_max) and ocp.nx == 2 * n

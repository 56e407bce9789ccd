"""The Puma 560 arm with gravity (Section III-C, eq. puma_dynamics): M(q) q̈ + C(q, q̇) + b q̇ + τ_grav = τ.

Kinematic and inertial parameters are the standard-DH set of Corke's Robotics Toolbox (``mdl_puma560``,
"params of 8/95"), from P. Corke and B. Armstrong-Hélouvry, "A search for consensus among model
parameters reported for the PUMA 560 robot", Proc. IEEE ICRA 1994, pp. 1608–1613, which builds on
B. Armstrong, O. Khatib and J. Burdick, "The explicit dynamic model and inertial parameters of the
PUMA 560 arm", Proc. IEEE ICRA 1986. Torque limits are the maximum joint torques of Armstrong et al.
1986 (Table 7). State x = [q, q̇], input τ (joint torques).
"""

from __future__ import annotations

from functools import cached_property

import casadi as ca
import numpy as np

from ocpkit.model.kinematics import Kinematics
from ocpkit.model.dynamics import Model
from ocpkit.model.problem import Problem
from ocpkit.model.rigid_body import Chain

# Standard DH per link: d (m), a (m), alpha (rad).
DH = (
    (0.0, 0.0, np.pi / 2),
    (0.0, 0.4318, 0.0),
    (0.15005, 0.0203, -np.pi / 2),
    (0.4318, 0.0, np.pi / 2),
    (0.0, 0.0, -np.pi / 2),
    (0.0, 0.0, 0.0),
)
MASS = (0.0, 17.4, 4.8, 0.82, 0.34, 0.09)  # kg (m1 unidentified: 0, as in RTB)
COM = (
    (0.0, 0.0, 0.0),
    (-0.3638, 0.006, 0.2275),
    (-0.0203, -0.0141, 0.070),
    (0.0, 0.019, 0.0),
    (0.0, 0.0, 0.0),
    (0.0, 0.0, 0.032),
)  # m, in DH link frame i
INERTIA = (
    (0.0, 0.35, 0.0),
    (0.13, 0.524, 0.539),
    (0.066, 0.086, 0.0125),
    (1.8e-3, 1.3e-3, 1.8e-3),
    (0.3e-3, 0.4e-3, 0.3e-3),
    (0.15e-3, 0.15e-3, 0.04e-3),
)  # Ixx Iyy Izz, kg m²
MOTOR_INERTIA = (200e-6, 200e-6, 200e-6, 33e-6, 33e-6, 33e-6)  # Jm, kg m² (motor side)
GEAR = (-62.6111, 107.815, -53.7063, 76.0364, 71.923, 76.686)  # G
MOTOR_VISCOUS = (1.48e-3, 0.817e-3, 1.38e-3, 71.2e-6, 82.6e-6, 36.7e-6)  # B, N m s/rad (motor side)
TAU_MAX = (97.6, 186.4, 89.4, 24.2, 20.1, 21.3)  # N m
Q_LIMITS_DEG = ((-160, 160), (-45, 225), (-225, 45), (-110, 170), (-100, 100), (-266, 266))


def puma560_model():
    """A pinocchio Model of the Puma 560 from its standard DH and inertial parameters.

    Joint i's frame is DH frame i−1 rotated by q_i about its z axis; link i's inertia, given in DH frame i,
    is moved into it by the constant DH offset Tz(d_i) Tx(a_i) Rx(α_i). Rotor inertias reflected through
    the gears (G² J_m) form the armature, added to M(q)'s diagonal. Gravity −9.81 m/s² along base z.
    Frames: one per joint (``joint1`` …) and ``tool``, DH frame 6 (the toolbox's ``fkine`` without a tool
    transform): with d₆ = 0 it lies at the wrist centre, where the axes of joints 4, 5 and 6 meet.
    """
    import pinocchio as pin

    model = pin.Model()
    model.name = "puma560"
    parent, offset, frame = 0, pin.SE3.Identity(), 0
    for i, (d, a, alpha) in enumerate(DH):
        parent = model.addJoint(parent, pin.JointModelRZ(), offset, f"joint{i + 1}")
        frame = model.addJointFrame(parent, frame)
        offset = pin.SE3(np.eye(3), np.array([a, 0.0, d])) * pin.SE3(_rot_x(alpha), np.zeros(3))
        body = pin.Inertia(MASS[i], np.array(COM[i]), np.diag(INERTIA[i]))
        model.appendBodyToJoint(parent, offset.act(body), pin.SE3.Identity())
    model.addFrame(pin.Frame("tool", parent, frame, offset, pin.FrameType.OP_FRAME))
    model.armature = np.array(MOTOR_INERTIA) * np.array(GEAR) ** 2
    model.lowerPositionLimit = np.deg2rad([lo for lo, _ in Q_LIMITS_DEG])
    model.upperPositionLimit = np.deg2rad([hi for _, hi in Q_LIMITS_DEG])
    model.effortLimit = np.array(TAU_MAX)
    return model


def _rot_x(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


class Puma560(Problem):
    """The Puma 560 under torque control with gravity.

    Viscous friction b = B G² per joint (the toolbox's motor-side B reflected to the joint: 5.8, 9.5,
    4.0, 0.41, 0.43, 0.22 N·m·s); Coulomb friction is left out (non-smooth). |τ_i| ≤ τ_max,i.
    Defaults: dt = 0.01 s, T = 50, 1 s closed loop (the paper's setup), Q = diag(100 per angle,
    1 per rate), R = 1e-3 I, terminal weight ``terminal_weight`` Q = 10 Q ("puma560:paper": Q, the paper's
    eq. mpc_problem, whose sum has no terminal term; :data:`PAPER_TERMINAL_WEIGHT`). Start and goal at rest,
    joint angles uniform in the middle half of each joint's range (seeded). ``kinematics``: its frames
    (``end_effector`` "tool", DH frame 6 at the wrist centre); ``link_radius`` for
    :func:`ocpkit.model.kinematics.spheres_along_links`.
    """

    duration = 1.0
    end_effector = "tool"
    link_radius = 0.08

    def __init__(self, terminal_weight: float = 10.0, name: str = "puma560"):
        self.name, self.terminal_weight = name, terminal_weight
        self.pin_model = puma560_model()
        self.chain = Chain(self.pin_model)
        self.damping = np.array(MOTOR_VISCOUS) * np.array(GEAR) ** 2
        self.tau_max = np.array(TAU_MAX)

    @cached_property
    def kinematics(self) -> Kinematics:
        return Kinematics(self.pin_model)

    def dynamics(self, error: float) -> Model:
        x, u = ca.SX.sym("x", 12), ca.SX.sym("u", 6)
        qdd = self.chain.forward_dynamics(x[:6], x[6:], u, damping=self.damping, inertia_scale=error)
        return Model(
            self.name,
            x,
            u,
            ca.vertcat(x[6:], qdd),
            state_names=[f"q{i}" for i in range(1, 7)] + [f"qd{i}" for i in range(1, 7)],
            input_names=[f"tau{i}" for i in range(1, 7)],
        )

    def defaults(self) -> dict:
        Q = np.diag(np.r_[100.0 * np.ones(6), np.ones(6)])
        return {
            "Q": Q,
            "R": 1e-3 * np.eye(6),
            "Q_terminal": self.terminal_weight * Q,
            "u_min": -self.tau_max,
            "u_max": self.tau_max,
        }

    def sample(self, seed: int):
        rng = np.random.default_rng(seed)
        lo, hi = self.pin_model.lowerPositionLimit, self.pin_model.upperPositionLimit
        mid, half = (lo + hi) / 2, (hi - lo) / 4
        q0, qg = rng.uniform(mid - half, mid + half, size=(2, 6))
        return np.r_[q0, np.zeros(6)], np.r_[qg, np.zeros(6)]


# The paper's cost (Section III-A, eq. mpc_problem) sums (x_goal − x_k)ᵀ Q (x_goal − x_k) over k = 0 … T−1 with no
# terminal term: x_T weighs as every other state. The default 10 Q makes a short horizon look ahead further than the
# paper's did (traditional MPC at T = 5 over T = 100, per-seed median over seeds 0–7: 1.105 with 10 Q, 1.735 with Q).
PAPER_TERMINAL_WEIGHT = 1.0


def _make(arg=None) -> Puma560:
    if arg == "paper":
        return Puma560(terminal_weight=PAPER_TERMINAL_WEIGHT, name="puma560:paper")
    if arg is not None:
        raise ValueError(f"puma560 takes no argument but 'paper' (the paper's cost), got {arg!r}")
    return Puma560()


REGISTRY = {"puma560": _make}

"""One 7-DoF Baxter arm behind a low-gain PD servo (Section VII "Hardware Experiments", eq. blow_molded).

    M(q) q̈ + C(q, q̇) q̇ = K_p (q_des − q) − K_d q̇

The robot compensates gravity itself, so g(q) is left out, as in the paper. The MPC's inputs are the
servo set points q_des at 100 Hz; the servo computes torques at 500 Hz. The controller's model is the
continuous servo above; the plant (:class:`SampledServo`) holds each servo torque for 2 ms, as the real
servo does. Kinematics and inertias are the manufacturer's URDF (Rethink Robotics' baxter_description,
BSD licence), trimmed to the right arm and its gripper in ``problems/data/baxter/``.
"""

from __future__ import annotations

import math
from functools import cached_property
from importlib import resources

import casadi as ca
import numpy as np

from ocpkit._checks import integer, positive
from ocpkit.model.kinematics import Kinematics
from ocpkit.model.dynamics import Model
from ocpkit.model.problem import Problem
from ocpkit.model.rigid_body import Chain

JOINTS = ("right_s0", "right_s1", "right_e0", "right_e1", "right_w0", "right_w1", "right_w2")
# Low servo gains: natural frequencies sqrt(K_p / M_ii(0)) of 0.5–1.5 Hz and damping ratios
# K_d / (2 sqrt(K_p M_ii(0))) of about 0.15, so every joint is clearly underdamped.
KP = (40.0, 40.0, 10.0, 10.0, 2.0, 2.0, 1.0)  # N·m/rad
KD = (4.0, 3.5, 0.3, 0.85, 0.1, 0.13, 0.06)  # N·m·s/rad
SERVO_RATE = 500.0  # Hz


def urdf_path() -> str:
    """Path of the shipped arm-only Baxter URDF."""
    return str(resources.files("ocpkit.problems").joinpath("data/baxter/baxter_right_arm.urdf"))


def baxter_arm_model():
    """The pinocchio Model of Baxter's right arm (7 revolute joints s0 … w2) from the shipped URDF."""
    import pinocchio as pin

    return pin.buildModelFromUrdf(urdf_path())


class SampledServo(Model):
    """The arm behind its PD servo sampled at ``rate`` Hz: the plant of the Baxter problem.

    ``f`` is the continuous servo (as in the controller's model), but :meth:`rk4` — what the simulator
    integrates — computes τ = K_p (q_des − q) − K_d q̇ at each servo tick and holds it for the tick while
    RK4 integrates M q̈ + C q̇ = τ. A step dt must be a whole number of servo ticks; ``substeps`` is the
    least number of RK4 steps per dt (at least one per tick).
    """

    def __init__(self, name, x, u, xdot, *, arm_f: ca.Function, kp, kd, rate: float, **names):
        super().__init__(name, x, u, xdot, **names)
        self.arm_f, self.rate = arm_f, positive(rate, "rate")
        self.kp, self.kd = ca.DM(kp), ca.DM(kd)
        self._servo_steps = {}

    def rk4(self, dt: float, substeps: int = 1) -> ca.Function:
        dt, substeps = positive(dt, "dt"), integer(substeps, "substeps", 1)
        ticks = round(dt * self.rate)
        if ticks < 1 or abs(ticks / self.rate - dt) > 1e-9 * max(1.0, dt):
            raise ValueError(f"dt must be a whole number of servo periods (1/{self.rate:g} s), got {dt!r}")
        key = (dt, substeps)
        if key not in self._servo_steps:
            per_tick = math.ceil(substeps / ticks)
            h = 1.0 / self.rate / per_tick
            n = self.nu
            x = self.x
            for _ in range(ticks):
                tau = self.kp * (self.u - x[:n]) - self.kd * x[n:]
                for _ in range(per_tick):
                    k1 = self.arm_f(x, tau)
                    k2 = self.arm_f(x + h / 2 * k1, tau)
                    k3 = self.arm_f(x + h / 2 * k2, tau)
                    k4 = self.arm_f(x + h * k3, tau)
                    x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            self._servo_steps[key] = ca.Function("F", [self.x, self.u], [x], ["x", "u"], ["x_next"])
        return self._servo_steps[key]


class Baxter(Problem):
    """Position control of Baxter's right arm through servo set points q_des (u = q_des, 7 inputs).

    Gains K_p, K_d per joint as in :data:`KP`, :data:`KD`; servo at 500 Hz; no joint friction beyond K_d
    (the URDF's 0.7 N·m·s "damping" is a Gazebo setting, not used). Set points are bounded by the URDF
    joint limits. Defaults: dt = 0.01 s, T = 100 (the paper's one-second look-ahead), 3 s closed loop,
    Q = diag(10 per angle, 0.1 per rate), R = 1e-3 I (small, since R pulls q_des towards 0: it leaves a
    steady-state error of about R/Q ≈ 1e-4 of the goal angle), terminal weight 10 Q. Start: at rest,
    uniform in the middle half of each joint's range; goal: a step of up to ±0.5 rad on every joint at
    once, within the joint limits (seeded). ``kinematics``: the URDF's frames (``end_effector``
    "right_gripper", the URDF's endpoint between the fingertips); ``link_radius`` for
    :func:`ocpkit.model.kinematics.spheres_along_links`.
    """

    horizon = 100
    duration = 3.0
    end_effector = "right_gripper"
    link_radius = 0.07

    def __init__(self):
        self.name = "baxter"
        self.pin_model = baxter_arm_model()
        names = [self.pin_model.names[i] for i in range(1, self.pin_model.njoints)]
        if tuple(names) != JOINTS:
            raise ValueError(f"the Baxter URDF must hold the joints {JOINTS}, found {names}")
        self.chain = Chain(self.pin_model)
        self.kp, self.kd = np.array(KP), np.array(KD)
        self.q_min = np.array(self.pin_model.lowerPositionLimit)
        self.q_max = np.array(self.pin_model.upperPositionLimit)

    @cached_property
    def kinematics(self) -> Kinematics:
        return Kinematics(self.pin_model)

    def _servo(self, error: float):
        x, u = ca.SX.sym("x", 14), ca.SX.sym("u", 7)
        q, qd = x[:7], x[7:]
        tau = ca.DM(self.kp) * (u - q) - ca.DM(self.kd) * qd
        qdd = self.chain.forward_dynamics(q, qd, tau, inertia_scale=error, gravity=False)
        names = {
            "state_names": [f"q_{j[6:]}" for j in JOINTS] + [f"qd_{j[6:]}" for j in JOINTS],
            "input_names": [f"qdes_{j[6:]}" for j in JOINTS],
        }
        return x, u, ca.vertcat(qd, qdd), names

    def dynamics(self, error: float) -> Model:
        x, u, xdot, names = self._servo(error)
        return Model(self.name, x, u, xdot, **names)

    def plant(self) -> SampledServo:
        """The true arm with its servo sampled at 500 Hz (not the continuous servo of ``model(1.0)``)."""
        if "_plant" not in self.__dict__:
            x, u, xdot, names = self._servo(1.0)
            xs, tau = ca.SX.sym("x", 14), ca.SX.sym("tau", 7)
            qdd = self.chain.forward_dynamics(xs[:7], xs[7:], tau, gravity=False)
            arm_f = ca.Function("arm", [xs, tau], [ca.vertcat(xs[7:], qdd)])
            self._plant = SampledServo(
                self.name, x, u, xdot, arm_f=arm_f, kp=self.kp, kd=self.kd, rate=SERVO_RATE, **names
            )
        return self._plant

    def defaults(self) -> dict:
        Q = np.diag(np.r_[10.0 * np.ones(7), 0.1 * np.ones(7)])
        # The input that holds a goal at rest is the set point q_des = q_goal: R pulls the set points there.
        hold = np.hstack([np.eye(7), np.zeros((7, 7))])
        return {
            "Q": Q,
            "R": 1e-3 * np.eye(7),
            "Q_terminal": 10 * Q,
            "u_goal_gain": hold,
            "u_min": self.q_min,
            "u_max": self.q_max,
        }

    def sample(self, seed: int):
        rng = np.random.default_rng(seed)
        mid, half = (self.q_min + self.q_max) / 2, (self.q_max - self.q_min) / 4
        q0 = rng.uniform(mid - half, mid + half)
        qg = np.clip(q0 + rng.uniform(-0.5, 0.5, size=7), self.q_min, self.q_max)
        return np.r_[q0, np.zeros(7)], np.r_[qg, np.zeros(7)]


def _make(arg=None) -> Baxter:
    if arg is not None:
        raise ValueError(f"baxter takes no argument, got {arg!r}")
    return Baxter()


REGISTRY = {"baxter": _make}

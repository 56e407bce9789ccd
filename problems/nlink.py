"""The paper's planar N-link robots (Section V-C "Experimental Setup" and Section VI-B): 1 to 13 links.

M(q) q̈ + C(q, q̇) q̇ + b q̇ = τ  (eq. threelink): the workspace lies in the plane perpendicular to gravity,
so g(q) = 0. State x = [q, q̇] (relative joint angles), input τ (joint torques).

"nlink:N:gravity" turns the plane vertical (not the paper's): gravity g = 9.81 m/s² in the arm's plane, along the
zero configuration, so that q = 0 hangs straight down and q = (π, 0, …, 0) stands upright — N = 2 is the double
pendulum of the non-convex suite's swing-up (:mod:`ocpkit.studies.nonconvex_cases`).
"""

from __future__ import annotations

from functools import cached_property

import casadi as ca
import numpy as np

from ocpkit._checks import integer, positive
from ocpkit.model.kinematics import Kinematics
from ocpkit.model.dynamics import Model
from ocpkit.model.problem import Problem
from ocpkit.model.rigid_body import Chain


def planar_chain(links: int, mass: float = 1.0, length: float = 0.25, gravity: float = 0.0):
    """A pinocchio Model of ``links`` identical uniform rods joined by revolute joints about z.

    Each rod has mass m and length l, its centre of mass at l/2 along the link's x axis and a rotational
    inertia about its centre of mass of diag(0, m l²/12, m l²/12) (thin uniform rod along x). Joint i+1
    sits at the tip of link i. Gravity is zero (it would act along −z, parallel to every joint axis), or
    ``gravity`` m/s² along +x, in the arm's plane: then q = 0 hangs down.
    Frames: one per joint (``joint1`` …) and ``tip``, the end of the last link (x = l in its joint's frame).
    """
    import pinocchio as pin

    links = integer(links, "links", 1)
    mass, length = positive(mass, "mass"), positive(length, "length")
    gravity = float(gravity)
    if not np.isfinite(gravity) or gravity < 0:
        raise ValueError(f"gravity must be finite and >= 0, got {gravity!r}")
    model = pin.Model()
    model.name = f"nlink{links}"
    model.gravity = pin.Motion(np.array([gravity, 0.0, 0.0]), np.zeros(3))
    rod = pin.Inertia(mass, np.array([length / 2, 0.0, 0.0]), np.diag([0.0, 1.0, 1.0]) * mass * length**2 / 12)
    parent, frame = 0, 0
    for i in range(links):
        offset = pin.SE3(np.eye(3), np.array([length if i else 0.0, 0.0, 0.0]))
        parent = model.addJoint(parent, pin.JointModelRZ(), offset, f"joint{i + 1}")
        model.appendBodyToJoint(parent, rod, pin.SE3.Identity())
        frame = model.addJointFrame(parent, frame)
    model.addFrame(
        pin.Frame("tip", parent, frame, pin.SE3(np.eye(3), np.array([length, 0.0, 0.0])), pin.FrameType.OP_FRAME)
    )
    return model


class NLink(Problem):
    """A planar robot of N links, each 1 kg and 0.25 m (uniform rod, see :func:`planar_chain`).

    Viscous damping b = 0.01 N·m·s per joint (clearly underdamped), torque limits ±2 N·m, no gravity (or
    ``gravity`` m/s² in the arm's plane, q = 0 hanging: see :func:`planar_chain`).
    Defaults: dt = 0.01 s, T = 50 (the paper's solve-time experiments; its closed-loop EMPC experiments
    use T = 100 over 10 s), Q = I (angles and rates alike: lighter rate weights let the 0.5 s horizon
    ring on 7 links), R = 0.01 I, terminal weight 100 Q.
    Start and goal: at rest, every joint angle uniform in [−π/2, π/2] (seeded).
    ``kinematics``: its frames (``end_effector`` "tip", the end of the last link); ``link_radius`` for
    :func:`ocpkit.model.kinematics.spheres_along_links`.
    """

    duration = 10.0
    end_effector = "tip"
    link_radius = 0.05

    def __init__(
        self,
        links: int = 2,
        *,
        damping: float = 0.01,
        tau_max: float = 2.0,
        sample_range: float = np.pi / 2,
        gravity: float = 0.0,
    ):
        self.links = integer(links, "links", 1)
        self.name = f"nlink:{self.links}" + (":gravity" if gravity else "")
        self.damping = float(damping)
        if not np.isfinite(self.damping) or self.damping < 0:
            raise ValueError(f"damping must be finite and >= 0, got {damping!r}")
        self.tau_max = positive(tau_max, "tau_max")
        self.sample_range = positive(sample_range, "sample_range")
        self.pin_model = planar_chain(self.links, gravity=gravity)
        self.gravity = float(gravity)
        self.chain = Chain(self.pin_model)

    @cached_property
    def kinematics(self) -> Kinematics:
        return Kinematics(self.pin_model)

    def dynamics(self, error: float) -> Model:
        n = self.links
        x, u = ca.SX.sym("x", 2 * n), ca.SX.sym("u", n)
        q, qd = x[:n], x[n:]
        qdd = self.chain.forward_dynamics(q, qd, u, damping=self.damping, inertia_scale=error)
        return Model(
            self.name,
            x,
            u,
            ca.vertcat(qd, qdd),
            state_names=[f"q{i + 1}" for i in range(n)] + [f"qd{i + 1}" for i in range(n)],
            input_names=[f"tau{i + 1}" for i in range(n)],
        )

    def defaults(self) -> dict:
        n = self.links
        Q = np.eye(2 * n)
        return {
            "Q": Q,
            "R": 0.01 * np.eye(n),
            "Q_terminal": 100 * Q,
            "u_min": np.full(n, -self.tau_max),
            "u_max": np.full(n, self.tau_max),
        }

    def sample(self, seed: int):
        rng = np.random.default_rng(seed)
        q0, qg = rng.uniform(-self.sample_range, self.sample_range, size=(2, self.links))
        zeros = np.zeros(self.links)
        return np.r_[q0, zeros], np.r_[qg, zeros]


LINKS = range(1, 14)  # the paper's robots: 1 to 13 links


GRAVITY = 9.81  # m/s², "nlink:N:gravity"


def _make(arg=None) -> NLink:
    if arg is None:
        raise ValueError("nlink needs a number of links, e.g. 'nlink:7' (1 to 13)")
    arg, _, variant = arg.partition(":")
    if variant not in ("", "gravity"):
        raise ValueError(f"unknown nlink variant {variant!r}; valid: nlink:N, nlink:N:gravity")
    try:
        links = int(arg)
    except ValueError:
        raise ValueError(f"nlink: number of links must be an integer from 1 to 13, got {arg!r}") from None
    if links not in LINKS:
        raise ValueError(
            f"nlink: number of links must be 1 to 13 (the paper's robots), got {links}; "
            "NLink(links) builds any size in Python"
        )
    return NLink(links, gravity=GRAVITY if variant else 0.0)


REGISTRY = {"nlink": _make}

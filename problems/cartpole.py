"""A cart-pole: a point mass m on a massless pole of length l, hinged on a cart of mass M pushed along a horizontal
track by a force u (no friction). θ = 0 hangs, as the pendulum's q = 0 does; θ = π stands upright.

(M + m) p̈ + m l cos θ θ̈ − m l sin θ θ̇² = u,   m l cos θ p̈ + m l² θ̈ + m g l sin θ = 0

— the model and parameters of the cart-pole swing-up example in M. Kelly, "An Introduction to Trajectory
Optimization: How to Do Your Own Direct Collocation", SIAM Review 59(4), 2017: M = 1 kg, m = 0.3 kg, l = 0.5 m,
g = 9.81 m/s². State x = [p, θ, ṗ, θ̇] (cart position [m], pole angle [rad], their rates), input u [N]. The error
multiplier scales M and m in the controller's model only. The track's ends are the task's (the non-convex suite's
swing-up: :mod:`ocpkit.studies.nonconvex_cases`), not the problem's.

Not the tutorial's ``examples/cartpole.py`` (θ = 0 upright there): this one is shipped, registered as "cartpole".
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ocpkit._checks import positive
from ocpkit.model.dynamics import Model
from ocpkit.model.problem import Problem


def pinocchio_model(M: float = 1.0, m: float = 0.3, l: float = 0.5, g: float = 9.81):
    """The same cart-pole as a pinocchio Model: a prismatic joint along x (the cart, mass M) carrying a revolute joint
    about z (the pole: mass m at (0, −l, 0) in its frame), gravity g along −y; q = (p, θ), θ = 0 hanging."""
    import pinocchio as pin

    model = pin.Model()
    model.name = "cartpole"
    model.gravity = pin.Motion(np.array([0.0, -g, 0.0]), np.zeros(3))
    cart = model.addJoint(0, pin.JointModelPX(), pin.SE3.Identity(), "cart")
    model.appendBodyToJoint(cart, pin.Inertia(M, np.zeros(3), np.eye(3) * 1e-3), pin.SE3.Identity())
    pole = model.addJoint(cart, pin.JointModelRZ(), pin.SE3.Identity(), "pole")
    model.appendBodyToJoint(pole, pin.Inertia(m, np.array([0.0, -l, 0.0]), np.zeros((3, 3))), pin.SE3.Identity())
    return model


class CartPole(Problem):
    """A pole on a cart (see the module docstring); force limit ±u_max.

    Defaults: M = 1 kg, m = 0.3 kg, l = 0.5 m, g = 9.81 m/s², |u| ≤ 20 N (Kelly's), dt = 0.01 s, T = 50,
    Q = diag(10, 10, 0.1, 0.1) (positions as the pendulum's angle, rates as its rate), R = 0.01. Start and goal:
    the pole hanging at rest, the cart at rest at a position uniform in ±0.5 m (seeded): a move of the cart.
    """

    name = "cartpole"
    angles = (False, True)  # which configuration coordinates are angles (modulo 2π): the pole's, not the cart's

    def __init__(self, M: float = 1.0, m: float = 0.3, l: float = 0.5, g: float = 9.81, u_max: float = 20.0):
        self.M, self.m, self.l = positive(M, "M"), positive(m, "m"), positive(l, "l")
        self.g, self.u_max = positive(g, "g"), positive(u_max, "u_max")

    def dynamics(self, error: float) -> Model:
        M, m, l, g = self.M * error, self.m * error, self.l, self.g
        x, u = ca.SX.sym("x", 4), ca.SX.sym("u", 1)
        s, c, thd = ca.sin(x[1]), ca.cos(x[1]), x[3]
        d = M + m * s**2  # the mass matrix's determinant over m l²
        pdd = (u[0] + m * s * (l * thd**2 + g * c)) / d
        thdd = -(u[0] * c + m * l * s * c * thd**2 + (M + m) * g * s) / (l * d)
        return Model(
            self.name,
            x,
            u,
            ca.vertcat(x[2], thd, pdd, thdd),
            state_names=["p", "theta", "pd", "thetad"],
            input_names=["force"],
        )

    def defaults(self) -> dict:
        return {
            "Q": np.diag([10.0, 10.0, 0.1, 0.1]),
            "R": np.array([[0.01]]),
            "u_min": [-self.u_max],
            "u_max": [self.u_max],
        }

    def sample(self, seed: int):
        rng = np.random.default_rng(seed)
        p0, pg = rng.uniform(-0.5, 0.5, size=2)
        return np.array([p0, 0.0, 0.0, 0.0]), np.array([pg, 0.0, 0.0, 0.0])


def _make(arg=None) -> CartPole:
    if arg is not None:
        raise ValueError(f"cartpole takes no argument, got {arg!r}")
    return CartPole()


REGISTRY = {"cartpole": _make}

"""Tutorial "Declare your own problem": a cart-pole, then every controller, the CLI and the studies take it as
``cartpole.py:CartPole``. Run as a script, it swings nothing up: it balances the pole for ``duration`` seconds."""

import sys

import casadi as ca
import numpy as np

from ocpkit import Model, Problem


class CartPole(Problem):
    """A pole (mass m, length l) on a cart (mass M) pushed by a force u; x = [p, θ, ṗ, θ̇], θ = 0 upright."""

    name, dt, horizon, duration = "cartpole", 0.01, 100, 2.0

    def dynamics(self, error):  # error: the controller's model error multiplier on the masses
        M, m, l, g = 1.0 * error, 0.1 * error, 0.5, 9.81
        x, u = ca.SX.sym("x", 4), ca.SX.sym("u", 1)
        s, c = ca.sin(x[1]), ca.cos(x[1])
        pdd = (u[0] + m * s * (l * x[3] ** 2 - g * c)) / (M + m * s**2)
        return Model(self.name, x, u, ca.vertcat(x[2], x[3], pdd, (g * s - c * pdd) / l))

    def defaults(self):
        Q = np.diag([100.0, 100.0, 1.0, 1.0])
        return {"Q": Q, "Q_terminal": 10 * Q, "R": [[0.01]], "u_min": [-20.0], "u_max": [20.0]}

    def sample(self, seed):
        rng = np.random.default_rng(seed)
        return np.r_[0, rng.uniform(-0.3, 0.3), 0, 0], np.r_[rng.uniform(-0.5, 0.5), 0, 0, 0]


if __name__ == "__main__":
    from ocpkit import LinearMPC, simulate

    duration = float(sys.argv[1]) if len(sys.argv) > 1 else CartPole.duration
    problem = CartPole()
    x0, goal = problem.sample(seed=0)
    traj = simulate(problem.plant(), LinearMPC(problem.ocp(knots=5)), x0, goal, duration=duration)
    print(f"cart at {traj.x[-1][0]:.3f} m (goal {goal[0]:.3f}), pole at {traj.x[-1][1]:.4f} rad after {duration} s")

"""Closed-loop LinearMPC on the robot problems (issue 3): N-link robots to a goal, Baxter overshoot."""

from __future__ import annotations

import control
import numpy as np
import pytest

from ocpkit.problems.baxter import Baxter
from ocpkit.problems.nlink import NLink
from ocpkit.sim.simulate import simulate
from ocpkit.solvers.qp import LinearMPC


def _reaches_goal(problem, knots, form, duration, tol=0.02, seed=0):
    x0, goal = problem.sample(seed)
    ocp = problem.ocp(knots=knots)
    traj = simulate(problem.plant(), LinearMPC(ocp, form=form), x0, goal, duration)
    assert traj.fallbacks == 0
    assert np.all(traj.u <= ocp.u_max + 1e-9) and np.all(traj.u >= ocp.u_min - 1e-9)
    err = np.abs(traj.x - goal).max(axis=1)
    assert err[0] > 0.5  # a real move, from rest …
    assert err[-1] < tol  # … to the goal at rest (angles and rates)
    assert np.abs(traj.u).max() > 0.9 * problem.tau_max  # the torque limit is active on the way


@pytest.mark.parametrize("knots, form", [(3, "condensed"), (None, "sparse")])
def test_nlink2_reaches_goal(knots, form):
    _reaches_goal(NLink(2), knots, form, duration=6.0)


def test_nlink7_reaches_goal_with_three_knots():
    _reaches_goal(NLink(7), 3, "condensed", duration=10.0)


@pytest.mark.slow
def test_nlink7_reaches_goal_traditional():
    _reaches_goal(NLink(7), None, "sparse", duration=10.0)


def _overshoot(traj_q, t, q0, q_goal):
    """Largest percent overshoot over the joints (python-control's step_info on each normalized step)."""
    return max(
        control.step_info((traj_q[:, j] - q0[j]) / (q_goal[j] - q0[j]), T=t, yfinal=1.0)["Overshoot"]
        for j in range(len(q0))
    )


def test_baxter_mpc_overshoots_less_than_the_bare_servo():
    p = Baxter()
    x0, goal = p.sample(0)
    q0, qg = x0[:7], goal[:7]
    duration, dt = 3.0, p.dt
    step = p.plant().rk4(dt, 10)
    xs = [x0]
    for _ in range(int(round(duration / dt))):  # the bare servo: set point = goal from t = 0
        xs.append(np.array(step(xs[-1], qg)).ravel())
    xs = np.array(xs)
    t = np.arange(len(xs)) * dt
    # Linearize about the plan's input: for set-point inputs u_goal = 0 is far from any equilibrium.
    mpc = LinearMPC(p.ocp(knots=3), form="condensed")
    traj = simulate(p.plant(), mpc, x0, goal, duration)
    assert traj.fallbacks == 0
    servo, controlled = _overshoot(xs[:, :7], t, q0, qg), _overshoot(traj.x[:, :7], traj.t, q0, qg)
    assert servo > 30.0  # clearly underdamped
    assert controlled < 0.5 * servo
    assert np.abs(traj.x[-1, :7] - qg).max() < 0.01

"""Closed-loop performance measures of the paper: actual cost, its ratio, overshoot, rise time, ITAE."""

from __future__ import annotations

import numpy as np

from ocpkit.model.ocp import OCP
from ocpkit.sim.simulate import Trajectory


def cost_by_term(traj: Trajectory, ocp: OCP) -> dict[str, float]:
    """The actual cost split by the OCP's cost terms (``ocp.cost.names``: "state", "input", the task's).

    Every term at the recorded states and applied inputs (x_i, u_i), i = 0 … H−1, towards the goal at that time (a
    moving reference's, ``traj.reference``), and the "state" term also at the last state x_H (obstacles are not a
    cost here)."""
    cost, H = ocp.cost, traj.u.shape[0]
    goals = traj.goals()
    if goals.shape != (H + 1, ocp.ng) or not np.isfinite(goals).all():
        raise ValueError(f"the trajectory's goals must be {ocp.ng} finite entries each, got shape {goals.shape}")
    terms = np.zeros(len(cost.names))
    if H:
        stage = cost.stage_terms.map(H)(traj.x[:-1].T, traj.u.T, goals[:-1].T)
        terms += np.asarray(stage, dtype=float).sum(axis=1)
    terms[0] += float(cost.stage_terms(traj.x[-1], np.zeros(ocp.nu), goals[-1])[0])  # "state" reads no input
    return dict(zip(cost.names, terms.tolist()))


def actual_cost(traj: Trajectory, ocp: OCP) -> float:
    """The MPC objective evaluated on the states and inputs actually applied (paper eq. actual_cost).

    Σ_{i=0}^{H} J(x_i, u_i) with J the OCP's stage cost: every recorded state x_0 … x_H against the goal and every
    applied input u_0 … u_{H−1} against the input goal; a task's terms at (x_i, u_i), i = 0 … H−1 (the sum of
    :func:`cost_by_term`)."""
    return float(sum(cost_by_term(traj, ocp).values()))


def actual_cost_ratio(traj: Trajectory, reference: Trajectory, ocp: OCP) -> float:
    """Actual cost of ``traj`` over that of ``reference`` (paper eq. actual_cost_ratio)."""
    return actual_cost(traj, ocp) / actual_cost(reference, ocp)


def step_metrics(traj: Trajectory, joints=None, *, min_step: float = 0.1) -> dict:
    """Percent overshoot and rise time (10–90 %) per joint via python-control's ``step_info``.

    Joint i is measured on its position (state i) moving from x_0 to the goal; a joint whose step is
    smaller than ``min_step`` (rad) gets NaN for both (a percentage of a tiny step is noise: 2146 %
    overshoot on a 0.02 rad pendulum step), and one that never reaches 90 % of its step gets a NaN
    rise time.
    """
    import control

    n_q = traj.x.shape[1] // 2
    joints = range(n_q) if joints is None else joints
    overshoot, rise = [], []
    for i in joints:
        q, q0, qg = traj.x[:, i], traj.x[0, i], traj.goal[i]
        if abs(qg - q0) < min_step:
            overshoot.append(np.nan)
            rise.append(np.nan)
            continue
        # Normalize to a unit step from 0 so the sign of the move does not matter.
        y = (q - q0) / (qg - q0)
        if y.max() < 0.9:  # never rose to 90 %: no rise time (step_info cannot measure it) and no overshoot
            overshoot.append(0.0)
            rise.append(np.nan)
            continue
        info = control.step_info(y, T=traj.t, yfinal=1.0)
        overshoot.append(info["Overshoot"])
        rise.append(info["RiseTime"])
    return {"overshoot": np.array(overshoot), "rise_time": np.array(rise)}


def itae(traj: Trajectory, joints=None) -> float:
    """Integral of time-weighted absolute position error, Σ t |q_goal − q| dt summed over joints."""
    n_q = traj.x.shape[1] // 2
    joints = list(range(n_q)) if joints is None else list(joints)
    err = np.abs(traj.goal[joints] - traj.x[:, joints])
    dt = traj.t[1] - traj.t[0]
    return float(np.sum(traj.t[:, None] * err) * dt)

"""The reach study's scenarios and trials (:mod:`ocpkit.studies.reach`): a seeded end-effector target behind a sphere,
reached by every controller on the same task OCP, and the keep-out ball of :mod:`ocpkit.studies.keepout` with a fair
nonlinear baseline."""

from __future__ import annotations

import casadi as ca
import numpy as np

from ocpkit import problems, solvers
from ocpkit._checks import choice
from ocpkit.codegen.kernels.runtime import current_arch
from ocpkit.model.kinematics import spheres_along_links
from ocpkit.model.task import Sphere, Task, UserTerm, reach
from ocpkit.model.task import clearances as task_clearances
from ocpkit.sim.metrics import actual_cost
from ocpkit.sim.simulate import REACHED, simulate
from ocpkit.studies import keepout
from ocpkit.studies.closed_loop import run_record, steady

ROBOTS = ("nlink:3", "baxter", "panda")
KEEPOUT = "keepout"
MARGIN, TOLERANCE = 0.01, 0.01  # obstacle margin [m] in the OCP; success: final distance [m]
OBSTACLE_RADIUS = {"nlink:3": 0.06, "baxter": 0.08, "panda": 0.08}
MIN_DISTANCE = 0.25  # start-to-target end-effector distance [m] at least
KNOTS = {"nlink:3": 5, "baxter": 3, "panda": 5}
ATTEMPTS = 200
HINGE_WEIGHT = 1e3  # the squared hinge's weight in the keep-out UserTerm
IPOPT, RTI, QP, QP_TRAJ, EMPC, CEM, MPPI = (
    "IPOPT",
    "RTI",
    "LinearMPC",
    "LinearMPC (trajectory)",
    "EMPC",
    "CEM",
    "MPPI",
)
SAMPLING = {"linearization": "plan"}  # sampling planners: affine model re-linearized about the plan each step
# IPOPT's iterations per step (its default: 200). Its Gauss–Newton Hessian (the default; it leaves out the
# clearances' and the dynamics' curvature) ran every step to 200 iterations on some reaches (nlink:3 seed 1: 1.1 s a
# step, 298 s a run; Baxter seed 0: 117 s), the largest share of `reproduce --quick`; an iteration count, not a time
# limit, so that a busy machine does not change the result.
IPOPT_BUDGET = {"max_iter": 50}
CONTROLLERS = {
    IPOPT: ("ipopt", IPOPT_BUDGET),
    RTI: ("rti", {}),
    QP: ("qp", {}),
    QP_TRAJ: ("qp", {"linearization": "trajectory"}),
    EMPC: ("empc", SAMPLING),
    CEM: ("cem", SAMPLING),
    MPPI: ("mppi", SAMPLING),
}
K_IPOPT, K_RTI, K_EMPC_HINGE, K_EMPC_SQUARED = (
    "IPOPT, squared hinge term",
    "RTI, squared hinge term",
    "EMPC, hinge fitness",
    "EMPC, squared hinge term",
)
KEEPOUT_CONTROLLERS = (K_IPOPT, K_RTI, K_EMPC_HINGE, K_EMPC_SQUARED)


# --- scenarios ------------------------------------------------------------------------------------------------


def clearances(pb, obstacles, q_rows) -> np.ndarray:
    """True clearance d (m, no margin) per configuration (rows of ``q_rows``) of the robot's spheres as
    :func:`ocpkit.model.task.reach` places them: min over sphere/obstacle pairs."""
    return task_clearances(pb.kinematics, spheres_along_links(pb.kinematics, pb.link_radius), obstacles, q_rows)


def scenario(robot: str, seed: int) -> dict:
    """The seeded scenario: start state, target point, obstacles and how many draws were rejected."""
    choice(robot, ROBOTS, "robot")
    pb = problems.make(robot)
    n, radius = pb.kinematics.n, OBSTACLE_RADIUS[robot]
    for attempt in range(ATTEMPTS):
        x0, xg = pb.sample(seed + 1_000_003 * attempt)
        p0, pg = pb.kinematics.positions(pb.end_effector, np.vstack([x0[:n], xg[:n]]))
        length = np.linalg.norm(pg - p0)
        if length < MIN_DISTANCE:
            continue
        rng = np.random.default_rng([seed, attempt])
        along = (pg - p0) / length
        side = np.cross(along, [0.0, 0.0, 1.0]) if robot.startswith("nlink") else np.cross(along, rng.normal(size=3))
        side /= np.linalg.norm(side)
        centre = p0 + rng.uniform(0.35, 0.65) * (pg - p0) + rng.uniform(-0.5, 0.5) * radius * side
        obstacles = [Sphere(tuple(centre), radius)]
        if clearances(pb, obstacles, np.vstack([x0[:n], xg[:n]])).min() < MARGIN:
            continue
        return {"x0": x0, "q_target": xg[:n], "target": pg, "obstacles": obstacles, "rejected": attempt}
    raise RuntimeError(f"no collision-free {robot} scenario for seed {seed} in {ATTEMPTS} draws")


# --- trials ---------------------------------------------------------------------------------------------------


def trial(scenario: str, controller: str, horizon: int, duration: float, population: int, arch: str, seed: int) -> dict:
    """One closed-loop run: a reach ``scenario`` ("nlink:3", "baxter") or the keep-out ball ("keepout")."""
    choice(scenario, (*ROBOTS, KEEPOUT), "scenario")
    if scenario == KEEPOUT:
        return keepout_trial(controller, horizon, duration, population, arch, seed)
    return reach_trial(scenario, controller, horizon, duration, population, arch, seed)


def _controller(solver, options, ocp, population, arch, seed, **extra):
    if solver in ("empc", "cem", "mppi"):
        options = {**options, "population": population, "arch": arch, "seed": seed}
    return solvers.make(solver, ocp, **options, **extra)


def _times(traj, ctrl) -> dict:
    total = traj.times("total")
    return {
        "step_median": float(np.median(total)),
        "step_max": float(total.max()),
        "solve_median": float(np.median(traj.times("solve"))),
        **run_record(traj, ctrl),
    }


def reach_trial(
    robot: str, controller: str, horizon: int, duration: float, population: int, arch: str, seed: int
) -> dict:
    choice(controller, tuple(CONTROLLERS), "controller")
    s = scenario(robot, seed)
    pb = problems.make(robot)
    n = pb.kinematics.n
    ocp = reach(pb, s["obstacles"], margin=MARGIN, knots=KNOTS[robot], horizon=horizon)
    goal = ocp.goal(s["x0"], position=s["target"])
    solver, options = CONTROLLERS[controller]
    ctrl = _controller(solver, options, ocp, population, arch, seed)
    steady(ctrl, s["x0"], goal)
    traj = simulate(pb.plant(), ctrl, s["x0"], goal, duration)
    d = traj.clearances(ocp)
    ee = pb.kinematics.positions(pb.end_effector, traj.x[:, :n])
    progress = traj.progress(pb.kinematics, pb.end_effector, s["target"], tolerance=TOLERANCE)
    collisions = int((d < 0).sum())
    return {
        "success": bool(progress.verdict == REACHED and collisions == 0),
        "reached": progress.verdict == REACHED,
        "verdict": progress.verdict,
        "final_change": progress.change,
        "collision_steps": collisions,
        "success_while_colliding": traj.success_while_colliding(ocp),
        "successes": traj.successes,
        "soft_steps": traj.soft_steps,
        "soft_causes": traj.soft_causes(),
        "steps": len(traj.solutions),
        "min_clearance": float(d.min()),
        "final_distance": progress.final,
        "start_distance": float(progress.error[0]),
        "actual_cost": actual_cost(traj, ocp),
        **_times(traj, ctrl),
        "rejected": s["rejected"],
        "knots": KNOTS[robot],
        "device": current_arch() if solver in ("empc", "cem", "mppi") else "cpu",
        "ee": ee,
        "target": s["target"],
        "obstacles": np.array([[*o.center, o.radius] for o in s["obstacles"]]),
    }


def squared_hinge_term(centre) -> UserTerm:
    """max(0, r + 0.01 − ‖q − c‖) (C¹ once squared) as a stage and terminal UserTerm of weight HINGE_WEIGHT."""
    c = ca.DM(np.asarray(centre, dtype=float))

    def residual(x, u, target):
        e = x[: keepout.LINKS] - c
        return ca.fmax(0, keepout.RADIUS + 0.01 - ca.sqrt(ca.dot(e, e) + 1e-12))

    return UserTerm("keepout", residual, HINGE_WEIGHT, stage=True, terminal=True)


def keepout_trial(controller: str, horizon: int, duration: float, population: int, arch: str, seed: int) -> dict:
    choice(controller, KEEPOUT_CONTROLLERS, "controller")
    pb = problems.make(f"nlink:{keepout.LINKS}")
    plain = pb.ocp(knots=keepout.KNOTS, horizon=horizon)
    x0, goal = pb.sample(seed)
    centre = (x0[: keepout.LINKS] + goal[: keepout.LINKS]) / 2
    penalty = keepout.keepout_penalty(centre)
    if controller == K_EMPC_HINGE:
        stage, terminal = keepout.penalized_costs(plain, penalty)
        ctrl = _controller("empc", SAMPLING, plain, population, arch, seed, stage_cost=stage, terminal_cost=terminal)
    else:
        ocp = pb.ocp(knots=keepout.KNOTS, horizon=horizon, task=Task([squared_hinge_term(centre)]))
        solver, options = {K_IPOPT: ("ipopt", {}), K_RTI: ("rti", {}), K_EMPC_SQUARED: ("empc", SAMPLING)}[controller]
        ctrl = _controller(solver, options, ocp, population, arch, seed)
    steady(ctrl, x0, goal)
    traj = simulate(pb.plant(), ctrl, x0, goal, duration)
    penalties = np.asarray(penalty.map(traj.x.shape[0])(traj.x.T)).ravel()
    quadratic = actual_cost(traj, plain)
    return {
        "actual_cost": quadratic + float(penalties.sum()),
        "quadratic_cost": quadratic,
        "penalty": float(penalties.sum()),
        "steps_inside": int((np.linalg.norm(traj.x[:, : keepout.LINKS] - centre, axis=1) < keepout.RADIUS).sum()),
        "final_error": float(np.abs(traj.x[-1] - goal).max()),
        **_times(traj, ctrl),
        "device": current_arch() if "EMPC" in controller else "cpu",
    }

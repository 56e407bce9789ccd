"""The non-convex suite's cases (:mod:`ocpkit.studies.nonconvex`): reaches whose straight end-effector path is
blocked, each drawn from its seed.

A draw starts as the reach study's (:func:`ocpkit.studies.reach_trials.scenario`): start and goal configuration from
``problem.sample``, the target the goal's end-effector position, at least :data:`MIN_DISTANCE` from the start's. Then,
with ``along`` the unit vector from the start's end effector p_0 to the target p_g and ``side`` a unit vector across it
(in the plane z = 0 for the planar arms, a seeded random direction otherwise), the case places its spheres (radius
:data:`RADIUS` per robot):

- ``sphere``: one sphere on the straight path at a fraction uniform in [0.35, 0.65] of it, moved sideways by up to
  half its radius;
- ``spheres``: three, at fractions 0.3, 0.5 and 0.7 (± 0.05), each moved sideways by up to its radius: a staggered
  wall;
- ``passage``: two spheres side by side across the path at a fraction in [0.4, 0.6], a gap of :data:`GAP` between
  them (the link's diameter, twice the margin and 2 cm), the gap's centre moved sideways by half a radius plus half
  the gap, so that the straight path runs through one sphere and the way through is narrow;
- ``limits``: one sphere as in ``sphere``, and joint position limits (the robot's where it has them, ±:data:`LIMIT`
  rad on the planar arms) with the goal configuration's largest joint moved to :data:`LIMIT_GAP` inside its nearer
  limit before the target is computed: a target near the joint limits, the limits as the OCP's state bounds.

Every case blocks the straight path (the end effector's own sphere moving along it would hit a sphere); a draw whose
start or goal configuration is within the margin of a sphere (or, for ``limits``, whose start is beyond a limit) is
rejected and redrawn from s + 1 000 003·k (k = 1, 2, …), deterministically, as in the reach study.

``swingup`` (:data:`SWINGUP`, on :data:`SWING_ROBOTS`: the pendulum, the double pendulum "nlink:2:gravity" and the
cart-pole "cartpole", q = 0 hanging): start hanging, every joint angle uniform in ±:data:`START_ANGLE` rad and velocity
in ±:data:`START_SPEED` rad/s (``numpy.random.default_rng(s)``), goal upright at rest (q₁ = π, the other joints 0);
every joint's torque limited to ±:data:`TORQUE_FRACTION` of the torque that holds the straight arm horizontal at
joint 1 (:func:`static_torque`), so no quasi-static path exists, nor a single push (a pendulum pushed at τ from
hanging gains τ·π by the top, which takes 2 m g l: τ < 2/π m g l): the controller must swing back first and pump.
(Pumping at the limit reaches upright in about 1.5 s, development draws 0–2.) No obstacles, no rejections.

The cart-pole's cart starts within ±:data:`START_CART` m of the track's centre at up to :data:`START_SPEED` m/s, must
stay on a track of ±:data:`TRACK` m (the case's ``limits``, state bounds of its OCP) and ends at its centre: goal
(p, θ) = (0, π) at rest. Its force is limited to ±:data:`FORCE_FRACTION` of the force whose work over the longest
one-way stroke the track allows (from −START_CART to +TRACK) lifts the pole, 2 m g l (:func:`swing_limit`): no single
stroke gets it up, however timed, and the controller must pump it back and forth.
"""

from __future__ import annotations

import numpy as np

from ocpkit import problems
from ocpkit._checks import choice
from ocpkit.model.task import Sphere
from ocpkit.problems.cartpole import CartPole
from ocpkit.studies.reach_trials import ATTEMPTS, MARGIN, clearances

ROBOTS = ("nlink:3", "nlink:7", "panda")
CASES = ("sphere", "spheres", "passage", "limits")
SWINGUP = "swingup"
SWING_ROBOTS = ("pendulum", "nlink:2:gravity", "cartpole")
START_ANGLE, START_SPEED = 0.2, 0.5  # the swing-up's start: rad and rad/s about hanging at rest
TORQUE_FRACTION = 0.6  # the swing-up's torque limit: this share of the torque holding the arm horizontal
# The cart-pole's track [m]: ±TRACK. The single-stroke bound leaves less force the longer the track, and the swing-up
# then takes longer than the 3 s horizon: on ±1 m (the limit would be 2.14 N) IPOPT on the open-loop swing-up (hanging
# to upright at rest, 2 random guesses, continued from 20 N down) found none below 3.5 N in 3, 4 or 5 s; on ±0.5 m
# (3.92 N) one at 3.36 N in 4 s, none below 4.5 N in 3 s; on ±0.3 m one at the limit, 5.89 N, in 3 s (3 guesses).
TRACK = 0.3
START_CART = 0.1  # the cart-pole's start: the cart within this [m] of the track's centre
FORCE_FRACTION = 0.8  # the cart-pole's force limit: this share of the single-stroke force (see the module docstring)
RADIUS = {"nlink:3": 0.06, "nlink:7": 0.1, "panda": 0.08}
MIN_DISTANCE = {"nlink:3": 0.25, "nlink:7": 0.5, "panda": 0.25}
LIMIT = 2.6  # the planar arms' joint limits [rad] in the limits case (they have none of their own)
LIMIT_GAP = 0.05  # the limits case's goal joint sits this far [rad] inside its limit
# The study's seed s draws case SEED_OFFSET + s: the suite was developed on draws 0 … 99, never on these.
SEED_OFFSET = 490_000


def gap(pb) -> float:
    """The passage's width [m]: the link's diameter, twice the margin and 2 cm."""
    return 2 * (pb.link_radius + MARGIN) + 0.02


def joint_limits(robot: str, pb) -> tuple[np.ndarray, np.ndarray]:
    """(q_min, q_max) of the limits case: the robot's position limits where finite, else ±LIMIT."""
    n = pb.kinematics.n
    lo, hi = getattr(pb, "q_min", np.full(n, -np.inf)), getattr(pb, "q_max", np.full(n, np.inf))
    return np.where(np.isfinite(lo), lo, -LIMIT), np.where(np.isfinite(hi), hi, LIMIT)


def static_torque(pb, q) -> np.ndarray:
    """The torques that hold configuration ``q`` at rest on ``pb``'s plant (q̈ = 0 at q̇ = 0; the dynamics are affine
    in the input)."""
    q = np.asarray(q, dtype=float)
    n, f = q.size, pb.plant().f
    x = np.r_[q, np.zeros(n)]
    a0 = np.asarray(f(x, np.zeros(n))).ravel()[n:]
    B = np.column_stack([np.asarray(f(x, e)).ravel()[n:] - a0 for e in np.eye(n)])
    return np.linalg.solve(B, -a0)


def swing_limit(pb) -> float:
    """The swing-up's input limit, every input: TORQUE_FRACTION of joint 1's torque [N·m] holding the straight arm
    horizontal; on the cart-pole, FORCE_FRACTION of the force [N] doing the pole's lift 2 m g l over the stroke
    TRACK + START_CART."""
    if isinstance(pb, CartPole):
        return FORCE_FRACTION * 2 * pb.m * pb.g * pb.l / (TRACK + START_CART)
    n = pb.model().nx // 2
    return TORQUE_FRACTION * abs(float(static_torque(pb, np.r_[np.pi / 2, np.zeros(n - 1)])[0]))


def swingup(robot: str, seed: int) -> dict:
    """The drawn swing-up (see the module docstring): start state ``x0``, goal state ``x_goal`` (upright, at rest),
    input limit ``tau_max``, which configuration coordinates are ``angles`` (the rest, the cart's, are positions);
    ``limits`` (q_min, q_max): the cart-pole's track, else None; no ``obstacles``, ``target`` or rejections, as the
    reach cases have."""
    choice(robot, SWING_ROBOTS, "robot")
    pb = problems.make(robot)
    n = pb.model().nx // 2
    angles = np.array(getattr(pb, "angles", (True,) * n))
    rng = np.random.default_rng(seed)
    start = np.where(angles, START_ANGLE, START_CART)
    x0 = np.r_[rng.uniform(-start, start), rng.uniform(-START_SPEED, START_SPEED, n)]
    x_goal = np.zeros(2 * n)
    x_goal[np.argmax(angles)] = np.pi  # the first joint upright
    track = np.where(angles, np.inf, TRACK)
    return {
        "x0": x0,
        "x_goal": x_goal,
        "tau_max": swing_limit(pb),
        "angles": angles,
        "target": None,
        "obstacles": [],
        "limits": None if angles.all() else (-track, track),
        "rejected": 0,
    }


def case(robot: str, kind: str, seed: int) -> dict:
    """The drawn case: start state ``x0``, goal configuration ``q_target``, ``target`` point, ``obstacles``, joint
    ``limits`` ((q_min, q_max) or None) and how many draws were ``rejected``; for :data:`SWINGUP` see
    :func:`swingup`."""
    choice(kind, (*CASES, SWINGUP), "case")
    if kind == SWINGUP:
        return swingup(robot, seed)
    choice(robot, ROBOTS, "robot")
    pb = problems.make(robot)
    n, radius = pb.kinematics.n, RADIUS[robot]
    limits = joint_limits(robot, pb) if kind == "limits" else None
    for attempt in range(ATTEMPTS):
        x0, xg = pb.sample(seed + 1_000_003 * attempt)
        rng = np.random.default_rng([seed, attempt])
        qg = xg[:n].copy()
        if limits is not None:
            if ((x0[:n] < limits[0]) | (x0[:n] > limits[1])).any():
                continue
            j = int(np.argmax(np.abs(qg)))
            qg[j] = limits[1][j] - LIMIT_GAP if qg[j] >= 0 else limits[0][j] + LIMIT_GAP
        p0, pg = pb.kinematics.positions(pb.end_effector, np.vstack([x0[:n], qg]))
        length = np.linalg.norm(pg - p0)
        if length < MIN_DISTANCE[robot]:
            continue
        along = (pg - p0) / length
        side = np.cross(along, [0.0, 0.0, 1.0]) if robot.startswith("nlink") else np.cross(along, rng.normal(size=3))
        side /= np.linalg.norm(side)
        obstacles = [Sphere(tuple(c), radius) for c in _centres(kind, p0, pg, side, radius, gap(pb), rng)]
        if clearances(pb, obstacles, np.vstack([x0[:n], qg])).min() < MARGIN:
            continue
        return {"x0": x0, "q_target": qg, "target": pg, "obstacles": obstacles, "limits": limits, "rejected": attempt}
    raise RuntimeError(f"no collision-free {robot} {kind} case for seed {seed} in {ATTEMPTS} draws")


def _centres(kind, p0, pg, side, radius, width, rng) -> list:
    """The spheres' centres of case ``kind`` on the straight path p0 → pg (see the module docstring)."""
    if kind in ("sphere", "limits"):
        return [p0 + rng.uniform(0.35, 0.65) * (pg - p0) + rng.uniform(-0.5, 0.5) * radius * side]
    if kind == "spheres":
        return [
            p0 + (f + rng.uniform(-0.05, 0.05)) * (pg - p0) + rng.uniform(-1, 1) * radius * side
            for f in (0.3, 0.5, 0.7)
        ]
    middle = p0 + rng.uniform(0.4, 0.6) * (pg - p0) + rng.choice([-1.0, 1.0]) * (radius + width) / 2 * side
    return [middle + sign * (radius + width / 2) * side for sign in (-1.0, 1.0)]

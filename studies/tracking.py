"""Follow a moving reference (not a paper experiment): every controller with the reference's preview over its horizon
against the same controller holding the reference's present value as its goal (the loop users wrote before goal
windows, :mod:`ocpkit.model.reference`).

Scenarios:

* "circle": the Panda's hand along a circle of radius 0.1 m at 0.3 m/s (one turn in 2.1 s) in a plane through its
  start pose, tilted per seed;
* "eight": the Panda's hand along a figure eight (0.1 m half-width, the same peak speed) while a sphere of 5 cm
  radius crosses the path at constant velocity (an :class:`ocpkit.model.reference.ObstaclePath`, predicted over the
  horizon at its measured velocity);
* "joints": nlink:7 following a joint-space minimum-jerk move of ±0.5 rad per joint from a seeded configuration at
  rest (q and q̇ as the reference; 1.5 s), then holding.

Measures: RMS and max tracking error (the hand's distance to the reference point, m; for "joints" max_i |q_i −
q_ref,i|, rad), the lag (the time shift of the reference that best fits the path, s), collisions (states whose true
clearance is below zero), step successes and the per-step optimization time.
"""

from __future__ import annotations

import numpy as np

from ocpkit import problems, solvers
from ocpkit._checks import choice
from ocpkit.codegen.kernels.runtime import current_arch
from ocpkit.model.reference import ObstaclePath, Reference
from ocpkit.model.task import Sphere, reach
from ocpkit.runs.study import Study, grid
from ocpkit.sim import plots
from ocpkit.sim.plots import number
from ocpkit.sim.simulate import simulate
from ocpkit.studies.closed_loop import run_record
from ocpkit.studies.evidence import combine, decide, every, median_interval, paired, series
from ocpkit.studies.report import ANSWERED, Claim, answered, markdown_table, section, timing_context, trials_line

NAME = "tracking"
TITLE = "Follow a moving reference: the preview over the horizon vs a goal held at the reference's present value"
SCENARIOS = ("circle", "eight", "joints")
PREVIEW, HELD = "preview", "held"
RADIUS, SPEED = 0.1, 0.3  # the circle's radius [m] and the hand's speed along it [m/s]
SPHERE = 0.05  # the crossing sphere's radius [m]
HORIZON, KNOTS = 30, 5
JOINT_MOVE, JOINT_TIME = 0.5, 1.5  # "joints": each joint moves ±0.5 rad (seeded sign) in 1.5 s, minimum jerk
CONTROLLERS = {
    "LinearMPC": ("qp", {}),
    "LinearMPC (trajectory)": ("qp", {"linearization": "trajectory"}),
    "RTI": ("rti", {}),
    "IPOPT": ("ipopt", {}),
    "EMPC": ("empc", {"linearization": "plan"}),
    "CEM": ("cem", {"linearization": "plan"}),
    "MPPI": ("mppi", {"linearization": "plan"}),
}
# quick: the QP controllers (the main job's budget: IPOPT's Panda steps take 30-93 ms, the sampling planners' 8-9 ms)
SIZES = {
    "quick": {
        "scenario": list(SCENARIOS),
        "controller": ["LinearMPC", "RTI"],
        "duration": 2.1,
        "plant": "model",
        "seeds": 5,
    },
    "full": {
        "scenario": list(SCENARIOS),
        "controller": list(CONTROLLERS),
        "duration": 4.2,
        "plant": ["model", "mujoco"],
        "seeds": 10,
    },
}
# The claim: the preview lowers the RMS tracking error at least this many times below holding g(t), seed by seed
PREVIEW_GAIN = 2.0


def minimum_jerk(q0, q1, duration: float) -> Reference:
    """x_ref(t) = [q(t), q̇(t)] of the minimum-jerk move q0 → q1 in ``duration`` s, held at q1 after it."""
    q0, q1 = np.asarray(q0, dtype=float), np.asarray(q1, dtype=float)
    t = np.linspace(0.0, duration, 151)
    s = t / duration
    shape = 10 * s**3 - 15 * s**4 + 6 * s**5
    rate = (30 * s**2 - 60 * s**3 + 30 * s**4) / duration
    return Reference(t, np.hstack([q0 + np.outer(shape, q1 - q0), np.outer(rate, q1 - q0)]))


def _plane(seed: int) -> np.ndarray:
    """Two orthonormal directions spanning the seed's plane: the y-z plane tilted about z by up to ±30°."""
    tilt = np.deg2rad(np.random.default_rng(seed).uniform(-30.0, 30.0))
    return np.array([[-np.sin(tilt), np.cos(tilt), 0.0], [0.0, 0.0, 1.0]])


def hand_path(scenario: str, start: np.ndarray, seed: int):
    """p(t) of the hand's reference: starting at ``start`` (the hand at the start pose), RADIUS in size, moving at
    SPEED (peak speed for the eight)."""
    a, b = _plane(seed)
    w = SPEED / RADIUS
    if scenario == "circle":
        return lambda t: start + RADIUS * ((np.cos(w * t) - 1.0) * a + np.sin(w * t) * b)
    # the lemniscate of Gerono x = sin(wt), y = sin(wt)cos(wt): peak speed RADIUS·w at t = 0
    return lambda t: start + RADIUS * (np.sin(w * t) * a + 0.5 * np.sin(2 * w * t) * b)


def crossing(start: np.ndarray, seed: int, duration: float) -> ObstaclePath:
    """The sphere crossing the eight: from 0.25 m in front of the path's centre, through it at mid-run, on."""
    a, b = _plane(seed)
    normal = np.cross(a, b)
    centre, speed = start + 0.5 * RADIUS * b, 0.5 / duration  # crosses 0.25 m either side of the plane in a run
    return ObstaclePath(lambda t: [[*(centre + normal * (0.25 - speed * t)), SPHERE]])


def setting(scenario: str, seed: int, duration: float):
    """(problem, OCP, x0, reference, obstacle path or None, error(trajectory, delay) -> its tracking error per state
    against the reference ``delay`` steps late, :meth:`ocpkit.sim.simulate.Trajectory.tracking_error`)."""
    if scenario == "joints":
        pb = problems.make("nlink:7")
        ocp = pb.ocp(knots=KNOTS, horizon=HORIZON)
        x0, _ = pb.sample(seed)
        x0[7:] = 0.0  # at rest
        move = np.random.default_rng(seed).choice([-1.0, 1.0], 7) * JOINT_MOVE
        ref = minimum_jerk(x0[:7], x0[:7] + move, JOINT_TIME)
        return pb, ocp, x0, ref, None, lambda traj, delay: traj.tracking_error(states=7, delay=delay)
    pb = problems.make("panda")
    q0 = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
    x0 = np.r_[q0, np.zeros(7)]
    start = pb.kinematics.positions(pb.end_effector, q0[None])[0]
    path = hand_path(scenario, start, seed)
    obstacles = crossing(start, seed, duration) if scenario == "eight" else None
    declared = [Sphere(obstacles.at(0.0)[0, :3], SPHERE)] if obstacles else []
    ocp = reach(pb, declared, knots=KNOTS, horizon=HORIZON)
    ref = Reference.from_function(lambda t: ocp.goal(np.zeros(ocp.nx), position=path(t)), ocp.ng)

    def error(traj, delay):
        return traj.tracking_error(pb.kinematics, pb.end_effector, traj.targets(ocp), delay=delay)

    return pb, ocp, x0, ref, obstacles, error


def lag(error_late, dt: float, max_lag: float = 0.5) -> float:
    """The time shift τ = j·dt ∈ [0, max_lag] s of the reference that the path fits best: argmin_τ RMS e(t; ref(t −
    τ)), with ``error_late(j)`` the tracking error against the reference j steps late."""
    rms = [np.sqrt(np.mean(error_late(j) ** 2)) for j in range(int(round(max_lag / dt)) + 1)]
    return float(int(np.argmin(rms)) * dt)


def trial(scenario: str, controller: str, preview: str, duration: float, plant: str, seed: int) -> dict:
    """One closed loop of ``controller`` on ``scenario``, with the reference's preview or holding its present value."""
    choice(scenario, SCENARIOS, "scenario")
    choice(controller, tuple(CONTROLLERS), "controller")
    choice(preview, (PREVIEW, HELD), "preview")
    pb, ocp, x0, ref, obstacles, error = setting(scenario, seed, duration)
    solver, options = CONTROLLERS[controller]
    ctrl = solvers.make(solver, ocp, **({"seed": seed} if solver in ("empc", "cem", "mppi") else {}), **options)
    goal = ref if preview == PREVIEW else ref.without_preview()
    target = pb.plant() if plant == "model" else _mujoco(pb)
    traj = simulate(target, ctrl, x0, goal, duration, obstacles=obstacles)
    e = error(traj, 0)
    clearance = traj.clearances(ocp)
    return {
        "rms_error": float(np.sqrt(np.mean(e**2))),
        "max_error": float(e.max()),
        "lag": lag(lambda j: error(traj, j), traj.t[1] - traj.t[0]),
        "collisions": int((clearance < 0).sum()),
        "min_clearance": float(clearance.min()),
        "successes": traj.successes,
        "steps": len(traj.solutions),
        "solve_median": float(np.median(traj.times("solve"))),
        "solve_max": float(np.max(traj.times("solve"))),
        "device": current_arch() if solver in ("empc", "cem", "mppi") else "cpu",
        **run_record(traj, ctrl),
    }


def _mujoco(pb):
    from ocpkit.sim.mujoco_plant import MuJoCoPlant

    return MuJoCoPlant(pb)


def study(size: str) -> Study:
    choice(size, tuple(SIZES), "size")
    axes = dict(SIZES[size])
    seeds = axes.pop("seeds")
    return Study(NAME, trial, grid(**axes, preview=[PREVIEW, HELD], seeds=seeds))


def report(df, out_dir) -> str:
    ok = df[df["status"] == "ok"]
    trials = trials_line(
        df,
        {
            "scenarios": df["scenario"].nunique(),
            "controllers": df["controller"].nunique(),
            "seeds": df["seed"].nunique(),
        },
    )
    if ok.empty:
        return section(TITLE, [], {}, trials=trials, claims=[], notes=["No trial succeeded."])
    order = [c for c in CONTROLLERS if c in set(ok["controller"])]
    figs, tables = [], {}
    for scenario in [s for s in SCENARIOS if s in set(ok["scenario"])]:
        rows = ok[ok["scenario"] == scenario]
        unit = "rad" if scenario == "joints" else "m"
        labels, values = [], []
        for c in order:
            for mode in (PREVIEW, HELD):
                labels.append(f"{c}, {mode}")
                values.append(rows[(rows["controller"] == c) & (rows["preview"] == mode)]["rms_error"].dropna().values)
        figs.append(
            plots.boxes(
                labels,
                values,
                out_dir / f"tracking_{scenario}",
                xlabel="controller, reference",
                ylabel=f"RMS tracking error ({unit})",
                title=f"{scenario}: RMS tracking error over {rows['seed'].nunique()} seeds",
            )
        )
        summary = rows.groupby(["controller", "preview"])[
            ["rms_error", "max_error", "lag", "collisions", "successes", "solve_median"]
        ].median()
        summary["solve_median"] *= 1e3
        tables[
            f"{scenario}: medians over the seeds (RMS and max tracking error in {unit}, lag in s, colliding states, "
            "successful steps, per-step optimization time in ms)"
        ] = markdown_table(summary)
    tables[ANSWERED] = answered(ok)
    sampled = ok[ok["controller"].isin(["EMPC", "CEM", "MPPI"])]
    devices = f"; sampling planners on {', '.join(sorted(set(sampled['device'])))}" if len(sampled) else ""
    notes = [
        f"Runs: {number(ok['duration'].iloc[0])} s at 100 Hz, horizon {HORIZON}, {KNOTS} knots{devices}. 'held': the "
        "goal is the reference's present value, held over the horizon (a loop without preview); lag: the shift of "
        "the reference that the path fits best."
    ]
    return section(TITLE, figs, tables, trials=trials + " " + timing_context(ok), notes=notes, claims=claims(ok, order))


def claims(ok, order) -> list:
    """The preview's claims, each decided on per-seed ratios (held / preview RMS error, the same seed and plant)."""
    out = []
    for scenario, claim in (
        ("circle", "The preview tracks the Panda's circle closer than the held goal"),
        ("joints", "The preview tracks nlink:7's joint trajectory closer than the held goal"),
    ):
        rows = ok[ok["scenario"] == scenario]
        parts = {}
        for c in order:
            held = series(rows, "rms_error", index=["seed", "plant"], controller=c, preview=HELD)
            preview = series(rows, "rms_error", index=["seed", "plant"], controller=c, preview=PREVIEW)
            parts[c] = median_interval(paired(held, preview))
        out.append(
            Claim(
                claim,
                f"per-seed RMS error held / preview ≥ {number(PREVIEW_GAIN)} for every controller",
                combine(decide(i, PREVIEW_GAIN, ">=") for i in parts.values()),
                "; ".join(f"{c} {i.text()}" for c, i in parts.items()),
            )
        )
    eight = ok[ok["scenario"] == "eight"]
    verdict, evidence = every(eight["collisions"], lambda v: v == 0, "with a colliding state")
    out.append(
        Claim("No controller collides with the sphere crossing the eight", "0 colliding states", verdict, evidence)
    )
    return out

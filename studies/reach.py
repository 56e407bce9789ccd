"""Reaching past spherical obstacles: every controller on the same task OCP; and the keep-out ball of
:mod:`ocpkit.studies.keepout` with a fair nonlinear baseline (not a paper experiment; issue 29 item 4).

**Reach.** An end-effector target behind a sphere, on the planar 3-link arm (``nlink:3``: targets in its plane
z = 0, spheres centred in the plane), on Baxter's 7-DoF right arm (the shipped URDF, position servo) and on the
torque-controlled Panda (``panda``, the full size only: its sampling kernels compile for minutes). A scenario is
drawn from its seed, and the seeds were not tuned on: the start is ``problem.sample(s)``'s start, the target the
forward kinematics of its goal configuration (so the target is reachable), at least
:data:`~ocpkit.studies.reach_trials.MIN_DISTANCE` from the start's end effector; one sphere of radius
:data:`~ocpkit.studies.reach_trials.OBSTACLE_RADIUS` sits on the straight end-effector path at a fraction uniform in
[0.35, 0.65] of it, moved sideways by up to half its radius (so the straight path is blocked: the end effector's own
sphere would hit it). Scenarios whose start or target configuration is within the margin of the obstacle are
rejected and redrawn from s = seed + 1 000 003·k (k = 1, 2, ...), deterministically. Every controller gets the same
OCP, :func:`ocpkit.model.task.reach` (frame-position term, the problem's velocity and input weights, obstacle margin
0.01 m, robot spheres along the links of the problem's ``link_radius``), the goal
``ocp.goal(x_start, position=target)`` (no joint target: the posture is free). A trial succeeds when the final end
effector is within 1 cm of the target and the true clearance (without margin) is ≥ 0 at every recorded plant state.

What a trial records about its steps and its loop (:mod:`ocpkit.sim.simulate`): a step counts as a success only with
status "success"; "soft" steps (the solver's input applied, its plan breaking a clearance or state bound) and
fallbacks are counted apart, with their causes; "success while colliding" counts the steps reported "success" whose
actual next state collides (true clearance < 0: a success the plant contradicts); ``collision_steps`` the colliding
states. The loop-level verdict (:meth:`ocpkit.sim.simulate.Trajectory.progress`) is "reached" (within 1 cm at the
end), "stalled" (not reached, and the distance changed by at most 1 mm over the last 0.5 s: every step may have
succeeded, the loop did not) or "moving" (not reached, still changing when the run ended).

**Keep-out, fair baseline.** The joint-space ball of :mod:`ocpkit.studies.keepout` (3-link arm, radius r = 0.3 rad
half-way between start and goal, hinge penalty w·max(0, r − ‖q − c‖), w = 100): EMPC with that penalized fitness
against IPOPT and RTI given the penalty in C¹ form, a :class:`ocpkit.model.task.UserTerm` with the squared hinge
residual max(0, r + 0.01 − ‖q − c‖) and weight :data:`~ocpkit.studies.reach_trials.HINGE_WEIGHT`, and EMPC given
that same OCP (its fitness then is the squared hinge: the search, not the cost, differs from IPOPT's). Every run is
scored on the same actual penalized cost as in keepout: the quadratic cost plus the hinge penalty on every recorded
state.
"""

from __future__ import annotations

from ocpkit._checks import choice
from ocpkit.runs.study import Study, grid
from ocpkit.studies.reach_trials import CONTROLLERS, KEEPOUT, KEEPOUT_CONTROLLERS, ROBOTS, trial
from ocpkit.studies.reach_sections import keepout_section, reach_section
from ocpkit.studies.report import ANSWERED, answered, section, timing_context, trials_line

NAME = "reach"
TITLE = "Reaching past spherical obstacles (every controller, one task OCP) and the keep-out ball with a fair baseline"
# quick: fewer seeds, shorter runs, Baxter at a shorter horizon, no Panda. A robot a size leaves out has 0 seeds
# (or no entry).
SIZES = {
    "quick": {
        "seeds": {"nlink:3": 4, "baxter": 1, "panda": 0, KEEPOUT: 2},
        "duration": {"nlink:3": 2.5, "baxter": 1.0, KEEPOUT: 5.0},
        "horizon": {"nlink:3": 50, "baxter": 20, KEEPOUT: 100},
        "population": 256,
        "arch": "cpu",
    },
    "full": {
        "seeds": {"nlink:3": 20, "baxter": 10, "panda": 10, KEEPOUT: 10},
        "duration": {"nlink:3": 3.0, "baxter": 3.0, "panda": 2.0, KEEPOUT: 5.0},
        "horizon": {"nlink:3": 50, "baxter": 50, "panda": 50, KEEPOUT: 100},
        "population": 1024,
        "arch": "auto",
    },
}


def study(size: str) -> Study:
    choice(size, tuple(SIZES), "size")
    s = SIZES[size]
    common = {"population": s["population"], "arch": s["arch"]}
    trials = []
    for robot in ROBOTS:
        if not s["seeds"].get(robot):
            continue  # a size may leave a robot out (0 seeds, or none given)
        trials += grid(
            scenario=robot,
            controller=list(CONTROLLERS),
            horizon=s["horizon"][robot],
            duration=s["duration"][robot],
            **common,
            seeds=s["seeds"][robot],
        )
    if s["seeds"][KEEPOUT]:
        trials += grid(
            scenario=KEEPOUT,
            controller=list(KEEPOUT_CONTROLLERS),
            horizon=s["horizon"][KEEPOUT],
            duration=s["duration"][KEEPOUT],
            **common,
            seeds=s["seeds"][KEEPOUT],
        )
    return Study(NAME, trial, trials)


def report(df, out_dir) -> str:
    ok = df[df["status"] == "ok"]
    reach_df = ok[ok["scenario"].isin(ROBOTS)]
    keep_df = ok[ok["scenario"] == KEEPOUT]
    trials = trials_line(
        df,
        {
            "scenarios (2 robots + keep-out)": df["scenario"].nunique(),
            "controllers": df["controller"].nunique(),
            "seeds (per scenario, up to)": df.groupby("scenario")["seed"].nunique().max() if len(df) else 0,
        },
    )
    if ok.empty:
        return section(TITLE, [], {}, trials=trials, claims=[], notes=["No trial succeeded."])
    figs, tables, notes, claims = [], {}, [], []
    if not reach_df.empty:
        reach_section(reach_df, out_dir, figs, tables, notes, claims)
    if not keep_df.empty:
        keepout_section(keep_df, out_dir, figs, tables, notes, claims)
    tables[ANSWERED] = answered(ok)
    return section(TITLE, figs, tables, trials=trials + " " + timing_context(ok), notes=notes, claims=claims)

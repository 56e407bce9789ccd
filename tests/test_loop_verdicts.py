"""Loop-level verdicts (issue 43): reached, stalled or moving; soft steps and successes the plant contradicts."""

import numpy as np
import pytest

from ocpkit import problems
from ocpkit.status import LIMITED, SOFT, SUCCESS, Reason, Solution
from ocpkit.sim.simulate import MOVING, REACHED, STALLED, Trajectory, simulate
from ocpkit.solvers.qp import LinearMPC
from ocpkit.model.task import Sphere, reach

ARM = problems.make("nlink:3")  # planar, three 0.25 m links: the tip reaches 0.75 m from the base
CLEARANCE = (
    "DAQP optimal; soft: clearance (robot sphere 2, obstacle 0) violated by 0.012 at x_3 of the plan on the "
    "nonlinear model"
)
BOUND = "DAQP optimal; soft: state bound x[4] violated by 0.2 at x_1 of the plan on the nonlinear model"


def _step(status=SUCCESS, raw="", fallback=False, reason=None) -> Solution:
    return Solution(
        u=np.zeros(1), knots=np.zeros((1, 1)), status=status, raw_status=raw, fallback=fallback, reason=reason
    )


def _trajectory(x, steps=None, goal=None) -> Trajectory:
    x = np.asarray(x, dtype=float)
    x = x[:, None] if x.ndim == 1 else x
    steps = steps or [_step() for _ in range(len(x) - 1)]
    return Trajectory(
        t=0.01 * np.arange(len(x)),
        x=x,
        u=np.zeros((len(x) - 1, 1)),
        goal=np.zeros(x.shape[1]) if goal is None else goal,
        solutions=steps,
    )


def test_verdicts_on_a_joint_goal():
    t = 0.01 * np.arange(201)
    assert _trajectory(np.exp(-5 * t)).progress().verdict == REACHED  # 4.5e-5 from the goal after 2 s
    stuck = _trajectory(0.05 + np.exp(-5 * t)).progress()  # 5 cm short, still within 1 mm over the last 0.5 s
    assert stuck.verdict == STALLED and stuck.final == pytest.approx(0.05, abs=1e-4) and stuck.change < 1e-3
    assert "STALLED" in stuck.text() and "no progress" in stuck.text()
    swinging = _trajectory(0.5 * np.cos(6 * t)).progress()
    assert swinging.verdict == MOVING and swinging.change > 0.4 and "still moving" in swinging.text()
    # shorter than the window: not enough to call it stalled
    short = _trajectory(0.05 * np.ones(30)).progress()
    assert short.verdict == MOVING and np.isnan(short.change) and short.to_dict()["change"] is None
    # the thresholds are the caller's: 2 cm counts as reached with tolerance=0.03
    assert _trajectory(0.02 * np.ones(100)).progress(tolerance=0.03).verdict == REACHED
    # the largest state error counts: a velocity still off the goal is not reached
    x = np.column_stack([np.zeros(100), 0.2 * np.ones(100)])
    assert _trajectory(x).progress().final == pytest.approx(0.2)


def test_verdict_on_a_frame_target():
    q = np.tile([0.3, 0.4, 0.5, 0.0, 0.0, 0.0], (101, 1))
    tip = ARM.kinematics.positions(ARM.end_effector, q[:1, :3])[0]
    at = _trajectory(q, goal=np.zeros(6)).progress(ARM.kinematics, ARM.end_effector, tip)
    assert at.verdict == REACHED and at.final < 1e-12 and at.unit == "m"  # the joint goal (zeros) plays no part
    short = _trajectory(q, goal=np.zeros(6)).progress(ARM.kinematics, ARM.end_effector, tip + [0.03, 0.04, 0])
    assert short.verdict == STALLED and short.final == pytest.approx(0.05)
    assert short.text().startswith("verdict: STALLED — tip's distance to the target 0.0500 m at the end")


def test_progress_names_what_is_missing():
    traj = _trajectory(np.zeros(10))
    with pytest.raises(ValueError, match="frame is missing"):
        traj.progress(ARM.kinematics, target=[0, 0, 0])
    with pytest.raises(ValueError, match="target must be a point"):
        traj.progress(ARM.kinematics, "tip", [0, 0])
    with pytest.raises(ValueError, match="window"):
        traj.progress(window=0)


def test_soft_steps_are_counted_apart_from_successes_and_fallbacks():
    steps = [
        _step(),
        _step(SOFT, CLEARANCE, reason=Reason.CLEARANCE),
        _step(SOFT, CLEARANCE, reason=Reason.CLEARANCE),
        _step(SOFT, BOUND, reason=Reason.STATE_BOUND),
        _step(LIMITED, "iteration limit", fallback=True),
    ]
    traj = _trajectory(np.zeros(6), steps)
    assert (traj.successes, traj.soft_steps, traj.fallbacks) == (1, 3, 1)
    assert traj.soft_causes() == "clearance 2, state bound 1" and traj.fallback_causes() == "limited 1"
    # the causes are the steps' reasons, not words of their raw status: a soft step that says none is "soft"
    said = [_step(SOFT, BOUND, reason=Reason.CLEARANCE), _step(SOFT, CLEARANCE)]
    assert _trajectory(np.zeros(3), said).soft_causes() == "clearance 1, soft 1"


def test_what_answered_the_steps_is_tallied_per_run_and_summed_over_runs_in_the_report():
    import pandas as pd

    from ocpkit.studies.report import answered

    steps = [_step() for _ in range(3)] + [_step(LIMITED, "iteration limit", fallback=True)]
    for step, path in zip(steps, ("C step", "Python step, C step building", "C step", "fallback (plan)")):
        step.path = path
    traj = _trajectory(np.zeros(5), steps)
    assert traj.paths() == "C step 2, Python step, C step building 1, fallback (plan) 1"
    runs = pd.DataFrame(
        {
            "controller": ["QP", "QP", "old"],
            "paths": [traj.paths(), "C step 10", None],  # "old": stored before runs recorded their paths
            "fallbacks": [1, 0, 0],
            "fallback_causes": [traj.fallback_causes(), "", ""],
        }
    )
    table = answered(runs)
    assert "| QP | 2 | C step 12, Python step, C step building 1, fallback (plan) 1 | 1 | limited 1 |" in table
    assert "| old | 1 | not recorded | 0 | – |" in table


def test_success_while_colliding_counts_successes_the_plant_contradicts():
    ball = Sphere((0.75, 0.0, 0.0), 0.05)  # on the tip when the arm is stretched along x (q = 0)
    ocp = reach(ARM, [ball], knots=3, horizon=5)
    clear, hit = [0.5, 0.5, 0.5, 0, 0, 0], [0.0, 0.0, 0.0, 0, 0, 0]
    # success into hit, soft into hit, success out, in
    steps = [_step(), _step(SOFT, CLEARANCE, reason=Reason.CLEARANCE), _step(), _step()]
    traj = _trajectory([clear, hit, hit, clear, hit], steps, goal=np.zeros(9))
    d = traj.clearances(ocp)
    assert (d[[0, 3]] > 0).all() and (d[[1, 2, 4]] < 0).all()
    assert traj.success_while_colliding(ocp) == 2  # steps 0 and 3; the soft step 1 is not a success
    assert np.isinf(traj.clearances(ARM.ocp())).all() and traj.success_while_colliding(ARM.ocp()) == 0


def test_out_of_reach_target_stalls_while_every_step_succeeds():
    """The issue's case: a reach that stops 5 cm short reports success on every step; the loop says stalled."""
    x0, _ = ARM.sample(0)
    target = np.array([0.48, 0.64, 0.0])  # 0.80 m from the base, 5 cm beyond the stretched arm
    ocp = reach(ARM, knots=5)
    traj = simulate(ARM.plant(), LinearMPC(ocp, linearization="trajectory"), x0, ocp.goal(x0, position=target), 3.0)
    assert traj.successes == len(traj.solutions) == 300
    progress = traj.progress(ARM.kinematics, ARM.end_effector, target)
    assert progress.verdict == STALLED, progress.text()
    assert progress.final == pytest.approx(0.05, abs=2e-3) and progress.change <= 1e-3

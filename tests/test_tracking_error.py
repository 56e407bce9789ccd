"""Trajectory.tracking_error and Trajectory.targets: the distance to a moving reference at every recorded time, as the
CLI's simulate --reference and the tracking study report it (issue 46)."""

import numpy as np
import pytest

from ocpkit import problems
from ocpkit.model.task import reach
from ocpkit.sim.simulate import Trajectory

N3 = problems.make("nlink:3")
RNG = np.random.default_rng(0)


def _run(reference: np.ndarray, nx: int = 6) -> Trajectory:
    """A recorded run of 11 states against ``reference`` (11, ng): the states made up, no controller needed."""
    t = 0.01 * np.arange(11)
    return Trajectory(t, RNG.normal(size=(11, nx)), np.zeros((10, 3)), reference[-1], reference=reference)


def test_the_joint_error_is_the_largest_state_error_against_the_reference_at_each_time():
    ref = RNG.normal(size=(11, 6))
    traj = _run(ref)
    np.testing.assert_array_equal(traj.tracking_error(), np.abs(traj.x - ref).max(axis=1))
    np.testing.assert_array_equal(traj.tracking_error(states=3), np.abs(traj.x[:, :3] - ref[:, :3]).max(axis=1))
    # two steps late: the reference at t − 2·dt, its first value before the start
    late = ref[[0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8]]
    np.testing.assert_array_equal(traj.tracking_error(delay=2), np.abs(traj.x - late).max(axis=1))


def test_a_held_goal_is_the_reference_at_every_time():
    goal = RNG.normal(size=6)
    traj = Trajectory(0.01 * np.arange(4), RNG.normal(size=(4, 6)), np.zeros((3, 3)), goal)
    np.testing.assert_array_equal(traj.tracking_error(), np.abs(traj.x - goal).max(axis=1))


def test_a_frame_error_is_its_distance_to_the_moving_target_point():
    ocp = reach(N3)
    points = 0.5 + 0.1 * RNG.normal(size=(11, 3))
    goals = np.array([ocp.goal(np.zeros(ocp.nx), position=p) for p in points])
    traj = _run(goals)
    np.testing.assert_array_equal(traj.targets(ocp), points)
    frame = N3.end_effector
    where = N3.kinematics.positions(frame, traj.x[:, :3])
    error = traj.tracking_error(N3.kinematics, frame, traj.targets(ocp))
    np.testing.assert_allclose(error, np.linalg.norm(where - points, axis=1), rtol=0, atol=1e-15)
    late = traj.tracking_error(N3.kinematics, frame, traj.targets(ocp), delay=1)
    np.testing.assert_allclose(late, np.linalg.norm(where - points[[0, *range(10)]], axis=1), rtol=0, atol=1e-15)


def test_what_is_missing_is_named():
    ocp = reach(N3)
    traj = _run(np.array([ocp.goal(np.zeros(ocp.nx), position=[0.5, 0.5, 0.0])] * 11))
    with pytest.raises(ValueError, match="needs kinematics, frame and targets; targets is missing"):
        traj.tracking_error(N3.kinematics, N3.end_effector)
    with pytest.raises(ValueError, match="no target of term 'orientation'; targets: \\['position'\\]"):
        traj.targets(ocp, "orientation")
    with pytest.raises(ValueError, match="targets must have shape \\(11, 3\\)"):
        traj.tracking_error(N3.kinematics, N3.end_effector, traj.targets(ocp)[1:])
    with pytest.raises(ValueError, match="delay must be >= 0"):
        traj.tracking_error(delay=-1)

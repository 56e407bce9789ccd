"""The animation draws what moved where it is at each frame: the run's obstacles (Trajectory.obstacles) and a moving
reference's target point (issue 46)."""

import numpy as np
import pytest

from ocpkit import problems
from ocpkit.cli import main
from ocpkit.model.task import Sphere, reach
from ocpkit.sim.animation import MotionPicture
from ocpkit.sim.simulate import Trajectory

T = 0.01 * np.arange(51)
RADIUS = 0.06


def _run(problem, ocp, x0, centres, points) -> Trajectory:
    """A run of 51 states held at ``x0`` whose obstacle passed ``centres`` (51, 3) and target ``points`` (51, 3)."""
    goals = np.array([ocp.goal(x0, position=p) for p in points])
    obstacles = np.c_[centres, np.full(len(T), RADIUS)][:, None, :]
    x = np.tile(x0, (len(T), 1))
    return Trajectory(T, x, np.zeros((50, ocp.nu)), goals[-1], reference=goals, obstacles=obstacles)


def _line(a, b) -> np.ndarray:
    return a + np.outer(T / T[-1], np.subtract(b, a))


def test_the_drawn_sphere_and_target_move_with_the_run_in_3d(tmp_path):
    pb = problems.make("panda")
    ocp = reach(pb, [Sphere((0.4, -0.3, 0.3), RADIUS)])
    centres, points = _line([0.4, -0.3, 0.3], [0.4, 0.3, 0.5]), _line([0.5, 0.0, 0.3], [0.3, 0.1, 0.6])
    x0 = np.r_[0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785, np.zeros(7)]
    traj = _run(pb, ocp, x0, centres, points)
    picture = MotionPicture(traj, pb, target=traj.targets(ocp), obstacles=ocp.task.obstacles, max_frames=6)
    try:
        ((wire, shadow),) = picture.obstacle_artists
        for k in (0, len(picture.indices) - 1):
            picture.draw(k)
            i = picture.indices[k]
            on = picture.drawn(wire)
            on = on[~np.isnan(on).any(axis=1)]
            np.testing.assert_allclose(np.linalg.norm(on - centres[i], axis=1), RADIUS, atol=1e-12)
            below = picture.drawn(shadow)[:, :2] - centres[i, :2]  # the shadow: the circle under it on the floor
            np.testing.assert_allclose(np.linalg.norm(below, axis=1), RADIUS, atol=1e-12)
            np.testing.assert_allclose(picture.drawn(picture.target_artist)[0], points[i])
            np.testing.assert_allclose(picture.drawn(picture.drop)[:, :2], [points[i, :2]] * 2)
        assert picture.indices[-1] == len(T) - 1
        # the limits hold the sphere and the target wherever they went
        for low, high, axis in zip(*np.array([picture.axes.get_xlim(), picture.axes.get_ylim()]).T, range(2)):
            assert low <= (centres[:, axis] - RADIUS).min() and (centres[:, axis] + RADIUS).max() <= high
        frames = list(picture.images())  # drawn as animated artists over the background
        assert (np.asarray(frames[0]) != np.asarray(frames[-1])).any()
    finally:
        picture.close()


def test_the_drawn_circle_moves_in_the_plane():
    pb = problems.make("nlink:3")
    ocp = reach(pb, [Sphere((0.6, 0.3, 0.0), RADIUS)])
    centres, points = _line([0.6, 0.3, 0.0], [0.2, 0.6, 0.0]), _line([0.3, 0.5, 0.0], [0.5, 0.2, 0.0])
    traj = _run(pb, ocp, np.r_[0.3, 0.2, 0.1, np.zeros(3)], centres, points)
    picture = MotionPicture(traj, pb, target=traj.targets(ocp), obstacles=ocp.task.obstacles)
    try:
        ((circle,),) = picture.obstacle_artists
        for k in (0, len(picture.indices) - 1):
            picture.draw(k)
            i = picture.indices[k]
            assert circle.center == pytest.approx(centres[i, :2]) and circle.radius == pytest.approx(RADIUS)
            np.testing.assert_allclose(picture.drawn(picture.target_artist)[0], points[i])
    finally:
        picture.close()


def test_a_still_run_draws_the_obstacles_as_given_and_nothing_moves():
    pb = problems.make("nlink:3")
    ball = Sphere((0.6, 0.3, 0.0), RADIUS)
    traj = Trajectory(T, np.zeros((len(T), 6)), np.zeros((50, 3)), np.zeros(6))
    picture = MotionPicture(traj, pb, target=[0.3, 0.5, 0.0], obstacles=[ball])
    try:
        assert picture.moving == []
        ((circle,),) = picture.obstacle_artists
        assert circle.center == pytest.approx(ball.center[:2])
        np.testing.assert_allclose(picture.drawn(picture.target_artist)[0], [0.3, 0.5, 0.0])
    finally:
        picture.close()


def test_cli_animates_the_moving_reference_target(tmp_path, monkeypatch):
    from ocpkit.sim import animation

    drawn = {}
    monkeypatch.setattr(animation, "animate", lambda traj, path, problem, **scene: drawn.update(scene) or path)
    t = np.linspace(0.0, 1.0, 11)
    ref = np.c_[t, 0.3 + 0.1 * t, 0.5 - 0.1 * t, 0 * t]
    np.savetxt(tmp_path / "ref.csv", ref, delimiter=",", header="t,position[0],position[1],position[2]", comments="")
    args = ["simulate", "nlink:3", "--target", "0.3,0.5,0", "--reference", str(tmp_path / "ref.csv")]
    assert main([*args, "--duration", "0.3", "--animate", str(tmp_path / "run.gif")]) == 0
    times = 0.01 * np.arange(31)
    np.testing.assert_allclose(drawn["target"], np.c_[0.3 + 0.1 * times, 0.5 - 0.1 * times, 0 * times], atol=1e-12)

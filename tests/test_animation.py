"""Pictures of motion (ocpkit.sim.animation): the GIF a closed loop becomes, the robot it draws, and
`simulate --animate`.

What a frame shows is checked on the artists' data against forward kinematics computed another way (the planar
chain's closed form, pinocchio's frame placements), and the written GIF by its frames and size."""

import json

import numpy as np
import pytest
from PIL import Image

from ocpkit import problems, solvers
from ocpkit.sim.animation import MotionPicture, Skeleton, animate, check_path
from ocpkit.cli import main
from ocpkit.sim.simulate import Trajectory, simulate
from ocpkit.model.task import Sphere, reach

MAX_BYTES = 2_000_000
# the README's planar reach: the tip from seed 0's start round a ball to a point (as tests/test_cli_task.py)
TARGET, BALL = np.array([0.3, 0.5, 0.0]), Sphere((0.55, 0.2, 0.0), 0.08)


def _frames(path) -> list[np.ndarray]:
    with Image.open(path) as gif:
        out = []
        for k in range(gif.n_frames):
            gif.seek(k)
            out.append(np.asarray(gif.convert("RGB")))
    return out


def _planar_tip(q) -> np.ndarray:
    """The N-link chain's tip in closed form: links of 0.25 m at the absolute angles cumsum(q)."""
    angles = np.cumsum(q)
    return np.array([0.25 * np.cos(angles).sum(), 0.25 * np.sin(angles).sum(), 0.0])


@pytest.fixture(scope="module")
def planar_reach():
    pb = problems.make("nlink:3")
    ocp = reach(pb, [BALL], knots=5)
    x0, _ = pb.sample(0)
    goal = ocp.goal(x0, position=TARGET)
    return pb, simulate(pb.plant(), solvers.make("qp", ocp), x0, goal, 1.5)


def test_planar_reach_gif_shows_the_tip_arriving_at_the_target(planar_reach, tmp_path):
    pb, traj = planar_reach
    path = traj.animate(tmp_path / "reach.gif", pb, target=TARGET, obstacles=[BALL])
    frames = _frames(path)
    assert len(frames) >= 10 and path.stat().st_size <= MAX_BYTES
    assert (frames[0] != frames[-1]).any(axis=-1).mean() > 0.005  # the arm moved: over 0.5 % of the pixels differ
    with Image.open(path) as gif:  # real time: the frames' durations add up to the run, plus the held last frame
        durations = []
        for k in range(gif.n_frames):
            gif.seek(k)
            durations.append(gif.info["duration"])
    assert sum(durations[:-1]) == pytest.approx(1000 * traj.t[-1], abs=10) and durations[-1] == 1000

    picture = MotionPicture(traj, pb, target=TARGET, obstacles=[BALL])
    try:
        assert picture.planar and picture.indices[0] == 0 and picture.indices[-1] == len(traj.t) - 1
        picture.draw(len(picture.indices) - 1)
        arm, tip = picture.drawn(picture.robot), picture.drawn(picture.tip)[0]
        final = _planar_tip(traj.x[-1, :3])
        # the drawn arm: base at the origin, a joint at each link's end, its last point the chain's tip
        np.testing.assert_allclose(arm[0], 0, atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(np.diff(arm, axis=0), axis=1), 0.25, atol=1e-9)
        np.testing.assert_allclose(arm[-1], final, atol=1e-9)
        np.testing.assert_allclose(tip, final, atol=1e-9)
        assert np.linalg.norm(tip - TARGET) < 0.01  # it reached the target
        np.testing.assert_allclose(picture.drawn(picture.target_artist)[0], TARGET)
        np.testing.assert_allclose(picture.drawn(picture.trail)[-1], final, atol=1e-9)
        circle = picture.axes.patches[0]
        assert circle.center == pytest.approx(BALL.center[:2]) and circle.radius == pytest.approx(BALL.radius)
        assert "t = 1.50 s" == picture.clock.get_text()
        picture.draw(0)
        np.testing.assert_allclose(picture.drawn(picture.tip)[0], _planar_tip(traj.x[0, :3]), atol=1e-9)
        assert picture.clock.get_text() == "t = 0.00 s"
    finally:
        picture.close()


def test_arm_in_3d_reaches_its_joint_goal_pose():
    import pinocchio as pin

    pb = problems.make("puma560")
    x0, goal = pb.sample(1)  # seed 1 settles within 0.8 s
    traj = simulate(pb.plant(), solvers.make("qp", pb.ocp(knots=5)), x0, goal, 1.0)
    picture = MotionPicture(traj, pb)
    try:
        assert not picture.planar and picture.target is None
        picture.draw(len(picture.indices) - 1)
        data = pin.Data(pb.pin_model)
        tool = pb.pin_model.getFrameId("tool")

        def pinocchio_tool(q):
            pin.framesForwardKinematics(pb.pin_model, data, q)
            return data.oMf[tool].translation.copy()

        ghost = picture.drawn(picture.ghost)
        np.testing.assert_allclose(ghost[-1], pinocchio_tool(goal[:6]), atol=1e-9)  # the goal pose, drawn faint
        end = picture.drawn(picture.tip)[0]
        np.testing.assert_allclose(end, pinocchio_tool(traj.x[-1, :6]), atol=1e-9)
        assert np.linalg.norm(end - ghost[-1]) < 0.01  # the arm arrived at its goal pose
        shadow = picture.drawn(picture.shadow)
        robot = picture.drawn(picture.robot)
        np.testing.assert_allclose(shadow[:, :2], robot[:, :2])  # straight below the arm, on the floor
        assert (shadow[:, 2] == picture.axes.get_zlim()[0]).all()
    finally:
        picture.close()


def test_3d_arm_with_target_and_obstacle(tmp_path):
    pb = problems.make("panda")
    ball = Sphere((0.4, -0.25, 0.35), 0.08)
    target = np.array([0.4, 0.0, 0.3])
    ocp = reach(pb, [ball], knots=5)
    x0, _ = pb.sample(0)
    traj = simulate(pb.plant(), solvers.make("qp", ocp), x0, ocp.goal(x0, position=target), 1.5)
    path = animate(traj, tmp_path / "panda.gif", pb, target=target, obstacles=[ball])
    frames = _frames(path)
    assert len(frames) >= 10 and path.stat().st_size <= MAX_BYTES and (frames[0] != frames[-1]).any()
    without_target = MotionPicture(traj, pb)
    assert without_target.ghost is None and without_target.target_artist is None  # a reach goal's angles: no pose
    without_target.close()
    picture = MotionPicture(traj, pb, target=target, obstacles=[ball])
    try:
        picture.draw(len(picture.indices) - 1)
        assert picture.ghost is None
        assert np.linalg.norm(picture.drawn(picture.tip)[0] - target) < 0.01
        np.testing.assert_allclose(picture.drawn(picture.robot)[0], 0)  # the base segment starts at the world origin
        ((wire, shadow),) = picture.obstacle_artists  # the ball's wireframe and its shadow on the floor
        on = picture.drawn(wire)
        on = on[~np.isnan(on).any(axis=1)]
        np.testing.assert_allclose(np.linalg.norm(on - ball.center, axis=1), ball.radius, atol=1e-12)
        assert (picture.drawn(shadow)[:, 2] == picture.floor).all()
    finally:
        picture.close()


def test_pendulum_is_drawn_as_its_rod():
    pb = problems.make("pendulum")
    t = np.array([0.0, 0.05, 0.1])  # 20 frames per second: one frame per state
    q = np.array([0.0, np.pi / 2, np.pi])  # hanging, horizontal, upright
    traj = Trajectory(t=t, x=np.column_stack([q, np.zeros(3)]), u=np.zeros((2, 1)), goal=np.array([np.pi, 0.0]))
    picture = MotionPicture(traj, pb)
    try:
        assert picture.planar and list(picture.indices) == [0, 1, 2]
        for k, bob in enumerate([(0, -pb.l), (pb.l, 0), (0, pb.l)]):
            picture.draw(k)
            np.testing.assert_allclose(picture.drawn(picture.robot), [[0, 0, 0], [*bob, 0]], atol=1e-12)
        np.testing.assert_allclose(picture.drawn(picture.ghost)[-1], [0, pb.l, 0], atol=1e-12)
    finally:
        picture.close()


def test_long_run_keeps_real_time_with_fewer_frames():
    pb = problems.make("pendulum")
    t = np.arange(1001) * 0.01  # 10 s
    traj = Trajectory(
        t=t,
        x=np.column_stack([np.linspace(0, 3, 1001), np.zeros(1001)]),
        u=np.zeros((1000, 1)),
        goal=np.array([3.0, 0.0]),
    )
    picture = MotionPicture(traj, pb, max_frames=50)
    try:
        assert len(picture.indices) == 50 and picture.indices[-1] == 1000
    finally:
        picture.close()


def test_errors_name_the_argument(tmp_path):
    pb = problems.make("pendulum")
    traj = Trajectory(t=np.array([0.0, 0.01]), x=np.zeros((2, 2)), u=np.zeros((1, 1)), goal=np.zeros(2))
    with pytest.raises(ValueError, match=r"path .*out\.mp4: an animation is written as a GIF.*\(not \.mp4\)"):
        animate(traj, tmp_path / "out.mp4", pb)
    with pytest.raises(ValueError, match="--animate out: .*it has no suffix"):
        check_path("out", "--animate")
    with pytest.raises(ValueError, match="target must be 3 finite numbers"):
        MotionPicture(traj, pb, target=[1.0, 2.0])
    with pytest.raises(ValueError, match="frame 'tip': the pendulum has no frames"):
        Skeleton(pb, "tip")
    with pytest.raises(ValueError, match="unknown frame 'hand'"):
        Skeleton(problems.make("nlink:2"), "hand")
    with pytest.raises(ValueError, match="problem 'box' has no kinematics to draw"):
        Skeleton(type("Box", (), {"name": "box"})())
    assert not (tmp_path / "out.mp4").exists()


def test_cli_animate(tmp_path, capsys):
    gif = tmp_path / "sim.gif"
    args = ["simulate", "pendulum", "--duration", "1", "--out", str(tmp_path / "sim.png"), "--animate", str(gif)]
    assert main([*args, "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["animation"] == str(gif) and len(_frames(gif)) >= 10 and gif.stat().st_size <= MAX_BYTES
    # a bad suffix is refused before the run, naming the option
    assert main([*args[:-1], str(tmp_path / "sim.mp4")]) == 2
    err = capsys.readouterr().err
    assert "--animate" in err and "give a path ending in .gif" in err and "not .mp4" in err
    assert not (tmp_path / "sim.mp4").exists()


def test_report_section_embeds_one_animation_per_robot_family(tmp_path):
    from ocpkit.studies import motion

    text = motion.section(tmp_path)
    embedded = [line for line in text.splitlines() if line.startswith("![")]
    assert len(embedded) == len(motion.SCENES) == 3
    for line in embedded:
        gif = tmp_path / line[line.index("](") + 2 : -1]
        assert gif.parent == tmp_path / motion.FOLDER and len(_frames(gif)) >= 10
        assert gif.stat().st_size <= MAX_BYTES
    # what each run reached is said under its picture: the pendulum settled, the reaches arrived clear of the ball
    assert "largest joint error at the end" in text and text.count("m from the target, smallest clearance") == 2

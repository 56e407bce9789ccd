"""Task-space targets on the command line (--target, --obstacle, --frame, --task) and the docs' reach tutorial."""

import json
import re
import shutil

import numpy as np
import pytest

from conftest import DOCS, EXAMPLES, run_example
from ocpkit import cli
from ocpkit.cli import main
from ocpkit.cli.task import reach_ocp, reach_task, read_task_file
from ocpkit.problems import make
from pinocchio.rpy import rpyToMatrix

# nlink:3 (planar, z = 0): the tip from seed 0's start, (0.43, -0.21), round a ball to (0.3, 0.5); without the ball
# the tip's path passes through it.
SCENE = ["nlink:3", "--target", "0.3,0.5,0", "--obstacle", "0.55,0.2,0,0.08"]
TOML = """
target = [0.3, 0.5, 0.0]
frame = "tip"
margin = 0.01
[[obstacle]]
center = [0.55, 0.2, 0.0]
radius = 0.08
"""


def _simulate(args, tmp_path, capsys) -> dict:
    assert main(["simulate", *args, "--duration", "1.5", "--out", str(tmp_path / "sim.png"), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_target_and_obstacle_flags(tmp_path, capsys):
    out = _simulate(SCENE, tmp_path, capsys)
    reach = out["reach"]
    assert reach["frame"] == "tip" and reach["target"] == [0.3, 0.5, 0.0] and reach["states"] == 151
    assert reach["obstacles"] == [[0.55, 0.2, 0.0, 0.08]] and reach["margin"] == 0.01
    assert reach["final_distance"] < 0.01, reach
    assert 0 < reach["min_clearance"] < 0.02 and reach["collisions"] == 0, reach  # the ball was in the way
    assert reach["success_while_colliding"] == 0 and out["successes"] + out["soft"] + out["fallbacks"] == 150
    assert out["progress"]["verdict"] == "reached" and out["progress"]["final"] == reach["final_distance"]
    # the text summary says the same: the reach line, then the loop's verdict
    assert main(["simulate", *SCENE, "--duration", "1.5", "--out", str(tmp_path / "sim.png")]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert re.fullmatch(
        r"reach: tip 0\.00\d\d m from the target \(0\.3, 0\.5, 0\) after 1\.5 s; min clearance "
        r"0\.0\d{3} m to 1 obstacle \(margin 0\.01 m\); no collision in 151 states",
        lines[-2],
    ), lines
    assert re.fullmatch(
        r"verdict: reached — tip's distance to the target 0\.00\d\d m at the end \(within 0\.01 m\)", lines[-1]
    ), lines
    assert re.search(r": actual cost \d+\.\d{4}; 150 steps: \d+ success, \d+ soft( \(.*\))?, \d+ fallbacks", lines[0])


def test_stalled_reach_is_said_while_every_step_succeeds(tmp_path, capsys):
    """The issue's case: 5 cm short of a target beyond the arm's reach (0.80 m, links 3 × 0.25 m), every step a
    success; the loop is stalled."""
    args = ["nlink:3", "--target", "0.48,0.64,0", "--linearization", "trajectory", "--duration", "3"]
    assert main(["simulate", *args, "--out", str(tmp_path / "sim.png"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["successes"] == out["steps"] == 300 and out["soft"] == out["fallbacks"] == 0
    progress = out["progress"]
    assert progress["verdict"] == "stalled" and abs(progress["final"] - 0.05) < 2e-3 and progress["change"] <= 1e-3
    assert progress["error"] == "tip's distance to the target" and progress["unit"] == "m"
    assert (progress["tolerance"], progress["window"], progress["still"]) == (0.01, 0.5, 0.001)
    assert main(["simulate", *args, "--out", str(tmp_path / "sim.png")]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert "300 steps: 300 success, 0 soft, 0 fallbacks" in lines[0]
    assert re.fullmatch(
        r"verdict: STALLED — tip's distance to the target 0\.0[45]\d\d m at the end \(not within "
        r"0\.01 m\), changed 0\.000\d m over the last 0\.5 s \(at most 0\.001 m: no progress\)",
        lines[-1],
    ), lines


def test_soft_steps_and_their_causes(tmp_path, capsys):
    """An obstacle over the start (the tip's sphere inside it): the plans that break its clearance while the arm
    gets out are soft steps, printed with their cause beside the fallbacks, never successes."""
    args = [
        "nlink:3",
        "--target",
        "0.3,0.5,0",
        "--obstacle",
        "0.43,-0.21,0,0.05",
        "--linearization",
        "trajectory",
        "--duration",
        "1",
    ]
    assert main(["simulate", *args, "--out", str(tmp_path / "sim.png"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["soft"] > 0 and out["soft_causes"].startswith("clearance"), out
    assert out["successes"] + out["soft"] + out["fallbacks"] == out["steps"] == 100
    assert out["reach"]["collisions"] > 0 and out["reach"]["success_while_colliding"] == 0
    assert main(["simulate", *args, "--out", str(tmp_path / "sim.png")]) == 0
    text = capsys.readouterr().out
    assert (
        f"{out['successes']} success, {out['soft']} soft ({out['soft_causes']}), {out['fallbacks']} fallbacks" in text
    )
    assert "steps reported success while colliding" in text


def test_task_file_is_the_flags(tmp_path, capsys):
    task = tmp_path / "reach.toml"
    task.write_text(TOML)
    flags = _simulate(SCENE, tmp_path, capsys)
    from_file = _simulate(["nlink:3", "--task", str(task)], tmp_path, capsys)
    assert from_file["reach"] == flags["reach"] and from_file["actual_cost"] == flags["actual_cost"]


def test_flags_override_the_file_and_negative_values(tmp_path, capsys):
    task = tmp_path / "reach.toml"
    task.write_text(TOML)
    # --target replaces the file's, --obstacle adds a second ball; "-0.3,…" is a value, not an option
    assert (
        main(
            ["solve", "nlink:3", "--task", str(task), "--target", "-0.3,0.5,0", "--obstacle", "-0.6,0,0,0.05", "--json"]
        )
        == 0
    )
    reach = json.loads(capsys.readouterr().out)["reach"]
    assert reach["target"] == [-0.3, 0.5, 0.0] and len(reach["obstacles"]) == 2
    assert reach["obstacles"][1] == [-0.6, 0.0, 0.0, 0.05] and reach["states"] == 51  # solve: the plan, x_0 … x_T


def test_solve_reports_its_plan(capsys):
    assert main(["solve", *SCENE, "--frame", "joint3"]) == 0
    out = capsys.readouterr().out
    assert re.search(
        r"reach: joint3 \d\.\d{4} m from the target \(0\.3, 0\.5, 0\) at the plan's end \(x_T, T = 50, "
        r"the OCP's model\); min clearance -?\d\.\d{4} m to 1 obstacle",
        out,
    ), out


def _bad_files(tmp_path):
    files = {
        "bad.toml": "target = [1, 2,\n",
        "key.toml": "target = [0.3, 0.5, 0]\ngoal = 1\n",
        "none.toml": "margin = 0.02\n",
        "obstacle.toml": "target = [0.3, 0.5, 0]\n[[obstacle]]\ncentre = [1, 2, 3]\n",
        "radius.toml": "target = [0.3, 0.5, 0]\n[[obstacle]]\ncenter = [1, 2, 3]\nradius = -1\n",
        "weight.toml": "target = [0.3, 0.5, 0]\nposition_weight = 0\n",
        "short.toml": "target = [0.3, 0.5]\n",
        "frame.toml": 'target = [0.3, 0.5, 0]\nframe = "hand"\n',
        # issue 44, item 10: booleans, bytes that are not UTF-8, lengths, the world frame, a target at 1e300
        "bools.toml": "target = [true, false, true]\n",
        "strings.toml": 'target = ["1", "2", "3"]\n',
        "radius6.toml": "target = [0.3, 0.5, 0]\nlink_radius = 1e6\n",
        "margin6.toml": "target = [0.3, 0.5, 0]\nmargin = 1e6\n",
        "universe.toml": 'target = [0.3, 0.5, 0]\nframe = "universe"\n',
        "far.toml": "target = [1e300, 0, 0]\n",
        "turn.toml": "target = [0.3, 0.5, 0]\norientation = [0, 0]\n",
        "limits.toml": "target = [0.3, 0.5, 0]\njoint_limits = 1\n",
        "elbow.toml": 'target = [0.3, 0.5, 0]\n[[frame_target]]\nframe = "joint3"\n',
    }
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    (tmp_path / "latin1.toml").write_bytes("target = [0.3, 0.5, 0]\n# café\n".encode("latin-1"))


@pytest.mark.parametrize(
    "args,message",
    [
        (
            ["nlink:3", "--target", "0.3,0.5,0", "--obstacle", "1,2,3"],
            "--obstacle 1,2,3: an obstacle is 'x,y,z,r' (centre and radius in metres), got '1,2,3'",
        ),
        (["nlink:3", "--target", "0.3,0.5,0", "--obstacle", "1,2,3,-1"], "--obstacle 1,2,3,-1: Sphere radius"),
        (["nlink:3", "--obstacle", "1,2,3,0.1"], "--obstacle needs --target x,y,z"),
        (["nlink:3", "--frame", "tip"], "--frame needs --target x,y,z"),
        (
            ["nlink:3", "--target", "0.3,0.5"],
            "--target is 'x,y,z' (the end effector's target point in metres, world frame), got '0.3,0.5'",
        ),
        (["pendulum", "--target", "0.3,0.5,0"], "--target: pendulum has no kinematics"),
        (
            ["nlink:3", "--target", "0.3,0.5,0", "--frame", "tipp"],
            "--frame 'tipp': unknown frame 'tipp'; did you mean 'tip'?",
        ),
        (["nlink:3", "--task", "missing.toml"], "--task missing.toml: no such file"),
        (["nlink:3", "--task", "bad.toml"], "--task bad.toml: not valid TOML"),
        (["nlink:3", "--task", "key.toml"], "--task key.toml: unknown key 'goal'; a task file has target, frame"),
        (["nlink:3", "--task", "none.toml"], "--task none.toml: no target = [x, y, z] in the file"),
        (["nlink:3", "--task", "obstacle.toml"], "--task obstacle.toml: obstacle 1 has the keys ['centre']"),
        (["nlink:3", "--task", "radius.toml"], "--task radius.toml: obstacle 1: radius must be a positive number"),
        (["nlink:3", "--task", "weight.toml"], "--task weight.toml: position_weight must be a positive number, got 0"),
        (
            ["nlink:3", "--task", "short.toml"],
            "--task short.toml: target is [x, y, z] (the end effector's target point",
        ),
        (
            ["nlink:3", "--task", "frame.toml"],
            "--task frame.toml: frame 'hand': unknown frame 'hand'; the model's "
            "frames: universe, joint1, joint2, joint3, tip",
        ),
        (["pendulum", "--task", "short.toml"], "--task short.toml: target is [x, y, z]"),
        (
            ["nlink:3", "--task", "bools.toml"],
            "--task bools.toml: target is [x, y, z] (the end effector's target point in "
            "metres, world frame), got [True, False, True]",
        ),
        (["nlink:3", "--task", "strings.toml"], "--task strings.toml: target is [x, y, z]"),
        (["nlink:3", "--task", "latin1.toml"], "--task latin1.toml: not UTF-8 text (byte 28); a TOML file is UTF-8"),
        (
            ["nlink:3", "--task", "radius6.toml"],
            "--task radius6.toml: link_radius must be > 0 and at most 10 m (a robot's scale), got 1000000.0",
        ),
        (["nlink:3", "--task", "margin6.toml"], "--task margin6.toml: margin must be within ±10 m"),
        (
            ["nlink:3", "--task", "universe.toml"],
            "--task universe.toml: frame 'universe': is fixed to the world (it does not move with the joints)",
        ),
        (["nlink:3", "--target", "0.3,0.5,0", "--frame", "universe"], "--frame 'universe': is fixed"),
        (
            ["nlink:3", "--task", "far.toml"],
            "--task far.toml: target [1e+300, 0.0, 0.0] is 1e+300 m from the world "
            "origin, beyond the robot's plausible workspace (75 m, 100 × its size)",
        ),
        (["nlink:3", "--target", "1e300,0,0"], "--target [1e+300, 0.0, 0.0] is 1e+300 m from the world origin"),
        (
            ["nlink:3", "--target", "0.3,0.5,0", "--frame-target", "tip=0,0,1e300"],
            "--frame-target tip=0,0,1e300 [0.0, 0.0, 1e+300] is 1e+300 m",
        ),
        # issue 44, item 12: the orientation, other frames and joint-limit terms, checked as the rest
        (["nlink:3", "--task", "turn.toml"], "--task turn.toml: orientation is roll, pitch, yaw (rad"),
        (["nlink:3", "--target", "0.3,0.5,0", "--orientation", "1,2"], "--orientation is roll, pitch, yaw (rad"),
        (["nlink:3", "--task", "limits.toml"], "--task limits.toml: joint_limits must be true or false, got 1"),
        (["nlink:3", "--target", "0.3,0.5,0", "--joint-limits"], "--joint-limits: nlink:3 has no joint limits"),
        (["nlink:3", "--orientation", "0,0,1"], "--orientation needs --target x,y,z"),
        (
            ["nlink:3", "--task", "elbow.toml"],
            "--task elbow.toml: frame_target 1 has the keys ['frame']; it takes frame",
        ),
        (["nlink:3", "--target", "0.3,0.5,0", "--frame-target", "elbow"], "--frame-target is NAME=x,y,z"),
        (
            ["nlink:3", "--target", "0.3,0.5,0", "--frame-target", "hand=0,0,0"],
            "--frame-target hand=0,0,0: unknown frame 'hand'",
        ),
        (
            ["nlink:3", "--target", "0.3,0.5,0", "--frame-target", "tip=0,0,0"],
            "--frame-target tip=0,0,0: frame 'tip' already has a target",
        ),
    ],
)
@pytest.mark.parametrize("command", ["solve", "simulate"])
def test_bad_input_is_one_line_naming_the_option(command, args, message, tmp_path, monkeypatch, capsys):
    _bad_files(tmp_path)
    monkeypatch.chdir(tmp_path)
    assert main([command, *args, "--out", "sim.png"] if command == "simulate" else [command, *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ocpkit: error: ") and message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "sim.png").exists()


def test_attach_values():
    assert cli._attach_values(
        ["simulate", "x", "--target", "-1,2,3", "--obstacle", "-1e-1,-2,0,0.5", "--frame", "-x"]
    ) == ["simulate", "x", "--target=-1,2,3", "--obstacle=-1e-1,-2,0,0.5", "--frame", "-x"]
    assert cli._attach_values(["--target", "--json"]) == ["--target", "--json"]


def test_reach_tutorial(tmp_path, monkeypatch, capsys):
    """The tutorial's script (examples/reach_obstacle.py) runs and prints what its page says; its TOML file
    (examples/reach.toml, shown on the same page) is the script's task, and the command line with it reaches the same
    point."""
    monkeypatch.chdir(tmp_path)
    run_example("reach_obstacle.py")
    printed = capsys.readouterr().out.strip()
    verdict, distance, clearance = re.fullmatch(
        r"(\w+): final distance (\S+) m, min clearance (\S+) m", printed
    ).groups()
    distance, clearance = float(distance), float(clearance)
    assert verdict == "reached" and distance < 0.01 and 0 < clearance < 0.02
    page = (DOCS / "tutorials" / "obstacles.md").read_text()
    assert f"It prints `{printed}`" in page and '--8<-- "reach.toml"' in page
    shutil.copy(EXAMPLES / "reach.toml", tmp_path / "reach.toml")
    task = read_task_file(tmp_path / "reach.toml")
    assert task["target"].tolist() == [0.4, 0.0, 0.3] and [(o.center, o.radius) for o in task["obstacles"]] == [
        ((0.4, -0.25, 0.35), 0.08)
    ]
    assert main(["simulate", "panda", "--task", "reach.toml", "--duration", "2", "--out", "arm.png", "--json"]) == 0
    reach = json.loads(capsys.readouterr().out)["reach"]
    assert reach["frame"] == "panda_hand_tcp" and reach["collisions"] == 0
    assert np.isclose(reach["final_distance"], distance, atol=5e-4), (reach, distance)
    assert np.isclose(reach["min_clearance"], clearance, atol=5e-4), (reach, clearance)


TURN = """
target = [0.3, 0.5, 0.0]
orientation = [0.0, 0.0, 2.0]
[[frame_target]]
frame = "joint3"
target = [0.404, 0.273, 0.0]
weight = 10.0
"""


def test_orientation_and_other_frames_from_the_flags_and_the_file(tmp_path, capsys):
    """Issue 44, item 12: the command line takes FrameOrientation (roll, pitch, yaw) and other frames' FramePosition
    terms, as Python does; the planar arm brings its tip to the point at yaw 2 rad."""
    flags = ["nlink:3", "--target", "0.3,0.5,0", "--orientation", "0,0,2", "--frame-target", "joint3=0.404,0.273,0"]
    out = _simulate([*flags, "--linearization", "trajectory"], tmp_path, capsys)
    reach = out["reach"]
    assert reach["final_distance"] < 0.02 and reach["final_orientation_error"] < 0.05, reach
    assert reach["frame_targets"][0]["frame"] == "joint3" and reach["frame_targets"][0]["target"] == [0.404, 0.273, 0.0]
    (tmp_path / "turn.toml").write_text(TURN)
    args = cli._parser().parse_args(["solve", "nlink:3", "--task", str(tmp_path / "turn.toml")])
    task = reach_task(args)
    ocp = reach_ocp(make("nlink:3"), args, task)
    assert ocp.terms == ["state", "input", "position", "orientation", "position_joint3"]
    assert task.goal(ocp, np.zeros(6))[6:].tolist() == [
        0.3,
        0.5,
        0.0,
        *np.ravel(rpyToMatrix(0, 0, 2.0)),
        0.404,
        0.273,
        0,
    ]
    assert main(["solve", *flags, "--json"]) == 0
    assert "final_orientation_error" in json.loads(capsys.readouterr().out)["reach"]
    assert main(["solve", *flags]) == 0
    assert re.search(
        r"reach: tip \d\.\d{4} m from the target \(0\.3, 0\.5, 0\) at the plan's end .*, \d\.\d{4} rad "
        r"from its orientation; joint3 \d\.\d{4} m from \(0\.404, 0\.273, 0\)",
        capsys.readouterr().out,
    )


def test_joint_limits_term_from_the_flag_and_the_file(tmp_path):
    """--joint-limits and joint_limits = true: JointLimitBarrier at the robot's limits (the Puma's)."""
    (tmp_path / "limits.toml").write_text("target = [0.3, 0.3, 0.5]\njoint_limits = true\njoint_limit_weight = 50\n")
    for argv, weight in (
        (["--target", "0.3,0.3,0.5", "--joint-limits"], 1e3),
        (["--task", str(tmp_path / "limits.toml")], 50.0),
    ):
        args = cli._parser().parse_args(["solve", "puma560", *argv])
        task = reach_task(args)
        assert task.joint_limits == weight
        ocp = reach_ocp(make("puma560"), args, task)
        assert ocp.terms == ["state", "input", "position", "joint_limits"]


def test_export_takes_the_task_options(tmp_path, capsys):
    """Issue 44, item 12: `ocpkit export` takes --target/--frame/--task as solve and simulate do, and its round trip
    runs on the task's goal."""
    (tmp_path / "reach.toml").write_text('target = [0.3, 0.2, 0.0]\nframe = "tip"\n')
    assert (
        main(
            [
                "export",
                "nlink:2",
                "--horizon",
                "20",
                "--task",
                str(tmp_path / "reach.toml"),
                "--out",
                str(tmp_path / "c"),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "round trip:" in out and "— agree" in out, out
    assert "NG" in (tmp_path / "c" / "mpc.h").read_text()  # the step's goal is [x_goal; target]
    assert main(["export", "nlink:2", "--horizon", "20", "--target", "1e300,0,0", "--out", str(tmp_path / "d")]) == 2
    assert "--target [1e+300, 0.0, 0.0] is 1e+300 m" in capsys.readouterr().err and not (tmp_path / "d").exists()

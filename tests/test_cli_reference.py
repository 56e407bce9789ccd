"""simulate --reference, --no-preview, --obstacle-path and the task file's reference and obstacle_path (issue 46)."""

import json

import numpy as np
import pytest

from ocpkit.cli import main


def _sinusoid(path):
    """nlink:3's three joints on a 0.3 rad, 0.5 Hz sinusoid with their rates, as a CSV of named columns."""
    t = np.linspace(0.0, 3.0, 301)
    w, phase = np.pi, np.array([0.0, 1.0, 2.0])
    q = 0.3 * np.sin(w * t[:, None] + phase) - 0.3 * np.sin(phase)
    rates = 0.3 * w * np.cos(w * t[:, None] + phase)
    header = "t,q1,q2,q3,qd1,qd2,qd3"
    np.savetxt(path, np.column_stack([t, q, rates]), delimiter=",", header=header, comments="")
    return path


def _run(args, capsys) -> dict:
    assert main(["simulate", *args, "--duration", "1.0", "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_a_previewed_reference_is_tracked_closer_than_a_held_one(tmp_path, capsys):
    ref = str(_sinusoid(tmp_path / "ref.csv"))
    preview = _run(["nlink:3", "--reference", ref], capsys)["progress"]
    held = _run(["nlink:3", "--reference", ref, "--no-preview"], capsys)["progress"]
    assert preview["rms_error"] < 0.25 * held["rms_error"], (preview, held)


def test_an_obstacle_path_moves_the_obstacle_into_the_path_and_the_loop_keeps_clear(tmp_path, capsys):
    path = tmp_path / "obstacle.csv"
    path.write_text("t,obstacle0_x,obstacle0_y,obstacle0_z,obstacle0_radius\n0,0.9,0.9,0,0.06\n1.0,0.35,0.5,0,0.06\n")
    scene = ["nlink:3", "--target", "0.2,0.6,0", "--obstacle", "0.9,0.9,0,0.06"]
    moved = _run([*scene, "--obstacle-path", str(path)], capsys)["reach"]
    assert moved["collisions"] == 0 and moved["min_clearance"] > 0, moved
    # the clearance is measured against where the obstacle was: held there, the ball never comes near
    still = _run(scene, capsys)["reach"]
    assert still["min_clearance"] > moved["min_clearance"] + 0.05, (still["min_clearance"], moved["min_clearance"])


def test_the_task_file_names_the_motion_files_relative_to_itself(tmp_path, capsys):
    _sinusoid(tmp_path / "ref.csv")
    (tmp_path / "obstacle.csv").write_text("t,obstacle0_x\n0,0.9\n1,0.35\n")
    (tmp_path / "task.toml").write_text(
        'target = [0.2, 0.6, 0.0]\nobstacle_path = "obstacle.csv"\n[[obstacle]]\ncenter = [0.9, 0.9, 0.0]\n'
        "radius = 0.06\n"
    )
    out = _run(["nlink:3", "--task", str(tmp_path / "task.toml")], capsys)
    assert out["reach"]["collisions"] == 0


@pytest.mark.parametrize(
    "args, message",
    [
        (["--no-preview"], "--no-preview applies to --reference only"),
        (["--obstacle-path", "{dir}/obstacle.csv"], "--obstacle-path moves the task's obstacles: declare them"),
        (["--reference", "{dir}/missing.csv"], "--reference: no such file"),
        (["--reference", "{dir}/bad.csv"], "unknown column(s) ['elbow']"),
        (["--reference", "{dir}/ref.txt"], "--reference: a .csv or .npz file, got ref.txt"),
    ],
)
def test_bad_motion_input_is_one_line_naming_it(args, message, tmp_path, capsys):
    (tmp_path / "obstacle.csv").write_text("t,obstacle0_x\n0,0.9\n")
    (tmp_path / "bad.csv").write_text("t,elbow\n0,1\n")
    (tmp_path / "ref.txt").write_text("t\n0\n")
    assert main(["simulate", "nlink:3", *[a.format(dir=tmp_path) for a in args]]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1, err

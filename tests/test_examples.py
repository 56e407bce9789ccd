"""The docs' tutorials run: every script in examples/ is executed as a user would run it (``python SCRIPT``, from a
folder outside the checkout), at tiny sizes in the default run and at the sizes the docs quote with ``-m slow``,
where what it prints is what the docs say it prints."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
DOCS = ROOT / "docs"


def run(script: str, *args, cwd: Path, timeout: float = 300) -> str:
    """Run ``examples/SCRIPT`` with ``args`` in ``cwd``; return its stdout (the test fails on a non-zero exit)."""
    proc = subprocess.run(
        [sys.executable, str(EXAMPLES / script), *map(str, args)],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert proc.returncode == 0, f"{script} exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr}"
    return proc.stdout


def numbers(text: str) -> list[float]:
    return [float(v) for v in re.findall(r"-?\d+\.\d+(?:e-?\d+)?", text)]


# script -> the arguments of its tiny run (a duration in seconds, or an output folder under the test's tmp_path)
FAST = {
    "first_controller.py": (),
    "first_study.py": ("{tmp}/study",),
    "cartpole.py": (0.5,),
    "urdf_robot.py": (0.3,),
    "reach_obstacle.py": (0.3,),
    "tracking.py": (0.2,),
    "mujoco_plant.py": (0.2,),
    "export_c.py": ("{tmp}/pendulum_c",),
}
SLOW = {"robustness_study.py", "dask_study.py"}  # studies: each starts worker processes (7-12 s on 2 cores)


def test_every_example_is_run_and_shown():
    """Each script in examples/ is run here and included into a docs page (so no tutorial is left untested)."""
    scripts = {p.name for p in EXAMPLES.glob("*.py")}
    assert scripts == set(FAST) | SLOW
    included = set(re.findall(r'--8<-- "([^"]+)"', "".join(p.read_text() for p in DOCS.rglob("*.md"))))
    assert scripts | {"pendulum_loop.c", "reach.toml"} <= included


@pytest.mark.parametrize("script", sorted(FAST))
def test_example_runs(script, tmp_path):
    out = run(script, *(str(a).format(tmp=tmp_path) for a in FAST[script]), cwd=tmp_path)
    assert out.strip()
    if script == "export_c.py":  # the C program and ExportedMPC in Python give the same first input
        c_u0 = re.search(r"^u0 (\S+)", out, re.M).group(1)
        assert re.search(rf"^Python u0 {re.escape(c_u0)} ", out, re.M), out
        assert "failures 0" in out
    if script == "first_study.py":  # a second run resumes: every trial is stored, the same table comes back
        assert run(script, tmp_path / "study", cwd=tmp_path) == out


@pytest.mark.slow
def test_reach_obstacle_prints_what_the_docs_say(tmp_path):
    assert run("reach_obstacle.py", cwd=tmp_path).strip() == "reached: final distance 0.0008 m, min clearance 0.0100 m"


@pytest.mark.slow
def test_tracking_prints_what_the_docs_say(tmp_path):
    assert numbers(run("tracking.py", cwd=tmp_path)) == [0.0093, 0.0957, 0.0204, 0.0182]


@pytest.mark.slow
def test_urdf_robot_reaches_its_goal(tmp_path):
    assert numbers(run("urdf_robot.py", cwd=tmp_path) + ".0")[0] < 1e-3  # final joint error, rad


@pytest.mark.slow
def test_mujoco_plant_agrees(tmp_path):
    assert numbers(run("mujoco_plant.py", cwd=tmp_path))[0] < 1e-8  # ocpkit's plant vs MuJoCo, 1 s of LinearMPC


@pytest.mark.slow
def test_robustness_study_writes_its_report(tmp_path):
    out = run("robustness_study.py", tmp_path / "cartpole", cwd=tmp_path)
    assert "traditional" in out and "robustness.md" in out
    assert "cartpole" in (tmp_path / "cartpole" / "robustness.md").read_text()


@pytest.mark.slow
def test_dask_study_runs_on_its_cluster(tmp_path):
    out = run("dask_study.py", tmp_path / "horizon", cwd=tmp_path)
    assert "12 trials on 2 workers" in out

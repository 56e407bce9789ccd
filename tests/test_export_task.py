"""The exported C step with a task's cost terms (issue 29): the frame-position term of ocpkit.task.reach in C, equal
to LinearMPC's Python step (Gauss–Newton about the plan, ocpkit.task_rows.TaskRows) along closed loops; a task
with obstacles is still refused."""
from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest

from ocpkit.controller import SUCCESS
from ocpkit.export import ExportedMPC, build, export
from ocpkit.problem import Problem
from ocpkit.problems import make
from ocpkit.simulate import simulate
from ocpkit.solvers.qp import LinearMPC
from ocpkit.task import reach
from ocpkit.problems.panda import urdf_path as panda_urdf

pytestmark = pytest.mark.skipif(shutil.which("cc") is None or shutil.which("make") is None,
                                reason="needs cc and make")

PANDA = panda_urdf()


def _target(problem, seed):
    """The end effector's position at a sampled configuration: a reachable target."""
    _, q = problem.sample(seed)
    fk = problem.kinematics.function(problem.end_effector)
    return np.asarray(fk(q[:problem.kinematics.n])[0]).ravel()


def _same_closed_loop(problem, ocp, out_dir, seed, duration, tol=1e-8):
    """The C step (ExportedMPC) and LinearMPC's Python step in closed loops from the same start towards the same
    target: the same inputs at every step, all successes; returns the C loop and its target."""
    x0, _ = problem.sample(seed)
    target = _target(problem, seed + 1)
    goal = ocp.goal(x0, position=target)
    with ExportedMPC(ocp, out_dir) as c:
        a = simulate(ocp.model, c, x0, goal, duration)
    b = simulate(ocp.model, LinearMPC(ocp, native=False), x0, goal, duration)
    assert len(a.solutions) >= 100
    assert all(s == SUCCESS for s in a.statuses), a.statuses
    assert all(s == SUCCESS for s in b.statuses), b.statuses
    np.testing.assert_allclose(a.u, b.u, atol=tol, rtol=0)
    np.testing.assert_allclose(a.x, b.x, atol=1e3 * tol, rtol=0)
    return a, target


@pytest.fixture(scope="module")
def nlink3(tmp_path_factory):
    problem = make("nlink:3")
    ocp = reach(problem, knots=5, compiled=False)
    x0, _ = problem.sample(0)
    goal = ocp.goal(x0, position=_target(problem, 1))
    out = export(ocp, tmp_path_factory.mktemp("reach_nlink3"), x0=x0, goal=goal, steps=100)
    build(out.out_dir, target="all")
    return problem, ocp, out


def test_reach_c_step_equals_python_step_nlink3(nlink3):
    problem, ocp, out = nlink3
    loop, target = _same_closed_loop(problem, ocp, out.out_dir, seed=0, duration=1.2)
    fk = problem.kinematics.function(problem.end_effector)
    assert np.linalg.norm(np.asarray(fk(loop.x[-1][:problem.kinematics.n])[0]).ravel() - target) < 0.05


def test_generated_goal_is_the_whole_goal_vector(nlink3):
    """The header, example and README say the goal has ng entries; the example's closed loop runs in C."""
    problem, ocp, out = nlink3
    header = (out.out_dir / "mpc.h").read_text()
    assert f"#define MPC_NG {ocp.ng}" in header and "goal: MPC_NG doubles, x_goal then the task's targets" in header
    assert "const double goal[MPC_NG]" in (out.out_dir / "main.c").read_text()
    assert "`MPC_NG`" in (out.out_dir / "README.md").read_text()
    run = subprocess.run(["./example"], cwd=out.out_dir, capture_output=True, text=True, timeout=60)
    assert run.returncode == 0 and "failures 0" in run.stdout, run.stdout + run.stderr


def test_a_direct_call_needs_the_whole_goal(nlink3):
    problem, ocp, out = nlink3
    x0, _ = problem.sample(0)
    goal = ocp.goal(x0, position=_target(problem, 1))
    with ExportedMPC(ocp, out.out_dir) as c:
        with pytest.raises(ValueError, match=f"whole goal vector of {ocp.ng} entries"):
            c._solve(x0, goal[:ocp.nx].copy())
        direct = c._solve(x0, goal)  # as LinearMPC's C step calls it: the whole vector
        c.reset()
        assert direct.status == SUCCESS
        np.testing.assert_allclose(c.solve(x0, goal).u, direct.u, atol=1e-12)


def test_a_task_with_obstacles_is_refused(tmp_path):
    problem = make("nlink:3")
    ocp = reach(problem, ["0.3,0.2,0,0.05"], knots=5, compiled=False)
    with pytest.raises(ValueError, match="obstacles.*cannot be exported.*obstacle rows"):
        export(ocp, tmp_path / "out")
    assert not (tmp_path / "out").exists()


@pytest.mark.slow  # 10-30 s: the 7-DoF build; nlink:3 covers the same path in the default run
def test_reach_c_step_equals_python_step_panda(tmp_path):
    arm = Problem.from_urdf(PANDA, locked_joints=["panda_finger_joint1", "panda_finger_joint2"])
    ocp = reach(arm, knots=5, compiled=False)
    out = export(ocp, tmp_path / "panda")
    build(out.out_dir)
    # The arm's reach QP is ill-conditioned (cond P ≈ 5e7 at |z| ≈ 220 N·m): summation order alone moves u by
    # ~1e-8 here, and so does x0 + 1e-12 in the Python step itself (8e-9 along this loop): agreement to 5e-8.
    _same_closed_loop(arm, ocp, out.out_dir, seed=1, duration=1.0, tol=5e-8)

"""The exported C step with a task's cost terms (issue 29): the frame-position term of ocpkit.model.task.reach in C,
equal to LinearMPC's Python step (Gauss–Newton about the plan, ocpkit.qp.task_rows.TaskRows) along closed loops; with
obstacles, their linearized clearance rows built in C as the Python step builds them (issue 43)."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest

from ocpkit.status import INFEASIBLE, SOFT, SUCCESS
from ocpkit.export import ExportedMPC, build, export
from ocpkit.model.problem import Problem
from ocpkit.problems import make
from ocpkit.sim.simulate import simulate
from ocpkit.solvers.qp import LinearMPC
from ocpkit.model.task import reach
from ocpkit.problems.panda import urdf_path as panda_urdf

pytestmark = pytest.mark.skipif(shutil.which("cc") is None or shutil.which("make") is None, reason="needs cc and make")

PANDA = panda_urdf()


def _target(problem, seed):
    """The end effector's position at a sampled configuration: a reachable target."""
    _, q = problem.sample(seed)
    fk = problem.kinematics.function(problem.end_effector)
    return np.asarray(fk(q[: problem.kinematics.n])[0]).ravel()


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


def _built_reach(folder, obstacles=()):
    """nlink:3's reach OCP (5 knots) past ``obstacles``, exported with an example loop of 100 steps and built."""
    problem = make("nlink:3")
    ocp = reach(problem, list(obstacles), knots=5, compiled=False)
    x0, _ = problem.sample(0)
    goal = ocp.goal(x0, position=_target(problem, 1))
    out = export(ocp, folder, x0=x0, goal=goal, steps=100)
    build(out.out_dir, target="all")
    return problem, ocp, out


@pytest.fixture(scope="module")
def nlink3(tmp_path_factory):
    return _built_reach(tmp_path_factory.mktemp("reach_nlink3"))


def test_reach_c_step_equals_python_step_nlink3(nlink3):
    problem, ocp, out = nlink3
    loop, target = _same_closed_loop(problem, ocp, out.out_dir, seed=0, duration=1.2)
    fk = problem.kinematics.function(problem.end_effector)
    assert np.linalg.norm(np.asarray(fk(loop.x[-1][: problem.kinematics.n])[0]).ravel() - target) < 0.05


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
            c._solve(x0, goal[: ocp.nx].copy())
        direct = c._solve(x0, goal)  # as LinearMPC's C step calls it: the whole vector
        c.reset()
        assert direct.status == SUCCESS
        np.testing.assert_allclose(c.solve(x0, goal).u, direct.u, atol=1e-12)


# A ball beside the reach of tests/test_native.py's closed loop: the arm starts 1.2 cm from it (the margin is 1 cm).
BALL = "0.58,-0.02,0,0.06"


@pytest.fixture(scope="module")
def nlink3_ball(tmp_path_factory):
    return _built_reach(tmp_path_factory.mktemp("reach_ball"), [BALL])


def test_obstacles_are_exported_as_rows_and_said(nlink3_ball):
    """The QP has room for the bounded rows at every stage (16 robot spheres, one ball: 16 a stage over 50); the
    header and README say what the rows are and what an infeasible QP gives; the example's loop runs in C."""
    problem, ocp, out = nlink3_ball
    assert out.obstacle_rows == ocp.horizon * 16 and out.n_constraints == 0
    header = (out.out_dir / "mpc.h").read_text()
    assert "#define MPC_NA 800" in header and "#define MPC_NOS 16" in header and "mpc_set_plan" in header
    assert "Its obstacles (1 spheres, kept 0.01 m from 16 spheres" in header and "MPC_INFEASIBLE" in header
    assert "up to 800 obstacle rows" in (out.out_dir / "README.md").read_text()
    run = subprocess.run(["./example"], cwd=out.out_dir, capture_output=True, text=True, timeout=60)
    assert run.returncode == 0 and "failures 0" in run.stdout, run.stdout + run.stderr


def _recorded(obj, method: str) -> list:
    """The list the results of ``obj.method`` are appended to, call by call (the Python step's hard QP:
    ``_recorded(ctrl._transcriptions[0], "build")``)."""
    results, call = [], getattr(obj, method)

    def call_and_keep(*args, **kwargs):
        results.append(call(*args, **kwargs))
        return results[-1]

    setattr(obj, method, call_and_keep)
    return results


def test_c_steps_obstacle_rows_are_the_python_steps(nlink3_ball):
    """Past the ball the C step builds the Python step's QP, obstacle rows included (the C solver on the Python QP
    gives the C step's answer), and both answer alike: the same statuses ("soft" where the plan's nonlinear rollout
    breaks a clearance), knots to 1e-8."""
    problem, ocp, out = nlink3_ball
    x, _ = problem.sample(0)
    goal = ocp.goal(x, position=_target(problem, 1))
    py = LinearMPC(ocp, native=False)
    built = _recorded(py._transcriptions[0], "build")
    F, rows, statuses = ocp.discrete(), 0, set()
    with ExportedMPC(ocp, out.out_dir) as c:
        for _ in range(60):
            a, b = c.solve(x, goal), py.solve(x, goal)
            assert a.status == b.status, (a.raw_status, b.raw_status)
            np.testing.assert_allclose(a.knots, b.knots, atol=1e-8, rtol=0)
            qp = built[-1]
            if qp.C.shape[0] > len(qp.box):  # obstacle rows: the C solver on the Python QP answers as the C step
                rows += 1
                status, z = c.solve_qp(qp)
                assert status == SUCCESS
                np.testing.assert_allclose(z, a.knots.ravel(), atol=1e-8, rtol=0)
            statuses.add(a.status)
            x = np.asarray(F(x, a.u)).ravel()
    assert rows >= 30 and statuses == {SUCCESS, SOFT}, (rows, statuses)


def test_inside_the_margin_the_pure_export_says_infeasible(nlink3_ball):
    """A start under 5 mm from the ball (inside the 1 cm margin): no plan keeps the hard rows, the C step says
    "infeasible" and answers with the controller's fallback; LinearMPC's Python step answers with the QP whose
    obstacle rows are softened."""
    problem, ocp, out = nlink3_ball
    x = _inside_the_margin(problem, ocp)
    goal = ocp.goal(x, position=_target(problem, 1))
    with ExportedMPC(ocp, out.out_dir) as c:
        sol = c.solve(x, goal)
        assert sol.status == INFEASIBLE and sol.fallback and "DAQP infeasible" in sol.raw_status, sol.raw_status
    b = LinearMPC(ocp, native=False).solve(x, goal)
    assert not b.fallback and b.status == SOFT


def _inside_the_margin(problem, ocp):
    """A state whose arm is under 5 mm from the ball (inside the margin): sample(0) turned about the first joint."""
    from ocpkit.model.task import clearances

    x, _ = problem.sample(0)
    for q0 in np.linspace(x[0], x[0] - 0.3, 301):
        x[0] = q0
        gap = clearances(problem.kinematics, ocp.task.robot, ocp.task.obstacles, x[None, :3])[0]
        if gap < 0.005:
            return x
    raise AssertionError("no start inside the margin")


def test_set_plan_makes_the_c_step_linearize_about_it(nlink3_ball):
    """After a step answered elsewhere (LinearMPC's softened QP, a brake) the library follows the plan it is given:
    the C step then equals the Python step linearized about the same plan."""
    problem, ocp, out = nlink3_ball
    x, _ = problem.sample(0)
    goal = ocp.goal(x, position=_target(problem, 1))
    plan = np.clip(np.random.default_rng(3).normal(0.0, 2.0, (ocp.knots, ocp.nu)), ocp.u_min, ocp.u_max)
    py = LinearMPC(ocp, native=False)
    with ExportedMPC(ocp, out.out_dir) as c:
        assert c.sets_plan
        c.solve(x, goal)
        c.set_plan(plan)
        py.plan = plan
        a, b = c.solve(x, goal), py.solve(x, goal)
        assert a.status == b.status
        np.testing.assert_allclose(a.knots, b.knots, atol=1e-8, rtol=0)
        c.set_plan(None)  # no plan: the cold start's
        py.reset()
        np.testing.assert_allclose(c.solve(x, goal).knots, py.solve(x, goal).knots, atol=1e-8, rtol=0)
        with pytest.raises(ValueError, match="knots must have shape"):
            c.set_plan(plan[:2])


@pytest.mark.slow  # 10-30 s: the 7-DoF build; nlink:3 covers the same path in the default run
def test_reach_c_step_equals_python_step_panda(tmp_path):
    arm = Problem.from_urdf(PANDA, locked_joints=["panda_finger_joint1", "panda_finger_joint2"])
    ocp = reach(arm, knots=5, compiled=False)
    out = export(ocp, tmp_path / "panda")
    build(out.out_dir)
    # The arm's reach QP is ill-conditioned (cond P ≈ 5e7 at |z| ≈ 220 N·m): summation order alone moves u by
    # ~1e-8 here, and so does x0 + 1e-12 in the Python step itself (8e-9 along this loop): agreement to 5e-8.
    _same_closed_loop(arm, ocp, out.out_dir, seed=1, duration=1.0, tol=5e-8)


def test_obstacle_rows_are_bounded_as_the_python_step_bounds_them(tmp_path):
    """Eight balls along both sides of the arm, 1.2 cm from it at the start: each robot sphere has 2 to 4 obstacles
    within the activation distance, so each keeps its 2 closest and a stage its 24 closest pairs (TaskRows.select).
    The C step keeps the same rows: its steps equal the Python step's."""
    from ocpkit.model.kinematics import sphere_centers, spheres_along_links
    from ocpkit.model.task import Sphere

    problem = make("nlink:3")
    x, _ = problem.sample(0)
    robot = spheres_along_links(problem.kinematics, problem.link_radius)
    C = np.asarray(sphere_centers(problem.kinematics, robot)(x[:3]))[:2]
    balls = []
    for i in (2, 6, 10, 14):
        along = (C[:, i + 1] - C[:, i - 1]) / np.linalg.norm(C[:, i + 1] - C[:, i - 1])
        for side in (1, -1):
            centre = C[:, i] + side * 0.12 * np.array([-along[1], along[0]])
            balls.append(Sphere((*centre, 0.0), 0.03))
    ocp = reach(problem, balls, knots=5, compiled=False)
    goal = ocp.goal(x, position=_target(problem, 1))
    out = export(ocp, tmp_path / "balls")
    build(out.out_dir)
    py = LinearMPC(ocp, native=False)
    kept = _recorded(py._transcriptions[0].task, "select")
    F = ocp.discrete()
    with ExportedMPC(ocp, out.out_dir) as c:
        for _ in range(10):
            a, b = c.solve(x, goal), py.solve(x, goal)
            assert a.status == b.status and not a.fallback, (a.raw_status, b.raw_status)
            np.testing.assert_allclose(a.knots, b.knots, atol=1e-8, rtol=0)
            x = np.asarray(F(x, a.u)).ravel()
    assert max(np.bincount(stage).max() for stage, _, _ in kept) == 24

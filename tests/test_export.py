"""The exported C step (built with cc here) against LinearMPC in Python, its fallback, and a clean build."""
from __future__ import annotations

import os
import shutil
import subprocess

import numpy as np
import pytest

from ocpkit.controller import SUCCESS
from ocpkit.export import ExportedMPC, build, export
from ocpkit.problems import make
from ocpkit.solvers.qp import LinearMPC

pytestmark = pytest.mark.skipif(shutil.which("cc") is None or shutil.which("make") is None,
                                reason="needs cc and make")


def _problem(name):
    try:
        return make(name)
    except ValueError:
        pytest.skip(f"problem {name!r} is not registered")


def _compare(problem, ocp, exported, linearization, seeds, steps, tol=1e-6):
    """Closed loops on the discrete model: the C step's u, knots and status equal LinearMPC's every step."""
    F = ocp.discrete()
    for seed in seeds:
        x, goal = problem.sample(seed)
        ref = LinearMPC(ocp, form="condensed", eps=1e-12 if problem.name.startswith("pendulum") else 1e-10,
                        linearization=linearization)
        exported.reset()
        for k in range(steps):
            a, b = ref.solve(x, goal), exported.solve(x, goal)
            assert a.status == b.status == SUCCESS, (seed, k, a.raw_status, b.raw_status)
            np.testing.assert_allclose(b.u, a.u, atol=tol, rtol=0, err_msg=f"seed {seed} step {k}")
            np.testing.assert_allclose(b.knots, a.knots, atol=tol, rtol=0)
            x = np.asarray(F(x, a.u)).ravel()


@pytest.fixture(scope="module")
def bounded_pendulum(tmp_path_factory):
    """Pendulum with |q̇| ≤ 6 (state-bound rows, active in these loops), linearized about the plan, solved by DAQP."""
    problem = make("pendulum")
    ocp = problem.ocp(knots=5, horizon=50, x_min=[-np.inf, -6.0], x_max=[np.inf, 6.0])
    out = export(ocp, tmp_path_factory.mktemp("pend_daqp"), qp="daqp", linearization="plan")
    build(out.out_dir)
    return problem, ocp, ExportedMPC(ocp, out.out_dir)


def test_pendulum_matches_linear_mpc_with_state_bounds(bounded_pendulum):
    problem, ocp, c = bounded_pendulum
    _compare(problem, ocp, c, "plan", seeds=range(4), steps=25)


def test_generated_model_is_the_discrete_model(bounded_pendulum):
    _, ocp, c = bounded_pendulum
    rng = np.random.default_rng(3)
    for _ in range(5):
        x, u = rng.normal(size=2), rng.normal(size=1)
        np.testing.assert_allclose(c.model_step(x, u), np.asarray(ocp.discrete()(x, u)).ravel(), atol=1e-12)


def test_failure_returns_the_controller_fallback(bounded_pendulum):
    problem, ocp, c = bounded_pendulum
    c.reset()
    goal = np.array([1.0, 0.0])
    first = c.solve([0.0, 0.0], goal)
    assert first.ok
    # q̇ = 8 cannot be brought under 6 in one step with |τ| ≤ 5: the state rows are infeasible.
    expected = c.fallback("x", "x")
    sol = c.solve([0.0, 9.0], goal)
    assert not sol.ok and sol.fallback and sol.status in ("infeasible", "limited", "exception")
    np.testing.assert_allclose(sol.knots, expected.knots, atol=1e-12)
    np.testing.assert_allclose(sol.u, expected.u, atol=1e-12)
    np.testing.assert_array_equal(c.plan, sol.knots)
    assert c.solve([0.0, 0.0], goal).ok  # recovers, starting cold


@pytest.mark.parametrize("name", ["nlink:3", pytest.param("nlink:7", marks=pytest.mark.slow)])
def test_nlink_matches_linear_mpc(name, tmp_path):
    problem = _problem(name)
    ocp = problem.ocp(knots=5, horizon=50)
    out = export(ocp, tmp_path, qp="daqp", linearization="goal")
    build(out.out_dir)
    _compare(problem, ocp, ExportedMPC(ocp, out.out_dir), "goal", seeds=range(3), steps=10)


def test_qrqp_folder_builds_from_a_clean_copy(tmp_path):
    """The self-contained (qrqp) folder builds with only its Makefile and cc, and its example converges."""
    problem = make("pendulum")
    ocp = problem.ocp(knots=5, horizon=50)
    x0, goal = problem.sample(1)
    out = export(ocp, tmp_path / "gen", qp="qrqp", x0=x0, goal=goal, steps=300)
    text = "".join(p.read_text() for p in out.out_dir.iterdir())
    assert "casadi/include" not in text and "site-packages" not in text
    copy = shutil.copytree(out.out_dir, tmp_path / "copy")
    env = {"PATH": os.environ["PATH"]}  # no Python or CasADi environment
    subprocess.run(["make"], cwd=copy, env=env, check=True, capture_output=True)
    run = subprocess.run(["./example"], cwd=copy, env=env, check=True, capture_output=True, text=True)
    assert "failures 0" in run.stdout
    final = np.array(run.stdout.split("x_final")[1].split("\n")[0].split(), dtype=float)
    assert abs(final[0] - goal[0]) < 0.05, run.stdout
    # and the same library, loaded back, matches LinearMPC
    _compare(problem, ocp, ExportedMPC(ocp, copy), "goal", seeds=[1, 2], steps=10)


def test_unsupported_combinations_are_refused(tmp_path):
    ocp = make("pendulum").ocp(knots=3, horizon=10)
    with pytest.raises(ValueError, match="hpipm"):
        export(ocp, tmp_path, qp="hpipm")
    with pytest.raises(ValueError, match="sparse"):
        export(ocp, tmp_path, form="sparse")
    with pytest.raises(ValueError, match="qp must be"):
        export(ocp, tmp_path, qp="proxqp")
    with pytest.raises(ValueError, match="linearization"):
        export(ocp, tmp_path, linearization="x")
    with pytest.raises(ValueError, match="name"):
        export(ocp, tmp_path, name="not-an-identifier")
    with pytest.raises(ValueError, match="out_dir"):
        ExportedMPC(ocp, tmp_path / "missing")

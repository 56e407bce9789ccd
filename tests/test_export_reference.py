"""The exported C step's goal window and moving obstacles (issue 46, items 1, 2 and 5): ``<name>_step_window`` takes the
goal at every stage and the obstacles at every stage at run time. Equal rows give the held step bit for bit; a moving
window gives the condensed QP of the per-stage goals (a dense formulation here, solved by the library's own DAQP);
moved obstacles change the answer as the Python step's clearances say, with the library built once; ``ocpkit export
--reference-window`` builds an example that follows a reference from a CSV file."""

from __future__ import annotations

import dataclasses
import shutil
import subprocess

import numpy as np
import pytest

from ocpkit.export import ExportedMPC, build, export
from ocpkit.model.task import reach
from ocpkit.problems import make
from ocpkit.qp.transcription import CondensedQP
from ocpkit.solvers.qp import LinearMPC
from ocpkit.status import SUCCESS

pytestmark = pytest.mark.skipif(shutil.which("cc") is None or shutil.which("make") is None, reason="needs cc and make")

BALL = "0.58,-0.02,0,0.06"  # beside nlink:3's reach (tests/test_export_task.py): the arm starts 1.2 cm from it


def _built(folder, ocp, **options):
    out = export(ocp, folder, **options)
    build(out.out_dir)
    return out.out_dir


@pytest.fixture(scope="module")
def joint(tmp_path_factory):
    """nlink:3 with an input goal that depends on the goal (u_g = K x_goal): every term moves with the window."""
    problem = make("nlink:3")
    K = 0.3 * np.random.default_rng(1).normal(size=(3, 6))
    ocp = problem.ocp(knots=5, u_goal_gain=K)
    return problem, ocp, _built(tmp_path_factory.mktemp("window_joint"), ocp)


@pytest.fixture(scope="module")
def ball(tmp_path_factory):
    """nlink:3's reach past a ball (task terms with targets, obstacle rows)."""
    problem = make("nlink:3")
    ocp = reach(problem, [BALL], knots=5, compiled=False)
    return problem, ocp, _built(tmp_path_factory.mktemp("window_ball"), ocp)


def _target(problem, seed):
    _, q = problem.sample(seed)
    fk = problem.kinematics.function(problem.end_effector)
    return np.asarray(fk(q[: problem.kinematics.n])[0]).ravel()


def _ramp(a, b, T):
    """Rows k = 0 … T moving from a to b."""
    s = np.linspace(0.0, 1.0, T + 1)[:, None]
    return (1 - s) * a + s * b


def _steps(c, x0, goal, window, steps=8, obstacles=None):
    """(u, knots) of each step of a closed loop on the library's model, by _solve (window None: the held step)."""
    c.reset()
    x, out = np.array(x0, dtype=float), []
    for _ in range(steps):
        sol = c._solve(x, goal, window=window, obstacles=obstacles)
        assert sol.status == SUCCESS, sol.raw_status
        out.append((sol.u.copy(), sol.knots.copy()))
        x = c.model_step(x, sol.u)
    return out


def _same_bits(a, b):
    for (ua, ka), (ub, kb) in zip(a, b, strict=True):
        assert ua.tobytes() == ub.tobytes() and ka.tobytes() == kb.tobytes()


@pytest.mark.parametrize("case", ["joint", "ball", "rti"])
def test_equal_rows_are_the_held_step_bit_for_bit(case, joint, ball, tmp_path):
    if case == "rti":
        problem, ocp = joint[0], joint[1]
        folder = _built(tmp_path / "rti", ocp, linearization="trajectory", iterations=2)
    else:
        problem, ocp, folder = joint if case == "joint" else ball
    x0, goal = problem.sample(0)
    if case == "ball":
        goal = ocp.goal(x0, position=_target(problem, 1))
    window = np.tile(goal, (ocp.horizon + 1, 1))
    obstacles = ocp.obstacle_window() if case == "ball" else None  # the declared ones, given at run time
    with ExportedMPC(ocp, folder) as c:
        held = _steps(c, x0, goal, None)
        _same_bits(_steps(c, x0, goal, window), held)
        if obstacles is not None:
            _same_bits(_steps(c, x0, goal, window, obstacles=obstacles), held)


def _dense_qp(ocp, x, window, qp):
    """``qp`` (CondensedQP's, towards row 0) with the per-stage goals' cost: P = SᵀQ̄S + φᵀφ⊗R, q = SᵀQ̄(v − x̄_goal) −
    Σ_k Φ_kᵀ R u_g(x_goal,k), S and v of the affine model about (x, u_g(row 0)), built densely here."""
    n, m, T = ocp.nx, ocp.nu, ocp.horizon
    tr = CondensedQP(ocp)
    Ad, Bd, wd = (np.asarray(a, dtype=float) for a in ocp.affine()(x, ocp.input_goal(window[0, :n])))
    S, v = tr.prediction(Ad, Bd, wd.ravel(), x)
    Qbar = np.zeros((T * n, T * n))
    for k in range(T):
        Qbar[k * n : (k + 1) * n, k * n : (k + 1) * n] = ocp.Q if k < T - 1 else ocp.Q_terminal
    phi = ocp.parameterization.basis
    Phi = np.kron(phi, np.eye(m))  # (T·m, p·m): u = Φ z
    ug = np.concatenate([ocp.input_goal(g[:n]) for g in window[:T]])
    Rbar = np.kron(np.eye(T), ocp.R)
    P = S.T @ Qbar @ S + Phi.T @ Rbar @ Phi
    q = S.T @ Qbar @ (v - window[1:, :n].ravel()) - Phi.T @ Rbar @ ug
    np.testing.assert_allclose(P, qp.P, rtol=1e-10, atol=1e-10 * np.abs(P).max())  # the same Hessian as condensed
    return dataclasses.replace(qp, P=0.5 * (P + P.T), q=q)


def test_a_moving_window_solves_the_qp_of_the_per_stage_goals(joint):
    problem, ocp, folder = joint
    n, T = ocp.nx, ocp.horizon
    x0, goal = problem.sample(0)
    _, other = problem.sample(5)
    window = _ramp(goal, other, T)
    with ExportedMPC(ocp, folder) as c:
        for x in (x0, 0.5 * (x0 + goal)):
            c.reset()
            sol = c._solve(x, window[0], window=window)
            assert sol.status == SUCCESS, sol.raw_status
            Ad, Bd, wd = (np.asarray(a, dtype=float) for a in ocp.affine()(x, ocp.input_goal(window[0, :n])))
            held = CondensedQP(ocp).build(Ad, Bd, wd.ravel(), x, window[0])
            status, z = c.solve_qp(_dense_qp(ocp, x, window, held))
            assert status == SUCCESS
            np.testing.assert_allclose(sol.knots.ravel(), z, atol=1e-9, rtol=0)
            np.testing.assert_allclose(sol.u, ocp.parameterization.basis[0] @ z.reshape(ocp.knots, ocp.nu), atol=1e-9)
            c.reset()
            assert np.abs(c._solve(x, window[0]).u - sol.u).max() > 1e-3  # the window matters
        # through solve(): the window Controller.solve validated (its answer clipped to the input bounds)
        c.reset()
        direct = c._solve(x0, window[0], window=window).u
        c.reset()
        np.testing.assert_array_equal(c.solve(x0, window).u, np.clip(direct, ocp.u_min, ocp.u_max))


def test_moved_obstacles_change_the_answer_as_the_python_step_says(ball, tmp_path):
    """The ball moved at run time (no rebuild): held at a new place, the C step equals LinearMPC's Python step of an
    OCP declaring the ball there; moved far, the Python step without obstacles; moving over the horizon, the plan's
    predicted clearances to the ball at each stage are kept (the Python clearances of the same window)."""
    problem, ocp, folder = ball
    library = folder / "libmpc.so"
    built = library.stat().st_mtime_ns
    x0, _ = problem.sample(0)
    goal = ocp.goal(x0, position=_target(problem, 1))
    declared = ocp.obstacle_window()
    place = np.array([0.6, 0.05, 0.0, 0.06])  # 1.5 cm from the arm at the start, the declared ball 0.2 cm
    cases = {"moved": place, "far": np.array([10.0, 10.0, 0.0, 0.06])}
    with ExportedMPC(ocp, folder) as c:
        first = c.solve(x0, goal).u
        for what, ball_there in cases.items():
            py_ocp = reach(
                problem, [",".join(map(str, ball_there))] if what == "moved" else [], knots=5, compiled=False
            )
            py = LinearMPC(py_ocp, native=False)
            c.reset()
            x = x0.copy()
            for _ in range(5):
                a, b = py.solve(x, goal), c.solve(x, goal, obstacles=ball_there[None])
                assert a.status == b.status == SUCCESS, (what, a.raw_status, b.raw_status)
                np.testing.assert_allclose(b.u, a.u, atol=1e-8, rtol=0, err_msg=what)
                x = c.model_step(x, b.u)
            c.reset()
            assert np.abs(c.solve(x0, goal, obstacles=ball_there[None]).u - first).max() > 1e-6, what
        # a ball crossing the path over the horizon: each stage's clearance of the plan's prediction against its row
        c.reset()
        T = ocp.horizon
        path = np.repeat(_ramp(declared[0, 0], place, T)[:, None, :], 1, axis=1)
        sol = c.solve(x0, goal, obstacles=path)
        assert sol.status == SUCCESS, sol.raw_status
        xs = c.rollout(x0, ocp.parameterization.inputs(sol.knots))
        tf = ocp.task_functions
        centres = np.stack([np.asarray(tf.spheres(xk)[0]) for xk in xs[1:]], axis=1)  # (3, T, spheres)
        d = tf.pair_clearances(centres, path[1:])
        assert d.min() > -1e-3, d.min()
        assert not np.allclose(sol.u, c.solve(x0, goal).u)
    assert library.stat().st_mtime_ns == built  # no rebuild


def test_cli_export_with_a_reference_window_builds_and_follows_it(tmp_path, monkeypatch, capsys):
    """``ocpkit export nlink:3 --reference-window ref.csv``: the example reads the reference rows from reference.csv
    and steps with mpc_step_window along it."""
    from ocpkit.cli import main

    problem = make("nlink:3")
    ocp = problem.ocp(knots=5)
    t = np.arange(0.0, 3.0, 0.05)
    goals = np.zeros((t.size, ocp.ng))
    goals[:, 0] = 0.4 * np.sin(t)
    monkeypatch.chdir(tmp_path)
    header = ",".join(["t", *ocp.goal_names()])
    np.savetxt("ref.csv", np.column_stack([t, goals]), delimiter=",", header=header, comments="")
    assert main(["export", "nlink:3", "--knots", "5", "--out", "out", "--reference-window", "ref.csv"]) == 0
    said = capsys.readouterr().out
    assert "agree" in said and "along ref.csv" in said, said
    out = tmp_path / "out"
    rows = np.genfromtxt(out / "reference.csv", delimiter=",", skip_header=1)
    assert rows.shape == (100 + ocp.horizon + 1, ocp.ng)
    np.testing.assert_allclose(rows[:, 0], 0.4 * np.sin(np.minimum(0.01 * np.arange(rows.shape[0]), t[-1])), atol=2e-4)
    assert "mpc_step_window(&mem, x, ref + k * MPC_NX, u, &status)" in (out / "main.c").read_text()
    example = subprocess.run(["make", "-s", "run"], cwd=out, capture_output=True, text=True, timeout=300)
    assert example.returncode == 0 and "failures 0" in example.stdout, example.stdout + example.stderr
    assert "following reference.csv (151 rows)" in example.stdout, example.stdout

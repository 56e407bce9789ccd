"""The exported C step (built with cc here) against LinearMPC in Python, its fallback, and a clean build."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from ocpkit.status import SUCCESS
from ocpkit.export import ExportedMPC, build, export
from ocpkit.model.parameterization import Parameterization
from ocpkit.problems import make
from ocpkit.solvers.qp import LinearMPC

pytestmark = pytest.mark.skipif(shutil.which("cc") is None or shutil.which("make") is None, reason="needs cc and make")


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
        ref = LinearMPC(
            ocp,
            form="condensed",
            eps=1e-12 if problem.name.startswith("pendulum") else 1e-10,
            linearization=linearization,
            native=False,
        )  # the Python step: an independent path
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
    """A refused C step answers with the safe fallback: from q̇ = 9, past the bound 6, the shifted plan's prediction
    breaks the bound, so the controller brakes (ocpkit.safety.Brake) instead of replaying it."""
    from ocpkit.safety import Brake

    problem, ocp, c = bounded_pendulum
    c.reset()
    goal = np.array([1.0, 0.0])
    first = c.solve([0.0, 0.0], goal)
    assert first.ok
    # q̇ = 8 cannot be brought under 6 in one step with |τ| ≤ 5: the state rows are infeasible.
    sol = c.solve([0.0, 9.0], goal)
    assert not sol.ok and sol.fallback and sol.status in ("infeasible", "limited", "exception")
    assert sol.path == "fallback (brake)", sol.path
    brake = Brake(ocp)(np.array([0.0, 9.0]), np.clip(ocp.input_goal(goal), ocp.u_min, ocp.u_max))
    np.testing.assert_allclose(sol.u, brake, atol=1e-12)
    assert sol.u[0] == ocp.u_min[0]  # full braking torque against q̇ > 0
    np.testing.assert_array_equal(c.plan, sol.knots)
    assert c.solve([0.0, 0.0], goal).ok  # recovers, starting cold


def test_a_refused_step_passed_on_says_fallback(bounded_pendulum):
    """The library's own fallback, passed on to a caller of ``_solve`` (LinearMPC's C step), says so in ``path``."""
    _, _, c = bounded_pendulum
    c.reset()
    sol = c._solve(np.array([0.0, 9.0]), np.array([1.0, 0.0]))
    assert not sol.ok and sol.fallback and sol.path.startswith("fallback"), (sol.status, sol.path)
    c.reset()


def test_a_library_exported_for_another_ocp_is_refused_naming_what_differs(bounded_pendulum):
    """The library carries its OCP's digest: other weights, another model or knot count of the same sizes are
    refused on load in one line naming the field, not solved with the library's data."""
    problem, ocp, c = bounded_pendulum
    bounds = {"x_min": [-np.inf, -6.0], "x_max": [np.inf, 6.0]}
    same = problem.ocp(knots=5, horizon=50, **bounds)
    ExportedMPC(same, c.out_dir).close()  # an equal OCP built anew loads
    cases = {
        "Q differs": problem.ocp(knots=5, horizon=50, Q=np.diag([100.0, 0.1]), **bounds),
        "model differs": problem.ocp(knots=5, horizon=50, error=1.2, **bounds),
        "x_max differs": problem.ocp(knots=5, horizon=50, x_min=[-np.inf, -6.0], x_max=[np.inf, 7.0]),
        "knots 5 vs 4": problem.ocp(knots=4, horizon=50, **bounds),
    }
    for what, other in cases.items():
        with pytest.raises(ValueError, match=f"exported for another OCP: {what}") as info:
            ExportedMPC(other, c.out_dir)
        assert "\n" not in str(info.value) and str(c.out_dir) in str(info.value), str(info.value)


def test_a_library_others_can_write_is_not_loaded(bounded_pendulum, tmp_path):
    """An exported library in a folder others can write, or itself writable by others, is refused before dlopen
    (a planted library's constructor would run as whoever loads it)."""
    from ocpkit.codegen.cache import UnsafeCacheError

    problem, ocp, c = bounded_pendulum
    copy = shutil.copytree(c.out_dir, tmp_path / "copy")
    try:
        for path, mode in ((copy, 0o777), (copy / "libmpc.so", 0o666)):
            original = path.stat().st_mode & 0o777
            path.chmod(mode)
            with pytest.raises(UnsafeCacheError, match="writable by other users") as info:
                ExportedMPC(ocp, copy)
            assert "\n" not in str(info.value)
            path.chmod(original)
        ExportedMPC(ocp, copy).close()
    finally:
        copy.chmod(0o700)


def test_the_digest_names_task_fields_and_a_casadi_upgrade():
    """What the digest tells apart without a build: a task's obstacles and margin; a model hash that differs under
    another CasADi version says so; a library without a digest (an older ocpkit's) is refused."""
    import types

    from ocpkit.export.digest import differences, ocp_entries
    from ocpkit.export.library import _check_digest
    from ocpkit.model.task import Sphere, reach

    problem = make("nlink:3")
    ball = Sphere((0.5, 0.1, 0.0), 0.04)
    stored = "; ".join(ocp_entries(reach(problem, [ball], knots=3, horizon=20)))
    assert differences(stored, reach(problem, [ball], knots=3, horizon=20)) == ""
    moved = reach(problem, [Sphere((0.5, 0.2, 0.0), 0.04)], knots=3, horizon=20)
    assert differences(stored, moved) == "obstacles differs"
    assert differences(stored, reach(problem, [ball], margin=0.02, knots=3, horizon=20)) == "margin 0.01 vs 0.02"
    assert "targets 3 vs 0, task_terms differs" in differences(stored, problem.ocp(knots=3, horizon=20))
    old = "; ".join(e if not e.startswith(("casadi", "model")) else e.split()[0] + " 0.0.1" for e in stored.split("; "))
    assert (
        differences(old, reach(problem, [ball], knots=3, horizon=20))
        == f"model differs (exported with CasADi 0.0.1, running {ca.__version__}: its serialization may differ too)"
    )
    with pytest.raises(ValueError, match="has no mpc_ocp_digest \\(exported by an older ocpkit\\)"):
        _check_digest(types.SimpleNamespace(), "mpc", Path("old/libmpc.so"), moved)


def test_status_and_reason_strings_name_every_code(bounded_pendulum, tmp_path):
    """``mpc_status_string`` and ``mpc_reason_string`` (tests/c/status_names.c calls them for -1 … 5 and -1 …
    MPC_NREASONS) name the statuses and the reasons as ocpkit does: reason 0 none, then REASONS in order."""
    from ocpkit.status import REASONS, SOFT, STATUSES, Reason

    out = bounded_pendulum[2].out_dir
    program = tmp_path / "status_names"
    subprocess.run(
        [
            "cc",
            "-std=c99",
            "-Wall",
            "-Werror",
            "-I",
            str(out),
            "-o",
            str(program),
            str(Path(__file__).parent / "c" / "status_names.c"),
            "-L",
            str(out),
            "-lmpc",
            f"-Wl,-rpath,{out.resolve()}",
        ],
        check=True,
        capture_output=True,
        text=True,
    )
    lines = subprocess.run([str(program)], check=True, capture_output=True, text=True).stdout.splitlines()
    c_statuses = STATUSES[: STATUSES.index(SOFT)]  # the C step's codes 0 … 4
    statuses, reasons = lines[: len(c_statuses) + 2], lines[len(c_statuses) + 2 :]
    assert statuses == ["-1 unknown"] + [f"{i} {s}" for i, s in enumerate(c_statuses)] + [f"{len(c_statuses)} unknown"]
    words = ["none"] + list(REASONS)
    assert reasons == (
        ["reason -1 unknown"]
        + [f"reason {i} {w}" for i, w in enumerate(words)]
        + [
            f"reason {len(words)} unknown",
            f"reason MPC_REASON_ITERATION_LIMIT {1 + REASONS.index(Reason.ITERATION_LIMIT)}",
        ]
    )


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


# --- robot scale: size, several instances, quiet OSQP, variants of the condensing -------------------------


def test_generated_c_size_does_not_grow_with_the_horizon(tmp_path):
    """The condensing is loops over the basis' pieces: T = 400 writes about the C of T = 50."""
    ocp50 = make("nlink:3").ocp(knots=5, horizon=50)
    ocp400 = make("nlink:3").ocp(knots=5, horizon=400)
    small = export(ocp50, tmp_path / "t50").c_bytes
    large = export(ocp400, tmp_path / "t400").c_bytes
    assert large < 1.05 * small, (small, large)


def test_nlink7_generated_c_is_small(tmp_path):
    """The per-stage model is generated once (f and its Jacobians), not the unrolled discrete Jacobian."""
    info = export(_problem("nlink:7").ocp(knots=5, horizon=100), tmp_path / "n7")
    assert info.c_bytes < 400_000, info.c_bytes  # the unrolled SX step was 5.2 MB


@pytest.mark.parametrize("variant", ["zoh", "identity", "bspline", "custom", "full_q_and_goal_gain"])
def test_condensing_variants_match_linear_mpc(variant, tmp_path):
    """Other bases (other pieces: the cubic B-spline's and a dense basis' are two steps long), non-diagonal Q and
    Q_T and an input goal linear in the goal (u_goal + K goal)."""
    problem = make("pendulum")
    if variant in ("zoh", "bspline"):
        ocp = problem.ocp(knots=4 if variant == "zoh" else 6, horizon=30, parameterization=variant)
    elif variant == "custom":
        ocp = problem.ocp(parameterization=Parameterization.custom(_bumps(30, 5)))
    elif variant == "identity":
        ocp = problem.ocp(knots=None, horizon=12)
    else:
        ocp = problem.ocp(
            knots=5,
            horizon=40,
            Q=[[10.0, 1.0], [1.0, 1.0]],
            Q_terminal=[[30.0, 2.0], [2.0, 3.0]],
            u_goal=[0.2],
            u_goal_gain=[[0.5, 0.0]],
        )
    info = export(ocp, tmp_path / variant, linearization="plan")
    build(info.out_dir)
    with ExportedMPC(ocp, info.out_dir) as c:
        _compare(problem, ocp, c, "plan", seeds=[0, 1], steps=12)


def _bumps(T, p):
    """A dense user basis: normalized Gaussian bumps, every row a convex combination of all p knots."""
    B = np.exp(-0.5 * ((np.linspace(0, 1, T)[:, None] - np.linspace(0, 1, p)[None]) * p) ** 2)
    return B / B.sum(axis=1, keepdims=True)


@pytest.mark.parametrize("kind", ["bspline", "custom"])
def test_real_time_iteration_with_other_bases_matches_linear_mpc(kind, tmp_path):
    """The C step's stage-by-stage (trajectory) build reads the whole basis (PHI_ALL): nlink:3 with a B-spline and
    a dense basis against LinearMPC(linearization="trajectory") in Python."""
    problem = make("nlink:3")
    par = Parameterization.bspline(30, 5) if kind == "bspline" else Parameterization.custom(_bumps(30, 5))
    ocp = problem.ocp(parameterization=par)
    info = export(ocp, tmp_path / kind, linearization="trajectory")
    build(info.out_dir)
    with ExportedMPC(ocp, info.out_dir) as c:
        _compare(problem, ocp, c, "trajectory", seeds=[0], steps=8)


def test_two_instances_step_alternately(tmp_path):
    """Two instances of one library, stepping in turn from different states, each equal to its own LinearMPC."""
    problem = (
        make("nlink:2") if "nlink" in __import__("ocpkit.problems", fromlist=["names"]).names() else make("pendulum")
    )
    ocp = problem.ocp(knots=5, horizon=40)
    info = export(ocp, tmp_path / "two", linearization="plan")
    build(info.out_dir)
    F = ocp.discrete()
    with ExportedMPC(ocp, info.out_dir) as c1, ExportedMPC(ocp, info.out_dir) as c2:
        loops = []
        for seed, c in ((0, c1), (3, c2)):
            x, goal = problem.sample(seed)
            loops.append([c, LinearMPC(ocp, form="condensed", eps=1e-10, linearization="plan"), x, goal])
        assert not np.allclose(loops[0][2], loops[1][2])
        for k in range(10):
            for loop in loops:
                c, ref, x, goal = loop
                a, b = ref.solve(x, goal), c.solve(x, goal)
                assert a.ok and b.ok, (k, b.raw_status)
                np.testing.assert_allclose(b.u, a.u, atol=1e-6, rtol=0)
                np.testing.assert_allclose(b.knots, a.knots, atol=1e-6, rtol=0)
                loop[2] = np.asarray(F(x, a.u)).ravel()
    assert c1.closed and c2.closed
    with pytest.raises(RuntimeError, match="closed"):
        c1.solve(*problem.sample(0))
    c1.close()  # twice is fine


def test_instances_beyond_the_slots_fail_cleanly_and_slots_are_reused(tmp_path):
    ocp = make("pendulum").ocp(knots=3, horizon=20)
    info = export(ocp, tmp_path / "slots", qp="osqp")
    (info.out_dir / "Makefile").write_text(
        (info.out_dir / "Makefile").read_text().replace("MAX_INSTANCES ?= 16", "MAX_INSTANCES ?= 2")
    )
    build(info.out_dir)
    a, b = ExportedMPC(ocp, info.out_dir), ExportedMPC(ocp, info.out_dir)
    with pytest.raises(RuntimeError, match="memory slots"):
        ExportedMPC(ocp, info.out_dir)
    a.close()
    with ExportedMPC(ocp, info.out_dir) as c:  # a's slot, reused
        assert c.solve([0.5, 0.0], [0.0, 0.0]).ok
    assert b.solve([0.5, 0.0], [0.0, 0.0]).ok
    b.close()


def test_osqp_export_is_quiet_and_matches(tmp_path, capfd):
    problem = make("pendulum")
    ocp = problem.ocp(knots=5, horizon=40)
    info = export(ocp, tmp_path / "osqp", qp="osqp")
    build(info.out_dir)
    capfd.readouterr()
    with ExportedMPC(ocp, info.out_dir) as c:
        _compare(problem, ocp, c, "goal", seeds=[0], steps=10, tol=1e-5)
    out = capfd.readouterr()
    assert out.out == "" and out.err == "", out


# --- the output folder and the tools (issue 19) ------------------------------------------------------------


def test_out_dir_must_be_empty_unless_force(tmp_path):
    ocp = make("pendulum").ocp(knots=3, horizon=10)
    user = tmp_path / "mine"
    user.mkdir()
    (user / "README.md").write_text("my notes")
    with pytest.raises(ValueError, match="not empty.*README.md.*force"):
        export(ocp, user)
    assert (user / "README.md").read_text() == "my notes"
    export(ocp, user, force=True)
    assert (user / "Makefile").is_file()
    afile = tmp_path / "afile"
    afile.write_text("x")
    with pytest.raises(ValueError, match="is a file"):
        export(ocp, afile, force=True)


def test_cli_export_refuses_a_users_folder_and_a_file(tmp_path, monkeypatch, capsys):
    from ocpkit.cli import main

    monkeypatch.chdir(tmp_path)
    Path("mine").mkdir()
    Path("mine/main.c").write_text("int main(void) { return 0; }\n")
    assert main(["export", "pendulum", "--knots", "3", "--horizon", "10", "--out", "mine"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not empty" in err and "--force" in err
    assert Path("mine/main.c").read_text() == "int main(void) { return 0; }\n"
    Path("f.txt").write_text("x")
    assert main(["export", "pendulum", "--knots", "3", "--horizon", "10", "--out", "f.txt"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "is a file" in err


# --- links in the output folder (issue 28) ------------------------------------------------------------------


@pytest.mark.parametrize("force", [False, True])
def test_a_symlink_in_out_dir_is_refused_and_its_target_untouched(force, tmp_path):
    ocp = make("pendulum").ocp(knots=3, horizon=10)
    victim = tmp_path / "victim.h"
    victim.write_text("/* the user's own header */\n")
    out = tmp_path / "gen"
    out.mkdir()
    (out / "mpc.h").symlink_to(victim)
    with pytest.raises(ValueError, match=r"symbolic link.*mpc\.h -> .*victim\.h"):
        export(ocp, out, force=force)
    assert victim.read_text() == "/* the user's own header */\n"
    assert (out / "mpc.h").is_symlink() and sorted(p.name for p in out.iterdir()) == ["mpc.h"]


def test_cli_export_force_refuses_a_symlink_in_one_line(tmp_path, monkeypatch, capsys):
    from ocpkit.cli import main

    monkeypatch.chdir(tmp_path)
    Path("victim.c").write_text("int x;\n")
    Path("gen").mkdir()
    Path("gen/mpc_casadi.c").symlink_to(tmp_path / "victim.c")
    assert main(["export", "pendulum", "--knots", "3", "--horizon", "10", "--out", "gen", "--force"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "symbolic link" in err and "mpc_casadi.c" in err, err
    assert Path("victim.c").read_text() == "int x;\n"


def test_out_dir_that_is_a_symlink_is_refused_naming_its_target(tmp_path):
    ocp = make("pendulum").ocp(knots=3, horizon=10)
    real = tmp_path / "real"
    real.mkdir()
    (tmp_path / "link").symlink_to(real)
    with pytest.raises(ValueError, match=f"symbolic link to {re.escape(str(real))}.*--out {re.escape(str(real))}"):
        export(ocp, tmp_path / "link")
    assert list(real.iterdir()) == []
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    with pytest.raises(ValueError, match="symbolic link"):
        export(ocp, tmp_path / "dangling", force=True)
    assert not (tmp_path / "nowhere").exists()
    # a link above the folder is an ordinary path: the export goes where it leads
    info = export(ocp, tmp_path / "link" / "sub")
    assert (real / "sub" / "Makefile").is_file() and info.out_dir == tmp_path / "link" / "sub"


def test_force_replaces_files_and_never_writes_into_them(tmp_path):
    """--force renames new files into place: a file of the folder hard-linked elsewhere keeps its content there,
    both for ocpkit's own files and for CasADi's generated ones, and no scratch file is left behind."""
    ocp = make("pendulum").ocp(knots=3, horizon=10)
    out = tmp_path / "gen"
    export(ocp, out)
    names = sorted(p.name for p in out.iterdir())
    mode = (out / "mpc.c").stat().st_mode & 0o777
    for name in ("mpc.h", "mpc_casadi.c", "Makefile"):
        (tmp_path / f"keep-{name}").write_text("mine\n")
        (out / name).unlink()
        os.link(tmp_path / f"keep-{name}", out / name)
    export(ocp, out, force=True)
    for name in ("mpc.h", "mpc_casadi.c", "Makefile"):
        assert (tmp_path / f"keep-{name}").read_text() == "mine\n", name
        assert (out / name).read_text() != "mine\n" and (out / name).stat().st_nlink == 1
    assert sorted(p.name for p in out.iterdir()) == names
    assert (out / "mpc.h").stat().st_mode & 0o777 == mode == (out / "mpc_casadi.c").stat().st_mode & 0o777


def test_build_refuses_a_symlink_make_would_write_through(tmp_path):
    ocp = make("pendulum").ocp(knots=3, horizon=10)
    info = export(ocp, tmp_path / "gen")
    victim = tmp_path / "victim.o"
    victim.write_text("keep\n")
    (info.out_dir / "mpc.o").symlink_to(victim)
    with pytest.raises(ValueError, match=r"symbolic link.*mpc\.o"):
        build(info.out_dir)
    assert victim.read_text() == "keep\n"


@pytest.mark.parametrize("missing", ["cc", "make"])
def test_missing_tool_is_one_line(missing, tmp_path, monkeypatch, capsys):
    from ocpkit.cli import main
    from ocpkit.export import BuildError

    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for tool in ("cc", "make"):
        if tool != missing:
            (bin_dir / tool).symlink_to(shutil.which(tool))
    monkeypatch.setenv("PATH", str(bin_dir))
    monkeypatch.delenv("CC", raising=False)
    ocp = make("pendulum").ocp(knots=3, horizon=10)
    info = export(ocp, tmp_path / "gen")
    with pytest.raises(BuildError, match=f"`{missing}` not found"):
        build(info.out_dir)
    monkeypatch.chdir(tmp_path)
    assert main(["export", "pendulum", "--knots", "3", "--horizon", "10", "--out", "cli"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"`{missing}` not found" in err
    assert not Path("cli").exists()  # checked before any work


def test_each_source_is_compiled_once(bounded_pendulum):
    """`make lib` compiled the step and the generated code; the example only adds main.c and links."""
    _, _, c = bounded_pendulum
    plan = subprocess.run(
        ["make", "-n", "-C", str(c.out_dir), "example"], capture_output=True, text=True, check=True
    ).stdout
    compiles = [line for line in plan.splitlines() if " -c " in line]
    assert len(compiles) == 1 and "main.c" in compiles[0], plan
    makefile = (c.out_dir / "Makefile").read_text()
    assert "OPT ?= -O2" in makefile and "OPT_STEP ?= -O3" in makefile


def test_bench_export_prints_the_columns(tmp_path):
    from ocpkit.benchmarks.export import bench_export

    lines = []
    rows = bench_export(["pendulum"], horizon=30, steps=5, out_root=tmp_path, out=lines.append)
    assert rows[0]["max_abs_du"] <= 1e-6 and rows[0]["c_failures"] == 0 and rows[0]["c_bytes"] > 0
    assert rows[0]["example_median_s"] > 0
    for column in ("C kB", "build s", "C ms", "example ms", "Python ms", "max|du|"):
        assert column in lines[0]


# --- the step's own code paths (issue 18: the fast step) ---------------------------------------------------------


def test_linear_model_uses_its_constant_discrete_model(tmp_path):
    """A linear model exports its generated constant (A_d, B_d, w_d) instead of RK4 sensitivities."""
    problem = _problem("pendulum:linear")
    ocp = problem.ocp(knots=5, horizon=40)
    info = export(ocp, tmp_path / "lin")
    assert "#define MODEL_RK4 0" in (info.out_dir / "mpc.c").read_text()
    build(info.out_dir)
    with ExportedMPC(ocp, info.out_dir) as c:
        _compare(problem, ocp, c, "goal", seeds=[0, 1], steps=8)


@pytest.mark.parametrize("simd", ["sse2", "none"])
def test_vector_code_paths_match_linear_mpc(simd, tmp_path):
    """`make SIMD=sse2` (no AVX2 path) and `SIMD=none` (plain C) give LinearMPC's step too: nlink:3 fills whole
    register tiles, the bounded pendulum only remainders; the split times add up to about the step."""
    for name, kw, lin in (
        ("nlink:3", {}, "goal"),
        ("pendulum", {"x_min": [-np.inf, -6.0], "x_max": [np.inf, 6.0]}, "plan"),
    ):
        problem = _problem(name)
        ocp = problem.ocp(knots=5, horizon=50, **kw)
        info = export(ocp, tmp_path / f"{simd}-{name.replace(':', '')}", linearization=lin)
        subprocess.run(["make", "-s", f"SIMD={simd}", "lib"], cwd=info.out_dir, check=True, capture_output=True)
        with ExportedMPC(ocp, info.out_dir) as c:
            _compare(problem, ocp, c, lin, seeds=[0], steps=6)
            sol = c.solve(*problem.sample(1))
            parts = sum(sol.times[k] for k in ("model", "build", "solve"))
            assert 0 < parts <= c.step_seconds


def test_gram_schedule_reaches_every_piece_length():
    """The C step's Γ_L schedule (doublings and single stages) ends at each length in turn, and stays short."""
    from ocpkit.export.constants import DOUBLE, INC, RESET, SAVE, gram_schedule

    for lengths in ([1], [2], [3], [7, 8], [24, 25], [25], [1, 100], [5, 50, 51]):
        ops, s, reached = gram_schedule(lengths), 1, []
        for op in ops:
            if op == DOUBLE:
                s *= 2
            elif op == INC:
                s += 1
            elif op == RESET:
                s = 1
            else:
                assert op == SAVE + len(reached)
                reached.append(s)
        assert reached == lengths, (lengths, ops)
        assert len(ops) <= len(lengths) + sum(2 * L.bit_length() for L in lengths), ops

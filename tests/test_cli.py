import json
import re
import subprocess
import sys
import time

import pytest

from ocpkit import cli, solvers, studies
from ocpkit.cli import main


def run(*args, cwd):
    # Outside the checkout, so the installed package (with ocpkit.problems, ocpkit.solvers) is imported.
    return subprocess.run(
        [sys.executable, "-m", "ocpkit.cli", *args], capture_output=True, text=True, timeout=120, cwd=cwd
    )


def test_solve_json(capsys):
    assert main(["solve", "pendulum", "--knots", "5", "--json", "--seed", "2"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["status"] == "success" and len(out["u"]) == 1 and len(out["knots"]) == 5
    assert set(out["times"]) == {"model", "build", "solve", "total"} and out["iterations"] > 0
    assert main(["solve", "pendulum", "--knots", "5", "--json", "--seed", "2", "--compiled"]) == 0
    compiled = json.loads(capsys.readouterr().out)
    assert abs(compiled["u"][0] - out["u"][0]) < 1e-6


@pytest.mark.parametrize(
    "args,message",
    [
        (["solve", "pendulm"], "unknown problem 'pendulm'"),
        (["solve", "pendulum", "--solver", "foo"], "unknown solver 'foo'"),
        (["solve", "pendulum", "--knots", "0"], "knots must be >= 1"),
        (["solve", "pendulum", "--horizon", "-3"], "horizon must be >= 1"),
        (["solve", "pendulum", "--form", "dense"], "invalid choice"),
        (["bench", "qp", "--arch", "cpu"], "--arch applies to `ocpkit bench empc` only"),
    ],
)
def test_bad_names_exit_2_one_line(args, message, tmp_path):
    res = run(*args, cwd=tmp_path)
    assert res.returncode == 2
    assert message in res.stderr and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1


def test_simulate_writes_figure(tmp_path, capsys):
    fig = tmp_path / "sim.png"
    assert main(["simulate", "pendulum:linear", "--knots", "3", "--duration", "0.2", "--out", str(fig), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert fig.stat().st_size > 1000 and out["steps"] == 20 and out["actual_cost"] > 0
    assert out["fallbacks"] == 0 and out["fallback_causes"] == ""  # by status when there are any


def _no_cuda_driver() -> bool:
    import ctypes

    try:
        ctypes.CDLL("libcuda.so.1")
    except OSError:
        return True
    return False


@pytest.mark.parametrize(
    "args,message",
    [
        (["simulate", "pendulum", "--out", "/proc/fig.png"], "--out /proc/fig.png: not writable"),
        (["study", "knots", "--out", "/proc/x"], "--out /proc/x: not writable"),
        (["study", "knots", "--out", "o", "--export", "."], "--export .: is a folder"),
        (
            ["study", "knots", "--out", "o", "--scheduler", "tcp://127.0.0.1:1"],
            "cannot reach the Dask scheduler at tcp://127.0.0.1:1",
        ),
        (["study", "knots", "--out", "o", "--trial-timeout", "-1"], "--trial-timeout must be a positive number"),
        (
            ["solve", "pendulum", "--horizon", "100000", "--parameterization", "identity"],
            "needs about 298.0 GiB for its dense matrices",
        ),
        pytest.param(
            ["solve", "pendulum", "--solver", "empc", "--arch", "cuda"],
            "this machine has none",
            marks=pytest.mark.skipif(not _no_cuda_driver(), reason="a CUDA driver is present"),
        ),
    ],
)
def test_checked_before_any_work_one_line(args, message, tmp_path):
    res = run(*args, cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    assert message in res.stderr and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())  # nothing written before


def test_a_damaged_store_is_one_line(tmp_path):
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / "results.sqlite").write_bytes(b"not a database" * 100)
    res = run("study", "knots", "--problem", "pendulum:linear", "--out", "o", cwd=tmp_path)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "results store o/results.sqlite" in res.stderr and "damaged" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1


def test_study_exports_one_file_and_resumes_with_flags(tmp_path):
    import sqlite3

    args = ("study", "knots", "--problem", "pendulum:linear", "--out", "o", "--workers", "1")
    res = run(*args, "--export", "all.sqlite", "--trial-timeout", "120", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    with sqlite3.connect(tmp_path / "all.sqlite") as con:
        n = con.execute("SELECT count(*) FROM trials WHERE status = 'ok'").fetchone()[0]
    assert n > 0 and not (tmp_path / "all.sqlite-wal").exists()
    res = run(*args, "--retry-failed", "--reuse-stale", cwd=tmp_path)  # every trial stored: nothing to run
    assert res.returncode == 0, res.stderr
    assert "report: o/knots.md" in res.stdout


# --- every solver method and option of the Python API, with the same defaults in solve, simulate and export ---


@pytest.fixture
def made(monkeypatch):
    """Records the (solver name, OCP, options) the command line hands to solvers.make, which still builds it."""
    calls = []
    real = solvers.make

    def make(name, ocp, **options):
        calls.append((name, ocp, options))
        return real(name, ocp, **options)

    monkeypatch.setattr(solvers, "make", make)
    return calls


def test_the_command_lines_choices_are_the_solvers():
    from ocpkit.solvers import nlp, qp

    assert cli.NLP_METHODS == nlp.METHODS and cli.DYNAMICS == nlp.DYNAMICS
    assert sorted(cli.QP_BACKENDS) == sorted(qp.QP_SOLVERS)
    # a new solver must be placed in the table
    assert set(cli.SAMPLING) | {"qp", "rti", "ipopt"} == set(solvers.names())
    sampling = pytest.importorskip("ocpkit.solvers.sampling")  # starts Taichi
    assert cli.VARIANTS == sampling.VARIANTS


def test_real_time_iteration_is_a_solver_not_a_method(tmp_path):
    """Issue 45: --solver rti; --method takes NonlinearMPC's methods, read from its table (solvers.methods)."""
    from ocpkit.solvers import methods

    assert "rti" in solvers.names() and cli.NLP_METHODS == tuple(methods.METHODS) and "rti" not in cli.NLP_METHODS
    res = run("solve", "pendulum", "--solver", "ipopt", "--method", "rti", cwd=tmp_path)
    assert res.returncode == 2 and "invalid choice: 'rti'" in res.stderr


@pytest.mark.parametrize(
    "args,options",
    [
        (["--solver", "ipopt"], {}),
        (["--solver", "ipopt", "--method", "ipopt"], {"method": "ipopt"}),
        (["--solver", "ipopt", "--method", "sqp"], {"method": "sqp"}),
        (["--solver", "ipopt", "--method", "fatrop"], {"method": "fatrop"}),
        (["--solver", "rti"], {}),
        (
            ["--solver", "rti", "--iterations", "3", "--form", "sparse", "--qp", "osqp"],
            {"iterations": 3, "form": "sparse", "qp": "osqp"},
        ),
        (
            ["--solver", "ipopt", "--method", "sqp", "--dynamics", "affine", "--linearization", "plan"],
            {"method": "sqp", "dynamics": "affine", "linearization": "plan"},
        ),
        (["--linearization", "goal"], {"linearization": "goal"}),
        (["--linearization", "plan"], {"linearization": "plan"}),
        (["--linearization", "trajectory", "--form", "sparse"], {"linearization": "trajectory", "form": "sparse"}),
    ],
)
def test_solve_takes_every_method_and_linearization(args, options, made, capsys):
    assert main(["solve", "pendulum", "--horizon", "20", "--seed", "1", "--json", *args]) == 0
    out = json.loads(capsys.readouterr().out)
    [(name, _, given)] = made
    assert name == args[args.index("--solver") + 1] if "--solver" in args else name == "qp"
    assert given == options and out["status"] == "success"
    ctrl = out["controller"]
    if name == "ipopt":
        assert ctrl.startswith(f"NonlinearMPC({options.get('method', 'ipopt')}, {options.get('dynamics', 'nonlinear')}")
    elif name == "rti":
        assert ctrl.startswith(f"RealTimeIteration({options.get('iterations', 1)}, {options.get('form', 'condensed')}")
    else:
        assert ctrl.startswith("LinearMPC(")


def test_rti_iterations_reach_the_iteration(made, capsys):
    """--iterations K is RealTimeIteration's: K SQP steps per control step (here until its tolerance 0 stops)."""
    rc = [
        main(
            ["solve", "pendulum", "--horizon", "20", "--seed", "1", "--json", "--solver", "rti", "--iterations", str(k)]
        )
        for k in (1, 4)
    ]
    one, four = (json.loads(line) for line in capsys.readouterr().out.splitlines())
    assert rc == [0, 0] and [opts["iterations"] for _, _, opts in made] == [1, 4]
    assert four["iterations"] > one["iterations"]  # QP iterations summed over the SQP steps


@pytest.mark.parametrize("command", ["solve", "simulate"])
def test_solve_and_simulate_default_to_five_knots(command, made, tmp_path, capsys):
    extra = ["--duration", "0.05", "--out", str(tmp_path / "f.png")] if command == "simulate" else []
    assert main([command, "pendulum", "--horizon", "20", "--json", *extra]) == 0
    assert made[-1][1].knots == cli.DEFAULT_KNOTS == 5 and made[-1][1].horizon == 20
    assert main([command, "pendulum", "--horizon", "3", "--json", *extra]) == 0  # capped at a shorter horizon
    assert made[-1][1].knots == 3
    assert main([command, "pendulum", "--horizon", "20", "--parameterization", "identity", "--json", *extra]) == 0
    ocp = made[-1][1]
    assert ocp.knots == 20 and ocp.parameterization.kind == "identity"  # traditional MPC
    capsys.readouterr()


def test_export_defaults_to_the_same_knots_and_takes_the_linearization(tmp_path, capsys):
    assert main(["export", "pendulum", "--horizon", "10", "--out", str(tmp_path / "a")]) == 0
    out = capsys.readouterr().out
    assert "linear with 5 knots over T = 10" in out and "linearization goal" in out and "agree" in out
    assert (
        main(
            [
                "export",
                "pendulum",
                "--horizon",
                "10",
                "--parameterization",
                "zoh",
                "--knots",
                "3",
                "--linearization",
                "plan",
                "--out",
                str(tmp_path / "b"),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "zoh with 3 knots over T = 10" in out and "linearization plan" in out and "agree" in out


@pytest.mark.parametrize("command", ["solve", "simulate", "export"])
def test_help_says_the_default_knots(command, capsys):
    with pytest.raises(SystemExit) as exit_:
        main([command, "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert exit_.value.code == 0
    assert (
        "knot points p (default 5, or T when the horizon is shorter; the Python API's Problem.ocp(knots=None) is "
        "traditional MPC instead)" in text
    )
    assert "traditional MPC (one knot per step, p = T) is --parameterization identity" in text


@pytest.mark.parametrize(
    "args,message",
    [
        (["--iterations", "3"], "--iterations does not apply to solver 'qp': it applies to solver rti"),
        (
            ["--solver", "ipopt", "--iterations", "3"],
            "--iterations does not apply to solver 'ipopt' with --method ipopt:",
        ),
        (
            ["--solver", "ipopt", "--method", "sqp", "--iterations", "3"],
            "--iterations does not apply to solver 'ipopt' with --method sqp:",
        ),
        (["--solver", "cem", "--iterations", "2"], "--iterations does not apply to solver 'cem':"),
        (["--method", "sqp"], "--method does not apply to solver 'qp': it applies to solver ipopt"),
        (
            ["--solver", "ipopt", "--method", "fatrop", "--form", "sparse"],
            "--form does not apply to solver 'ipopt' with --method fatrop: it applies to solvers qp, rti",
        ),
        (["--solver", "ipopt", "--qp", "osqp"], "--qp does not apply to solver 'ipopt' with --method ipopt:"),
        (
            ["--solver", "ipopt", "--linearization", "plan"],
            "--linearization does not apply to solver 'ipopt' with --method ipopt --dynamics nonlinear:",
        ),
        (
            ["--solver", "rti", "--linearization", "trajectory"],
            "--linearization does not apply to solver 'rti' (it always linearizes along its iterate)",
        ),
        (
            ["--solver", "ipopt", "--method", "sqp", "--dynamics", "affine", "--linearization", "trajectory"],
            "--linearization trajectory applies to solver qp only; solver 'ipopt' with --method sqp takes goal or plan",
        ),
        (
            ["--solver", "empc", "--linearization", "trajectory"],
            "--linearization trajectory applies to solver qp only; solver 'empc' takes goal or plan",
        ),
        (
            ["--solver", "mppi", "--dynamics", "nonlinear", "--variant", "paper", "--linearization", "plan"],
            "--linearization does not apply to solver 'mppi' with --dynamics nonlinear --variant paper:",
        ),
        (["--solver", "rti", "--dynamics", "affine"], "--dynamics does not apply to solver 'rti':"),
        (
            ["--solver", "ipopt", "--method", "fatrop", "--dynamics", "nonlinear"],
            "--dynamics does not apply to solver 'ipopt' with --method fatrop: it applies to solver ipopt with "
            "--method ipopt or sqp, and solvers empc, cem, mppi",
        ),
        (["--dynamics", "affine"], "--dynamics does not apply to solver 'qp':"),
        (["--population", "8"], "--population does not apply to solver 'qp': it applies to solvers empc, cem, mppi"),
        (["--knots", "3", "--parameterization", "identity"], "--knots 3 does not apply to --parameterization identity"),
    ],
)
@pytest.mark.parametrize("command", ["solve", "simulate"])
def test_an_option_that_does_not_apply_is_refused(command, args, message, made, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main([command, "pendulum", *args]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not made and not any(tmp_path.iterdir())  # refused before any controller or output


def test_export_refuses_knots_with_traditional_mpc(tmp_path, capsys):
    assert (
        main(["export", "pendulum", "--knots", "3", "--parameterization", "identity", "--out", str(tmp_path / "e")])
        == 2
    )
    assert "--knots 3 does not apply to --parameterization identity" in capsys.readouterr().err
    assert not (tmp_path / "e").exists()


def test_study_help_names_every_registered_study(monkeypatch, capsys):
    for command in ("study", "reproduce"):
        with pytest.raises(SystemExit):
            main([command, "--help"]) if command == "study" else main(["--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert all(name in text for name in studies.NAMES), text
    # Derived from the registry, not written out: a study added to it appears in the help and is accepted.
    monkeypatch.setattr(studies, "NAMES", (*studies.NAMES, "brand_new"))
    with pytest.raises(SystemExit):
        main(["study", "--help"])
    assert "brand_new" in " ".join(capsys.readouterr().out.split())
    assert cli._parser().parse_args(["study", "brand_new"]).name == "brand_new"


def test_reproduce_only_runs_the_studies_it_names_in_the_reports_order(monkeypatch, tmp_path):
    from ocpkit.studies import reproduce as reproduce_module

    ran = []
    monkeypatch.setattr(reproduce_module, "reproduce", lambda size, out, names, **_: ran.append(names) or out)
    for only, expected in (
        (["tracking", "knots"], ("knots", "tracking")),
        (["paper", "knots"], studies.PAPER),
        ([], studies.NAMES),
    ):
        flags = [arg for name in only for arg in ("--only", name)]
        assert main(["reproduce", "--out", str(tmp_path / "r"), *flags]) == 0
        assert ran.pop() == expected
    assert set(studies.PAPER) < set(studies.NAMES)
    with pytest.raises(ValueError, match="unknown study 'knot'; known: .* or paper"):
        studies.chosen(["knot"])


def test_an_unknown_study_is_one_line_naming_the_studies(tmp_path):
    res = run("study", "knot", cwd=tmp_path)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "invalid choice: 'knot'" in res.stderr and all(name in res.stderr for name in studies.NAMES)
    assert len(res.stderr.strip().splitlines()) == 1


def test_sparse_proxqp_with_knots_on_a_long_horizon_is_announced_before_work(capsys):
    from ocpkit import cli
    from ocpkit.cli import checks
    from ocpkit.problems import make

    args = cli._parser().parse_args(["solve", "pendulum", "--horizon", "1000000", "--form", "sparse"])
    checks.check_size(make("pendulum"), args)
    err = capsys.readouterr().err
    assert "sparse ProxQP with knots" in err and "default budget" in err and "--qp osqp" in err, err
    args = cli._parser().parse_args(["solve", "pendulum", "--horizon", "1000000", "--form", "sparse", "--qp", "osqp"])
    checks.check_size(make("pendulum"), args)
    assert "ProxQP" not in capsys.readouterr().err


def test_version(capsys):
    from ocpkit import __version__, cli

    with pytest.raises(SystemExit) as exit_:
        cli.main(["--version"])
    assert exit_.value.code == 0 and capsys.readouterr().out.strip() == f"ocpkit {__version__}"


def test_integrator_option_reaches_the_controllers_ocp(tmp_path, capsys):
    args = ["simulate", "nlink:2", "--solver", "rti", "--duration", "0.1", "--json", "--out", str(tmp_path / "sim.png")]
    assert main(args + ["--integrator", "euler"]) == 0
    assert "integrator='euler'" in json.loads(capsys.readouterr().out)["controller"]
    res = run("solve", "nlink:2", "--integrator", "rk2", cwd=tmp_path)
    assert res.returncode == 2 and "invalid choice: 'rk2'" in res.stderr


def test_build_fills_the_taichi_kernels_a_later_run_loads(tmp_path):
    """`ocpkit build --solver empc` compiles the planner's kernels into the cache; the same controller in a later
    process loads every one of them (no kernel compiled there), and its solve says which path answered."""
    import os

    env = {
        **{k: v for k, v in os.environ.items() if k != "TI_OFFLINE_CACHE_FILE_PATH"},
        "OCPKIT_CACHE_DIR": str(tmp_path / "cache"),
    }
    args = ["pendulum", "--solver", "empc", "--population", "32", "--knots", "3"]
    built = subprocess.run(
        [sys.executable, "-m", "ocpkit.cli", "build", *args],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=tmp_path,
        env=env,
    )
    assert built.returncode == 0, built.stderr
    assert "answering by Taichi kernel (cpu)" in built.stdout
    kernels = tmp_path / "cache" / "taichi-kernels"
    before = sorted(p.name for p in kernels.glob("*.tic"))
    assert before
    solved = subprocess.run(
        [sys.executable, "-m", "ocpkit.cli", "solve", *args, "--json"],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=tmp_path,
        env=env,
    )
    assert solved.returncode == 0, solved.stderr
    assert json.loads(solved.stdout)["path"] == "Taichi kernel (cpu)"
    assert sorted(p.name for p in kernels.glob("*.tic")) == before


def test_export_offers_only_what_it_exports(capsys):
    """Issue 44, item 14: --qp hpipm and --form sparse were offered and always refused; the choices are the pairs
    ocpkit.export generates."""
    from ocpkit.cli.options import EXPORT_FORMS, EXPORT_QPS
    from ocpkit.export import SUPPORTED

    assert {(f, q) for f in EXPORT_FORMS for q in EXPORT_QPS} == SUPPORTED and EXPORT_QPS[0] == "daqp"
    for option, value in (("--qp", "hpipm"), ("--form", "sparse")):
        with pytest.raises(SystemExit) as exit_:
            main(["export", "pendulum", option, value])
        assert exit_.value.code == 2 and f"invalid choice: '{value}'" in capsys.readouterr().err


def test_simulate_writes_a_figure_only_when_asked(tmp_path, monkeypatch, capsys):
    """Issue 44, item 15: without --out no figure is written (it overwrote results/simulate.png on every run); the
    step times carry their unit; the figure's legend is the controller's short label, not its OCP's repr."""
    from ocpkit.sim import plots

    monkeypatch.chdir(tmp_path)
    assert main(["simulate", "pendulum:linear", "--knots", "3", "--duration", "0.2"]) == 0
    out = capsys.readouterr().out
    assert not any(tmp_path.iterdir()) and "figure:" not in out
    assert re.search(r"total solve time median \d+\.\d{3} ms \(p90 \d+\.\d{3} ms, max \d+\.\d{3} ms\)", out), out
    drawn = []
    monkeypatch.setattr(plots, "closed_loop", lambda trajectories, path, **kw: drawn.append(list(trajectories)) or path)
    assert main(["simulate", "pendulum:linear", "--knots", "3", "--duration", "0.2", "--out", "f.png", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["figure"] == "f.png"
    assert drawn == [["LinearMPC(condensed, daqp, Python step, 3 knots)"]]


def test_long_runs_say_what_they_do_on_stderr(tmp_path, monkeypatch, capsys):
    """Issue 44, item 15: export and simulate waited up to 50 s in silence; a phase that lasts (here: any) is said
    on stderr as it starts, and a closed loop's progress as it runs."""
    from ocpkit.cli import commands

    monkeypatch.setattr(commands, "SLOW", 0.0)
    monkeypatch.setattr(commands._Progress, "FIRST", 0.0)
    monkeypatch.setattr(commands._Progress, "EVERY", 0.0)
    slow = commands.Controller.solve

    def solve(self, x, goal):
        time.sleep(0.01)  # the timer's thread gets its turn
        return slow(self, x, goal)

    monkeypatch.setattr(commands.Controller, "solve", solve)
    assert main(["simulate", "pendulum:linear", "--knots", "3", "--duration", "0.05"]) == 0
    err = capsys.readouterr().err
    assert "ocpkit: LinearMPC(condensed, daqp, Python step, 3 knots): first solve, compiling" in err, err
    assert "ocpkit: simulating 5 steps: 1/5" in err and "ocpkit: simulating 5 steps: 4/5" in err, err
    assert main(["export", "pendulum", "--horizon", "10", "--out", str(tmp_path / "c")]) == 0
    err = capsys.readouterr().err
    assert re.search(r"ocpkit: building the C step in \S+ \(make: \d+ kB of C, about \d+ s the first time\)…", err), err


def test_study_help_says_its_defaults(capsys):
    with pytest.raises(SystemExit):
        main(["study", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "quick (minutes, the default) or full" in text and "(default: results/reproduce)" in text

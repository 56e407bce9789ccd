import json
import subprocess
import sys

import pytest

from ocpkit.cli import main


def run(*args, cwd):
    # Outside the checkout, so the installed package (with ocpkit.problems, ocpkit.solvers) is imported.
    return subprocess.run([sys.executable, "-m", "ocpkit.cli", *args], capture_output=True, text=True, timeout=120,
                          cwd=cwd)


def test_solve_json(capsys):
    assert main(["solve", "pendulum", "--knots", "5", "--json", "--seed", "2"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["status"] == "success" and len(out["u"]) == 1 and len(out["knots"]) == 5
    assert set(out["times"]) == {"model", "build", "solve", "total"} and out["iterations"] > 0
    assert main(["solve", "pendulum", "--knots", "5", "--json", "--seed", "2", "--compiled"]) == 0
    compiled = json.loads(capsys.readouterr().out)
    assert abs(compiled["u"][0] - out["u"][0]) < 1e-6


@pytest.mark.parametrize("args,message", [
    (["solve", "pendulm"], "unknown problem 'pendulm'"),
    (["solve", "pendulum", "--solver", "foo"], "unknown solver 'foo'"),
    (["solve", "pendulum", "--knots", "0"], "knots must be >= 1"),
    (["solve", "pendulum", "--horizon", "-3"], "horizon must be >= 1"),
    (["solve", "pendulum", "--form", "dense"], "invalid choice"),
    (["bench", "qp", "--arch", "cpu"], "--arch applies to `ocpkit bench empc` only"),
])
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


def _no_cuda_driver() -> bool:
    import ctypes

    try:
        ctypes.CDLL("libcuda.so.1")
    except OSError:
        return True
    return False


@pytest.mark.parametrize("args,message", [
    (["simulate", "pendulum", "--out", "/proc/fig.png"], "--out /proc/fig.png: not writable"),
    (["study", "knots", "--out", "/proc/x"], "--out /proc/x: not writable"),
    (["study", "knots", "--out", "o", "--export", "."], "--export .: is a folder"),
    (["study", "knots", "--out", "o", "--scheduler", "tcp://127.0.0.1:1"],
     "cannot reach the Dask scheduler at tcp://127.0.0.1:1"),
    (["study", "knots", "--out", "o", "--trial-timeout", "-1"], "--trial-timeout must be a positive number"),
    (["solve", "pendulum", "--horizon", "100000"], "needs about 298.0 GiB for its dense matrices"),
    pytest.param(["solve", "pendulum", "--solver", "empc", "--arch", "cuda"], "this machine has none",
                 marks=pytest.mark.skipif(not _no_cuda_driver(), reason="a CUDA driver is present")),
])
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

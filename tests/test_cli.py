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

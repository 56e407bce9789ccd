"""A user's own problem code that fails (issue 28, item 5): one line naming the user's file, line and exception —
in Python a ProblemError chained to the original, on the command line one line on stderr and exit 2 (the full
traceback with --debug) — and dynamics that return NaN named as such in simulate and export."""

from __future__ import annotations

import re
import shutil
import sys
import textwrap

import numpy as np
import pytest

from ocpkit.cli import main
from ocpkit.problems import make

BROKEN = {
    "import_raises.py": """
        import numpy as np

        ROBOT = None
        raise RuntimeError("no robot connected")
    """,
    "syntax.py": """
        from ocpkit.problems.pendulum import Pendulum

        def factory(:
            return Pendulum()
    """,
    "makers.py": """
        from ocpkit.problems.pendulum import Pendulum


        class Raises(Pendulum):
            def __init__(self):
                super().__init__()
                raise KeyError("mass")


        def factory():
            return 1 / 0


        def not_a_problem():
            return 42
    """,
    "nan_everywhere.py": """
        import casadi as ca
        import numpy as np
        from ocpkit import Model, Problem


        class NaNPole(Problem):
            name, dt, horizon, duration = "nanpole", 0.05, 20, 0.5

            def dynamics(self, error):
                x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
                return Model(self.name, x, u, ca.vertcat(x[1], ca.sqrt(-1 - x[0] ** 2) + u[0]))

            def defaults(self):
                return {"Q": np.eye(2), "R": [[0.1]], "u_min": [-2.0], "u_max": [2.0]}

            def sample(self, seed):
                return np.r_[0.1, 0.0], np.r_[0.0, 0.0]
    """,
    # finite at the start; NaN once p passes 1 (the drift carries it there in about 0.2 s)
    "nan_later.py": """
        import casadi as ca
        import numpy as np
        from ocpkit import Model, Problem


        class Drift(Problem):
            name, dt, horizon, duration = "drift", 0.05, 20, 1.0

            def dynamics(self, error):
                x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
                return Model(self.name, x, u, ca.vertcat(5.0 + 0 * x[1], u[0] - ca.sqrt(1 - x[0])))

            def defaults(self):
                return {"Q": np.eye(2), "R": [[0.1]], "u_min": [-2.0], "u_max": [2.0]}

            def sample(self, seed):
                return np.r_[0.0, 0.0], np.r_[0.0, 0.0]
    """,
}
# the line each message must name: the raising line, the bad syntax, a factory's `def`, a `dynamics` hook's `def`
LINE = {
    "import_raises.py": 4,
    "syntax.py": 3,
    "Raises": 7,
    "factory": 11,
    "not_a_problem": 14,
    "NaNPole.dynamics": 9,
    "Drift.dynamics": 9,
}


@pytest.fixture
def user_dir(tmp_path, monkeypatch):
    for name, code in BROKEN.items():
        (tmp_path / name).write_text(textwrap.dedent(code).lstrip("\n"))
    pkg = tmp_path / "userpkg_broken"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "robots.py").write_text(textwrap.dedent(BROKEN["import_raises.py"]).lstrip("\n"))
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield tmp_path
    for name in [k for k in sys.modules if k.startswith("userpkg_broken")]:
        del sys.modules[name]


def _one_line(capsys) -> str:
    """The one error line on stderr; progress lines of a slow phase ("ocpkit: building ……", said after a second on
    a busy machine) are not errors."""
    err = "".join(line for line in capsys.readouterr().err.splitlines(keepends=True) if not line.rstrip().endswith("…"))
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


CASES = [  # spec, file:line it must name, the exception it must name
    ("./import_raises.py:ROBOT", f"import_raises.py:{LINE['import_raises.py']}", "RuntimeError: no robot connected"),
    ("userpkg_broken.robots:ROBOT", f"robots.py:{LINE['import_raises.py']}", "RuntimeError: no robot connected"),
    ("./syntax.py:factory", f"syntax.py:{LINE['syntax.py']}", "SyntaxError"),
    ("./makers.py:Raises", f"makers.py:{LINE['Raises']}", "KeyError: 'mass'"),
    ("./makers.py:factory", f"makers.py:{LINE['factory']}", "ZeroDivisionError: division by zero"),
    ("./makers.py:not_a_problem", f"makers.py:{LINE['not_a_problem']}", "int, not an ocpkit.Problem"),
]


@pytest.mark.parametrize("spec, where, what", CASES)
def test_broken_spec_is_a_problem_error_naming_file_and_line(user_dir, spec, where, what):
    from ocpkit.model.problem import ProblemError

    with pytest.raises(ProblemError) as info:
        make(spec)
    message = str(info.value)
    assert where in message and what in message and spec in message and "\n" not in message, message
    if "not an ocpkit.Problem" in what:
        assert isinstance(info.value, TypeError)  # as before: the spec named something that is not a Problem
    else:
        assert info.value.__cause__ is not None and type(info.value.__cause__).__name__ in what


@pytest.mark.parametrize("spec, where, what", CASES)
def test_cli_broken_spec_is_one_line_and_exit_2(user_dir, capsys, spec, where, what):
    assert main(["solve", spec, "--knots", "3"]) == 2
    err = _one_line(capsys)
    assert err.startswith("ocpkit: error: ") and where in err and what in err, err


def test_debug_prints_the_full_traceback(user_dir, capsys):
    assert main(["solve", "./makers.py:Raises", "--knots", "3", "--debug"]) == 2
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and 'raise KeyError("mass")' in err
    assert err.strip().splitlines()[-1].startswith("ocpkit: error: ")
    assert main(["--debug", "solve", "./import_raises.py:ROBOT"]) == 2
    assert 'raise RuntimeError("no robot connected")' in capsys.readouterr().err


# --- dynamics that return NaN ------------------------------------------------------------------------------


def test_simulate_names_nan_dynamics(user_dir):
    from ocpkit.model.problem import DynamicsError, ProblemError
    from ocpkit.sim.simulate import simulate
    from ocpkit.solvers.qp import LinearMPC

    problem = make("./nan_everywhere.py:NaNPole")
    with pytest.raises(DynamicsError) as info:
        simulate(problem.plant(), LinearMPC(problem.ocp(knots=3)), *problem.sample(0), 0.5)
    message = str(info.value)
    assert "NaNPole.dynamics(error) returned NaN in xdot[1] at x = [0.1, 0.0], u = [" in message, message
    assert f"nan_everywhere.py:{LINE['NaNPole.dynamics']}" in message
    assert isinstance(info.value, ProblemError) and isinstance(info.value, FloatingPointError)

    problem = make("./nan_later.py:Drift")
    with pytest.raises(DynamicsError, match=r"Drift.dynamics\(error\) returned NaN in xdot\[1\] at x = ") as info:
        simulate(problem.plant(), LinearMPC(problem.ocp(knots=3)), *problem.sample(0), 1.0)
    assert info.value.x[0] > 1.0 and np.isfinite(info.value.x).all()  # where sqrt(1 - p) is NaN, shown exactly
    assert "closed-loop step 4" in str(info.value) and repr(float(info.value.x[0])) in str(info.value)


@pytest.mark.parametrize("spec", ["./nan_everywhere.py:NaNPole", "./nan_later.py:Drift"])
def test_cli_simulate_names_nan_dynamics_in_one_line(user_dir, capsys, spec):
    assert main(["simulate", spec, "--knots", "3", "--out", "fig.png"]) == 2
    err = _one_line(capsys)
    assert ".dynamics(error) returned NaN in xdot[1] at x = [" in err and "u = [" in err, err


@pytest.mark.skipif(shutil.which("cc") is None or shutil.which("make") is None, reason="needs cc and make")
def test_export_names_nan_dynamics(user_dir, capsys):
    from ocpkit.export import export
    from ocpkit.model.problem import DynamicsError

    problem = make("./nan_everywhere.py:NaNPole")
    with pytest.raises(DynamicsError, match=r"NaNPole.dynamics\(error\) returned NaN .*at x = \[0.1, 0.0\]"):
        export(problem.ocp(knots=3), user_dir / "gen", x0=problem.sample(0)[0])
    assert not (user_dir / "gen").exists()  # refused before any file is written
    assert main(["export", "./nan_everywhere.py:NaNPole", "--knots", "3", "--out", "cli"]) == 2
    err = _one_line(capsys)
    assert "NaNPole.dynamics(error) returned NaN" in err and "x must be finite" not in err, err
    # NaN only along the closed loop: the round trip names it
    assert main(["export", "./nan_later.py:Drift", "--knots", "3", "--out", "later"]) == 2
    err = _one_line(capsys)
    assert re.search(r"Drift.dynamics\(error\) returned NaN in xdot\[1\] at x = \[1\.\d+, \S+\], u = \[", err), err
    assert "round trip's closed loop, step" in err
    assert f"nan_later.py:{LINE['Drift.dynamics']}" in err

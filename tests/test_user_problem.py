"""A user's own problem, declared as in the tutorial (examples/cartpole.py), everywhere a problem is named: specs,
CLI, export, studies."""

from __future__ import annotations

import ast
import json
import re
import shutil
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from ocpkit import Model, Problem, problems
from ocpkit.cli import main
from ocpkit.problems import make, register
from ocpkit.problems.pendulum import Pendulum

from conftest import EXAMPLES


def test_tutorial_cartpole_is_short_and_public():
    """What a user writes is one short class on ocpkit's public names (the script's demo run aside)."""
    source = (EXAMPLES / "cartpole.py").read_text()
    tree = ast.parse(source)
    (cls,) = [node for node in tree.body if isinstance(node, ast.ClassDef)]
    assert cls.end_lineno - cls.lineno + 1 <= 20
    code = ast.get_source_segment(source, cls)
    assert "_model" not in code and "def dynamics(self, error)" in code
    ocpkit_imports = [
        n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and "ocpkit" in (n.module or "")
    ]
    assert set(ocpkit_imports) == {"ocpkit"}, ocpkit_imports


def test_cartpole_dynamics_match_an_independent_derivation(cartpole_dir):
    """The tutorial's closed-form accelerations equal the Lagrangian's mass matrix solved numerically."""
    p = make("./cartpole.py:CartPole")
    assert isinstance(p, Problem) and p.name == "cartpole" and p.horizon == 100
    rng = np.random.default_rng(0)
    for error in (1.0, 1.3):
        M, m, l, g = 1.0 * error, 0.1 * error, 0.5, 9.81
        f = p.model(error).f
        for _ in range(5):
            x, u = rng.normal(size=4) * [1, 2, 1, 3], rng.normal(size=1) * 10
            s, c = np.sin(x[1]), np.cos(x[1])
            # (M+m) p̈ + m l c θ̈ = u + m l s θ̇²;  c p̈ + l θ̈ = g s   (θ from upright)
            acc = np.linalg.solve([[M + m, m * l * c], [c, l]], [u[0] + m * l * s * x[3] ** 2, g * s])
            np.testing.assert_allclose(np.asarray(f(x, u)).ravel(), np.r_[x[2:], acc], rtol=1e-12, atol=1e-12)
    assert p.model(1.3) is p.model(1.3) and p.plant() is p.model(1.0)


def test_cartpole_closed_loop_reaches_its_goals(cartpole_dir):
    from ocpkit.sim.simulate import simulate
    from ocpkit.solvers.qp import LinearMPC

    p = make("./cartpole.py:CartPole")
    ctrl = LinearMPC(p.ocp(knots=5))
    for seed in range(3):
        x0, goal = p.sample(seed)
        ctrl.reset()
        traj = simulate(p.plant(), ctrl, x0, goal, p.duration)
        assert traj.fallbacks == 0
        assert np.abs(traj.x[-1] - goal).max() < 0.05, seed


def test_cli_solve_simulate_on_the_users_file(cartpole_dir, capsys):
    assert main(["solve", "./cartpole.py:CartPole", "--knots", "5", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["status"] == "success" and len(out["x0"]) == 4 and len(out["knots"]) == 5
    assert main(["simulate", "./cartpole.py:CartPole", "--knots", "5", "--out", "cp.png", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["steps"] == 200 and out["fallbacks"] == 0 and Path("cp.png").stat().st_size > 1000


@pytest.mark.skipif(shutil.which("cc") is None or shutil.which("make") is None, reason="needs cc and make")
def test_cli_export_builds_and_round_trips(cartpole_dir, capsys):
    assert main(["export", "./cartpole.py:CartPole", "--knots", "5", "--out", "cp_c"]) == 0
    out = capsys.readouterr().out
    assert "agree" in out and "DISAGREE" not in out
    du = float(re.search(r"max \|du\| = (\S+),", out).group(1))
    assert du <= 1e-6
    assert (cartpole_dir / "cp_c" / "libmpc.so").is_file() and (cartpole_dir / "cp_c" / "mpc.h").is_file()


def test_study_robustness_on_the_users_problem(cartpole_dir, capsys):
    """Table, figure and report section for the user's problem, trials in a spawned worker process."""
    assert (
        main(
            [
                "study",
                "robustness",
                "--problem",
                "./cartpole.py:CartPole",
                "--size",
                "quick",
                "--out",
                "res",
                "--workers",
                "1",
            ]
        )
        == 0
    )
    res = cartpole_dir / "res"
    section = (res / "robustness.md").read_text()
    assert "./cartpole.py:CartPole: median normalized cost" in section and "failed" not in section
    assert "](robustness_cartpole_py_CartPole.png)" in section
    assert (res / "robustness_cartpole_py_CartPole.png").stat().st_size > 5000
    import pandas as pd

    df = pd.read_csv(res / "robustness.csv")
    assert len(df) == 24 and (df["status"] == "ok").all() and set(df["problem"]) == {"./cartpole.py:CartPole"}
    # The normalization is by the same controller and seed at error 1: exactly 1 there.
    table = section.split("median normalized cost over 2 seeds:")[1]
    assert "| 1 | 1 | 1 | 1 | 1 |" in table


def test_study_specs_are_checked_before_any_trial(cartpole_dir, capsys):
    assert main(["study", "knots", "--problem", "./cartpole.py:Nope", "--out", "res"]) == 2
    assert "has no 'Nope'" in capsys.readouterr().err
    assert main(["study", "comparison", "--problem", "pendulum", "--out", "res"]) == 2
    assert "--problem applies to the studies knots, horizon, robustness" in capsys.readouterr().err
    from ocpkit.studies import get

    study = get("knots").study("quick", problems=["pendulum", "./cartpole.py:CartPole"])
    assert {t["problem"] for t in study.trials} == {"pendulum", "./cartpole.py:CartPole"}
    assert len(get("horizon").study("quick", problems="pendulum").trials) == 12


# --- specs ------------------------------------------------------------------------------------------------

_SPEC_MODULE = textwrap.dedent("""
    from ocpkit.problems.pendulum import Pendulum

    HEAVY = Pendulum(m=2.0)

    class Light(Pendulum):
        def __init__(self, mass="0.5"):
            super().__init__(m=float(mass))

    def factory(mass="1.0"):
        return Pendulum(m=float(mass))

    def not_a_problem():
        return 42
""")


@pytest.fixture
def spec_module(tmp_path, monkeypatch):
    pkg = tmp_path / "userpkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "robots.py").write_text(_SPEC_MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield tmp_path
    for name in [k for k in sys.modules if k.startswith("userpkg")]:
        del sys.modules[name]


def _mass(problem):
    """The pendulum's mass as its dynamics see it: q̈ at rest with τ = 1 is 1 / (m l²)."""
    return 1.0 / (float(problem.plant().f([0.0, 0.0], [1.0])[1]) * 0.5**2)


def test_module_and_file_specs_with_arguments(spec_module):
    assert _mass(make("userpkg.robots:HEAVY")) == pytest.approx(2.0)
    assert _mass(make("userpkg.robots:Light")) == pytest.approx(0.5)
    assert _mass(make("userpkg.robots:Light:3")) == pytest.approx(3.0)
    assert _mass(make("userpkg.robots:factory:1.5")) == pytest.approx(1.5)
    path = spec_module / "userpkg" / "robots.py"
    assert _mass(make(f"{path}:Light:0.25")) == pytest.approx(0.25)
    with pytest.raises(ValueError, match="instance and takes no argument"):
        make("userpkg.robots:HEAVY:2")
    with pytest.raises(TypeError, match="not an ocpkit.Problem"):
        make("userpkg.robots:not_a_problem")
    with pytest.raises(ValueError, match="names no problem"):
        make(f"{path}")
    with pytest.raises(ValueError, match="problems there: HEAVY, Light"):
        make("userpkg.robots:Missing")
    with pytest.raises(ValueError, match="cannot import module"):
        make("userpkg.nothere:X")


def test_register_makes_a_name_work_everywhere(capsys):
    register("heavy_pendulum", lambda arg=None: Pendulum(m=float(arg or 2.0)))
    try:
        assert "heavy_pendulum" in problems.names()
        assert _mass(make("heavy_pendulum")) == pytest.approx(2.0)
        assert _mass(make("heavy_pendulum:4")) == pytest.approx(4.0)
        assert main(["solve", "heavy_pendulum:3", "--knots", "3", "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["status"] == "success"
    finally:
        problems._REGISTERED.pop("heavy_pendulum", None)
    with pytest.raises(ValueError, match="taken by a shipped problem"):
        register("nlink", Pendulum)
    with pytest.raises(ValueError, match="identifier"):
        register("a:b", Pendulum)
    with pytest.raises(TypeError, match="callable"):
        register("x", 3)


@pytest.mark.parametrize(
    "spec, message",
    [
        ("pendulum:linaer", "unknown pendulum variant 'linaer'; valid: pendulum, pendulum:linear"),
        ("nlink:20", "must be 1 to 13"),
        ("nlink:0", "must be 1 to 13"),
        ("puma560:2", "takes no argument"),
        ("pendulm", "unknown problem 'pendulm'; known: baxter, cartpole, nlink, panda, pendulum, puma560, urdf"),
        ("./nowhere.py:X", "no such file"),
        ("urdf:", "urdf needs a file"),
    ],
)
def test_unknown_names_and_variants_list_the_valid_ones(spec, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        make(spec)


def test_cli_rejects_bad_variant_with_one_line(capsys):
    assert main(["solve", "pendulum:linaer"]) == 2
    err = capsys.readouterr().err
    assert "valid: pendulum, pendulum:linear" in err and len(err.strip().splitlines()) == 1
    assert main(["bench", "step", "--problem", "pendulum"]) == 2
    assert "--problem applies to `ocpkit bench qp|export|nlp|task|startup|peers` only" in capsys.readouterr().err


def test_bench_qp_takes_a_user_problem(cartpole_dir, capsys):
    from ocpkit.benchmarks.qp import bench_qp

    rows = bench_qp(["./cartpole.py:CartPole"], horizons=(20,), samples=1, out=lambda *_: None)
    assert {r["problem"] for r in rows} == {"./cartpole.py:CartPole"} and len(rows) == 4


def test_problem_hooks_are_public_and_checked():
    class Incomplete(Problem):
        name = "incomplete"

    with pytest.raises(NotImplementedError, match="dynamics"):
        Incomplete().model()

    class Wrong(Incomplete):
        def dynamics(self, error):
            return "not a model"

    with pytest.raises(TypeError, match="must return an ocpkit.Model"):
        Wrong().plant()
    assert not hasattr(Problem, "_model")
    assert Model.__name__ == "Model"

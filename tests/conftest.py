"""Shared fixtures: seeded random stable LTI systems as ocpkit Models; the docs' examples (the user-declared
cart-pole, the tutorials' scripts run as written)."""

import runpy
import shutil
import sys
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from ocpkit.model.dynamics import Model


def random_lti(seed: int, n: int = 4, m: int = 2) -> Model:
    """A seeded random continuous LTI system ẋ = A x + B u + w with stable (negative real part) A."""
    rng = np.random.default_rng(seed)
    M = rng.normal(size=(n, n))
    A = M - (np.abs(np.linalg.eigvals(M)).max() + 0.5) * np.eye(n)
    B = rng.normal(size=(n, m))
    w = 0.1 * rng.normal(size=n)
    x, u = ca.SX.sym("x", n), ca.SX.sym("u", m)
    return Model(f"lti{seed}", x, u, ca.mtimes(ca.DM(A), x) + ca.mtimes(ca.DM(B), u) + ca.DM(w))


@pytest.fixture
def lti():
    return random_lti


def smooth_basis(T: int, p: int) -> np.ndarray:
    """A dense "learned" T×p input basis: normalized Gaussian bumps (every row a convex combination of all p knots)."""
    t, c = np.linspace(0, 1, T)[:, None], np.linspace(0, 1, p)[None]
    B = np.exp(-0.5 * ((t - c) * p) ** 2)
    return B / B.sum(axis=1, keepdims=True)


def pytest_addoption(parser):
    parser.addoption(
        "--arch",
        default="cpu",
        choices=("cpu", "cuda"),
        help="Taichi arch of the rollout, translation and EMPC tests (default cpu)",
    )


@pytest.fixture(scope="session")
def taichi_arch(request):
    """Start Taichi on the arch given by `pytest --arch` (the process keeps it)."""
    from ocpkit.codegen.kernels import runtime

    return runtime.init(request.config.getoption("arch"))


ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"  # the tutorials' complete scripts, shown in the docs by inclusion
DOCS = ROOT / "docs"


def run_example(name: str, *args) -> None:
    """Run ``examples/NAME`` as ``python NAME ARGS`` does, in this process (what it prints goes to capsys)."""
    argv = sys.argv
    sys.argv = [str(EXAMPLES / name), *map(str, args)]
    try:
        runpy.run_path(sys.argv[0], run_name="__main__")
    finally:
        sys.argv = argv


@pytest.fixture
def cartpole_dir(tmp_path, monkeypatch):
    """A folder holding the tutorial's cartpole.py ("Declare your own problem"), as the working directory."""
    shutil.copy(EXAMPLES / "cartpole.py", tmp_path / "cartpole.py")
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.fixture
def cartpole(cartpole_dir):
    """The tutorial's user-declared cart-pole problem."""
    from ocpkit.problems import make

    return make("./cartpole.py:CartPole")

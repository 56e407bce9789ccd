"""Shared fixtures: seeded random stable LTI systems as ocpkit Models; the README's user-declared cart-pole."""

import re
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


README = Path(__file__).resolve().parents[1] / "README.md"


def readme_block(heading: str) -> str:
    """The first Python code block of the README section ``heading``, as written there."""
    text = README.read_text()
    return re.search(r"```python\n(.*?)```", text[text.index(f"## {heading}") :], re.S).group(1)


@pytest.fixture
def cartpole_dir(tmp_path, monkeypatch):
    """A folder holding the README's cartpole.py (section "Declare your own problem"), as the working directory."""
    (tmp_path / "cartpole.py").write_text(readme_block("Declare your own problem"))
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.fixture
def cartpole(cartpole_dir):
    """The README's user-declared cart-pole problem."""
    from ocpkit.problems import make

    return make("./cartpole.py:CartPole")

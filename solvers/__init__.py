"""MPC solvers by name: "qp" (LinearMPC), "ipopt" (NonlinearMPC), "empc", "cem", "mppi" (sampling on Taichi)."""
from __future__ import annotations

from importlib import import_module

from ocpkit.controller import Controller
from ocpkit.ocp import OCP

# solver name -> module defining it (imported only when used: the sampling solvers start Taichi)
_SOLVERS = {"qp": "qp", "ipopt": "nlp", "empc": "empc", "cem": "cem", "mppi": "mppi"}


def names() -> list[str]:
    """The registered solver names."""
    return sorted(_SOLVERS)


def make(name: str, ocp: OCP, **options) -> Controller:
    """A controller for ``ocp`` by solver name, with solver-specific options."""
    if name not in _SOLVERS:
        raise ValueError(f"unknown solver {name!r}; known: {', '.join(names())}")
    return import_module(f"ocpkit.solvers.{_SOLVERS[name]}").SOLVERS[name](ocp, **options)

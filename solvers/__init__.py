"""MPC solvers by name: "qp" (LinearMPC), and the others as they are registered."""
from __future__ import annotations

from importlib import import_module

from ocpkit.controller import Controller
from ocpkit.ocp import OCP

_MODULES = ("qp",)


def _registry() -> dict:
    entries = {}
    for module in _MODULES:
        entries.update(import_module(f"ocpkit.solvers.{module}").SOLVERS)
    return entries


def names() -> list[str]:
    """The registered solver names."""
    return sorted(_registry())


def make(name: str, ocp: OCP, **options) -> Controller:
    """A controller for ``ocp`` by solver name, with solver-specific options."""
    solvers = _registry()
    if name not in solvers:
        raise ValueError(f"unknown solver {name!r}; known: {', '.join(names())}")
    return solvers[name](ocp, **options)

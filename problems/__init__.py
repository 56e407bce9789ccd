"""The paper's systems, by name: "pendulum", "pendulum:linear", "nlink:7", "puma560", "baxter"."""
from __future__ import annotations

from importlib import import_module

from ocpkit.problem import Problem

_MODULES = ("pendulum",)


def _registry() -> dict:
    entries = {}
    for module in _MODULES:
        entries.update(import_module(f"ocpkit.problems.{module}").REGISTRY)
    return entries


def names() -> list[str]:
    """The registered problem families."""
    return sorted(_registry())


def make(name: str) -> Problem:
    """A problem by registry name, e.g. "pendulum:linear" or "nlink:7" (family, then an optional argument)."""
    if not isinstance(name, str):
        raise TypeError(f"problem name must be a string, got {name!r}")
    family, _, arg = name.partition(":")
    factories = _registry()
    if family not in factories:
        raise ValueError(f"unknown problem {name!r}; known: {', '.join(names())}")
    return factories[family](arg or None)

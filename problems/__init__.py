"""The paper's systems, by name: "pendulum", "pendulum:linear", "nlink:7", "puma560", "baxter"."""
from __future__ import annotations

from importlib import import_module

from ocpkit.problem import Problem

# family -> module defining it (imported only when the family is used)
_FAMILIES = {"pendulum": "pendulum", "nlink": "nlink", "puma560": "puma560", "baxter": "baxter"}


def names() -> list[str]:
    """The registered problem families."""
    return sorted(_FAMILIES)


def make(name: str) -> Problem:
    """A problem by registry name, e.g. "pendulum:linear" or "nlink:7" (family, then an optional argument)."""
    if not isinstance(name, str):
        raise TypeError(f"problem name must be a string, got {name!r}")
    family, _, arg = name.partition(":")
    if family not in _FAMILIES:
        raise ValueError(f"unknown problem {name!r}; known: {', '.join(names())}")
    return import_module(f"ocpkit.problems.{_FAMILIES[family]}").REGISTRY[family](arg or None)

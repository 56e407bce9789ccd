"""The paper's experiments as studies, by name; `reproduce` runs them all and writes a report."""

from __future__ import annotations

from importlib import import_module

NAMES = (
    "knots",
    "horizon",
    "robustness",
    "solve_times",
    "comparison",
    "keepout",
    "baxter",
    "reach",
    "tracking",
    "nonconvex",
)


def get(name: str):
    """A study module (with ``study(size)``, ``report(df, out_dir)``, ``NAME``, ``TITLE``) by name."""
    if name not in NAMES:
        raise ValueError(f"unknown study {name!r}; known: {', '.join(NAMES)}")
    return import_module(f"ocpkit.studies.{name}")

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
# The studies of the paper's own experiments (Sections III-VII); the others go beyond it. `reproduce --only paper`.
PAPER = ("knots", "horizon", "robustness", "solve_times", "comparison", "baxter")


def chosen(only=None) -> tuple:
    """The studies ``only`` names (study names, or "paper" for :data:`PAPER`) in the report's order; all if None."""
    if only is None:
        return NAMES
    wanted = set()
    for name in only:
        if name != "paper" and name not in NAMES:
            raise ValueError(f"unknown study {name!r}; known: {', '.join(NAMES)} or paper")
        wanted.update(PAPER if name == "paper" else (name,))
    return tuple(name for name in NAMES if name in wanted)


def get(name: str):
    """A study module (with ``study(size)``, ``report(df, out_dir)``, ``NAME``, ``TITLE``) by name."""
    if name not in NAMES:
        raise ValueError(f"unknown study {name!r}; known: {', '.join(NAMES)}")
    return import_module(f"ocpkit.studies.{name}")

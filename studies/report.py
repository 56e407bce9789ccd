"""Markdown pieces of a study report: sections with figures, tables, how the data were taken, and the
paper's claims checked against them."""
from __future__ import annotations

import numbers
import os
from dataclasses import dataclass

from ocpkit.plots import number


def markdown_table(df) -> str:
    """A pandas DataFrame as a Markdown table (index as the first column), numbers as :func:`ocpkit.plots.number`
    prints them."""
    def cell(v):
        return number(v) if isinstance(v, numbers.Number) and not isinstance(v, bool) else str(v)

    head = [str(df.index.name or "")] + [str(c) for c in df.columns]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for idx, row in df.iterrows():
        lines.append("| " + " | ".join([cell(idx)] + [cell(v) for v in row.values]) + " |")
    return "\n".join(lines)


HELD, NOT_HELD, NOT_TESTED = "held", "not held", "not tested at this size"


@dataclass(frozen=True)
class Claim:
    """One of the paper's claims, what our data show, and the verdict computed from them."""

    claim: str
    ours: str
    verdict: str


def verdict(holds) -> str:
    """HELD, NOT_HELD, or NOT_TESTED where ``holds`` is None (the data to decide are not in this run)."""
    return NOT_TESTED if holds is None else HELD if holds else NOT_HELD


def trials_line(df, axes: dict) -> str:
    """How many trials stand behind the section: ``axes`` name → number of values, e.g. problems, seeds."""
    ok = int((df["status"] == "ok").sum())
    grid = " × ".join(f"{n} {name}" for name, n in axes.items())
    return f"{ok} of {len(df)} trials succeeded ({grid})."


def timing_context(df) -> str:
    """The machine load while timing: the 1-min load average at the end of each trial (median, max)."""
    if "load" not in df or df["load"].isna().all():
        return "Machine load while timing: not recorded."
    load = df["load"].dropna()
    return (f"Machine load while timing: 1-min load average at the end of each trial median {number(load.median(), 2)}, "
            f"max {number(load.max(), 2)} on {os.cpu_count()} CPUs; BLAS/OpenMP threads limited to 1 inside each "
            "controller step; timings are medians of per-step wall times.")


def section(title: str, figures, tables: dict, *, trials: str, claims: list, notes=()) -> str:
    """A report section: title, the trials behind it, figures (PNG paths relative to the report), captioned
    tables, notes, and the claim checks it ends with."""
    parts = [f"## {title}", "", trials, ""]
    parts += [f"![{f.stem}]({f.name})" for f in figures]
    for caption, table in tables.items():
        parts += ["", f"{caption}:", "", table]
    if notes:
        parts += [""] + [f"- {n}" for n in notes]
    parts += ["", "Claim checks:", "", "| paper's claim | here | verdict |", "|---|---|---|"]
    parts += [f"| {c.claim} | {c.ours} | {c.verdict} |" for c in claims] or ["| – | no claim of the paper applies | – |"]
    return "\n".join(parts) + "\n"

"""Markdown pieces of a study report: sections with figures, tables, how the data were taken, and the
paper's claims checked against them."""

from __future__ import annotations

import numbers
import os
from dataclasses import dataclass

from ocpkit.sim.plots import number
from ocpkit.sim.simulate import summed_tallies


def markdown_table(df) -> str:
    """A pandas DataFrame as a Markdown table (index as the first column), numbers as :func:`ocpkit.sim.plots.number`
    prints them."""

    def cell(v):
        return number(v) if isinstance(v, numbers.Number) and not isinstance(v, bool) else str(v)

    head = [str(df.index.name or "")] + [str(c) for c in df.columns]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for idx, row in df.iterrows():
        lines.append("| " + " | ".join([cell(idx)] + [cell(v) for v in row.values]) + " |")
    return "\n".join(lines)


@dataclass(frozen=True)
class Claim:
    """One of the paper's claims, the paper's own figure where it states one, what our data show, the evidence the
    verdict rests on (a median, its interval and n: :mod:`ocpkit.studies.evidence`) and the verdict."""

    claim: str
    ours: str
    verdict: str
    evidence: str = ""
    paper: str = ""


ANSWERED = (
    "How the steps were answered (what answered them, summed over the runs; fallback steps by cause; EMPC's child "
    "win rate, median and range over runs)"
)


def answered(ok, by: str = "controller") -> str:
    """How each controller's steps were answered, as a Markdown table: runs, what answered the steps (each step's
    path, summed over the runs; "not recorded" for trials stored before 0.17.0), fallback steps and their causes (the
    failed step's status, summed over the runs), and EMPC's child win rate (the share of generations whose best
    candidate was a bred child rather than a carried-over parent or seed: 0 % means the plan was the seed's)."""
    import pandas as pd

    rows = {}
    for name, g in ok.groupby(by, sort=False):
        paths = g.get("paths", pd.Series(dtype=object)).dropna()
        wins = g["child_win_rate"].dropna() if "child_win_rate" in g else pd.Series(dtype=float)
        rows[name] = {
            "runs": len(g),
            "steps answered by": summed_tallies(paths) if len(paths) else "not recorded",
            "fallback steps": int(g["fallbacks"].sum()),
            "causes": summed_tallies(g.get("fallback_causes", pd.Series(dtype=object)).dropna()),
            "child win rate [%]": (
                f"{number(100 * wins.median(), 3)} ({number(100 * wins.min(), 3)}–{number(100 * wins.max(), 3)})"
            )
            if len(wins)
            else "–",
        }
    table = pd.DataFrame.from_dict(rows, orient="index")
    table.index.name = by
    return markdown_table(table)


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
    return (
        f"Machine load while timing: 1-min load average at the end of each trial median "
        f"{number(load.median(), 2)}, max {number(load.max(), 2)} on {os.cpu_count()} CPUs; BLAS/OpenMP threads "
        "limited to 1 inside each controller step; timings are medians of per-step wall times."
    )


def per_seed_section(heading: str, rows, out_dir) -> str:
    """A study's per-seed values in its verdicts' units (``rows``: a study module's ``per_seed_rows(df)``, indexed by
    its configuration and ``seed``, one column per metric) as Markdown, one table per metric (rows: configurations,
    columns: seeds); written in full precision to ``out_dir``/<heading>_per_seed.csv, beside the raw values of
    every trial (<heading>.csv, written by the runner)."""
    if rows.empty:
        return ""
    csv = f"{heading}_per_seed.csv"
    rows.to_csv(os.path.join(out_dir, csv))
    parts = [
        f"### {heading}: per seed, in the verdicts' units",
        "",
        f"Full precision: [{csv}]({csv}); every trial's raw values (actual costs, times): "
        f"[{heading}.csv]({heading}.csv).",
    ]
    axes = [n for n in rows.index.names if n != "seed"]
    for metric in rows.columns:
        table = rows[metric].unstack("seed")
        table.index = [" / ".join(map(str, i)) if isinstance(i, tuple) else str(i) for i in table.index]
        table.index.name = " / ".join(axes)
        table.columns = [f"seed {c}" for c in table.columns]
        parts += ["", f"{metric}:", "", markdown_table(table)]
    return "\n".join(parts) + "\n"


def section(title: str, figures, tables: dict, *, trials: str, claims: list, notes=()) -> str:
    """A report section: title, the trials behind it, figures (PNG paths relative to the report), captioned
    tables, notes, and the claim checks it ends with."""
    parts = [f"## {title}", "", trials, ""]
    parts += [f"![{f.stem}]({f.name})" for f in figures]
    for caption, table in tables.items():
        parts += ["", f"{caption}:", "", table]
    if notes:
        parts += [""] + [f"- {n}" for n in notes]
    parts += ["", "Claim checks:", "", "| paper's claim | paper | here | evidence | verdict |", "|---|---|---|---|---|"]
    parts += [f"| {c.claim} | {c.paper or '–'} | {c.ours} | {c.evidence or '–'} | {c.verdict} |" for c in claims] or [
        "| – | – | no claim of the paper applies | – | – |"
    ]
    return "\n".join(parts) + "\n"

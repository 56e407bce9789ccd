"""Solve times of parameterized convex-solver MPC (paper Section IV-F/G, Figs. 7–10).

N-link robots (1…13 links), horizons 50 and 100: the large matrix (sparse) and small matrix (condensed)
formulations, each traditional (p = T) and parameterized with 5 knot points, solved by OSQP as in the
paper. Each trial is one formulation on one robot: from N seeded random start/goal pairs, one cold MPC
solve each (nothing is applied to a plant), timing the optimizer ("optimization solve time",
``Solution.times["solve"]``) and the whole MPC step ("MPC solve time", ``times["total"]``: linearization,
building P, q, A, l, u, and the optimization).
"""

from __future__ import annotations

import os
import time

import numpy as np
import pandas as pd

from ocpkit import problems, solvers
from ocpkit.sim import plots
from ocpkit._checks import choice, integer, positive
from ocpkit.runs.study import Study, grid
from ocpkit.sim.plots import number
from ocpkit.studies.evidence import HELD, INCONCLUSIVE, NOT_HELD, combine, decide, median_interval, quartiles, timing
from ocpkit.studies.report import Claim, markdown_table, section, timing_context, trials_line

NAME = "solve_times"
TITLE = "Solve times of the convex formulations vs number of links (Figs. 7–10)"
HORIZONS = (50, 100)
KNOTS = 5
FORMS = ("sparse", "condensed")
NOT_REDUCED = 0.1  # "does not reduce": faster by less than this fraction
HARDLY = 1.5  # "hardly depends on the horizon": twice the horizon, at most this factor in time
HARDLY_SOURCE = "ours: the paper gives no number for 'hardly'"
# "max_dense_vars": the traditional small matrix QP has links × T dense variables and its OSQP solve grows
# steeply with them; quick skips it above this size (600: 7 links at T = 100 and 13 at T = 50, 700 and 650
# variables, took 35 and 33 s of the quick study's 104, a tenth of `reproduce --quick`). None: no skip.
# "time_budget": seconds of timed solves a trial may take before it stops short of "states" (at least MIN_STATES
# solved); None: every state. The full size runs every formulation, and its dense traditional QPs took 7, 16 and
# 48 s a solve at 7, 10 and 13 links, T = 100 (2-core machine, load 4): 100 states each would take about 5 h of the
# study; with 300 s a trial, the grid took 2.3 h there (load 5, 14 trials stopped short).
MIN_STATES = 5
SIZES = {
    "quick": {"links": [1, 3, 7, 13], "states": 20, "qp": "osqp", "max_dense_vars": 600, "time_budget": None},
    "full": {"links": list(range(1, 14)), "states": 100, "qp": "osqp", "max_dense_vars": None, "time_budget": 300.0},
}


def trial(
    links: int,
    horizon: int,
    form: str,
    knots: int | None,
    qp: str,
    states: int,
    seed: int,
    time_budget: float | None = None,
) -> dict:
    """Time one MPC formulation from ``states`` random start/goal pairs, one cold solve each.

    Pair i is ``problem.sample(seed * states + i)``, so every formulation sees the same states (a shorter trial
    solves a prefix of them: compare on the common prefix). One untimed solve first keeps one-off costs (building
    CasADi functions, importing the QP backend) out. ``time_budget``: stop once the timed solves have taken this
    many seconds, with at least :data:`MIN_STATES` solved (None: every state).
    """
    states = integer(states, "states", 1)
    time_budget = None if time_budget is None else positive(time_budget, "time_budget")
    pb = problems.make(f"nlink:{integer(links, 'links', 1)}")
    # no step budget: the slow formulations' times are what the figures show (trials have their own timeout)
    ctrl = solvers.make("qp", pb.ocp(knots=knots, horizon=horizon), form=form, qp=qp, time_limit=float("inf"))
    pairs = [pb.sample(seed * states + i) for i in range(states)]
    ctrl.solve(*pairs[0])
    sols, start = [], time.perf_counter()
    for x0, goal in pairs:
        if time_budget is not None and len(sols) >= MIN_STATES and time.perf_counter() - start >= time_budget:
            break
        ctrl.reset()  # a fresh problem: no warm start from another state
        sols.append(ctrl.solve(x0, goal))
    solve = np.array([s.times["solve"] for s in sols])
    total = np.array([s.times["total"] for s in sols])
    return {
        **quartiles("solve", solve),
        **quartiles("total", total),
        "model_median": float(np.median([s.times["model"] for s in sols])),
        "build_median": float(np.median([s.times["build"] for s in sols])),
        "failures": sum(not s.ok for s in sols),
        "solved": len(sols),
        "solve_times": solve,
        "total_times": total,
        "load": os.getloadavg()[0],
    }


def study(size: str) -> Study:
    choice(size, tuple(SIZES), "size")
    s = SIZES[size]
    trials = grid(
        links=s["links"],
        horizon=list(HORIZONS),
        form=list(FORMS),
        knots=[None, KNOTS],
        qp=s["qp"],
        states=s["states"],
        time_budget=s["time_budget"],
        seeds=1,
    )
    return Study(NAME, trial, [t for t in trials if not _skipped(t, s["max_dense_vars"])])


def _skipped(t: dict, max_dense_vars: int | None) -> bool:
    return (
        max_dense_vars is not None
        and t["form"] == "condensed"
        and t["knots"] is None
        and t["links"] * t["horizon"] > max_dense_vars
    )


def label(form: str, knots) -> str:
    """The formulation in the paper's words."""
    size = "large matrix" if form == "sparse" else "small matrix"
    return f"{size} ({form}), " + ("traditional" if knots is None or knots != knots else f"{int(knots)} knots")


def report(df, out_dir) -> str:
    ok = df[df["status"] == "ok"].copy()
    trials = trials_line(
        df, {"robots": df["links"].nunique(), "horizons": df["horizon"].nunique(), "formulations": len(FORMS) * 2}
    )
    if ok.empty:
        return section(TITLE, [], {}, trials=trials, claims=[], notes=["No trial succeeded."])
    ok["formulation"] = [label(f, k) for f, k in zip(ok["form"], ok["knots"])]
    states = int(ok["states"].iloc[0])
    up_to = "" if (_solved(ok) == ok["states"]).all() else "up to "  # a time budget stopped some trials short
    figs, tables = [], {}
    for horizon, g in ok.groupby("horizon"):
        for metric, what, fig in (
            ("solve_median", "optimization solve time", "solve"),
            ("total_median", "MPC solve time", "total"),
        ):
            med = g.pivot_table(index="links", columns="formulation", values=metric, aggfunc="median") * 1e3
            q1, q3 = (
                g.pivot_table(
                    index="links", columns="formulation", values=metric.replace("median", q), aggfunc="median"
                ).reindex(index=med.index, columns=med.columns)
                * 1e3
                for q in ("q1", "q3")
            )
            figs.append(
                plots.lines(
                    med.index,
                    {c: med[c].values for c in med.columns},
                    out_dir / f"solve_times_{fig}_T{horizon}",
                    xlabel="number of links",
                    ylabel=f"median {what} [ms]",
                    log=True,
                    counts=True,
                    spread={c: (q1[c].values, q3[c].values) for c in med.columns},
                    spread_label=f"shaded: quartiles over each point's states ({up_to}{states})",
                    title=f"Median {what}, horizon {horizon} ({up_to}{states} cold solves each)",
                )
            )
            tables[f"Median {what} over {up_to}{states} cold solves [ms], horizon {horizon}"] = markdown_table(med)
    return section(
        TITLE,
        figs,
        tables,
        trials=trials + " " + timing_context(ok),
        notes=_notes(ok, df),
        claims=claims(ok, df, out_dir),
    )


def per_seed_rows(df):
    """Each formulation's median times per (links, T) and its median optimization time over the parameterized
    small matrix's, for the report's appendix (one seed: :data:`SIZES`' states are its samples; the verdicts'
    per-state ratios come from the stored time arrays)."""
    ok = df[df["status"] == "ok"].copy()
    ok["formulation"] = [label(f, k) for f, k in zip(ok["form"], ok["knots"])]
    rows = ok.set_index(["links", "horizon", "formulation", "seed"])
    best = rows.xs(label("condensed", KNOTS), level="formulation")["solve_median"]
    keys = rows.index.droplevel("formulation")
    return pd.DataFrame(
        {
            "median optimization solve time [ms]": 1e3 * rows["solve_median"],
            "median MPC solve time [ms]": 1e3 * rows["total_median"],
            "optimization time / the parameterized small matrix's": rows["solve_median"].to_numpy()
            / best.reindex(keys).to_numpy(),
        }
    )


def _notes(ok, df) -> list:
    """What was skipped or failed, and what the times include."""
    notes = []
    have = {(r.links, r.horizon) for r in df[(df["form"] == "condensed") & df["knots"].isna()].itertuples()}
    missing = sorted({(r.links, r.horizon) for r in df.itertuples()} - have)
    if missing:
        notes.append(
            "Not run (too slow for this size): small matrix traditional at "
            + ", ".join(f"{l} links, T = {h}" for l, h in missing)
            + "."
        )
    model = ok.groupby("links")["model_median"].median() * 1e3
    notes.append(
        f"The MPC solve time includes the linearization (median {number(model.min(), 2)}–"
        f"{number(model.max(), 2)} ms from the fewest to the most links), the same for every formulation."
    )
    short = ok[_solved(ok) < ok["states"]]
    if not short.empty:
        notes.append(
            f"Stopped by the time budget ({number(short['time_budget'].iloc[0])} s of solves a trial) before "
            f"{int(short['states'].iloc[0])} states, so compared with the others on the states it solved: "
            + ", ".join(
                f"{label(r.form, r.knots)} at {r.links} links, T = {r.horizon} ({int(n)} states)"
                for r, n in zip(short.itertuples(), _solved(short))
            )
            + "."
        )
    notes.append(
        f"{int(ok['failures'].sum())} of {int(_solved(ok).sum())} solves did not return success "
        "(their times are included)."
    )
    return notes


def _solved(ok) -> pd.Series:
    """States each trial solved: all of ``states`` unless a time budget stopped it (trials stored before the budget
    existed solved them all)."""
    return ok["solved"].fillna(ok["states"]) if "solved" in ok else ok["states"]


def _paired(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-state ratio a / b over the states both solved (every trial solves a prefix of the same states)."""
    n = min(len(a), len(b))
    return a[:n] / b[:n]


def claims(ok, df, out_dir) -> list:
    """The paper's Section IV-G claims, each decided per (links, T) case on the per-state time ratios (every
    formulation solved the same states), and marked unreliable where the machine was overloaded."""
    times = _per_state(ok, df, out_dir)
    small, large = label("condensed", KNOTS), label("sparse", KNOTS)
    loads = ok["load"]
    out = []

    def compare(a, b, metric, threshold=1.0, claimed="<"):
        """{(links, T): (verdict, interval)} of the per-state ratio a / b."""
        result = {}
        for case, by_form in times[metric].items():
            if a in by_form and b in by_form:
                interval = median_interval(_paired(by_form[a], by_form[b]))
                result[case] = (decide(interval, threshold, claimed), interval)
        return result

    def text(result) -> str:
        return "; ".join(f"{links}/{T}: {i.text(3)}" for (links, T), (_, i) in sorted(result.items())) or "not run"

    def closest(results) -> str:
        """The rival that decides the case: the one whose interval reaches highest (nearest to refuting "< 1")."""
        rival, (_, interval) = max(results.items(), key=lambda kv: kv[1][1].high)
        return f"vs {rival}: {interval.text(3)}"

    others = sorted({f for by_form in times["solve"].values() for f in by_form} - {small})
    lowest = {}  # (links, T) -> {other formulation: (verdict, interval)}
    for other in others:
        for case, result in compare(small, other, "solve").items():
            lowest.setdefault(case, {})[other] = result
    out.append(
        Claim(
            "The parameterized small matrix formulation has the lowest optimization solve time",
            f"per state, its time / each other formulation's < 1, in every (links, T) case ({len(lowest)} cases)",
            timing(combine(v for r in lowest.values() for v, _ in r.values()), loads),
            "deciding rival per case (the interval reaching highest): "
            + "; ".join(f"{l}/{T} {closest(r)}" for (l, T), r in sorted(lowest.items())),
        )
    )
    result = compare(label("condensed", None), label("sparse", None), "solve")
    out.append(
        Claim(
            "The traditional small matrix formulation beats the large one on small problems only",
            "per state, small / large matrix time (traditional) < 1 at the fewest links and not at the most",
            timing(_small_only(result), loads),
            text(result),
        )
    )
    result = compare(large, label("sparse", None), "solve", threshold=1 - NOT_REDUCED, claimed=">=")
    out.append(
        Claim(
            "Parameterizing the large matrix formulation does not reduce its optimization solve time",
            f"per state, parameterized / traditional time ≥ {number(1 - NOT_REDUCED)} (less than "
            f"{number(100 * NOT_REDUCED)} % faster; ours: the paper gives no margin)",
            timing(combine(v for v, _ in result.values()), loads),
            text(result),
        )
    )
    for form in FORMS:
        result = compare(label(form, KNOTS), label(form, None), "total")
        out.append(
            Claim(
                f"Parameterization reduces the MPC solve time of the {form} formulation",
                "per state, parameterized / traditional MPC solve time < 1",
                timing(combine(v for v, _ in result.values()), loads),
                text(result),
            )
        )
    by_links = {}
    for (links, T), by_form in times["solve"].items():
        if small in by_form:
            by_links.setdefault(links, {})[T] = by_form[small]
    result = {
        links: median_interval(_paired(t[HORIZONS[1]], t[HORIZONS[0]]))
        for links, t in sorted(by_links.items())
        if set(HORIZONS) <= set(t)
    }
    if result:
        out.append(
            Claim(
                "The parameterized small matrix optimization time hardly depends on the horizon",
                f"per state, time at T = {HORIZONS[1]} / at T = {HORIZONS[0]} ≤ {number(HARDLY)} ({HARDLY_SOURCE})",
                timing(combine(decide(i, HARDLY, "<=") for i in result.values()), loads),
                "; ".join(f"{links} links: {i.text(3)}" for links, i in result.items()),
            )
        )
    return out


def _per_state(ok, df, out_dir) -> dict:
    """{"solve"/"total": {(links, T): {formulation: per-state times}}} from the stored arrays."""
    from ocpkit.studies.comparison import row_arrays

    times = {"solve": {}, "total": {}}
    for row in ok.index:
        arrays = row_arrays(df, row, out_dir)
        case = (int(ok.at[row, "links"]), int(ok.at[row, "horizon"]))
        for metric in times:
            times[metric].setdefault(case, {})[ok.at[row, "formulation"]] = np.asarray(arrays[f"{metric}_times"])
    return times


def _small_only(result) -> str:
    """Held when the first formulation is faster at the fewest links and not at the most (per horizon)."""
    verdicts = []
    for T in sorted({T for _, T in result}):
        cases = sorted(c for c in result if c[1] == T)
        if len(cases) < 2:
            continue
        first, last = result[cases[0]][0], result[cases[-1]][0]
        verdicts.append(
            HELD
            if first == HELD and last == NOT_HELD
            else NOT_HELD
            if first == NOT_HELD or last == HELD
            else INCONCLUSIVE
        )
    return combine(verdicts)

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

import numpy as np

from ocpkit import plots, problems, solvers
from ocpkit._checks import choice, integer
from ocpkit.study import Study, grid
from ocpkit.plots import number
from ocpkit.studies.report import Claim, markdown_table, section, timing_context, trials_line, verdict

NAME = "solve_times"
TITLE = "Solve times of the convex formulations vs number of links (Figs. 7–10)"
HORIZONS = (50, 100)
KNOTS = 5
FORMS = ("sparse", "condensed")
# "max_dense_vars": the traditional small matrix QP has links × T dense variables and its OSQP solve grows
# steeply (measured on 2 cores: 0.3–0.5 s at 7 links, T = 50; 2.5–4 s at 7 links, T = 100; 18–36 s at
# 13 links, T = 100); quick skips it above this size. None: no skip.
SIZES = {"quick": {"links": [1, 3, 7, 13], "states": 20, "qp": "osqp", "max_dense_vars": 700},
         "full": {"links": list(range(1, 14)), "states": 100, "qp": "osqp", "max_dense_vars": None}}


def trial(links: int, horizon: int, form: str, knots: int | None, qp: str, states: int, seed: int) -> dict:
    """Time one MPC formulation from ``states`` random start/goal pairs, one cold solve each.

    Pair i is ``problem.sample(seed * states + i)``, so every formulation sees the same states. One
    untimed solve first keeps one-off costs (building CasADi functions, importing the QP backend) out.
    """
    states = integer(states, "states", 1)
    pb = problems.make(f"nlink:{integer(links, 'links', 1)}")
    # no step budget: the slow formulations' times are what the figures show (trials have their own timeout)
    ctrl = solvers.make("qp", pb.ocp(knots=knots, horizon=horizon), form=form, qp=qp, time_limit=float("inf"))
    pairs = [pb.sample(seed * states + i) for i in range(states)]
    ctrl.solve(*pairs[0])
    sols = []
    for x0, goal in pairs:
        ctrl.reset()  # a fresh problem: no warm start from another state
        sols.append(ctrl.solve(x0, goal))
    solve = np.array([s.times["solve"] for s in sols])
    total = np.array([s.times["total"] for s in sols])
    return {**quartiles("solve", solve), **quartiles("total", total),
            "model_median": float(np.median([s.times["model"] for s in sols])),
            "build_median": float(np.median([s.times["build"] for s in sols])),
            "failures": sum(not s.ok for s in sols), "solve_times": solve, "total_times": total,
            "load": os.getloadavg()[0]}


def quartiles(name: str, values) -> dict:
    """``{name}_median``, ``{name}_q1`` and ``{name}_q3`` of ``values`` (seconds)."""
    q1, median, q3 = np.percentile(values, [25, 50, 75])
    return {f"{name}_median": float(median), f"{name}_q1": float(q1), f"{name}_q3": float(q3)}


def study(size: str) -> Study:
    choice(size, tuple(SIZES), "size")
    s = SIZES[size]
    trials = grid(links=s["links"], horizon=list(HORIZONS), form=list(FORMS), knots=[None, KNOTS], qp=s["qp"],
                  states=s["states"], seeds=1)
    return Study(NAME, trial, [t for t in trials if not _skipped(t, s["max_dense_vars"])])


def _skipped(t: dict, max_dense_vars: int | None) -> bool:
    return (max_dense_vars is not None and t["form"] == "condensed" and t["knots"] is None
            and t["links"] * t["horizon"] > max_dense_vars)


def label(form: str, knots) -> str:
    """The formulation in the paper's words."""
    size = "large matrix" if form == "sparse" else "small matrix"
    return f"{size} ({form}), " + ("traditional" if knots is None or knots != knots else f"{int(knots)} knots")


def report(df, out_dir) -> str:
    ok = df[df["status"] == "ok"].copy()
    trials = trials_line(df, {"robots": df["links"].nunique(), "horizons": df["horizon"].nunique(),
                              "formulations": len(FORMS) * 2})
    if ok.empty:
        return section(TITLE, [], {}, trials=trials, claims=[], notes=["No trial succeeded."])
    ok["formulation"] = [label(f, k) for f, k in zip(ok["form"], ok["knots"])]
    states = int(ok["states"].iloc[0])
    figs, tables = [], {}
    for horizon, g in ok.groupby("horizon"):
        for metric, what, fig in (("solve_median", "optimization solve time", "solve"),
                                  ("total_median", "MPC solve time", "total")):
            med = g.pivot_table(index="links", columns="formulation", values=metric, aggfunc="median") * 1e3
            figs.append(plots.lines(med.index, {c: med[c].values for c in med.columns},
                                    out_dir / f"solve_times_{fig}_T{horizon}", xlabel="number of links",
                                    ylabel=f"median {what} [ms]", log=True,
                                    title=f"Median {what}, horizon {horizon} ({states} cold solves each)"))
            tables[f"Median {what} over {states} cold solves [ms], horizon {horizon}"] = markdown_table(med)
    return section(TITLE, figs, tables, trials=trials + " " + timing_context(ok), notes=_notes(ok, df),
                   claims=claims(ok))


def _notes(ok, df) -> list:
    """What was skipped or failed, and what the times include."""
    notes = []
    have = {(r.links, r.horizon) for r in df[(df["form"] == "condensed") & df["knots"].isna()].itertuples()}
    missing = sorted({(r.links, r.horizon) for r in df.itertuples()} - have)
    if missing:
        notes.append("Not run (too slow for this size): small matrix traditional at "
                     + ", ".join(f"{l} links, T = {h}" for l, h in missing) + ".")
    model = ok.groupby("links")["model_median"].median() * 1e3
    notes.append(f"The MPC solve time includes the linearization (median {number(model.min(), 2)}–"
                 f"{number(model.max(), 2)} ms from the fewest to the most links), the same for every formulation.")
    notes.append(f"{int(ok['failures'].sum())} of {int(ok['states'].sum())} solves did not return success "
                 "(their times are included).")
    return notes


def claims(ok) -> list:
    """The paper's Section IV-G claims against the medians of this run."""
    opt = ok.pivot_table(index=["links", "horizon"], columns="formulation", values="solve_median")
    tot = ok.pivot_table(index=["links", "horizon"], columns="formulation", values="total_median")
    small, large = label("condensed", KNOTS), label("sparse", KNOTS)
    out = []
    fastest = opt.idxmin(axis=1) == small
    out.append(Claim("The parameterized small matrix formulation has the lowest optimization solve time",
                     f"lowest in {int(fastest.sum())} of {len(fastest)} (links, T) cases",
                     verdict(bool(fastest.all()))))
    wins, cases = _where(opt, label("condensed", None), label("sparse", None))
    # Held when it wins somewhere, and not on the largest robot compared.
    small_only = None if not cases else bool(wins and max(l for l, _ in wins) < max(l for l, _ in cases))
    out.append(Claim("The traditional small matrix formulation beats the large one on small problems only",
                     f"faster at {_cases(wins, cases)}", verdict(small_only)))
    wins, cases = _where(opt, large, label("sparse", None))
    out.append(Claim("Parameterizing the large matrix formulation does not reduce its optimization solve time",
                     f"reduces it at {_cases(wins, cases)}", verdict(None if not cases else not wins)))
    for form in FORMS:
        wins, cases = _where(tot, label(form, KNOTS), label(form, None))
        out.append(Claim(f"Parameterization reduces the MPC solve time of the {form} formulation",
                         f"reduces it at {_cases(wins, cases)}",
                         verdict(None if not cases else len(wins) == len(cases))))
    if small in opt:
        by_t = opt[small].unstack("horizon")
        if set(HORIZONS) <= set(by_t.columns):
            ratio = (by_t[HORIZONS[1]] / by_t[HORIZONS[0]]).dropna()
            out.append(Claim("The parameterized small matrix optimization time hardly depends on the horizon",
                             f"T = {HORIZONS[1]} / T = {HORIZONS[0]}: {number(ratio.min(), 3)}–"
                             f"{number(ratio.max(), 3)} over {len(ratio)} robots",
                             verdict(bool((ratio <= 1.5).all()))))
    return out


def _where(table, a: str, b: str):
    """The (links, T) cases where formulation ``a`` has the smaller median than ``b``, and all compared cases."""
    if a not in table or b not in table:
        return [], []
    both = table[[a, b]].dropna()
    return [case for case, faster in (both[a] < both[b]).items() if faster], list(both.index)


def _cases(wins, cases) -> str:
    if not cases:
        return "no case (not run)"
    return (f"{len(wins)} of {len(cases)} (links/T: "
            + (", ".join(f"{l}/{h}" for l, h in wins) or "none") + ")")

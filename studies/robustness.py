"""Robustness to model error (paper Section IV, Figs. 5–6, Tables I–II).

The controller's model has its inertial parameters multiplied by an error multiplier (pendulum: m and l;
Puma 560: the whole inertia matrix); the plant is exact. Normalized cost = actual cost with error / actual
cost of the same controller and start/goal without error. Overshoot and rise time show how conservative
each controller is. ``problems`` (specs) replace the paper's problems (``ocpkit study robustness --problem
./cartpole.py:CartPole``); the error multiplier then scales whatever that problem's ``dynamics(error)`` scales.
"""
from __future__ import annotations

from ocpkit import plots
from ocpkit.problems import filename
from ocpkit.study import Study, grid
from ocpkit.studies.closed_loop import grid_size, trial
from ocpkit.plots import number
from ocpkit.studies.report import Claim, markdown_table, section, trials_line, verdict

NAME = "robustness"
TITLE = "Robustness to model error (Figs. 5–6, Tables I–II)"
CONTROLLERS = [2, 4, 8, None]  # knot points; None = traditional MPC
SIZES = {"quick": {"errors": [0.5, 0.7, 0.9, 1.0, 1.1, 1.3, 1.5], "seeds": 8, "problems": ["pendulum", "puma560"]},
         "full": {"errors": [round(0.5 + 0.1 * i, 1) for i in range(11)], "seeds": 30,
                  "problems": ["pendulum", "puma560"]}}
USER_QUICK = {"errors": [0.7, 1.0, 1.3], "seeds": 2}


def study(size: str, problems=None) -> Study:
    """The study at ``size``; ``problems`` (specs) replace the paper's problems (quick: :data:`USER_QUICK`)."""
    s = grid_size(SIZES, size, problems, USER_QUICK)
    return Study(NAME, trial, grid(problem=s["problems"], knots=CONTROLLERS, error_multiplier=s["errors"], seeds=s["seeds"]))


def _label(knots) -> str:
    return "traditional" if knots != knots or knots is None else f"{int(knots)} knots"


def report(df, out_dir) -> str:
    ok = df[df["status"] == "ok"].copy()
    ok["controller"] = [_label(k) for k in ok["knots"]]
    base = ok[ok["error_multiplier"] == 1.0].set_index(["problem", "controller", "seed"])["actual_cost"]
    ok["normalized"] = ok["actual_cost"].values / base.loc[list(zip(ok["problem"], ok["controller"], ok["seed"]))].values
    figs, tables, notes, out = [], {}, [], []
    seeds = ok["seed"].nunique()
    for problem, g in ok.groupby("problem", sort=False):
        med = g.pivot_table(index="error_multiplier", columns="controller", values="normalized", aggfunc="median")
        figs.append(plots.lines(med.index, {c: med[c].values for c in med.columns},
                                out_dir / f"robustness_{filename(problem)}", xlabel="error multiplier",
                                ylabel="normalized cost (median)", log=True,
                                title=f"{problem}: sensitivity to model error ({seeds} seeds; reference: the same "
                                      "controller without error)"))
        tables[f"{problem}: median normalized cost over {seeds} seeds"] = markdown_table(med)
        steps = {}
        for metric, caption in (("overshoot", "median percent overshoot"), ("rise_time", "median rise time [s]")):
            t = g.pivot_table(index="error_multiplier", columns="controller", values=metric, aggfunc="median")
            tables[f"{problem}: {caption} over the runs with a step of at least 0.1 rad"] = markdown_table(t)
            steps[metric] = t
        excluded = int(g["overshoot"].isna().sum())
        q1, q3 = g["overshoot"].quantile([0.25, 0.75])
        outliers = int((g["overshoot"] > q3 + 1.5 * (q3 - q1)).sum())
        notes.append(f"{problem}: {excluded} of {len(g)} runs have no step of at least 0.1 rad (no overshoot or "
                     f"rise time); {outliers} overshoots lie beyond 1.5 IQR above the quartiles (medians resist them).")
        out += claims(problem, med, steps)
    trials = trials_line(df, {"problems": ok["problem"].nunique(), "controllers": ok["controller"].nunique(),
                              "error multipliers": ok["error_multiplier"].nunique(), "seeds": seeds})
    return section(TITLE, figs, tables, trials=trials, claims=out, notes=notes)


def claims(problem, med, steps) -> list:
    """The paper's Section IV claims for one problem against this run's medians."""
    out = []
    lo, hi = med.index.min(), med.index.max()
    if "traditional" in med and lo < 1 < hi:
        trad = med["traditional"]
        out.append(Claim(f"{problem}: underestimated inertia degrades the cost faster than overestimated",
                         f"traditional at error {number(lo)}: {number(trad[lo])}, at {number(hi)}: {number(trad[hi])}",
                         verdict(bool(trad[lo] > trad[hi]))))
        similar = [c for c in med.columns if c not in ("traditional", "2 knots")]
        if similar:
            spread = max(float((med[c] / trad).max()) for c in similar)
            spread = max(spread, max(float((trad / med[c]).max()) for c in similar))
            out.append(Claim(f"{problem}: with more than 2 knots the sensitivity is like traditional MPC's",
                             f"{', '.join(similar)} within a factor {number(spread, 3)} of traditional at every error",
                             verdict(spread <= 1.25)))
    over, rise = steps["overshoot"], steps["rise_time"]
    if {"2 knots", "traditional"} <= set(over.columns) and 1.0 in over.index:
        o2, ot = over.loc[1.0, "2 knots"], over.loc[1.0, "traditional"]
        r2, rt = rise.loc[1.0, "2 knots"], rise.loc[1.0, "traditional"]
        decided = None if any(v != v for v in (o2, ot, r2, rt)) else bool(o2 <= ot and r2 >= rt)
        out.append(Claim(f"{problem}: fewer knots are more conservative (less overshoot, longer rise time)",
                         f"at error 1, 2 knots vs traditional: overshoot {number(o2)} vs {number(ot)} %, rise "
                         f"{number(r2)} vs {number(rt)} s", verdict(decided)))
    if "traditional" in over and hi > 1 and 1.0 in over.index:
        a, b = over.loc[hi, "traditional"], over.loc[1.0, "traditional"]
        out.append(Claim(f"{problem}: overestimated inertia reduces overshoot", f"traditional, median overshoot at "
                         f"error {number(hi)}: {number(a)} % vs {number(b)} % at 1",
                         verdict(None if a != a or b != b else bool(a <= b))))
    return out

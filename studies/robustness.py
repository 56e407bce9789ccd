"""Robustness to model error (paper Section IV, Figs. 5–6, Tables I–II).

The controller's model has its inertial parameters multiplied by an error multiplier (pendulum: m and l;
Puma 560: the whole inertia matrix); the plant is exact. Normalized cost = actual cost with error / actual
cost of the same controller and start/goal without error. Overshoot and rise time show how conservative
each controller is. ``problems`` (specs) replace the paper's problems (``ocpkit study robustness --problem
./cartpole.py:CartPole``); the error multiplier then scales whatever that problem's ``dynamics(error)`` scales.
"""
from __future__ import annotations

import numpy as np

from ocpkit import plots
from ocpkit.problems import filename
from ocpkit.study import Study, grid
from ocpkit.studies.closed_loop import grid_size, trial
from ocpkit.plots import number
from ocpkit.studies.evidence import combine, decide, median_claim, median_interval, paired, series
from ocpkit.studies.report import Claim, markdown_table, section, timing_context, trials_line

NAME = "robustness"
TITLE = "Robustness to model error (Figs. 5–6, Tables I–II)"
CONTROLLERS = [2, 4, 8, None]  # knot points; None = traditional MPC
SIZES = {"quick": {"errors": [0.5, 0.7, 0.9, 1.0, 1.1, 1.3, 1.5], "seeds": 8, "problems": ["pendulum", "puma560"]},
         "full": {"errors": [round(0.5 + 0.1 * i, 1) for i in range(11)], "seeds": 30,
                  "problems": ["pendulum", "puma560"]}}
USER_QUICK = {"errors": [0.7, 1.0, 1.3], "seeds": 2}
# The paper's Tables I–II (inverted pendulum): percent overshoot and rise time [s] per error multiplier, for
# 2, 4 and 8 knots and traditional MPC, printed beside ours.
PAPER_COLUMNS = ("2 knots", "4 knots", "8 knots", "traditional")
PAPER_TABLES = {
    "overshoot": {0.5: (37.7, 40.2, 40.3, 43.5), 0.6: (26.5, 29.3, 29.3, 31.1), 0.7: (18.6, 19.8, 20.8, 22),
                  0.8: (12.1, 12.3, 13.8, 14.6), 0.9: (6.88, 6.78, 8.13, 8.64), 1.0: (3.05, 2.96, 3.89, 4.17),
                  1.1: (0.772, 0.732, 1.18, 1.3), 1.2: (0.0252, 0.0171, 0.0729, 0.0919), 1.3: (0, 0, 0, 0),
                  1.4: (0, 0, 0, 0), 1.5: (0, 0, 0, 0)},
    "rise_time": {0.5: (0.85, 0.41, 0.3, 0.28), 0.6: (0.65, 0.36, 0.3, 0.29), 0.7: (0.56, 0.35, 0.31, 0.3),
                  0.8: (0.54, 0.36, 0.32, 0.31), 0.9: (0.54, 0.38, 0.35, 0.34), 1.0: (0.59, 0.43, 0.39, 0.38),
                  1.1: (0.67, 0.5, 0.45, 0.44), 1.2: (0.78, 0.6, 0.55, 0.54), 1.3: (0.89, 0.71, 0.67, 0.66),
                  1.4: (0.96, 0.81, 0.77, 0.76), 1.5: (1.02, 0.88, 0.85, 0.84)}}
PAPER_PROBLEM = "pendulum"
SIMILAR = 1.25  # "like traditional MPC's": per-seed normalized costs within this factor of each other


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
        per_seed = {c: [g.loc[(g["controller"] == c) & (g["error_multiplier"] == e), "normalized"].values
                        for e in med.index] for c in med.columns}
        figs.append(plots.lines(med.index, per_seed, out_dir / f"robustness_{filename(problem)}",
                                xlabel="error multiplier (model inertia / true inertia)",
                                ylabel="normalized cost (ratio; line: median)", log=True,
                                spread_label=f"shaded: quartiles over {seeds} seeds",
                                references=[(1.0, "1: the same controller without error")],
                                title=f"{problem}: sensitivity to model error ({seeds} seeds)"))
        tables[f"{problem}: median normalized cost over {seeds} seeds"] = markdown_table(med)
        for metric, caption in (("overshoot", "median percent overshoot"), ("rise_time", "median rise time [s]")):
            t = g.pivot_table(index="error_multiplier", columns="controller", values=metric, aggfunc="median")
            if problem == PAPER_PROBLEM:
                t = with_paper(t, PAPER_TABLES[metric])
                caption += " (paper: its Table " + ("I" if metric == "overshoot" else "II") + ")"
            tables[f"{problem}: {caption} over the runs with a step of at least 0.1 rad"] = markdown_table(t)
        excluded = int(g["overshoot"].isna().sum())
        q1, q3 = g["overshoot"].quantile([0.25, 0.75])
        outliers = int((g["overshoot"] > q3 + 1.5 * (q3 - q1)).sum())
        notes.append(f"{problem}: {excluded} of {len(g)} runs have no step of at least 0.1 rad (no overshoot or "
                     f"rise time); {outliers} overshoots lie beyond 1.5 IQR above the quartiles (medians resist them).")
        out += claims(problem, g)
    trials = trials_line(df, {"problems": ok["problem"].nunique(), "controllers": ok["controller"].nunique(),
                              "error multipliers": ok["error_multiplier"].nunique(), "seeds": seeds})
    return section(TITLE, figs, tables, trials=trials + " " + timing_context(ok), claims=out, notes=notes)


def with_paper(table, paper: dict):
    """``table`` (rows: error multiplier, columns: controller) with the paper's value beside each of its columns."""
    out = table.copy()
    for j, c in enumerate(PAPER_COLUMNS):
        if c in out:
            out.insert(out.columns.get_loc(c) + 1, f"{c} (paper)", [paper.get(round(float(e), 1), (None,) * 4)[j]
                                                                    for e in out.index])
    return out


def claims(problem, g) -> list:
    """The paper's Section IV claims for one problem, each decided on per-seed pairs (the same start and goal)."""
    out = []

    def at(controller, error, metric):
        return series(g, metric, controller=controller, error_multiplier=error)

    errors = sorted(g["error_multiplier"].unique())
    lo, hi = errors[0], errors[-1]
    controllers = set(g["controller"])
    if "traditional" in controllers and lo < 1 < hi:
        ratio = paired(at("traditional", lo, "normalized"), at("traditional", hi, "normalized"))
        v, e = median_claim(ratio, 1.0, ">")
        out.append(Claim(f"{problem}: underestimated inertia degrades the cost faster than overestimated",
                         f"traditional, per seed: normalized cost at error {number(lo)} / at {number(hi)}", v, e))
        similar = sorted(c for c in controllers if c not in ("traditional", "2 knots"))
        if similar:
            verdicts, worst = [], (None, 1.0)
            for c in similar:
                for error in errors:
                    if error == 1.0:
                        continue
                    ratio = paired(at(c, error, "normalized"), at("traditional", error, "normalized"))
                    interval = median_interval(ratio)
                    verdicts.append(decide(interval, (1 / SIMILAR, SIMILAR), "=="))
                    far = max(abs(np.log(interval.low)), abs(np.log(interval.high)))
                    if far > abs(np.log(worst[1])):
                        worst = (f"{c} at error {number(error)}: {interval.text()}", np.exp(far))
            out.append(Claim(f"{problem}: with more than 2 knots the sensitivity is like traditional MPC's",
                             f"per-seed normalized cost of {', '.join(similar)} / traditional's, at every error: "
                             f"within {number(1 / SIMILAR, 2)}–{number(SIMILAR, 3)}×", combine(verdicts),
                             f"widest: {worst[0]}" if worst[0] else ""))
    if {"2 knots", "traditional"} <= controllers and 1.0 in errors:
        over = paired(at("2 knots", 1.0, "overshoot"), at("traditional", 1.0, "overshoot"), "difference")
        rise = paired(at("2 knots", 1.0, "rise_time"), at("traditional", 1.0, "rise_time"), "difference")
        v_over, e_over = median_claim(over, 0.0, "<=")
        v_rise, e_rise = median_claim(rise, 0.0, ">=")
        out.append(Claim(f"{problem}: fewer knots are more conservative (less overshoot, longer rise time)",
                         "at error 1, per seed, 2 knots − traditional: overshoot [%] ≤ 0 and rise time [s] ≥ 0",
                         combine([v_over, v_rise]), f"overshoot {e_over}; rise time {e_rise}",
                         paper="overshoot 3.05 vs 4.17 %, rise 0.59 vs 0.38 s" if problem == PAPER_PROBLEM else ""))
    if "traditional" in controllers and hi > 1 and 1.0 in errors:
        change = paired(at("traditional", hi, "overshoot"), at("traditional", 1.0, "overshoot"), "difference")
        v, e = median_claim(change, 0.0, "<")
        out.append(Claim(f"{problem}: overestimated inertia reduces overshoot",
                         f"traditional, per seed: overshoot at error {number(hi)} − at 1 [% points]", v, e,
                         paper="traditional: 4.17 % at 1, 0 % from 1.3" if problem == PAPER_PROBLEM else ""))
    return out

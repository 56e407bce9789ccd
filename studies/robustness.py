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
from ocpkit.studies.report import markdown_table, section

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
    figs, tables = [], {}
    for problem, g in ok.groupby("problem", sort=False):
        med = g.pivot_table(index="error_multiplier", columns="controller", values="normalized", aggfunc="median")
        figs.append(plots.lines(med.index, {c: med[c].values for c in med.columns},
                                out_dir / f"robustness_{filename(problem)}", xlabel="error multiplier",
                                ylabel="normalized cost (median)", log=True,
                                title=f"{problem}: sensitivity to model error"))
        tables[f"{problem}: median normalized cost"] = markdown_table(med, "{:.3f}")
        for metric, caption in (("overshoot", "mean percent overshoot"), ("rise_time", "mean rise time [s]")):
            t = g.pivot_table(index="error_multiplier", columns="controller", values=metric, aggfunc="mean")
            tables[f"{problem}: {caption}"] = markdown_table(t, "{:.3f}")
    return section(TITLE, figs, tables)

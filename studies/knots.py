"""Actual cost ratio vs number of knot points (paper Section III-D, Fig. 3).

Parameterized MPC with horizon 50 at 100 Hz for 1 s, normalized per start/goal by traditional MPC whose
horizon spans the whole simulation (100 steps), for the linear and nonlinear pendulum and the Puma 560 — or
for any problem specs given as ``problems`` (``ocpkit study knots --problem ./cartpole.py:CartPole``), each
over its own closed-loop duration.
"""
from __future__ import annotations

from ocpkit import plots
from ocpkit.problems import filename
from ocpkit.study import Study, grid
from ocpkit.studies.closed_loop import grid_size, trial
from ocpkit.studies.report import markdown_table, section

NAME = "knots"
TITLE = "Actual cost ratio vs number of knot points (Fig. 3)"
PROBLEMS = ("pendulum:linear", "pendulum", "puma560")
HORIZON, REFERENCE_HORIZON = 50, 100
SIZES = {"quick": {"knots": [1, 2, 3, 4, 6, 10, 25, 50], "seeds": 8, "problems": PROBLEMS},
         "full": {"knots": list(range(1, 51)), "seeds": 30, "problems": PROBLEMS}}
# The quick grid for problems given on the command line: small enough for a test of a user's problem.
USER_QUICK = {"knots": [1, 2, 3, 5, 10], "seeds": 3}


def study(size: str, problems=None) -> Study:
    """The study at ``size``; ``problems`` (specs) replace the paper's problems (quick: :data:`USER_QUICK`)."""
    s = grid_size(SIZES, size, problems, USER_QUICK)
    trials = (grid(problem=list(s["problems"]), horizon=HORIZON, knots=s["knots"], seeds=s["seeds"])
              + grid(problem=list(s["problems"]), horizon=REFERENCE_HORIZON, knots=[None], seeds=s["seeds"]))
    return Study(NAME, trial, trials)


def ratios(df, by: str):
    """Each trial's actual cost over the reference (traditional, horizon 100) trial of the same problem and seed."""
    ok = df[df["status"] == "ok"]
    ref = ok[ok["knots"].isna() & (ok["horizon"] == REFERENCE_HORIZON)].set_index(["problem", "seed"])["actual_cost"]
    rows = ok[ok["horizon"] == HORIZON] if by == "knots" else ok[ok["knots"].isna()]
    rows = rows.assign(ratio=rows["actual_cost"].values / ref.loc[list(zip(rows["problem"], rows["seed"]))].values)
    return rows


def report(df, out_dir) -> str:
    rows = ratios(df, "knots")
    figs = []
    for problem, g in rows.groupby("problem", sort=False):
        labels = sorted(g["knots"].dropna().unique())
        data = [g.loc[g["knots"] == k, "ratio"].values for k in labels]
        figs.append(plots.boxes([int(k) for k in labels], data, out_dir / f"knots_{filename(problem)}",
                                xlabel="number of knot points p (horizon 50)", ylabel="actual cost ratio",
                                title=f"{problem}: cost vs knots (reference: traditional, horizon 100)"))
    table = rows.pivot_table(index="knots", columns="problem", values="ratio", aggfunc="median")
    return section(TITLE, figs, {"Median actual cost ratio (rows: knots)": markdown_table(table, "{:.4f}")})



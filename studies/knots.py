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
from ocpkit.studies.report import Claim, markdown_table, section, trials_line, verdict
from ocpkit.plots import number

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
                                xlabel=f"number of knot points p (horizon {HORIZON})", ylabel="actual cost ratio",
                                title=f"{problem}: cost vs knots ({g['seed'].nunique()} seeds; reference: "
                                      f"traditional MPC, T = {REFERENCE_HORIZON})"))
    table = rows.pivot_table(index="knots", columns="problem", values="ratio", aggfunc="median")
    table.index = table.index.astype(int)
    ok = df[df["status"] == "ok"]
    trials = trials_line(df, {"problems": ok["problem"].nunique(), "knot counts + reference": ok["knots"].nunique(
        dropna=False), "seeds": ok["seed"].nunique()})
    caption = (f"Median actual cost ratio to traditional MPC with T = {REFERENCE_HORIZON} over the seeds "
               f"(rows: knots, horizon {HORIZON})")
    return section(TITLE, figs, {caption: markdown_table(table)}, trials=trials, claims=claims(rows, table))


def claims(rows, table) -> list:
    """The paper's Fig. 3 claims (Section III-D) against the ratios of this run."""
    out = []
    if 4 in table.index:
        at4 = table.loc[4]
        out.append(Claim("The cost hardly changes down to 3–4 knots", "median ratio at 4 knots: "
                         + ", ".join(f"{p} {number(v)}" for p, v in at4.items()),
                         verdict(bool((at4 <= 1.05).all()))))
    else:
        out.append(Claim("The cost hardly changes down to 3–4 knots", "4 knots not in this grid", verdict(None)))
    highest = table.idxmax()
    out.append(Claim("The cost is highest with one knot", "largest median at "
                     + ", ".join(f"{p}: {int(k)} knots" for p, k in highest.items()),
                     verdict(bool((highest == table.index.min()).all()) if table.index.min() == 1 else None)))
    linear = rows[rows["problem"] == "pendulum:linear"]
    if len(linear):
        low = linear["ratio"].min()
        out.append(Claim("The linear pendulum's ratio never goes below 1", f"smallest ratio {number(low, 6)}",
                         verdict(bool(low >= 1 - 1e-6))))
        top = linear[linear["knots"] == linear["knots"].max()]["ratio"].median()
        out.append(Claim("With more knots the linear pendulum converges to traditional MPC",
                         f"median ratio at {int(linear['knots'].max())} knots {number(top, 6)}",
                         verdict(bool(abs(top - 1) <= 1e-3))))
    else:
        out.append(Claim("The linear pendulum's ratio never goes below 1", "pendulum:linear not in this run",
                         verdict(None)))
    if {"pendulum", "pendulum:linear"} <= set(table.columns):
        few = table.loc[table.index <= 2]
        below = rows.loc[rows["problem"] == "pendulum", "ratio"].min()
        out.append(Claim("The nonlinear pendulum's median ratio is below the linear one's at few knots and "
                         "dips below 1", f"1–2 knots: {', '.join(number(v) for v in few['pendulum'])} vs "
                         f"{', '.join(number(v) for v in few['pendulum:linear'])}; smallest ratio {number(below)}",
                         verdict(bool((few["pendulum"] < few["pendulum:linear"]).all() and below < 1))))
    return out

"""Traditional MPC's actual cost ratio vs horizon length (paper Section III-D, Fig. 4).

The context for Fig. 3: shortening the horizon, the usual way to make MPC fast enough, costs far more
than parameterizing the inputs. Normalized by traditional MPC with a horizon spanning the simulation.
``problems`` (specs) replace the paper's problems, as in the knots study.
"""
from __future__ import annotations

from ocpkit import plots
from ocpkit.problems import filename
from ocpkit.study import Study, grid
from ocpkit.studies.closed_loop import grid_size, trial
from ocpkit.studies.knots import PROBLEMS, REFERENCE_HORIZON
from ocpkit.studies.report import markdown_table, section

NAME = "horizon"
TITLE = "Traditional MPC: actual cost ratio vs horizon (Fig. 4)"
SIZES = {"quick": {"horizons": [5, 10, 20, 30, 50, 75, 100], "seeds": 8},
         "full": {"horizons": [5, 10, 15, 20, 25, 30, 40, 50, 60, 70, 80, 90, 100], "seeds": 30}}
USER_QUICK = {"horizons": [10, 25, 50], "seeds": 3}


def study(size: str, problems=None) -> Study:
    """The study at ``size``; ``problems`` (specs) replace the paper's problems (quick: :data:`USER_QUICK`)."""
    s = grid_size({k: {**v, "problems": list(PROBLEMS)} for k, v in SIZES.items()}, size, problems, USER_QUICK)
    horizons = sorted(set(s["horizons"]) | {REFERENCE_HORIZON})
    return Study(NAME, trial, grid(problem=list(s["problems"]), horizon=horizons, knots=[None], seeds=s["seeds"]))


def report(df, out_dir) -> str:
    ok = df[df["status"] == "ok"]
    ref = ok[ok["horizon"] == REFERENCE_HORIZON].set_index(["problem", "seed"])["actual_cost"]
    ok = ok.assign(ratio=ok["actual_cost"].values / ref.loc[list(zip(ok["problem"], ok["seed"]))].values)
    figs = []
    for problem, g in ok.groupby("problem", sort=False):
        labels = sorted(g["horizon"].unique())
        figs.append(plots.boxes(labels, [g.loc[g["horizon"] == h, "ratio"].values for h in labels],
                                out_dir / f"horizon_{filename(problem)}", xlabel="horizon T (steps)",
                                ylabel="actual cost ratio", title=f"{problem}: traditional MPC vs horizon"))
    table = ok.pivot_table(index="horizon", columns="problem", values="ratio", aggfunc="median")
    return section(TITLE, figs, {"Median actual cost ratio (rows: horizon)": markdown_table(table, "{:.4f}")})

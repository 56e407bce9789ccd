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
from ocpkit.plots import number
from ocpkit.store import Store
from ocpkit.studies.report import Claim, markdown_table, section, trials_line, verdict

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
                                ylabel="actual cost ratio",
                                title=f"{problem}: traditional MPC vs horizon ({g['seed'].nunique()} seeds; "
                                      f"reference: T = {REFERENCE_HORIZON})"))
    table = ok.pivot_table(index="horizon", columns="problem", values="ratio", aggfunc="median")
    trials = trials_line(df, {"problems": ok["problem"].nunique(), "horizons": ok["horizon"].nunique(),
                              "seeds": ok["seed"].nunique()})
    caption = f"Median actual cost ratio to traditional MPC with T = {REFERENCE_HORIZON} (rows: horizon)"
    return section(TITLE, figs, {caption: markdown_table(table)}, trials=trials,
                   claims=claims(table, _knots_table(out_dir)))


def _knots_table(out_dir):
    """The knots study's median ratios from the same results folder, or None if it has not run there."""
    from ocpkit.studies.knots import ratios

    try:
        with Store(out_dir) as store:
            df = store.load("knots")
    except Exception:  # no store or no knots study in it: the cross-study claim is then not tested
        return None
    if df.empty or not (df["status"] == "ok").any():
        return None
    return ratios(df, "knots").pivot_table(index="knots", columns="problem", values="ratio", aggfunc="median")


def claims(table, knots_table) -> list:
    """The paper's Fig. 4 claims (Section III-D) against this run (and the knots study's, when beside it)."""
    shortest = table.index.min()
    rising = all((table.loc[shortest] >= table.loc[h] - 1e-9).all() for h in table.index)
    out = [Claim("A shorter horizon costs more", f"median ratio at T = {shortest}: "
                 + ", ".join(f"{p} {number(v)}" for p, v in table.loc[shortest].items()), verdict(rising))]
    claim = "Shortening the horizon costs far more than cutting knots"
    common = [] if knots_table is None else [p for p in table.columns if p in knots_table.columns]
    if not common:
        out.append(Claim(claim, "the knots study is not in this results folder", verdict(None)))
    else:
        fewest = knots_table.index.min()
        pairs = {p: (table.loc[shortest, p], knots_table.loc[fewest, p]) for p in common}
        out.append(Claim(claim, f"worst median ratio, T = {shortest} vs {int(fewest)} knot(s): "
                         + ", ".join(f"{p} {number(h)} vs {number(k)}" for p, (h, k) in pairs.items()),
                         verdict(all(h > k for h, k in pairs.values()))))
    return out

"""Traditional MPC's actual cost ratio vs horizon length (paper Section III-D, Fig. 4).

The context for Fig. 3: shortening the horizon, the usual way to make MPC fast enough, costs far more
than parameterizing the inputs. Normalized by traditional MPC with a horizon spanning the simulation.
``problems`` (specs) replace the paper's problems, as in the knots study.
"""

from __future__ import annotations

from ocpkit.sim import plots
from ocpkit.problems import filename
from ocpkit.runs.study import Study, grid
from ocpkit.studies.closed_loop import grid_size, trial
from ocpkit.studies.knots import HORIZON, PROBLEMS, REFERENCE_HORIZON
from ocpkit.runs.store import Store
from ocpkit.studies.calibration import puma_setup
from ocpkit.studies.evidence import NOT_TESTED, combine, median_claim, paired, series
from ocpkit.studies.report import Claim, markdown_table, section, timing_context, trials_line

NAME = "horizon"
TITLE = "Traditional MPC: actual cost ratio vs horizon (Fig. 4)"
SIZES = {
    "quick": {"horizons": [5, 10, 20, 30, 50, 75, 100], "seeds": 8},
    "full": {"horizons": [5, 10, 15, 20, 25, 30, 40, 50, 60, 70, 80, 90, 100], "seeds": 30},
}
USER_QUICK = {"horizons": [10, 25, 50], "seeds": 3}
FAR_MORE = (
    "III-D: 'the effect of decreasing horizon is far more dramatic than that of decreasing the number of "
    "parameter knot points'"
)


def study(size: str, problems=None) -> Study:
    """The study at ``size``; ``problems`` (specs) replace the paper's problems (quick: :data:`USER_QUICK`)."""
    s = grid_size({k: {**v, "problems": list(PROBLEMS)} for k, v in SIZES.items()}, size, problems, USER_QUICK)
    horizons = sorted(set(s["horizons"]) | {REFERENCE_HORIZON})
    return Study(NAME, trial, grid(problem=list(s["problems"]), horizon=horizons, knots=[None], seeds=s["seeds"]))


def ratios(df):
    """The successful trials with their actual cost over the reference horizon's (same problem and seed)."""
    ok = df[df["status"] == "ok"]
    ref = ok[ok["horizon"] == REFERENCE_HORIZON].set_index(["problem", "seed"])["actual_cost"]
    ok = ok.assign(ratio=ok["actual_cost"].values / ref.loc[list(zip(ok["problem"], ok["seed"]))].values)
    return ok


def per_seed_rows(df):
    """Each seed's cost ratio (the verdicts' unit) per problem and horizon, for the report's appendix."""
    ok = ratios(df)
    ok = ok[ok["horizon"] != REFERENCE_HORIZON]
    return ok.set_index(["problem", "horizon", "seed"])[["ratio"]].rename(
        columns={"ratio": f"actual cost / traditional MPC's at T = {REFERENCE_HORIZON}"}
    )


def report(df, out_dir) -> str:
    ok = ratios(df)
    figs = []
    for problem, g in ok.groupby("problem", sort=False):
        labels = sorted(g["horizon"].unique())
        figs.append(
            plots.boxes(
                labels,
                [g.loc[g["horizon"] == h, "ratio"].values for h in labels],
                out_dir / f"horizon_{filename(problem)}",
                xlabel="horizon T [steps]",
                ylabel="actual cost / reference's (ratio)",
                references=[(1.0, f"1: T = {REFERENCE_HORIZON}")],
                title=f"{problem}: traditional MPC vs horizon ({g['seed'].nunique()} seeds; "
                f"reference: T = {REFERENCE_HORIZON})",
            )
        )
    table = ok.pivot_table(index="horizon", columns="problem", values="ratio", aggfunc="median")
    trials = trials_line(
        df, {"problems": ok["problem"].nunique(), "horizons": ok["horizon"].nunique(), "seeds": ok["seed"].nunique()}
    )
    caption = f"Median actual cost ratio to traditional MPC with T = {REFERENCE_HORIZON} (rows: horizon)"
    return section(
        TITLE,
        figs,
        {**puma_setup(ok["problem"]), caption: markdown_table(table)},
        trials=trials + " " + timing_context(ok),
        claims=claims(ok, _knots_rows(out_dir)),
    )


def _knots_rows(out_dir):
    """The knots study's per-seed ratios from the same results folder, or None if it has not run there."""
    from ocpkit.studies.knots import ratios

    try:
        with Store(out_dir) as store:
            df = store.load("knots")
    except Exception:  # no store or no knots study in it: the cross-study claim is then not tested
        return None
    if df.empty or not (df["status"] == "ok").any():
        return None
    return ratios(df, "knots")


def claims(ok, knots_rows) -> list:
    """The paper's Fig. 4 claims (Section III-D), decided on per-seed ratios (and the knots study's, when beside it)."""
    shortest = ok["horizon"].min()
    problems = list(dict.fromkeys(ok["problem"]))

    parts = {p: median_claim(series(ok, "ratio", problem=p, horizon=shortest), 1.0, ">") for p in problems}
    out = [
        Claim(
            "A shorter horizon costs more",
            f"per-seed ratio at T = {shortest} to T = {REFERENCE_HORIZON} > 1",
            combine(v for v, _ in parts.values()),
            "; ".join(f"{p} {e}" for p, (_, e) in parts.items()),
            paper="III-D: 'a shorter horizon length encourages more greedy behavior, which leads to a less optimal "
            "solution'",
        )
    ]
    claim = "Shortening the horizon costs far more than cutting knots (at equal decision variables)"
    common = [] if knots_rows is None else [p for p in problems if p in set(knots_rows["problem"])]
    if not common:
        out.append(Claim(claim, "the knots study is not in this results folder", NOT_TESTED, paper=FAR_MORE))
    else:
        # Equal footing: T = shortest has T·m decision variables, p knots p·m; the most knots not above T gives the
        # knots side as many variables or fewer (fewer only makes the paper's claim harder to hold).
        knots = max((k for k in knots_rows["knots"].unique() if k <= shortest), default=knots_rows["knots"].min())
        parts = {
            p: median_claim(
                paired(
                    series(ok, "ratio", problem=p, horizon=shortest),
                    series(knots_rows, "ratio", problem=p, knots=knots),
                ),
                1.0,
                ">",
            )
            for p in common
        }
        out.append(
            Claim(
                claim,
                f"per seed: ratio at T = {shortest} ({shortest} inputs per joint) / ratio at {int(knots)} knots "
                f"(T = {HORIZON}, {int(knots)} inputs per joint) > 1 (ours: 'far' is not quantified; > 1 tests 'more')",
                combine(v for v, _ in parts.values()),
                "; ".join(f"{p} {e}" for p, (_, e) in parts.items()),
                paper=FAR_MORE,
            )
        )
    return out

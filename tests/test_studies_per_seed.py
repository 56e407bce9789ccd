"""The report's per-seed appendix in the verdicts' own units (issue 51): each study's ``per_seed_rows(df)`` and the
Markdown and CSV that :func:`ocpkit.studies.report.per_seed_section` makes of them."""

import numpy as np
import pandas as pd
import pytest

from ocpkit.studies import baxter, horizon, knots, report, robustness, solve_times


def _closed_loop(rows):
    return pd.DataFrame([{"status": "ok", **r} for r in rows])


def test_knots_and_horizon_give_each_seeds_ratio_to_the_reference():
    rows = [{"problem": "pendulum", "horizon": 100, "knots": None, "seed": s, "actual_cost": 2.0 + s} for s in (0, 1)]
    rows += [
        {"problem": "pendulum", "horizon": 50, "knots": k, "seed": s, "actual_cost": k * (2.0 + s)}
        for k in (1, 4)
        for s in (0, 1)
    ]
    df = _closed_loop(rows)
    table = knots.per_seed_rows(df)
    assert list(table.index.names) == ["problem", "knots", "seed"] and len(table) == 4
    assert table.iloc[:, 0].loc[("pendulum", 4, 1)] == pytest.approx(4.0)
    assert "traditional MPC's at T = 100" in table.columns[0]
    rows = [
        {"problem": "puma560", "horizon": h, "knots": None, "seed": s, "actual_cost": c * (1 + s)}
        for h, c in ((5, 3.0), (100, 1.5))
        for s in (0, 1, 2)
    ]
    table = horizon.per_seed_rows(_closed_loop(rows))
    assert list(table.index.get_level_values("horizon")) == [5, 5, 5]  # the reference (all 1) is left out
    assert np.allclose(table.iloc[:, 0], 2.0)


def test_robustness_gives_normalized_cost_overshoot_and_rise_time_per_seed():
    rows = [
        {
            "problem": "pendulum:paper",
            "knots": k,
            "error_multiplier": e,
            "seed": s,
            "actual_cost": (1 + s) * e,
            "overshoot": 4.0 * e,
            "rise_time": 0.38,
        }
        for k in (2, None)
        for e in (0.5, 1.0)
        for s in (0, 1)
    ]
    table = robustness.per_seed_rows(_closed_loop(rows))
    assert list(table.columns) == ["normalized cost", "percent overshoot", "rise time [s]"]
    assert table.loc[("pendulum:paper", "traditional", 0.5, 1), "normalized cost"] == pytest.approx(0.5)
    assert table.loc[("pendulum:paper", "2 knots", 0.5, 0), "percent overshoot"] == pytest.approx(2.0)


def test_solve_times_give_each_formulations_ratio_to_the_parameterized_small_matrix():
    rows = [
        {"links": 3, "horizon": 50, "form": f, "knots": k, "seed": 0, "solve_median": t, "total_median": 2 * t}
        for f, k, t in (("condensed", 5, 1e-4), ("sparse", 5, 3e-4), ("sparse", None, 2e-4))
    ]
    table = solve_times.per_seed_rows(_closed_loop(rows))
    ratio = table["optimization time / the parameterized small matrix's"]
    assert ratio.loc[(3, 50, solve_times.label("sparse", 5), 0)] == pytest.approx(3.0)
    assert ratio.loc[(3, 50, solve_times.label("condensed", 5), 0)] == pytest.approx(1.0)
    assert table["median MPC solve time [ms]"].max() == pytest.approx(0.6)


def test_baxter_gives_each_commands_and_joints_itae_ratio_to_the_servo():
    rows = [
        {
            "controller": c,
            "command": command,
            "seed": 0,
            **{f"itae_{j}": f * (1 + i) for i, j in enumerate(baxter.SHORT)},
        }
        for c, f in ((baxter.SERVO, 2.0), (baxter.QP, 1.0))
        for command in range(3)
    ]
    table = baxter.per_seed_rows(_closed_loop(rows))
    assert len(table) == 2 * 3 * len(baxter.SHORT)
    assert np.allclose(table.xs(baxter.QP, level="controller")["ITAE / the servo's"], 0.5)
    assert table.loc[(baxter.QP, 1, baxter.SHORT[2], 0), "ITAE"] == pytest.approx(3.0)


def test_section_prints_a_table_per_metric_and_writes_the_full_precision_csv(tmp_path):
    rows = [{"problem": "pendulum", "horizon": 100, "knots": None, "seed": s, "actual_cost": 3.0} for s in (0, 1)]
    rows += [{"problem": "pendulum", "horizon": 50, "knots": 2, "seed": s, "actual_cost": 3.0 + s / 7} for s in (0, 1)]
    text = report.per_seed_section("knots", knots.per_seed_rows(_closed_loop(rows)), tmp_path)
    assert "per seed, in the verdicts' units" in text and "[knots.csv](knots.csv)" in text
    assert "| problem / knots | seed 0 | seed 1 |" in text and "| pendulum / 2 | 1 | 1.048 |" in text
    saved = pd.read_csv(tmp_path / "knots_per_seed.csv")
    assert saved.iloc[1, -1] == pytest.approx(1 + 1 / 21, abs=1e-12)

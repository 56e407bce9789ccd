"""The solve-time, comparison and Baxter studies on tiny grids: trials stored, figures and tables written."""

import re

import numpy as np
import pytest

from ocpkit.runs import study as runner
from ocpkit.runs.store import Store
from ocpkit.studies import baxter, comparison, solve_times


def _run(module, tmp_path):
    df = runner.run(module.study("quick"), tmp_path, workers=1, progress=False)
    assert (df["status"] == "ok").all(), df["error"].dropna().tolist()
    return df, module.report(df, tmp_path)


def _figures(tmp_path, *stems):
    for stem in stems:
        assert (tmp_path / f"{stem}.png").stat().st_size > 5000
        assert (tmp_path / f"{stem}.pdf").exists()


def test_solve_times_tiny(monkeypatch, tmp_path):
    monkeypatch.setitem(
        solve_times.SIZES,
        "quick",
        {"links": [1, 2], "states": 2, "qp": "osqp", "max_dense_vars": 60, "time_budget": None},
    )
    df, text = _run(solve_times, tmp_path)
    # 2 robots × 2 horizons × 4 formulations, less the small matrix traditional QPs above 60 variables
    assert len(df) == 13 and (df["failures"] == 0).all()
    assert (df["solve_q1"] <= df["solve_median"]).all() and (df["solve_median"] <= df["solve_q3"]).all()
    assert (df["solve_median"] < df["total_median"]).all()
    assert "Not run (too slow for this size): small matrix traditional at 1 links, T = 100, 2 links, T = 50" in text
    assert "| links | large matrix (sparse), 5 knots |" in text
    # the solve-time verdict prints the interval that decides it: per case, the rival whose interval reaches highest
    assert re.search(r"deciding rival per case \(the interval reaching highest\): 1/50 vs [^;]+: [0-9.]+ \[", text)
    _figures(
        tmp_path, "solve_times_solve_T50", "solve_times_total_T50", "solve_times_solve_T100", "solve_times_total_T100"
    )
    with Store(tmp_path) as store:
        assert store.arrays("solve_times", solve_times.study("quick").trials[0])["solve_times"].shape == (2,)


def test_solve_times_states_are_shared_and_checked():
    a = solve_times.trial(links=1, horizon=10, form="sparse", knots=None, qp="osqp", states=2, seed=0)
    b = solve_times.trial(links=1, horizon=10, form="condensed", knots=None, qp="proxqp", states=2, seed=0)
    assert a["failures"] == b["failures"] == 0
    with pytest.raises(ValueError, match="states must be >= 1"):
        solve_times.trial(links=1, horizon=10, form="sparse", knots=None, qp="osqp", states=0, seed=0)
    with pytest.raises(ValueError, match="time_budget must be finite and > 0"):
        solve_times.trial(links=1, horizon=10, form="sparse", knots=None, qp="osqp", states=2, seed=0, time_budget=0)


def test_solve_times_budget_stops_a_trial_short_and_the_report_says_so(monkeypatch, tmp_path):
    """The full size's time budget: a trial past it stops after MIN_STATES states, the first ones of the same
    sequence, and the report names it and compares it on the states it solved."""
    full = solve_times.trial(links=1, horizon=10, form="sparse", knots=None, qp="osqp", states=7, seed=0)
    short = solve_times.trial(
        links=1, horizon=10, form="sparse", knots=None, qp="osqp", states=7, seed=0, time_budget=1e-9
    )
    assert full["solved"] == 7 and short["solved"] == solve_times.MIN_STATES == len(short["solve_times"])
    size = {"links": [1], "states": 7, "qp": "osqp", "max_dense_vars": None, "time_budget": 1e-9}
    monkeypatch.setitem(solve_times.SIZES, "quick", size)
    df, text = _run(solve_times, tmp_path)
    assert (df["solved"] == solve_times.MIN_STATES).all()
    assert "Stopped by the time budget (1e-09 s of solves a trial) before 7 states" in text
    assert "small matrix (condensed), traditional at 1 links, T = 100 (5 states)" in text
    assert "(up to 7 cold solves each)" not in text  # titles are in the figures; the tables say it
    assert "over up to 7 cold solves" in text
    with pytest.raises(ValueError, match="size must be one of"):
        solve_times.study("medium")


def test_comparison_tiny(monkeypatch, tmp_path):
    monkeypatch.setitem(
        comparison.SIZES, "quick", {"links": [2], "seeds": 1, "duration": 0.3, "population": 64, "arch": "cpu"}
    )
    monkeypatch.setattr(comparison, "SAMPLE_LINKS", 2)
    df, text = _run(comparison, tmp_path)
    assert len(df) == len(comparison.CONTROLLERS) and df["record"].all() and (df["fallbacks"] == 0).all()
    assert "| 2 | 1 |" in text  # traditional MPC is its own reference
    assert "The paper's Section VI-B numbers beside ours" in text and "accruing less than 20% more cost" in text
    assert "not tested: EMPC ran on cpu; the paper's times are GPU times" in text
    assert "The set-up: each setting, from the paper (quoted) or ours (why)" in text
    assert "| closed loop | 0.3 s, rest to rest | ours: paper VI-A: 'perform control at 100 Hz for ten seconds'" in text
    _figures(
        tmp_path,
        "comparison_sample_response",
        "comparison_cost_ratio",
        "comparison_solve_median",
        "comparison_total_median",
    )
    row = df.index[df["controller"] == "EMPC 1 gen"][0]
    arrays = comparison.row_arrays(df, row, tmp_path)
    assert arrays["x"].shape == (31, 4) and arrays["u"].shape == (30, 2)
    with pytest.raises(ValueError, match="controller must be one of"):
        comparison.trial(2, "ipopt", 0.1, 64, "cpu", False, 0)


def test_baxter_tiny(monkeypatch, tmp_path):
    monkeypatch.setitem(baxter.SIZES, "quick", {"seeds": 1, "duration": 1.0, "population": 64, "arch": "cpu"})
    df, text = _run(baxter, tmp_path)
    assert len(df) == 3 * (1 + len(baxter.CONTROLLERS)) and (df["fallbacks"] == 0).all()
    itae = {c: np.median(g[[f"itae_{j}" for j in baxter.SHORT]].to_numpy()) for c, g in df.groupby("controller")}
    assert itae[baxter.QP] < itae[baxter.SERVO]  # MPC damps the underdamped servo
    assert "(Table III)" in text and "| servo (step input) |" in text
    _figures(tmp_path, "baxter_command0", "baxter_command1", "baxter_command2", "baxter_solve_times")
    servo = df[df["controller"] == baxter.SERVO]
    assert (servo["solve_median"] == 0).all()
    with pytest.raises(ValueError, match="command must be one of"):
        baxter.trial(3, baxter.SERVO, 0.1, 64, "cpu", 0)


def test_baxter_commands_within_joint_limits():
    from ocpkit import problems

    pb = problems.make("baxter")
    for start, goal in baxter.COMMANDS:
        for q in (start, goal):
            assert np.all(q > pb.q_min) and np.all(q < pb.q_max)
        assert np.all(np.abs(goal - start) >= 0.3)  # every joint moves


def test_keepout_tiny(monkeypatch, tmp_path):
    from ocpkit.studies import keepout

    monkeypatch.setitem(keepout.SIZES, "quick", {"seeds": 2, "duration": 0.3, "population": 64, "arch": "cpu"})
    df, text = _run(keepout, tmp_path)
    assert len(df) == 6 and (df["status"] == "ok").all()
    assert (df["penalty"] >= 0).all() and "costs less than the QP on" in text
    _figures(tmp_path, "keepout_cost")
    # The penalty is what the zone costs: zero far from the centre, w·r at it.
    penalty = keepout.keepout_penalty([0.0, 0.0, 0.0])
    assert float(penalty([1.0, 0, 0, 0, 0, 0])) == 0.0
    assert float(penalty([0.0] * 6)) == keepout.WEIGHT * keepout.RADIUS

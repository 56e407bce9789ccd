"""The paper's pendulum set-up (studies/calibration.py): its calibrated cost, the anchor it was fitted on, and the
side-by-side of every Table I–II cell with the paper's number."""

import numpy as np
import pandas as pd
import pytest

from ocpkit import problems
from ocpkit.problems.pendulum import PAPER_COST
from ocpkit.studies import calibration, robustness


def test_paper_pendulum_carries_the_calibrated_cost():
    pb = problems.make("pendulum:paper")
    assert pb.name == "pendulum:paper" and pb.gravity
    assert np.allclose(np.diag(pb.defaults()["Q"]), [10.0, PAPER_COST["velocity_weight"]])
    assert pb.defaults()["R"][0, 0] == PAPER_COST["input_weight"]
    assert "calibrate" in PAPER_COST["provenance"] and "4.17" in PAPER_COST["provenance"]
    assert problems.make("pendulum").defaults()["R"][0, 0] == 0.01  # the other studies' pendulum is unchanged
    assert robustness.PAPER_PROBLEM == "pendulum:paper"
    assert all(robustness.PAPER_PROBLEM in s["problems"] for s in robustness.SIZES.values())


def test_precision_is_half_the_last_printed_digit():
    assert calibration.precision(4.17) == pytest.approx(0.005)
    assert calibration.precision(22) == 0.5 and calibration.precision(0) == 0.5
    # a 0 in a table that prints 0.0171 elsewhere means none, not 0 ± 0.5
    assert calibration.precision(0, calibration.PAPER_TABLES["overshoot"]) == pytest.approx(0.00005)
    assert calibration.precision(0, {1.0: (0, 0.3)}) == pytest.approx(0.05)
    assert calibration.precision(0.0171) == pytest.approx(0.00005)
    assert calibration.precision(0.3) == pytest.approx(0.05)


def test_fidelity_names_every_cell_its_difference_and_verdict():
    paper = calibration.PAPER_TABLES["overshoot"]
    ours = pd.DataFrame(
        {"2 knots": [paper[0.5][0] + 0.04, paper[1.0][0] + 1.0], "traditional": [paper[0.5][3], paper[1.0][3]]},
        index=pd.Index([0.5, 1.0], name="error_multiplier"),
    )
    cells = calibration.fidelity(ours, "overshoot")
    assert len(cells) == 4 and list(cells["paper"]) == [37.7, 43.5, 3.05, 4.17]
    assert np.allclose(cells["ours − paper"], [0.04, 0.0, 1.0, 0.0])
    assert list(cells["verdict"]) == [
        "within the paper's precision",
        "within the paper's precision",
        "not within ±0.005",
        "anchor (fitted): within the paper's precision",
    ]
    assert calibration.within_count(cells) == (2, 3)  # the anchor is fitted, not counted as a prediction


def test_setup_table_gives_every_setting_a_source():
    table = calibration.setup_table()
    assert all(s.startswith(("paper", "ours")) for s in table["source"])
    assert "calibrated Q velocity weight, R" in table.index


@pytest.mark.slow
def test_stored_calibration_reproduces_its_anchor():
    """The stored cost gives the anchor it records (30 closed loops); rerun calibrate() if the pendulum changes."""
    cell = calibration.anchor_cell(PAPER_COST["velocity_weight"], PAPER_COST["input_weight"])
    assert cell == pytest.approx(PAPER_COST["achieved"], abs=1e-9)


def test_horizon_against_knots_at_equal_decision_variables():
    """T = 5 is paired with the most knots not above 5 (4 here), not with 1 knot (issue 51)."""
    from ocpkit.studies import horizon

    seeds = range(8)
    ok = pd.DataFrame(
        [{"problem": "pendulum", "horizon": h, "seed": s, "ratio": r} for h, r in ((5, 2.0), (100, 1.0)) for s in seeds]
    )
    knots_rows = pd.DataFrame(
        [
            {"problem": "pendulum", "knots": k, "seed": s, "ratio": r * (1 + 0.01 * s)}
            for k, r in ((1, 3.0), (4, 1.2), (6, 1.0))
            for s in seeds
        ]
    )
    claim = horizon.claims(ok, knots_rows)[-1]
    assert claim.verdict == "held", claim
    assert "4 knots" in claim.ours and "equal decision variables" in claim.claim
    assert claim.paper.startswith("III-D: 'the effect of decreasing horizon is far more dramatic")


def test_demo_table_shows_each_controllers_final_error(monkeypatch, tmp_path, capsys):
    """A controller that drifts off the goal at a small cost ratio (CEM, p = T: issue 51) shows it in its row."""
    from ocpkit import solvers
    from ocpkit.cli import main

    monkeypatch.setattr(solvers, "names", lambda: ["qp"])  # the QP rows only: a quick table
    assert main(["demo", "--out", str(tmp_path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    head = next(line for line in lines if line.startswith("controller"))
    assert "final err" in head
    rows = [line.split() for line in lines if line.startswith("qp ")]
    assert len(rows) == 8 and all(float(r[-4]) < 0.2 for r in rows)


def test_solve_time_verdict_prints_the_rival_that_decides_it(monkeypatch):
    """ "Lowest solve time" is decided by the rival whose interval reaches highest, not the one with the highest
    median (issue 51: 1 link, T = 50, the large matrix with 5 knots, 0.5 [0.303, 1.32], was not printed)."""
    from ocpkit.studies import solve_times

    small = solve_times.label("condensed", solve_times.KNOTS)
    ones = np.ones(20)
    times = {small: ones, "steady": ones / np.linspace(0.88, 0.92, 20), "wide": ones / np.repeat([0.3, 1.2], 10)}
    monkeypatch.setattr(solve_times, "_per_state", lambda *a: {"solve": {(1, 50): times}, "total": {(1, 50): times}})
    claim = solve_times.claims(pd.DataFrame({"load": [0.0]}), None, None)[0]
    assert claim.verdict == "inconclusive"
    assert "1/50 vs wide: 0.75 [0.3, 1.2]" in claim.evidence, claim.evidence


def test_paper_puma_has_no_terminal_weight_and_is_the_paper_studies_puma():
    """The paper's cost (eq. mpc_problem) has no terminal term: x_T weighs Q, as the other states (issue 51: the
    default 10 Q made traditional MPC at T = 5 cost only 1.105x its best)."""
    from ocpkit.studies import knots

    paper, default = problems.make("puma560:paper"), problems.make("puma560")
    assert paper.name == "puma560:paper"
    assert np.array_equal(paper.defaults()["Q_terminal"], paper.defaults()["Q"])
    assert np.array_equal(default.defaults()["Q_terminal"], 10 * default.defaults()["Q"])  # the other users' Puma
    assert "puma560:paper" in knots.PROBLEMS
    assert all("puma560:paper" in s["problems"] for s in robustness.SIZES.values())
    with pytest.raises(ValueError, match="takes no argument but 'paper'"):
        problems.make("puma560:2")
    table = calibration.setup_table(calibration.PUMA_SETUP)
    assert table.loc["Puma: terminal weight", "source"].startswith("paper III-A")
    assert "Puma: terminal weight" in calibration.setup_table().index
    assert calibration.puma_setup(["pendulum"]) == {}
    assert "Puma: terminal weight" in next(iter(calibration.puma_setup(["puma560:paper"]).values()))


def test_stated_values_beside_ours_with_their_printed_precision():
    rows = calibration.stated(
        [
            ("a", "Table III", ".90", 0.904),  # printed with two decimals: ±0.005
            ("b", "Table III", "1.30", 1.31),
            ("c", "III-D: 'between three and four'", (3, 4), 4.0),
            ("d", "III-D", (3, 4), 6.0),
            ("e", "VI-D", "31", float("nan")),
        ]
    )
    assert list(rows["paper"]) == [".90", "1.30", "3–4", "3–4", "31"]  # as printed
    assert np.allclose(rows["ours − paper"].iloc[:4], [0.004, 0.01, 0.5, 2.5])
    assert list(rows["verdict"]) == [
        "within the paper's precision",
        "not within ±0.005",
        "within the paper's precision",
        "not within ±0.5",
        "not measured here",
    ]
    assert calibration.within_count(rows) == (2, 5)


def test_table_iii_every_cell_and_the_texts_reductions_beside_ours():
    from ocpkit.studies import baxter

    values = {baxter.SERVO: np.array([1.0, 1.3, 2.53]), baxter.QP: np.array([0.5, 0.9, 2.47])}
    rows = baxter.paper_values(values)
    assert len(rows) == 5  # mean and median per controller, and the QP's median reduction
    assert rows.loc[f"{baxter.SERVO}: median ITAE", "verdict"] == "within the paper's precision"
    assert rows.loc[f"{baxter.QP}: mean ITAE", "paper"] == "1.29"
    cut = rows.loc[f"{baxter.QP}: median ITAE reduction vs the servo [%]"]
    assert cut["paper"] == "31" and cut["ours"] == pytest.approx(100 * (1 - 0.9 / 1.3))
    assert cut["paper says"].startswith("VI-D: 'Parameterized OSQPMPC and EMPC reduce the median ITAE by 31%")


def test_knee_is_the_fewest_knots_from_which_every_median_is_slight():
    from ocpkit.studies import knots

    medians = pd.Series([1.5, 1.06, 1.02, 1.01, 1.07, 1.0], index=[1, 2, 3, 4, 6, 10])
    assert knots.knee(medians) == 10  # 6 knots is above again
    assert knots.knee(medians.drop(6)) == 3
    assert np.isnan(knots.knee(pd.Series([1.2, 1.1], index=[1, 2])))


def test_cost_ratios_leave_out_trials_whose_reference_is_not_stored():
    """A knots study stopped part way (or a failed reference trial) once made the horizon report raise KeyError."""
    from ocpkit.studies import knots

    def row(seed, k, horizon, cost, status="ok"):
        return {
            "problem": "pendulum",
            "seed": seed,
            "knots": k,
            "horizon": horizon,
            "actual_cost": cost,
            "status": status,
        }

    ref = knots.REFERENCE_HORIZON
    df = pd.DataFrame(
        [row(0, None, ref, 2.0), row(0, 3, knots.HORIZON, 3.0), row(1, 3, knots.HORIZON, 5.0)]
        + [row(2, None, ref, np.nan, "failed"), row(2, 3, knots.HORIZON, 4.0)]
    )
    rows = knots.ratios(df, "knots")
    assert rows["seed"].tolist() == [0] and rows["ratio"].tolist() == [1.5]


def test_never_below_one_names_the_runs_below_and_its_threshold():
    """Issue 51: the full size's 100 of 1,500 linear-pendulum runs below 1 − 1e-6 are named by seed and knots, and
    the threshold says whose it is."""
    from ocpkit.studies import knots

    rows = pd.DataFrame(
        [
            {
                "problem": "pendulum:linear",
                "knots": k,
                "seed": s,
                "ratio": 1 - 3e-5 if (s, k) in {(4, 30), (7, 50)} else 1.0,
            }
            for k in (1, 30, 50)
            for s in range(8)
        ]
    )
    table = rows.pivot_table(index="knots", columns="problem", values="ratio", aggfunc="median")
    claim = next(c for c in knots.claims(rows, table) if c.claim == "The linear pendulum's ratio never goes below 1")
    assert claim.verdict == "not held"
    assert claim.evidence == "2 of 24 runs below 1 − 1e-06 (seeds 4, 7; 30–50 knots)"
    assert "ours: above the solvers' round-off" in claim.ours

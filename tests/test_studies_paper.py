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

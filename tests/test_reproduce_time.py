"""`reproduce` reports compute time summed over runs: a resume does not overwrite it with its own seconds."""

import re

from ocpkit.runs.store import Store
from ocpkit.studies import get
from ocpkit.studies.reproduce import FULL_SECONDS_PER_TRIAL, SECONDS_PER_TRIAL, estimate, reproduce, unmeasured


def compute_seconds(report) -> float:
    return float(re.search(r"compute time: ([0-9.]+) s summed over the (\d+) study runs", report.read_text())[1])


def test_compute_time_sums_runs_and_a_resume_keeps_it(monkeypatch, tmp_path):
    monkeypatch.setitem(get("knots").SIZES, "quick", {"knots": [2, 50], "seeds": 1, "problems": ["pendulum:linear"]})
    trials = len(get("knots").study("quick").trials)
    assert estimate(("knots",), "quick", tmp_path, workers=1) == trials * SECONDS_PER_TRIAL["knots"]
    report = reproduce("quick", tmp_path, names=("knots",), workers=1, progress=False, pictures=False)
    assert estimate(("knots",), "quick", tmp_path, workers=1) == 0  # everything stored: nothing left to run
    first = compute_seconds(report)
    with Store(tmp_path) as store:
        runs, n = store.runs("knots"), len(store.load("knots"))
    assert len(runs) == 1 and runs.trials.tolist() == [n] and abs(first - runs.wall.sum()) < 0.1
    assert "wall time of this run" in report.read_text()
    # Widen the grid: the second run computes only the new trials, and the report adds their time to the first's.
    monkeypatch.setitem(get("knots").SIZES, "quick", {"knots": [2, 50], "seeds": 2, "problems": ["pendulum:linear"]})
    report = reproduce("quick", tmp_path, names=("knots",), workers=1, progress=False, pictures=False)
    with Store(tmp_path) as store:
        runs = store.runs("knots")
    assert runs.trials.tolist() == [n, n]
    assert compute_seconds(report) >= first and "over the 2 study runs" in report.read_text()
    # A resume with nothing left to run records no run and leaves the sum as it was.
    before = compute_seconds(report)
    report = reproduce("quick", tmp_path, names=("knots",), workers=1, progress=False, pictures=False)
    assert compute_seconds(report) == before


def test_the_full_size_is_estimated_from_its_own_trial_times(tmp_path):
    """Issue 51: `reproduce --full` had estimated from the quick size's per-trial times (solve_times: 2 min for a
    study of hours). A study measured at the full size counts at its own time; one not measured is named."""
    trials = len(get("knots").study("full").trials)
    assert estimate(("knots",), "full", tmp_path, workers=1) == trials * FULL_SECONDS_PER_TRIAL["knots"]
    assert (
        estimate(("knots",), "quick", tmp_path, workers=1)
        == len(get("knots").study("quick").trials) * SECONDS_PER_TRIAL["knots"]
    )
    assert unmeasured(("knots", "reach", "tracking"), "full") == ["reach", "tracking"]
    assert unmeasured(("reach",), "quick") == []

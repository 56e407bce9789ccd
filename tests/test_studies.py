"""The paper's studies end to end on tiny grids: trials stored, ratios computed, figures and tables written."""

import pytest

from ocpkit.runs.store import Store
from ocpkit.studies import get
from ocpkit.studies.closed_loop import trial
from ocpkit.studies.reproduce import reproduce


def test_closed_loop_trial_metrics():
    m = trial("pendulum:linear", seed=1, knots=3, duration=0.5)
    assert m["actual_cost"] > 0 and m["fallbacks"] == 0 and m["total_median"] > 0
    assert set(m) >= {"itae", "overshoot", "rise_time", "final_error", "solve_median", "total_p90"}


@pytest.fixture
def tiny(monkeypatch):
    monkeypatch.setitem(get("knots").SIZES, "quick", {"knots": [2, 50], "seeds": 2, "problems": ["pendulum:linear"]})
    monkeypatch.setitem(get("horizon").SIZES, "quick", {"horizons": [10], "seeds": 2})
    monkeypatch.setattr(get("horizon"), "PROBLEMS", ("pendulum:linear",))
    monkeypatch.setitem(get("robustness").SIZES, "quick", {"errors": [0.8, 1.0], "seeds": 1, "problems": ["pendulum"]})
    monkeypatch.setitem(
        get("robustness").MUJOCO_SIZES,
        "quick",
        {"problems": ["nlink:2"], "friction": [0.1], "armature": [0.5], "seeds": 1, "duration": 0.2, "arch": "cpu"},
    )
    monkeypatch.setitem(
        get("solve_times").SIZES,
        "quick",
        {"links": [1], "states": 2, "qp": "osqp", "max_dense_vars": None, "time_budget": None},
    )
    monkeypatch.setitem(
        get("comparison").SIZES, "quick", {"links": [1], "seeds": 1, "duration": 0.2, "population": 32, "arch": "cpu"}
    )
    monkeypatch.setattr(get("comparison"), "SAMPLE_LINKS", 1)
    monkeypatch.setitem(get("keepout").SIZES, "quick", {"seeds": 1, "duration": 0.2, "population": 32, "arch": "cpu"})
    monkeypatch.setitem(get("baxter").SIZES, "quick", {"seeds": 1, "duration": 0.2, "population": 32, "arch": "cpu"})
    monkeypatch.setitem(
        get("reach").SIZES,
        "quick",
        {
            "seeds": {"nlink:3": 1, "baxter": 0, "keepout": 1},
            "duration": {"nlink:3": 0.1, "baxter": 0.1, "keepout": 0.1},
            "horizon": {"nlink:3": 20, "baxter": 20, "keepout": 20},
            "population": 32,
            "arch": "cpu",
        },
    )
    monkeypatch.setitem(
        get("nonconvex").SIZES,
        "quick",
        {
            "seeds": {"nlink:3": 1},
            "controllers": ["LinearMPC (trajectory)", "EMPC"],
            "duration": 0.1,
            "horizon": 20,
            "population": 32,
            "arch": "cpu",
            "budget": 0.01,
            "swingup": {"seeds": {"pendulum": 1}, "horizon": 20, "duration": 0.1},
        },
    )


@pytest.fixture
def tiny_tracking(monkeypatch):
    monkeypatch.setitem(
        get("tracking").SIZES,
        "quick",
        {
            "scenario": ["circle", "eight", "joints"],
            "controller": ["LinearMPC"],
            "duration": 0.2,
            "plant": "model",
            "seeds": 1,
        },
    )


def _check_sections(text: str, count: int) -> None:
    """Every study section of a reproduce report says how many trials stand behind it and ends with its claim
    checks, each decided verdict with its evidence; ``count`` sections, the appendix of per-seed values last."""
    assert "wall time" in text and "casadi" in text and "failed" not in text
    sections = text.split("\n## ")[1:]
    assert len(sections) == count
    for part in sections:
        title = part.splitlines()[0]
        if title.startswith("Appendix"):
            assert "per seed" in part
            continue
        assert "trials succeeded (" in part, title
        claims = part.split("Claim checks:")[1]
        assert "| paper's claim | paper | here | evidence | verdict |" in claims, title
        rows = [row for row in claims.strip().splitlines()[2:] if row.startswith("|")]
        verdicts = [row.rsplit("|", 2)[-2].strip().split(" (")[0] for row in rows]
        assert verdicts and set(verdicts) <= {"held", "not held", "inconclusive", "not tested", "unreliable", "–"}, (
            title,
            verdicts,
        )
        for row in rows:  # n, and an interval where the verdict rests on a median
            if row.rsplit("|", 2)[-2].strip() in ("held", "not held", "inconclusive"):
                assert "n = " in row or " runs " in row, row
    assert "How verdicts are decided" in text


def _check_knots(out) -> None:
    """The knots study's figure, table and store in a reproduce folder, and a second run that redoes none of it."""
    assert (out / "knots_pendulum_linear.png").stat().st_size > 5000
    assert (out / "knots_pendulum_linear.pdf").exists()
    assert len((out / "knots.csv").read_text().splitlines()) == 7  # header and six trials
    df = Store(out).load("knots")
    assert len(df) == 6 and (df["status"] == "ok").all()
    ratios = get("knots").ratios(df, "knots")
    assert (ratios.loc[ratios["knots"] == 2, "ratio"] > 1).all()
    # Resume: a second run finds every trial stored and redoes none (the knots study: its report alone is rebuilt;
    # re-rendering every study's figures would add ~15 s and check nothing more).
    before = Store(out).load("knots")["finished"].tolist()
    reproduce("quick", out, names=("knots",), workers=1, progress=False, pictures=False)
    assert Store(out).load("knots")["finished"].tolist() == before


def test_reproduce_assembles_its_report_on_two_tiny_studies(tiny, tiny_tracking, tmp_path):
    """The fast twin of the slow run over every study below: two studies, their sections and the appendix."""
    report = reproduce("quick", tmp_path, names=("knots", "tracking"), workers=1, progress=False, pictures=False)
    text = report.read_text()
    assert "Fig. 3" in text and "Follow a moving reference" in text
    assert "- command: `ocpkit reproduce --quick --only knots --only tracking`" in text  # what this report holds
    _check_sections(text, 3)
    _check_knots(tmp_path)


@pytest.mark.slow
def test_reproduce_quick_on_tiny_grids(tiny, tiny_tracking, tmp_path):
    report = reproduce("quick", tmp_path, workers=1, progress=False)
    text = report.read_text()
    for title in (
        "Fig. 3",
        "Fig. 4",
        "Tables I–II",
        "Figs. 7–10",
        "Figs. 11–13",
        "keep-out zone",
        "Table III",
        "Reaching past spherical obstacles",
        "MuJoCo as the plant",
        "Follow a moving reference",
        "Non-convex reaches",
    ):
        assert title in text
    _check_sections(text, 12)  # the studies, robustness's MuJoCo variant, then the appendix of per-seed values
    _check_knots(tmp_path)


def test_unknown_study():
    with pytest.raises(ValueError, match="unknown study 'fig99'"):
        get("fig99")

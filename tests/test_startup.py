"""`ocpkit bench startup`: each run a fresh process in its own cache folder, empty then warm."""

import pytest

from ocpkit.benchmarks.startup import bench_startup


def test_each_run_reports_its_first_success_path_and_split():
    lines = []
    rows = bench_startup(problems=("pendulum",), controllers=("qp",), out=lambda *a, **k: lines.append(a[0]))
    assert [(r["controller"], r["cache"]) for r in rows] == [("qp", "empty"), ("qp", "warm")]
    for row in rows:
        assert "error" not in row, row
        assert 0 < row["first"] <= row["success"] <= row["steady"] and row["success_step"] == 0
        assert row["path"] == "Python step" and row["step"] > 0 and row["split"]["symbolic"] > 0
    assert any(line.lstrip().startswith("qp             warm") for line in lines)


def test_an_unknown_controller_is_named():
    with pytest.raises(ValueError, match="controllers must be among .*got nope"):
        bench_startup(problems=("pendulum",), controllers=("nope",))

"""The tracking study's trial (issue 46) on MuJoCo as the plant: without mismatch it tracks as on ocpkit's plant."""

import pytest

from ocpkit.studies.tracking import trial


def test_tracking_trial_on_mujoco_equals_the_model_plant():
    pytest.importorskip("mujoco")
    ours, theirs = (trial("circle", "LinearMPC", "preview", 0.3, plant, 0) for plant in ("model", "mujoco"))
    assert theirs["steps"] == ours["steps"] == 30 and theirs["collisions"] == 0
    for metric in ("rms_error", "max_error", "lag"):
        assert theirs[metric] == pytest.approx(ours[metric], rel=1e-9, abs=1e-12), metric

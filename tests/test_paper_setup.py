"""The paper's pendulum set-up far from its anchor (issue 51): what was tried to reproduce Tables I–II's far cells, each
setting with what the paper's text says of it, and the verdict the robustness report prints."""

import numpy as np

from ocpkit.studies import calibration


def test_every_setting_tried_is_re_anchored_and_says_why_it_was_not_adopted():
    table = calibration.tried_table()
    assert table.index[0] == "none (this set-up)"
    for setting, row in table.iterrows():
        if setting != table.index[0]:
            assert row["adopted"].startswith("no: ")
            assert "open" in row["the paper's text"] or "supported" in row["the paper's text"]
        overshoot = float(row["anchor (4.17 %, 0.38 s)"].split(" %")[0])
        if row["adopted"].startswith("no: no anchor"):  # not predicted: nothing to compare without the anchor
            assert row["traditional, error 0.5: overshoot % (paper 43.5)"] == "–"
        else:
            assert overshoot == calibration.ANCHOR_VALUES["overshoot"]  # R re-fitted for the anchor's overshoot
    # the one setting the text supports (Table II's 1.02 s rise time) does not bring error 0.5 nearer
    longer = table.loc["2 s closed loop"]
    assert longer["the paper's text"].startswith("supported") and "1.02 s" in longer["the paper's text"]
    far = "traditional, error 0.5: overshoot % (paper 43.5)"
    assert np.isclose(longer[far], table.loc["none (this set-up)", far], atol=0.5)


def test_the_set_up_table_says_error_half_is_not_reproduced():
    table = calibration.setup_table()
    row = table.loc["far from the anchor"]
    assert "no setting we tried and the paper supports reproduces error 0.5" in row["source"]
    assert "43.5" in row["value"]
    assert "Section IV states none" in table.loc["horizon", "source"]
    assert "1.02 s" in table.loc["closed loop", "source"]

"""experiments/gain_profile.py: the gain by clearance bin, against hand-counted drone-steps."""

import numpy as np
import pytest
from experiment_scripts import load


def test_profile_bins_by_clearance_and_counts_the_top_of_the_range():
    mod = load("gain_profile")
    # Range 0.2-1.2: "the top" is >= 1.19. Two steps in 0.0-0.1, one in 0.2-0.4, two beyond the last edge.
    rec = dict(gain=np.array([0.4, 0.6, 1.2, 1.195, 1.0]), clearance=np.array([0.05, 0.0, 0.3, 2.0, 9.0]),
               gain_min=0.2, gain_max=1.2)
    rows = mod.profile(rec)
    assert [r["bin"] for r in rows] == list(zip(mod.BIN_EDGES, (*mod.BIN_EDGES[1:], np.inf)))
    assert [r["steps"] for r in rows] == [2, 0, 1, 0, 0, 2]
    assert rows[0]["mean"] == pytest.approx(0.5) and rows[0]["top"] == 0.0
    assert rows[2]["mean"] == pytest.approx(1.2) and rows[2]["top"] == 1.0
    assert rows[5]["top"] == 0.5 and rows[5]["p5"] == pytest.approx(1.0 + 0.05 * 0.195)
    text = mod.table("runs/x", rec, rows)
    assert "| 0.1-0.2 | 0 | – | – | – |" in text and "| >= 1.6 | 2 | 1.098 |" in text


def test_a_bad_episode_count_is_a_one_line_error(capsys):
    assert load("gain_profile").main(["--checkpoint", "runs/none", "--episodes", "0", "--out", "/tmp/x"]) == 2
    assert capsys.readouterr().err.strip() == "gain_profile: invalid --episodes 0: must be > 0"

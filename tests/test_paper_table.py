"""experiments/paper_table.py --quick runs end to end: train, evaluate (with and without the filter), tabulate."""

import csv

import pytest
from drones import GEOMETRIC_FLAGS
from experiment_scripts import load


def _module():
    return load("paper_table")


def test_quick_table_runs_end_to_end(tmp_path):
    mod = _module()
    out = tmp_path / "results"
    # One scenario, one trained method (evaluated with and without the filter) and the MPC keep CI short;
    # the full command runs every method the same way.
    assert mod.main(["--quick", "--methods", "mappo,mpc", "--scenarios", "race", *GEOMETRIC_FLAGS,
                     "--out", str(out), "--runs", str(tmp_path / "runs")]) == 0
    rows = list(csv.DictReader((out / "paper_table_quick.csv").open()))
    assert [(r["method"], r["variant"]) for r in rows] == [("mappo", ""), ("mappo", "+ filter"), ("mpc", "")]
    for r in rows:
        assert 0.0 <= float(r["race_success"]) <= 1.0 and r["obstacles_success"] == ""
    md = (out / "paper_table_quick.md").read_text()
    assert "| MAPPO | – | " in md and "50 / 40 / 30" in md and "60 / 50 / 15" in md


def test_bad_method_is_a_clear_error(capsys):
    with pytest.raises(SystemExit) as e:
        _module().parse_args(["--methods", "ppo2"])
    assert e.value.code == 2
    assert "invalid method 'ppo2'" in capsys.readouterr().err

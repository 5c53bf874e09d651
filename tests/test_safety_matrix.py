"""experiments/safety_matrix.py --quick runs end to end with the shipped race policy, caches its cells, reuses them."""

import importlib.util
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _module():
    spec = importlib.util.spec_from_file_location("safety_matrix", ROOT / "experiments" / "safety_matrix.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclasses look their module up while they are built
    spec.loader.exec_module(mod)
    return mod


def test_quick_matrix_runs_caches_and_reuses_its_cells(tmp_path, capsys):
    mod = _module()
    out = tmp_path / "results"
    # race (4 drones, the shipped policy, also in SITL), race-moving2 (10 cylinders: the shipped policy does not fit),
    # lab (no policy given) and dynamic-1 (the shipped dynamic policy by default, 1 of its 3 slots moving):
    # every kind of row in one short run.
    argv = ["--quick", "--episodes", "2", "--only", "race,race-moving2,lab,dynamic-1", "--policy",
            "race-moving=pretrained", "--out", str(out)]
    assert mod.main(argv) == 0
    err = capsys.readouterr().err
    assert "cell 1/5 race: 2 episodes with pretrained" in err and "cell 5/5 race (SITL)" in err
    assert "dynamic-1: 2 episodes with pretrained:dynamic" in err
    doc = json.loads((out / "safety_matrix_quick.json").read_text())
    rows = {(r["cell"], r["mode"]): r for r in doc["cells"]}
    assert len(rows) == len(mod.CELLS) + sum(c.headline for c in mod.CELLS)
    race, sitl = rows[("race", "sim")], rows[("race", "sitl")]
    for r in (race, sitl):
        assert r["status"] == "done" and r["result"]["episodes"] == 2 and r["seed"] == mod.MATRIX_SEED
        assert 0.0 <= r["result"]["filter_intervention_rate"] <= 1.0
    assert 0.0 <= race["result"]["filter_infeasible_rate"] <= 1.0
    assert sitl["result"]["filter_infeasible_rate"] is None  # the flight runtime does not report the slack
    misfit = rows[("race-moving2", "sim")]
    assert misfit["status"] == "not run" and misfit["reason"].startswith("the policy cannot fly it: ")
    # 10 cylinders and 3 neighbours observed where the policy observes 8 and 3, in one line
    assert "\n" not in misfit["reason"] and "gives 10 and 3: the observation layouts differ" in misfit["reason"]
    assert rows[("lab", "sim")]["reason"] == "no lab policy (--policy lab=RUN)"
    assert rows[("dynamic-3", "sitl")]["status"] == "not run"
    md = (out / "safety_matrix_quick.md").read_text()
    assert "| race | `race` | pretrained | 2 |" in md
    assert "not run: no lab policy (--policy lab=RUN)" in md
    assert "| dynamic-1-fast | `dynamic` min_moving=1 max_moving=1 moving_period=2.667 |" in md
    assert not (out / "safety_matrix.md").exists() and not (out / "cells").exists()  # quick never mixes with full
    cells = {p.name: p.stat().st_mtime_ns for p in (out / "cells-quick").iterdir()}
    assert set(cells) == {"race.json", "race-sitl.json", "dynamic-1.json"}  # only finished cells are kept
    assert rows[("dynamic-1", "sim")]["status"] == "done"
    bundle = (out / "bundles" / "race" / "manifest.json").stat().st_mtime_ns

    # A re-run reuses the finished cells (and the bundle) instead of flying them again.
    assert mod.main(argv) == 0
    err = capsys.readouterr().err
    assert "race: reused" in err and "race (SITL): reused" in err and "race: 2 episodes with" not in err
    assert "race-moving2: not run: the policy cannot fly it" in err  # a misfit is checked again, not cached
    assert {p.name: p.stat().st_mtime_ns for p in (out / "cells-quick").iterdir()} == cells
    assert (out / "bundles" / "race" / "manifest.json").stat().st_mtime_ns == bundle
    again = {(r["cell"], r["mode"]): r for r in json.loads((out / "safety_matrix_quick.json").read_text())["cells"]}
    assert again[("race", "sim")]["result"] == race["result"]


def test_cached_cell_is_recomputed_when_its_key_changes(tmp_path):
    mod = _module()
    cell = mod.CELLS[0]
    key = mod.cell_key(cell, "sim", "pretrained", 8, 1)
    path = tmp_path / "race.json"
    mod.write_atomic(path, json.dumps({"key": key, "row": {"status": "done"}}))
    assert mod.cached(path, key) == {"status": "done"}
    assert mod.cached(path, mod.cell_key(cell, "sim", "pretrained", 8, 2)) is None  # another seed
    assert mod.cached(path, mod.cell_key(cell, "sim", "pretrained", 16, 1)) is None  # other episodes
    assert mod.cached(path, mod.cell_key(cell, "sim", str(tmp_path), 8, 1)) is None  # another policy
    path.write_text("{")  # half a file (not from write_atomic): recomputed, not a crash
    assert mod.cached(path, key) is None


def test_cells_of_the_issue():
    mod = _module()
    by = {c.name: c for c in mod.CELLS}
    assert len(by) == len(mod.CELLS) == 16
    assert {n for n, c in by.items() if c.headline} == {"race", "dynamic-3", "obstacles-16"}
    assert {n for n, c in by.items() if c.episodes == mod.HEADLINE_EPISODES} == {"race", "dynamic-3", "obstacles-16"}
    assert by["dynamic-2"].overrides == ("min_moving=2", "max_moving=2")
    period = float(by["dynamic-2-fast"].overrides[-1].split("=")[1])
    assert period * 1.5 == pytest.approx(mod.EnvConfig.moving_period)
    assert by["race-moving2"].overrides == ("num_obstacles=8", "num_moving=2", "min_moving=2", "max_moving=2")
    assert by["obstacles-64"].overrides == ("num_agents=64", "max_neighbours=3")
    # A cell's own policy wins over its kind's.
    policies = {"dynamic": "runs/a", "dynamic-1": "runs/b"}
    assert mod.policy_of(by["dynamic-1"], policies) == ("dynamic-1", "runs/b")
    assert mod.policy_of(by["dynamic-2"], policies) == ("dynamic", "runs/a")
    assert mod.policy_of(by["lab"], policies) is None


@pytest.mark.parametrize("argv, message", [
    (["--only", "race,nope"], "invalid --only 'race,nope': unknown cell 'nope'; allowed: race, obstacles, lab,"),
    (["--policy", "swarm=pretrained"], "unknown kind 'swarm'; allowed: race, race-moving, race-swarm,"),
    (["--policy", "lab=/no/such/run"], "no run folder '/no/such/run'"),
    (["--policy", "lab=pretrained:nope"], "no run folder 'pretrained:nope'; allowed: a folder from `aswarm train` or "
                                          "a shipped policy (pretrained, pretrained:"),
    (["--policy", "lab"], "invalid --policy 'lab': allowed: KIND=RUN"),
    (["--episodes", "0"], "invalid --episodes 0: must be > 0"),
])
def test_bad_arguments_are_one_line_errors(argv, message, capsys):
    with pytest.raises(SystemExit) as e:
        _module().parse_args(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err

"""experiments/safety_matrix.py --quick runs end to end with the shipped race policy, caches its cells, reuses them."""

import json

import pytest
from experiment_scripts import load


def _module(name: str = "safety_matrix"):
    return load(name)


def test_quick_matrix_runs_caches_and_reuses_its_cells(tmp_path, capsys, monkeypatch):
    mod = _module()
    out = tmp_path / "results"
    # race (4 drones, the shipped policy, also in SITL), race-moving2 (10 cylinders: the shipped policy does not fit),
    # lab (no policy: as if pretrained:lab had not shipped) and dynamic-1 (the shipped dynamic policy by default, 1
    # of its 3 slots moving): every kind of row in one short run.
    monkeypatch.delitem(mod.DEFAULT_POLICIES, "lab")
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
    # --sim-only flies no SITL row but still reports a finished one; an unfinished one says why it did not run.
    assert mod.main(argv[:-2] + ["--sim-only", "--out", str(out)]) == 0
    capsys.readouterr()
    sim_only = {(r["cell"], r["mode"]): r for r in json.loads((out / "safety_matrix_quick.json").read_text())["cells"]}
    assert sim_only[("race", "sitl")]["result"] == sitl["result"]
    assert sim_only[("dynamic-3", "sitl")]["reason"] == "--sim-only"


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
    # The same policy with other filter settings in its config (its checkpoints as they are): recomputed.
    from aswarm.analysis import evaluate

    config = json.loads((evaluate.PRETRAINED / "config.json").read_text())
    runs = {}
    for slack in (0.1, 1.0):
        config["train"]["safety_filter"]["static_slack"] = slack
        runs[slack] = tmp_path / f"slack{slack}"
        runs[slack].mkdir()
        (runs[slack] / "config.json").write_text(json.dumps(config))
    mod.write_atomic(path, json.dumps({"key": mod.cell_key(cell, "sim", str(runs[0.1]), 8, 1), "row": {}}))
    assert mod.cached(path, mod.cell_key(cell, "sim", str(runs[0.1]), 8, 1)) == {}
    assert mod.cached(path, mod.cell_key(cell, "sim", str(runs[1.0]), 8, 1)) is None
    path.write_text("{")  # half a file (not from write_atomic): recomputed, not a crash
    assert mod.cached(path, key) is None


def test_a_cell_whose_layouts_changed_is_flown_again(tmp_path):
    """The full run's key holds a digest of the cell's layouts: a row cached from other layouts is stale; one
    cached before keys held the digest still matches on the rest."""
    mod = _module()
    cell = mod.CELLS[0]
    before = mod.cell_key(cell, "sim", "pretrained", 8, 1)
    first, moved = (mod.cell_key(cell, "sim", "pretrained", 8, 1, layout=d) for d in ("aaa", "bbb"))
    assert "layout" not in before and first == {**before, "layout": "aaa"}
    path = tmp_path / "race.json"
    mod.write_atomic(path, json.dumps({"key": first, "row": {"status": "done"}}))
    assert mod.cached(path, first) == {"status": "done"} and mod.cached(path, moved) is None
    mod.write_atomic(path, json.dumps({"key": before, "row": {"status": "done"}}))
    assert mod.cached(path, moved) == {"status": "done"}
    # The digest the full run gives: of the policy's env with the cell's overrides, on the drone flown (that it
    # is the same for the same layouts: tests/test_env.py).
    swarm = next(c for c in mod.CELLS if c.name == "obstacles-64")
    a, b = (mod.layout_digest(swarm, "pretrained:obstacles16", seed, "identified") for seed in (1, 2))
    assert len(a) == 64 and a != b


def test_a_policy_trained_again_to_the_same_update_is_another_policy(tmp_path):
    mod = _module()
    cell = mod.CELLS[0]
    from aswarm.analysis import evaluate

    runs = []
    for weights in (b"first", b"second"):  # the same config, the same step, other weights
        run = tmp_path / weights.decode()
        (run / "checkpoints" / "488" / "policy" / "d").mkdir(parents=True)
        (run / "checkpoints" / "488" / "policy" / "d" / "blob").write_bytes(weights)
        (run / "config.json").write_text((evaluate.PRETRAINED / "config.json").read_text())
        runs.append(str(run))
    first, second = (mod.cell_key(cell, "sim", r, 8, 1) for r in runs)
    assert first["policy_step"] == second["policy_step"] == 488 and first["policy_digest"] != second["policy_digest"]
    path = tmp_path / "race.json"
    mod.write_atomic(path, json.dumps({"key": first, "row": {"status": "done"}}))
    assert mod.cached(path, first) == {"status": "done"}
    second_at_first = {**second, "policy": first["policy"]}  # even under the first's name (a shipped folder replaced)
    assert mod.cached(path, second_at_first) is None
    # A cell cached before keys held the digest matches on the rest of its key.
    legacy = {k: v for k, v in first.items() if k != "policy_digest"}
    mod.write_atomic(path, json.dumps({"key": legacy, "row": {"status": "done"}}))
    assert mod.cached(path, first) == {"status": "done"}
    assert mod.cached(path, {**first, "seed": 2}) is None


def test_identified_drone_flies_apart_from_the_stored_one(tmp_path, monkeypatch):
    mod = _module()
    cell = mod.CELLS[0]
    stored = mod.cell_key(cell, "sim", "pretrained", 8, 1)
    assert "drone" not in stored and mod.cell_key(cell, "sim", "pretrained", 8, 1, "stored") == stored
    identified = mod.cell_key(cell, "sim", "pretrained", 8, 1, "identified")
    assert identified == {**stored, "drone": "identified"}
    # The identified drone is today's default (0.108 s spin-down), whatever the policy's run stored (0 for runs
    # from before session 22).
    assert mod.DRONES["identified"] == ("cf.motor_tau_down=0.108",)
    assert mod.parse_args(["--drone", "identified"]).drone == "identified"
    assert mod.parse_args([]).drone == "stored"
    with pytest.raises(SystemExit):
        mod.parse_args(["--drone", "geometric"])
    # The cell's own overrides and pins, then the drone's, reach the evaluation.
    from aswarm.analysis import evaluate

    flown = []
    def fake(run, scenario, n, seed, overrides, progress=None):
        flown.append(overrides)
        return {"episodes": n}

    monkeypatch.setattr(evaluate, "evaluate_checkpoint", fake)
    dyn = next(c for c in mod.CELLS if c.name == "dynamic-3")
    for drone in ("stored", "identified"):
        assert mod.run_cell(dyn, "sim", "pretrained:dynamic", "dynamic", 2, 1, tmp_path, drone)["status"] == "done"
    assert flown == [dyn.flown, dyn.flown + ["cf.motor_tau_down=0.108"]]


def test_a_bundle_is_exported_again_when_the_policy_config_changes(tmp_path, monkeypatch):
    """A shipped policy's config may change its filter without new checkpoints (pretrained:dynamic's moving-cylinder
    gain cap), or the policy be trained again to the same update (another gamma): its SITL cells must not fly the
    bundle exported before."""
    mod = _module()
    from aswarm.flight import export

    calls = []
    monkeypatch.setattr(export, "export", lambda run, path, force, env_overrides: calls.append(run) or path)
    folder = tmp_path / "bundles" / "dynamic"
    folder.mkdir(parents=True)
    source = {"checkpoint": "pretrained:dynamic", "trained_updates": mod.newest_step("pretrained:dynamic"),
              "export_env_overrides": [], "train_config": mod.train_config("pretrained:dynamic")}
    (folder / "manifest.json").write_text(json.dumps({"source": source}))
    assert mod.bundle_for("dynamic", "pretrained:dynamic", tmp_path, []) == folder and calls == []
    train = source["train_config"]
    for changed in ({"safety_filter": {**train["safety_filter"], "moving_gain_max": 0.0}}, {"gamma": 0.99}):
        (folder / "manifest.json").write_text(json.dumps({"source": {**source, "train_config": {**train, **changed}}}))
        mod.bundle_for("dynamic", "pretrained:dynamic", tmp_path, [])
    assert calls == ["pretrained:dynamic"] * 2


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
    assert by["obstacles-64"].overrides == ("num_agents=64", "max_neighbours=3", "filter_neighbours=8")
    # Every cell with moving cylinders flies them at its one speed, whatever range the policy trained on.
    moving = {n for n, c in by.items() if any(o.startswith("max_moving=") for o in c.overrides)}
    assert moving == {n for n, c in by.items() if "moving_speed_scale=1.0,1.0" in c.flown} and len(moving) == 7
    # --episodes sets every cell's, but the largest swarms keep their fewer.
    got = [mod.episodes_of(by[c], False, 2000) for c in ("race", "race-8", "race-16", "obstacles-32", "obstacles-64")]
    assert got == [2000, 2000, 2000, 1000, 500]
    # The issue's 2,000 for a cell with at most 16 drones; race-16 on its own clock, the race's doubled.
    assert by["race-8"].episodes == by["race-16"].episodes == mod.CELL_EPISODES
    assert by["race-16"].overrides[-1] == "episode_seconds=120.0"
    assert [mod.episodes_of(by[c], True, 2) for c in ("race", "obstacles-64")] == [2, 2]
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


def test_two_matrices_compare_cell_by_cell_with_newcombe_intervals(tmp_path, capsys):
    from aswarm.analysis.evaluate import wilson

    mod = _module("compare_matrices")
    # Newcombe (1998), Statistics in Medicine 17, table II, example (a): 56/70 against 48/80, method 10: the
    # difference 0.2 has the 95 % interval [0.0524, 0.3339].
    lo, hi = mod.newcombe(56 / 70, wilson(56, 70), 48 / 80, wilson(48, 80))
    assert (round(lo, 4), round(hi, 4)) == (0.0524, 0.3339)

    def matrix(path, success, collisions, n):
        r = {"episodes": n, "mission_time": 30.0, "success_rate": success / n, "success_ci95": wilson(success, n),
             "collision_rate": collisions / n, "collision_ci95": wilson(collisions, n)}
        cells = [{"cell": "race", "mode": "sim", "result": r}, {"cell": "lab", "mode": "sim", "result": None}]
        path.write_text(json.dumps({"cells": cells}))
        return path

    a, b = matrix(tmp_path / "a.json", 1990, 2, 2000), matrix(tmp_path / "b.json", 950, 40, 1000)
    assert mod.main([str(a), str(b), "--labels", "full,fixed", "--out", str(tmp_path / "c.md")]) == 0
    row = next(line for line in (tmp_path / "c.md").read_text().splitlines() if line.startswith("| race"))
    assert "| 2000 / 1000 |" in row and "99.5 [99.1, 99.7]" in row and "-3.9 [" in row and "] *" in row
    assert "lab" not in (tmp_path / "c.md").read_text()  # not run in either: no row
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"cells": [{"cell": "lab", "mode": "sim", "result": {"episodes": 1}}]}))
    with pytest.raises(SystemExit, match="no cell in common"):
        mod.main([str(a), str(other)])

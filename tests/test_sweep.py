"""Sweeps: bad files fail before compiling; an [optuna] search asks, trains and tells in rounds, prunes, and
resumes. (The tiny sweep resumed and equal to its trials run one by one: test_sharding.py, where it is also the
reference of the sweep on two devices.)"""

import json
import sys
import tomllib
import types
from pathlib import Path

import jax
import numpy as np
import pytest

from aswarm import cli
from aswarm.agents import hparams
from aswarm.analysis import evaluate
from aswarm.training import checkpoint, runner, sweep

SWEEPS = Path(__file__).resolve().parent.parent / "sweeps"
CI_SWEEP = SWEEPS / "ci_tiny.toml"
HEAD = 'scenario = "hover"\ntotal_steps = 128\nseeds = [0, 1]\n'
BAD = [
    (HEAD + "[grid]\nactor_lrr = [1e-3]\n", "unknown field 'actor_lrr'"),
    (HEAD + "[grid]\n", "[grid] is empty"),
    (HEAD + "[grid]\nactor_lr = []\n", "non-empty list"),
    (HEAD + '[grid]\nactor_lr = ["fast"]\n', "invalid value 'fast' (str); allowed: a finite number"),
    (HEAD + "[grid]\nnum_envs = [8.5]\n", "allowed: an integer"),
    (HEAD + "[grid]\nenv.bogus = [1.0]\n", "unknown env field 'bogus'"),
    (HEAD + "[grid]\ngain_min = [3.0]\n", "need 0 < min < max"),
    (HEAD + "[random]\nsamples = 0\nclip = {low = 0.1, high = 0.3}\n", "invalid samples"),
    (HEAD + "[random]\nsamples = 2\nnum_envs = {low = 8, high = 16}\n", "a range needs a float field"),
    (HEAD + "[random]\nsamples = 2\nactor_lr = {low = 0.0, high = 1e-3, log = true}\n", "low > 0 for log"),
    (HEAD, "needs exactly one of [grid], [random] or [optuna]; found none"),
    ('total_steps = 128\nseeds = [0]\n[grid]\nclip = [0.1]\n', "missing scenario"),
    ('scenario = "hover"\ntotal_steps = 128\nseeds = [0, 0]\n[grid]\nclip = [0.1]\n', "distinct"),
    ("scenario = [", "not valid TOML"),
]


@pytest.mark.parametrize("text,message", BAD)
def test_bad_sweep_file_fails_before_compile(tmp_path, monkeypatch, capsys, text, message):
    def no_compile(*args, **kwargs):
        raise AssertionError("compiled before the sweep file was checked")

    monkeypatch.setattr(jax, "jit", no_compile)
    monkeypatch.setattr("aswarm.agents.train.make_train", no_compile)
    path = tmp_path / "bad.toml"
    path.write_text(text)
    assert cli.main(["sweep", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()


def test_random_search_is_reproducible_and_log_uniform():
    doc = {"scenario": "hover", "total_steps": 128, "seeds": [0], "sample_seed": 3,
           "random": {"samples": 6, "actor_lr": {"low": 1e-4, "high": 1e-2, "log": True}, "clip": [0.1, 0.2],
                      "env": {"collision_penalty": [50.0, 100.0]}}}
    a, b = sweep.parse(doc), sweep.parse(doc)
    assert a.configs == b.configs and len(a.configs) == 6
    lrs = [c.actor_lr for c in a.configs]
    assert all(1e-4 <= x <= 1e-2 for x in lrs) and len(set(lrs)) == 6
    assert {c.clip for c in a.configs} <= {0.1, 0.2}
    # Env fields are baked into the environment's code: each value is its own compiled group.
    gs = sweep.groups(a)
    assert len(gs) == len({c.env_overrides for c in a.configs})
    assert all(set(g.sweep_fields) <= {"actor_lr", "clip"} for g in gs)


def test_a_different_sweep_in_the_same_folder_is_refused(tmp_path):
    spec = sweep.load(CI_SWEEP)
    (tmp_path / "sweep.json").write_text(json.dumps({"source": "another sweep"}))
    with pytest.raises(ValueError, match="holds a different sweep"):
        sweep.run(spec, tmp_path, progress=False)


def test_hparams_reject_fields_that_change_shapes():
    with pytest.raises(ValueError, match="invalid sweep field 'num_envs'"):
        hparams.check_fields(["num_envs"])
    with pytest.raises(ValueError, match="exactly the sweep fields"):
        hparams.check_values(("actor_lr",), {})


def test_one_host_loop_marks_a_diverged_trial_and_stops_when_every_trial_has(tmp_path):
    """The NaN policy of runs and sweep groups alike, on a stand-in program (no compile): trial 1 goes NaN at
    update 3 and is marked while trial 0 trains on; when trial 0 goes NaN too (update 5), the loop stops before
    logging or saving that chunk. Resuming truncates the logs (atomically) to the restored update."""
    import jax.numpy as jnp

    from aswarm import envs
    from aswarm.agents.config import TrainConfig
    from aswarm.agents.train import TrainState
    from aswarm.training import runner, sharding

    cfg = TrainConfig(scenario="hover", method="mappo", num_envs=4, rollout_steps=2, minibatches=1,
                      updates_per_chunk=2, total_steps=4 * 2 * 8, checkpoint_minutes=1e-6)
    limit = jnp.array([4, 2])  # trial i's loss and parameters are NaN past this update

    def init_fn():
        return TrainState(params={"w": jnp.ones((2, 3))}, opt_state={"mu": jnp.zeros((2, 3))},
                          obs_norm={"mean": jnp.zeros((2, 5))}, env_state={"x": jnp.zeros((2, 4))},
                          key=jnp.zeros((2, 2), jnp.uint32), update=jnp.zeros(2, jnp.int32), env_steps=jnp.zeros(2))

    def chunk_fn(ts, k):
        u = ts.update[:, None] + jnp.arange(1, k + 1)
        loss = jnp.where(u > limit[:, None], jnp.nan, u * 1.0)
        update = ts.update + k
        w = jnp.where((update > limit)[:, None], jnp.nan, ts.params["w"] + k)
        zeros = jnp.zeros_like(loss)
        metrics = {"train/loss": loss, "episode/success": zeros, "episode/episode_return": zeros,
                   "episode/collision": zeros, "episodes": zeros}
        return ts.replace(params={"w": w}, update=update), metrics

    mesh = sharding.make_mesh(2, cfg.num_envs, jax.devices()[:1])
    program = runner.Program(envs.make("hover"), init_fn, chunk_fn, (), mesh, stacked=True)
    dirs = [tmp_path / "t0", tmp_path / "t1"]
    for d in dirs:
        d.mkdir()
    logs = []
    with pytest.raises(runner.TrainingDiverged, match=r"at update 5; the last good checkpoint \(update 4\)"):
        runner.run_loop(program, cfg, tmp_path / "g", dirs, progress=False, log=logs.append, label="g")
    assert (dirs[1] / "DIVERGED").read_text().strip().endswith("at update 3")
    assert (dirs[0] / "DIVERGED").read_text().strip().endswith("at update 5")
    assert "g: t1 diverged at update 3" in logs
    rows = [runner.read_metrics(d) for d in dirs]
    assert [r["update"] for r in rows[0]] == [r["update"] for r in rows[1]] == [1, 2, 3, 4]
    assert [r["train/loss"] for r in rows[0]] == [1.0, 2.0, 3.0, 4.0]
    assert np.isnan(rows[1][2]["train/loss"]) and rows[1][1]["train/loss"] == 2.0
    assert checkpoint.manager(tmp_path / "g").latest_step() == 4
    with (dirs[0] / "metrics.jsonl").open("a") as f:  # a row written after the checkpoint by a killed run
        f.write(json.dumps({**rows[0][-1], "update": 5}) + "\n")
    with pytest.raises(runner.TrainingDiverged):
        runner.run_loop(program, cfg, tmp_path / "g", dirs, progress=False, log=logs.append, label="g")
    assert "g: resumed at update 4" in logs
    assert [r["update"] for r in runner.read_metrics(dirs[0])] == [1, 2, 3, 4]
    assert not list(tmp_path.rglob("*.tmp"))


def test_sweep_sets_nested_env_fields_and_names_the_allowed_ones():
    doc = {"scenario": "hover", "total_steps": 128, "seeds": [0],
           "grid": {"env": {"cf": {"mass": [0.027, 0.03]}}, "gains.max_tilt_deg": [20.0]}}
    with pytest.raises(ValueError, match=r"unknown field 'gains.max_tilt_deg'.* or env.FIELD"):
        sweep.parse(doc)
    doc["grid"]["env.gains.max_tilt_deg"] = doc["grid"].pop("gains.max_tilt_deg")
    spec = sweep.parse(doc)
    assert [(c.env.cf.mass, c.env.gains.max_tilt_deg) for c in spec.configs] == [(0.027, 20.0), (0.03, 20.0)]
    assert len(sweep.groups(spec)) == 2  # env values are baked into the program: one compile each
    with pytest.raises(ValueError, match=r"unknown env field 'cf.mas'; allowed: .*cf.mass"):
        sweep.parse({**doc, "grid": {"env": {"cf": {"mas": [0.03]}}}})


# --- [optuna] searches -------------------------------------------------------------------------------------------

OPTUNA = HEAD + "[optuna]\nrounds = 2\nbatch = 2\n"
BAD_OPTUNA = [
    (OPTUNA + "[optuna.space]\nnum_envs = {low = 8, high = 16}\n", "[optuna.space] num_envs: not searchable"),
    (OPTUNA + "[optuna.space]\nenv.collision_penalty = [50.0, 100.0]\n",
     "[optuna.space] env.collision_penalty: not searchable"),
    (OPTUNA + "[optuna.space]\nactor_lrr = [1e-3]\n", "[optuna.space] actor_lrr: unknown field 'actor_lrr'"),
    (OPTUNA + "roundz = 3\n[optuna.space]\nclip = [0.1]\n", "[optuna] unknown key 'roundz'"),
    (OPTUNA + 'objective = "speed"\n[optuna.space]\nclip = [0.1]\n', "[optuna] objective: invalid value 'speed'"),
    (OPTUNA + 'direction = "up"\n[optuna.space]\nclip = [0.1]\n', "[optuna] direction: invalid value 'up'"),
    (OPTUNA + 'sampler = "cma"\n[optuna.space]\nclip = [0.1]\n', "[optuna] sampler: invalid value 'cma'"),
    (HEAD + "[optuna]\nrounds = 2\nbatch = 0\n[optuna.space]\nclip = [0.1]\n", "[optuna] batch: invalid value 0"),
    (HEAD + "[optuna]\nbatch = 2\n[optuna.space]\nclip = [0.1]\n", "[optuna] rounds: missing"),
    (OPTUNA, "[optuna.space] is missing or empty"),
    (OPTUNA + "[optuna.space]\nactor_lr = {low = 1e-2, high = 1e-3}\n", "[optuna.space] actor_lr: invalid range"),
    (OPTUNA + "[optuna.space]\nclip = {low = 0.1, high = 0.3, mode = 1}\n",
     "[optuna.space] clip: invalid range {'low': 0.1, 'high': 0.3, 'mode': 1}; allowed keys: low, high, log"),
    (OPTUNA + "[optuna.space]\nactor_lr = {low = 1e-4, high = 1e-2, log = true, step = 1e-4}\n",
     "[optuna.space] actor_lr: invalid step"),
    (OPTUNA + "[optuna.space]\nclip = [0.1, 0.1]\n", "[optuna.space] clip: a choice is listed twice"),
    (OPTUNA + "[optuna.space]\ngamma = {low = 0.9, high = 1.5}\n", "[optuna.space] gamma: invalid gamma=1.5"),
    (HEAD + "[fixed]\nclip = 0.2\n" + OPTUNA[len(HEAD):] + "[optuna.space]\nclip = [0.1]\n",
     "[optuna.space] clip: both fixed and searched"),
    (OPTUNA + "[optuna.space]\nclip = [0.1]\n[grid]\nactor_lr = [1e-3]\n", "found [grid] and [optuna]"),
    ("sample_seed = 1\n" + OPTUNA + "[optuna.space]\nclip = [0.1]\n", "sample_seed is for [random]"),
    (HEAD + "[optuna]\nrounds = 100\nbatch = 4\n[optuna.space]\nclip = [0.1]\n", "800 trials (100 rounds x 4"),
]


@pytest.mark.parametrize("text,message", BAD_OPTUNA)
def test_bad_optuna_table_fails_before_compile_naming_the_key(tmp_path, monkeypatch, capsys, text, message):
    test_bad_sweep_file_fails_before_compile(tmp_path, monkeypatch, capsys, text, message)


def test_optuna_is_needed_only_for_an_optuna_table(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "optuna", None)  # `import optuna` now raises ImportError
    assert sweep.load(CI_SWEEP).optuna is None
    path = tmp_path / "search.toml"
    path.write_text(OPTUNA + "[optuna.space]\nclip = [0.1, 0.2]\n")
    assert cli.main(["sweep", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "pip install 'aswarm[optuna]'" in err and err.count("\n") == 1, err


def test_optuna_table_parses():
    spec = sweep.load(SWEEPS / "race_optuna.toml")
    search = spec.optuna
    assert spec.configs == () and spec.seeds == (0, 1)
    assert (search.objective, search.direction, search.rounds, search.batch) == ("success", "maximize", 4, 4)
    assert (search.sampler, search.seed, search.pruner, search.prune_warmup) == ("tpe", 0, "median", 90)
    assert search.startup_trials == search.prune_startup == 4  # defaults: one round
    assert search.fields == ("actor_lr", "correction_penalty", "critic_lr", "entropy_coef")
    dists = search.distributions()
    assert dists["actor_lr"].log and (dists["actor_lr"].low, dists["actor_lr"].high) == (5e-4, 5e-3)
    assert dists["correction_penalty"].choices == (0.0, 1.0, 2.0)
    # Collision is minimised unless the file says otherwise; int and stepped ranges.
    doc = tomllib.loads(OPTUNA + 'objective = "collision"\n[optuna.space]\ncorrection_penalty = {low = 0, high = 4, '
                        'int = true}\nclip = {low = 0.1, high = 0.3, step = 0.05}\n')
    search = sweep.parse(doc).optuna
    assert search.direction == "minimize"
    dists = search.distributions()
    assert type(dists["correction_penalty"]).__name__ == "IntDistribution" and dists["clip"].step == 0.05
    assert search.configure({"correction_penalty": 3, "clip": 0.15}).correction_penalty == 3.0


def test_optuna_sampler_is_deterministic_given_the_seed():
    """Rounds asked twice from the same records draw the same; another seed draws otherwise. An invalid draw
    (gain_min >= gain_max) is failed and drawn again, and a round's plan asks the same trials again."""
    from aswarm.training import optuna_search

    doc = tomllib.loads(OPTUNA.replace("batch = 2", "batch = 4") + "[optuna.space]\n"
                        "gain_min = {low = 0.5, high = 2.5}\ngain_max = {low = 0.6, high = 2.6}\nclip = [0.1, 0.2]\n")
    search = sweep.parse(doc).optuna

    def ask(search, records, r, plan=None):
        return optuna_search.ask_round(search, optuna_search.rebuild_study(search, records, r), r, plan)[0]

    first = ask(search, [], 0)
    assert first == ask(search, [], 0)
    assert [d["params"] for d in first] != [d["params"] for d in ask(sweep.parse(
        {**doc, "optuna": {**doc["optuna"], "seed": 1}}).optuna, [], 0)]
    assert any(d["config"] is None for d in first), "seed 0 draws an invalid configuration in round 0"
    assert [d["config"] for d in first if d["config"] is not None] == [0, 1, 2, 3]
    assert all(d["params"]["gain_min"] < d["params"]["gain_max"] for d in first if d["config"] is not None)
    assert ask(search, [], 0, {"draws": first}) == first
    # Round 1 comes from TPE's model of round 0 (startup_trials = batch): the same again from the same records.
    record = {"trials": [{**d, "state": "FAIL", "value": None, "intermediate": {}} if d["config"] is None else
                         {**d, "state": "COMPLETE", "value": d["params"]["gain_max"] - d["params"]["gain_min"],
                          "intermediate": {"2": 0.0}} for d in first]}
    second = ask(search, [record], 1)
    assert second == ask(search, [record], 1)
    assert [d["config"] for d in second if d["config"] is not None] == [4, 5, 6, 7]
    assert min(d["number"] for d in second) == len(first)


def test_optuna_pruning_marks_a_trial_and_ends_the_round_when_all_are(tmp_path):
    """The runner's on_chunk: each configuration's objective so far is reported at multiples of updates_per_chunk
    and the median pruner prunes the one below the completed trial's curve; when none is left, the round ends."""
    from aswarm.training import optuna_search

    text = OPTUNA.replace("total_steps = 128", "total_steps = 2048") + (  # 64 updates
        'objective = "episode_return"\n[fixed]\nnum_envs = 8\nrollout_steps = 4\nupdates_per_chunk = 2\n'
        "[optuna.space]\nclip = {low = 0.1, high = 0.3}\n")
    search = sweep.parse(tomllib.loads(text)).optuna
    record = {"trials": [{"number": 0, "config": 0, "params": {"clip": 0.2}, "state": "COMPLETE", "value": 5.0,
                          "intermediate": {"2": 1.0, "4": 2.0}},
                         {"number": 1, "config": 1, "params": {"clip": 0.1}, "state": "COMPLETE", "value": 5.0,
                          "intermediate": {"2": 1.0, "4": 2.0}}]}
    study = optuna_search.rebuild_study(search, [record], 1)
    _, trials = optuna_search.ask_round(search, study, 1)
    dirs = {c: [tmp_path / f"c{c:02d}-s{s}" for s in (0, 1)] for c in trials}
    good, bad = sorted(trials)

    def write(c: int, returns: list[float]) -> None:
        for d in dirs[c]:
            d.mkdir(exist_ok=True)
            rows = [{"update": u, "episodes": 1.0, "episode/episode_return": r, "episode/success": 0.0,
                     "episode/collision": 0.0} for u, r in enumerate(returns, 1)]
            (d / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))

    watch = optuna_search.Watch(search, study, trials, dirs, last_updates=2, log=lambda _: None, label="round 1")
    write(good, [1.5, 1.5, 3.0])
    write(bad, [0.0, 0.0, 9.0])
    assert not watch(3, {})  # reports update 2 (not 3: off the grid), where `bad` is below the median, 1.0
    assert watch.pruned == {bad: 2} and watch.reported == {good: {2: 1.5}, bad: {2: 0.0}}
    assert study.trials[trials[bad].number].state.name == "PRUNED"
    assert all((d / "PRUNED").read_text().startswith("pruned by Optuna at update 2") for d in dirs[bad])
    assert not any((d / "PRUNED").exists() for d in dirs[good])
    write(good, [1.5, 1.5, 1.0, 1.0])  # update 4: 1.0 < 2.0
    assert watch(4, {}) and watch.stopped and watch.pruned == {bad: 2, good: 4}


def _stand_in_program(curve):
    """sweep.build_program without a compile: a chunk's metrics are ``curve(hparams, updates [K, k], inits)``."""
    import jax.numpy as jnp

    from aswarm import envs
    from aswarm.agents.train import TrainState

    def build(group, mesh):
        inits = []

        def init_fn(keys, values):
            inits.append(1)
            k = keys.shape[0]
            return TrainState(params={"w": jnp.zeros((k, 3))}, opt_state={"mu": jnp.zeros((k, 3))},
                              obs_norm={"mean": jnp.zeros((k, 5))}, env_state={"x": jnp.zeros((k, 4))},
                              key=jnp.zeros((k, 2), jnp.uint32), update=jnp.zeros(k, jnp.int32),
                              env_steps=jnp.zeros(k), hparams=values)

        def chunk_fn(ts, k):
            ret = curve(ts.hparams, ts.update[:, None] + jnp.arange(1, k + 1), len(inits))
            zeros = jnp.zeros_like(ret)
            metrics = {"train/loss": zeros, "episode/episode_return": ret, "episode/success": zeros,
                       "episode/collision": zeros, "episodes": jnp.ones_like(ret)}
            return ts.replace(update=ts.update + k), metrics

        return types.SimpleNamespace(env=envs.make("hover")), init_fn, chunk_fn, mesh

    return build


STAND_IN = OPTUNA.replace("total_steps = 128", "total_steps = 256").replace("rounds = 2", "rounds = 3") + (
    'objective = "episode_return"\nprune_startup = 1\n[fixed]\nnum_envs = 8\nrollout_steps = 4\nupdates_per_chunk = 2\n'
    "[optuna.space]\nactor_lr = {low = 1e-4, high = 1e-2, log = true}\nclip = [0.1, 0.2]\n")


def test_optuna_search_resumes_to_what_an_uninterrupted_one_draws_and_tells(tmp_path, monkeypatch):
    """On a stand-in program (no compile): 3 rounds of 2 configurations x 2 seeds, 8 updates each. Killed in round
    0 (at update 3, mid-chunk), the search resumes and asks, prunes and tells exactly what an uninterrupted one does;
    finished rounds are not trained again."""
    import jax.numpy as jnp

    monkeypatch.setattr(sweep, "build_program", _stand_in_program(
        lambda h, u, inits: -(jnp.log10(h["actor_lr"])[:, None] + 3) ** 2 + 0.01 * u))
    spec = sweep.parse(tomllib.loads(STAND_IN), source=STAND_IN)
    quiet = dict(progress=False, log=lambda _: None)
    assert sweep.run(spec, tmp_path / "a", max_updates=3, **quiet) is None
    assert not (tmp_path / "a" / "rounds" / "r00.json").exists()
    resumed = sweep.run(spec, tmp_path / "a", **quiet)
    whole = sweep.run(spec, tmp_path / "b", **quiet)
    for r in range(3):
        a, b = (json.loads((tmp_path / d / "rounds" / f"r{r:02d}.json").read_text()) for d in "ab")
        assert a["trials"] == b["trials"]
    assert resumed["configs"] == whole["configs"] and resumed["optuna"]["best"] == whole["optuna"]["best"]
    # Told values are the final metric of the logs, mean over the seeds.
    for t in whole["optuna"]["trials"]:
        if t["state"] == "COMPLETE":
            logs = [runner.read_metrics(tmp_path / "b" / "trials" / f"c{t['config']:02d}-s{s}") for s in (0, 1)]
            finals = [sweep.final_metrics(rows, spec.last_updates)["episode_return"] for rows in logs]
            assert t["value"] == pytest.approx(np.mean(finals))
    monkeypatch.setattr(sweep, "build_program", None)  # finished: nothing to build, train or tell again
    assert sweep.run(spec, tmp_path / "a", **quiet)["configs"] == resumed["configs"]


def test_optuna_search_stops_a_round_whose_every_trial_is_pruned(tmp_path, monkeypatch):
    """Rounds after the first are far worse (a stand-in whose curves fall after its first init): every trial of
    round 1 is pruned at update 2, the round stops there, and the report says so."""
    monkeypatch.setattr(sweep, "build_program", _stand_in_program(
        lambda h, u, inits: 0.01 * u * h["clip"][:, None] - 10.0 * (inits > 1)))
    spec = sweep.parse(tomllib.loads(STAND_IN.replace("rounds = 3", "rounds = 2")), source=STAND_IN)
    out = tmp_path / "search"
    results = sweep.run(spec, out, progress=False, log=lambda _: None)
    r1 = json.loads((out / "rounds" / "r01.json").read_text())
    assert r1["stopped_early"] and r1["updates"] == 2
    assert [t["state"] for t in r1["trials"]] == ["PRUNED", "PRUNED"]
    assert all(t["pruned_at"] == 2 and t["value"] == pytest.approx(t["intermediate"]["2"]) for t in r1["trials"])
    assert [r["update"] for r in runner.read_metrics(out / "trials" / "c02-s0")] == [1, 2]
    assert checkpoint.manager(out / "trials" / "c02-s1").latest_step() == 2
    assert results["optuna"]["counts"] == {"COMPLETE": 2, "PRUNED": 2, "FAIL": 0}
    assert [e["state"] for e in results["configs"]] == ["COMPLETE", "COMPLETE", "PRUNED", "PRUNED"]
    assert results["optuna"]["best"]["config"] == results["configs"][0]["config"]
    table = sweep.format_table(results)
    assert table.count("(pruned at update 2)") == 2
    report = (out / "report.md").read_text()
    assert "## Optuna search" in report and "2 completed, 2 pruned, 0 failed" in report
    assert (out / "optuna.png").stat().st_size > 10_000 and (out / "trials.csv").read_text().count("\n") == 5


def test_tiny_optuna_search_trains_two_rounds_in_one_compiled_program(tmp_path, monkeypatch):
    """The real trainer: 2 rounds of 2 hover configurations (4 updates of 8 worlds x 4 steps), compiled once;
    Optuna is told each trial's final return, read from its own logs."""
    from aswarm.training import optuna_search

    builds = []
    build = sweep.build_program
    monkeypatch.setattr(sweep, "build_program", lambda *a: builds.append(1) or build(*a))
    text = CI_SWEEP.read_text().split("[grid]")[0].replace("seeds = [0, 1]", "seeds = [0]").replace(
        'name = "ci_tiny"', 'name = "tiny_optuna"') + (
        "env.episode_seconds = 0.2  # 5 steps: episodes end within the tiny budget\n"
        '[optuna]\nobjective = "episode_return"\nrounds = 2\nbatch = 2\n'
        "[optuna.space]\nactor_lr = {low = 1e-4, high = 1e-2, log = true}\n")
    path = tmp_path / "tiny_optuna.toml"
    path.write_text(text)
    out = tmp_path / "search"
    assert cli.main(["sweep", str(path), "--out", str(out), "--quiet"]) == 0
    assert len(builds) == 1
    results = json.loads((out / "results.json").read_text())
    told = results["optuna"]["trials"]
    assert len(told) == 4 and all(t["state"] in ("COMPLETE", "PRUNED") for t in told)
    assert len({t["params"]["actor_lr"] for t in told}) == 4
    for t in told:
        rows = runner.read_metrics(out / "trials" / f"c{t['config']:02d}-s0")
        assert [r["update"] for r in rows] == [1, 2, 3, 4]
        if t["state"] == "COMPLETE":
            assert t["value"] == pytest.approx(sweep.final_metrics(rows, 2)["episode_return"])
            assert np.isfinite(t["value"]) and t["intermediate"].keys() == {"2"}
    best = results["optuna"]["best"]
    assert best["value"] == max(t["value"] for t in told if t["state"] == "COMPLETE")
    assert results["configs"][0]["config"] == best["config"]
    trained, restored = evaluate.load(out / "trials" / best["trials"][0])
    assert trained.actor_lr == pytest.approx(best["params"]["actor_lr"]) and int(restored["update"]) == 4
    assert "Best trial: c" in (out / "report.md").read_text() and (out / "optuna.png").exists()
    assert optuna_search.best_trial([json.loads((out / "rounds" / f"r0{r}.json").read_text()) for r in (0, 1)],
                                    "maximize")["config"] == best["config"]

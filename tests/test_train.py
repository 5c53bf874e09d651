"""Training: learning happens, checkpoints round-trip, resume reproduces, faults stop cleanly."""

import dataclasses
import functools
import json
import re
import shutil
from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from drones import GEOMETRIC, GEOMETRIC_FLAGS

from aswarm import envs
from aswarm.agents.config import TrainConfig
from aswarm.core.safety import SafetyFilterConfig
from aswarm.training import checkpoint, runner

# One small run for the trainer's mechanics (methods differ), on the geometric drone (tests/drones.py): the
# same program for every test that uses it as it is (the persistent compile cache, conftest.py).
SMALL = dict(scenario="hover", num_envs=32, rollout_steps=8, minibatches=2, epochs=2, updates_per_chunk=2,
             total_steps=32 * 8 * 4, env_overrides=GEOMETRIC)


@pytest.fixture(scope="module")
def mappo_run(tmp_path_factory):
    """One finished run of ``SMALL`` with MAPPO, for the tests that read a run and do not change it (each extra
    run cost its tracing and lowering, some 5 s, even where the compiled program came from the cache)."""
    return runner.train(TrainConfig(method="mappo", **SMALL), tmp_path_factory.mktemp("mappo") / "r", progress=False)


def _restore(run_dir):
    cfg = checkpoint.load_config(run_dir)
    from aswarm.agents.train import make_train

    _, init, _, _ = make_train(cfg)
    like = jax.jit(init)(jax.random.PRNGKey(cfg.seed))
    return checkpoint.restore(checkpoint.manager(run_dir), like)


def test_hover_learns_from_scratch(tmp_path):
    # The firmware drone, nothing randomised, with gentler exploration: under PPO's initial white-noise commands
    # (std 1 of 2 m/s, a new one every 40 ms) it hits the floor within a second in 98 % of episodes (the
    # geometric drone in 2 %), and this budget is too small to learn past that (README, issue #12).
    cfg = TrainConfig(scenario="hover", method="mappo", num_envs=128, rollout_steps=32, updates_per_chunk=10,
                      total_steps=128 * 32 * 20, action_std_scale=0.3, env_overrides=(("randomize.enabled", False),))
    run = runner.train(cfg, tmp_path / "run", progress=False)
    rows = runner.read_metrics(run)
    # The deterministic policy on the same 64 unseen episodes, before (the run's initial parameters) and after.
    # (Training rows are no "before": the first episodes to end are the quick successes, and by the time the
    # failures time out the policy has already learnt.)
    from aswarm.agents.train import make_train
    from aswarm.analysis import evaluate

    agent, init, _, _ = make_train(cfg)
    ts = jax.jit(init)(jax.random.PRNGKey(cfg.seed))
    _, trained = evaluate.load(run)
    key = jax.random.PRNGKey(10_000)
    before = evaluate.rollout_episodes(agent, ts.params, ts.obs_norm, agent.env, 64, key)[0]["success"]
    after = evaluate.rollout_episodes(agent, trained["params"], trained["obs_norm"], agent.env, 64, key)[0]["success"]
    assert float(np.mean(before)) < 0.2 and float(np.mean(after)) > 0.6, (np.mean(before), np.mean(after))
    assert rows[-1]["train/explained_variance"] > rows[0]["train/explained_variance"]
    assert (run / "curves.png").stat().st_size > 10_000
    assert (run / "tb").is_dir() and json.loads((run / "config.json").read_text())["train"]["method"] == "mappo"


def test_a2c_takes_one_full_batch_step_per_rollout():
    cfg = TrainConfig(method="a2c", **SMALL)
    assert (cfg.num_epochs, cfg.num_minibatches) == (1, 1)
    from aswarm.agents.train import make_train

    _, init, update_chunk, _ = make_train(cfg)
    ts = jax.jit(init)(jax.random.PRNGKey(0))
    ts2, m = jax.jit(update_chunk, static_argnums=1)(ts, 2)
    assert m["train/loss"].shape == (2,) and np.all(np.isfinite(m["train/loss"]))
    changed = jax.tree.map(lambda a, b: bool(np.any(np.asarray(a) != np.asarray(b))), ts.params["actor"],
                           ts2.params["actor"])
    assert all(jax.tree.leaves(changed))


def test_eval_json_is_the_only_stdout(mappo_run, capsys):
    from aswarm import cli
    from aswarm.analysis import evaluate

    capsys.readouterr()
    assert cli.main(["eval", "--checkpoint", str(mappo_run), "--episodes", "8", "--json"]) == 0
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    # Progress comes from inside the program, to stderr: a line per fifth of the episode's steps.
    lines = [x for x in captured.err.splitlines() if x.startswith("aswarm eval: episodes 1-8 of 8: step ")]
    assert len(lines) == evaluate.PROGRESS_LINES
    assert out["episodes"] == 8 and 0.0 <= out["success_rate"] <= 1.0
    lo, hi = out["success_ci95"]
    assert lo <= out["success_rate"] <= hi


def test_checkpoint_round_trip_and_resume_matches_uninterrupted(tmp_path):
    cfg = TrainConfig(method="attention_penalty", **SMALL)
    full = runner.train(cfg, tmp_path / "full", progress=False)
    part = runner.train(cfg, tmp_path / "part", progress=False, max_updates=2)
    a = _restore(part)
    assert int(a.update) == 2
    resumed = runner.train(None, part, resume=True, progress=False)
    s_full, s_res = _restore(full), _restore(resumed)
    assert int(s_full.update) == int(s_res.update) == 4
    for x, y in zip(jax.tree.leaves((s_full.params, s_full.opt_state, s_full.obs_norm, s_full.key)),
                    jax.tree.leaves((s_res.params, s_res.opt_state, s_res.obs_norm, s_res.key))):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    rows_full = runner.read_metrics(full)
    rows_res = runner.read_metrics(resumed)
    assert [r["update"] for r in rows_res] == [1, 2, 3, 4]
    assert rows_full[-1]["train/loss"] == rows_res[-1]["train/loss"]


def test_existing_run_folder_is_not_overwritten(mappo_run):
    before = {p: p.stat().st_mtime_ns for p in mappo_run.rglob("*")}
    with pytest.raises(ValueError, match="already holds checkpoints: use --resume"):
        runner.train(TrainConfig(method="mappo", **SMALL), mappo_run, progress=False)
    assert {p: p.stat().st_mtime_ns for p in mappo_run.rglob("*")} == before


def test_nan_stops_training_and_keeps_last_good_checkpoint(tmp_path, monkeypatch):
    cfg = TrainConfig(method="mappo", checkpoint_minutes=1e-6, **SMALL)
    real = runner.make_train

    def poisoned(config, **kw):
        agent, init, chunk, train = real(config, **kw)

        def chunk_nan(ts, k):
            ts, m = chunk(ts, k)
            bad = ts.update > 2
            params = jax.tree.map(lambda p: jax.numpy.where(bad, jax.numpy.nan, p), ts.params)
            return ts.replace(params=params), m

        return agent, init, chunk_nan, train

    monkeypatch.setattr(runner, "make_train", poisoned)
    with pytest.raises(runner.TrainingDiverged, match=r"NaN/Inf .* last good checkpoint \(update 2\)"):
        runner.train(cfg, tmp_path / "nan", progress=False)
    monkeypatch.setattr(runner, "make_train", real)
    s = _restore(tmp_path / "nan")
    assert int(s.update) == 2
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(s.params))


def test_unreadable_or_mismatched_checkpoint_is_a_clear_error(tmp_path, mappo_run):
    with pytest.raises(checkpoint.CheckpointError, match="not a run folder"):
        checkpoint.load_config(tmp_path)
    (tmp_path / "config.json").write_text("{not json")
    with pytest.raises(checkpoint.CheckpointError, match="not a valid aswarm run config"):
        checkpoint.load_config(tmp_path)
    cfg = TrainConfig(method="mappo", **SMALL)
    run = Path(shutil.copytree(mappo_run, tmp_path / "r"))  # changed below
    # The policy-only copy (how the shipped pretrained policy is made) restores the same arrays.
    from aswarm.analysis import evaluate

    small = checkpoint.copy_policy(run, tmp_path / "policy-only")
    assert not any(small.rglob("state"))
    chex.assert_trees_all_equal(evaluate.load(run)[1], evaluate.load(small)[1])
    other = dataclasses.replace(cfg, actor_hidden=(16,))
    runner.write_config(run, other)
    with pytest.raises(checkpoint.CheckpointError, match="cannot be restored into this configuration"):
        _restore(run)


@pytest.mark.parametrize("bad,message", [
    (dict(method="magic"), r"invalid method='magic': allowed: attention_cbf"),
    (dict(gamma=1.5), r"invalid gamma=1.5: must be in \(0, 1\]"),
    (dict(num_envs=0), r"invalid num_envs=0: must be > 0"),
    (dict(actor_lr=float("nan")), r"invalid actor_lr=nan: must be a finite number"),
    (dict(minibatches=7), r"invalid minibatches=7: must divide"),
    (dict(target_tau=1.5), r"invalid target_tau=1.5: must be in \[0, 1\]"),
    (dict(correction_penalty=-1.0), r"invalid correction_penalty=-1.0: must be >= 0"),
    (dict(devices=-1), r"invalid devices=-1: must be >= 0"),
])
def test_bad_train_config_is_a_clear_error(bad, message):
    with pytest.raises(ValueError, match=message):
        TrainConfig(**bad)


def test_eval_errors_are_clear(tmp_path, monkeypatch):
    # (That the shipped policies load and fly is tests/test_safety_matrix.py's quick matrix: it flies them.)
    from aswarm.analysis import evaluate

    with pytest.raises(checkpoint.CheckpointError, match="does not exist"):
        evaluate.evaluate_checkpoint(tmp_path / "missing")
    with pytest.raises(ValueError, match="invalid episodes=0"):
        evaluate.evaluate_checkpoint(tmp_path, episodes=0)
    with pytest.raises(checkpoint.CheckpointError, match="unknown shipped policy 'pretrained:nowhere': allowed: "
                                                         "pretrained, pretrained:dynamic"):
        evaluate.evaluate_checkpoint("pretrained:nowhere")
    monkeypatch.setattr(evaluate, "PRETRAINED", tmp_path / "pretrained" / "race")  # an install without it
    with pytest.raises(checkpoint.CheckpointError, match="pretrained policy is missing from this install"):
        evaluate.evaluate_checkpoint("pretrained")


def test_cli_reports_bad_values_in_one_line(capsys):
    from aswarm import cli

    assert cli.main(["train", "--scenario", "nowhere"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["aswarm train: error: unknown scenario 'nowhere': allowed: hover, obstacles, race, dynamic, lab"]
    assert cli.main(["train", "--env", "num_agents=0"]) == 2
    assert "invalid num_agents=0" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        cli.main(["train", "--gamma", "abc"])
    assert e.value.code == 2 and "invalid gamma='abc': allowed: a number" in capsys.readouterr().err


def test_correction_penalty_charges_the_filters_correction_in_the_training_reward():
    from aswarm.agents.train import make_train

    # A low fixed gain makes the floor barrier slow every random descent faster than 0.25 m/s.
    base = dict(method="fixed_cbf", safety_filter=SafetyFilterConfig(fixed_gain=0.3), scenario="hover", num_envs=16,
                rollout_steps=8, minibatches=2, total_steps=16 * 8, env_overrides=GEOMETRIC)
    # The penalty is a value-only hyperparameter: one compiled trainer serves both values.
    _, init, update_chunk, _ = make_train(TrainConfig(**base), sweep_fields=("correction_penalty",))
    init, chunk = jax.jit(init), jax.jit(update_chunk, static_argnums=1)
    metrics = {}
    for c in (0.0, 5.0):
        _, m = chunk(init(jax.random.PRNGKey(0), {"correction_penalty": jnp.float32(c)}), 1)
        metrics[c] = {k: float(v[0]) for k, v in m.items()}
    m0, m5 = metrics[0.0], metrics[5.0]
    # The first rollout is the same (same params and keys): only the reward the learner sees differs.
    assert m0["safety/intervention_rate"] == m5["safety/intervention_rate"] > 0.05
    assert m0["safety/correction_penalty"] == 0.0 and m5["safety/correction_penalty"] > 0.0
    np.testing.assert_allclose(m0["train/step_reward"] - m5["train/step_reward"], m5["safety/correction_penalty"],
                               rtol=1e-4)
    assert m0["episode/episode_return"] == m5["episode/episode_return"]  # the env's return is not charged


def test_policy_with_k_nearest_neighbours_flies_other_swarm_sizes(tmp_path):
    from aswarm.analysis import evaluate

    cfg = TrainConfig(scenario="hover", method="attention_cbf", num_envs=16, rollout_steps=8, minibatches=2,
                      total_steps=16 * 8, env_overrides=GEOMETRIC + (("max_neighbours", 2), ("num_agents", 2)))
    run = runner.train(cfg, tmp_path / "k2", progress=False)
    # More drones than K (each sees its 2 nearest). Fewer than K (absent rows) is how it trained: 2 drones see 1.
    out = evaluate.evaluate_checkpoint(run, episodes=4, env_overrides=["num_agents=6"])
    assert out["num_agents"] == 6 and out["episodes"] == 4 and 0.0 <= out["drone_success_rate"] <= 1.0
    with pytest.raises(ValueError, match="observation layouts differ"):
        evaluate.evaluate_checkpoint(run, episodes=4, env_overrides=["num_agents=6", "max_neighbours=0"])


def test_target_critics_follow_the_critics_by_soft_updates():
    from aswarm.agents.train import make_train

    _, init, update_chunk, _ = make_train(TrainConfig(method="mappo", target_tau=0.25, **SMALL))
    ts = jax.jit(init)(jax.random.PRNGKey(0))
    chex.assert_trees_all_equal(ts.target, {k: ts.params[k] for k in ("critic", "cost_critic")})
    ts1, _ = jax.jit(update_chunk, static_argnums=1)(ts, 1)
    want = jax.tree.map(lambda t, p: 0.25 * p + 0.75 * t, ts.target, {k: ts1.params[k] for k in ts.target})
    chex.assert_trees_all_close(ts1.target, want, rtol=1e-6, atol=1e-7)
    assert not np.allclose(ts1.params["critic"]["params"]["MLP_0"]["Dense_0"]["kernel"],
                           ts.params["critic"]["params"]["MLP_0"]["Dense_0"]["kernel"])
    assert jax.eval_shape(make_train(TrainConfig(method="mappo", **SMALL))[1], jax.random.PRNGKey(0)).target == {}


def test_run_loads_its_env_as_stored_not_rebuilt_from_the_preset(tmp_path, monkeypatch):
    from aswarm.envs import presets
    from aswarm.training import run_config

    cfg = TrainConfig(method="mappo", **{**SMALL, "env_overrides": GEOMETRIC + (("cf.mass", 0.03),
                                                                            ("gains.max_tilt_deg", 20.0))})
    assert cfg.env.cf.mass == 0.03 and cfg.env.gains.max_tilt_deg == 20.0 and cfg.env.scenario == "hover"
    runner.write_config(tmp_path, cfg)
    # Editing a preset changes new runs only: the stored run keeps the env it was trained on.
    hover = presets.SCENARIOS["hover"]
    monkeypatch.setitem(presets.SCENARIOS, "hover",
                        dataclasses.replace(hover, preset={**hover.preset, "episode_seconds": 9.0}))
    assert TrainConfig(**SMALL).env.episode_seconds == 9.0
    loaded = checkpoint.load_config(tmp_path)
    assert loaded == cfg and loaded.env.episode_seconds == 6.0 and loaded.env.cf.mass == 0.03
    assert json.loads(run_config.dumps(loaded)) == json.loads((tmp_path / "config.json").read_text())
    # An old config.json without a usable env: one line naming the converter, which fills what is missing as the
    # old loader did (preset + env_overrides) and keeps what is stored.
    raw = json.loads((tmp_path / "config.json").read_text())
    del raw["env"]["episode_seconds"], raw["env"]["cf"]["kf"]
    raw["env"]["layout_jitter"] = 0.5
    (tmp_path / "config.json").write_text(json.dumps(raw))
    with pytest.raises(checkpoint.CheckpointError, match=r"holds no usable env .*`aswarm convert-run ") as e:
        checkpoint.load_config(tmp_path)
    assert "\n" not in str(e.value)
    from aswarm import cli

    assert cli.main(["convert-run", str(tmp_path)]) == 0
    fixed = checkpoint.load_config(tmp_path)
    assert fixed.env.episode_seconds == 9.0 and fixed.env.layout_jitter == 0.5 and fixed.env.cf.mass == 0.03
    assert fixed.env.cf.kf == envs.EnvConfig().cf.kf and (tmp_path / "config.json.orig").exists()
    del raw["env"]
    (tmp_path / "config.json").write_text(json.dumps(raw))
    with pytest.raises(checkpoint.CheckpointError, match="no 'env' section"):
        checkpoint.load_config(tmp_path)
    # The shipped policies' folders (env_overrides and an env section) load their env as stored.
    from aswarm.analysis import evaluate

    for folder in (evaluate.PRETRAINED, evaluate.PRETRAINED_GEOMETRIC):
        shipped = checkpoint.load_config(folder)
        stored = json.loads((folder / "config.json").read_text())["env"]
        loaded = json.loads(json.dumps(dataclasses.asdict(shipped.env)))
        # What it stores is kept; what it predates is the drone it was trained on (envs.config.LEGACY_DRONE).
        assert all(loaded[k] == v if not isinstance(v, dict) else {f: loaded[k][f] for f in v} == v
                   for k, v in stored.items())
        if "controller" not in stored:
            assert shipped.env.controller == "geometric" and not shipped.env.randomize.enabled
            assert shipped.env.command_accel_limit == 0.0
    fw = checkpoint.load_config(evaluate.PRETRAINED)
    assert (fw.env.controller, fw.env.command_accel_limit, fw.safety_filter.lookahead_scale) == ("pid", 3.0, 0.9)
    # Fields added after it (session 22) read back as the drone and scene it was trained on: rotors that slow
    # down with the same time constant as they speed up, cylinders at one speed.
    assert fw.env.cf.motor_tau_down == 0.0 and fw.env.moving_speed_scale == (1.0, 1.0)
    assert envs.EnvConfig().cf.motor_tau_down == 0.108


def test_every_nested_env_field_is_settable_with_one_line_errors(capsys):
    from aswarm import cli, config_args

    got = config_args.parse_assignments(["cf.mass=0.03", "gains.max_tilt_deg=20", "num_agents=2"], envs.EnvConfig)
    assert got == {"cf.mass": 0.03, "gains.max_tilt_deg": 20.0, "num_agents": 2}
    env = config_args.replace_fields(envs.EnvConfig(), got)
    assert (env.cf.mass, env.gains.max_tilt_deg, env.num_agents, env.cf.kf) == (0.03, 20.0, 2, envs.EnvConfig().cf.kf)
    for item, message in [
        ("cf.mas=1", r"unknown env config field 'cf.mas': allowed: cf.arm_length, .*cf.mass"),
        ("gainz.kp_rate=1", r"unknown env config field 'gainz.kp_rate': allowed: .*gains.FIELD"),
        ("cf=1", r"invalid cf: a group of fields; allowed: cf.arm_length"),
        ("num_agents.x=1", r"unknown env config field 'num_agents.x': num_agents has no fields"),
        ("gains.max_tilt_deg=steep", r"invalid gains.max_tilt_deg='steep': allowed: a number"),
        ("cf.inertia=1,x,3", r"invalid cf.inertia='1,x,3': allowed: comma-separated floats"),
    ]:
        with pytest.raises(ValueError, match=message):
            config_args.parse_assignments([item], envs.EnvConfig)
    # From the command line, before anything compiles: the same one line, exit 2; validation of the value too.
    assert cli.main(["train", "--env", "cf.mas=1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("aswarm train: error: unknown env config field 'cf.mas': allowed: cf.")
    assert cli.main(["train", "--env", "gains.kp_rate=nan"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["aswarm train: error: invalid gains.kp_rate='nan': allowed: a finite number"]
    # Physical nonsense is refused by the env config in one line (MuJoCo's own error for a negative mass is
    # several lines and names no flag).
    for item, line in [("cf.mass=-1", "invalid cf.mass=-1.0: must be > 0"),
                       ("cf.inertia=1e-5,0,1e-5", "invalid cf.inertia=(1e-05, 0.0, 1e-05): must be > 0"),
                       ("cf.thrust_to_weight=0.9", "invalid cf.thrust_to_weight=0.9: must be > 1"),
                       ("gains.max_tilt_deg=95", "invalid gains.max_tilt_deg=95.0: must be in (0, 90) degrees")]:
        assert cli.main(["train", "--env", item]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("aswarm train: error: " + line), err


def test_resume_applies_budget_flags_and_refuses_the_others(tmp_path, capsys):
    from aswarm import cli

    # SMALL's sizes and chunks of 2 updates: its programs, compiled by the tests above, are in the persistent cache
    # (a chunk of 1 update is a program of its own, some 10 s to compile).
    flags = ["--scenario", "hover", "--method", "mappo", "--num-envs", "32", "--rollout-steps", "8",
             "--minibatches", "2", "--epochs", "2", "--updates-per-chunk", "2", "--quiet"]
    run = tmp_path / "r"
    assert cli.main(["train", *flags, *GEOMETRIC_FLAGS, "--total-steps", str(32 * 8 * 2), "--out", str(run)]) == 0
    capsys.readouterr()
    for extra, flag in [(["--actor-lr", "0.1"], "--actor-lr"), (["--num-envs", "64"], "--num-envs"),
                        (["--method", "a2c"], "--method"), (["--env", "num_agents=2"], "--env"),
                        (["--out", str(tmp_path / "x")], "--out"), (["--total-steps", "10"], "--total-steps")]:
        assert cli.main(["train", "--resume", str(run), *extra]) == 2, extra
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"aswarm train: error: invalid {flag}"), err
        assert "allowed" in err[0]
    assert len(runner.read_metrics(run)) == 2 and checkpoint.load_config(run).total_steps == 32 * 8 * 2
    # The flags it was trained with may be given again; --total-steps extends the run and is stored.
    assert cli.main(["train", "--resume", str(run), *flags, "--total-steps", str(32 * 8 * 4),
                     "--checkpoint-minutes", "0.5"]) == 0
    cfg = checkpoint.load_config(run)
    assert (cfg.total_steps, cfg.checkpoint_minutes) == (32 * 8 * 4, 0.5)
    assert [r["update"] for r in runner.read_metrics(run)] == [1, 2, 3, 4]
    assert checkpoint.manager(run).latest_step() == 4


def test_progress_shows_the_chunks_episodes_weighted_and_keeps_them_through_a_chunk_without_any():
    from aswarm.training.runner import chunk_episode_means

    # Trial 0 ends 2 episodes at success 1.0 and 6 at 0.5 (update means); trial 1 ends none.
    metrics = {"episodes": np.array([[2.0, 0.0, 6.0], [0.0, 0.0, 0.0]]),
               "episode/success": np.array([[1.0, 0.0, 0.5], [0.0, 0.0, 0.0]]),
               "episode/collision": np.array([[0.0, 0.0, 0.25], [0.0, 0.0, 0.0]]),
               "episode/episode_return": np.array([[10.0, 0.0, 2.0], [0.0, 0.0, 0.0]])}
    shown = chunk_episode_means(metrics, None)
    np.testing.assert_allclose(shown["episode/success"][0], (2 * 1.0 + 6 * 0.5) / 8)
    np.testing.assert_allclose(shown["episode/collision"][0], 6 * 0.25 / 8)
    np.testing.assert_allclose(shown["episode/episode_return"][0], (20 + 12) / 8)
    assert np.isnan(shown["episode/success"][1])  # nothing seen yet
    quiet = {k: np.zeros_like(v) for k, v in metrics.items()}
    again = chunk_episode_means(quiet, shown)
    np.testing.assert_allclose(again["episode/success"], shown["episode/success"])


def test_the_trainers_rollout_and_learn_compose_to_its_update():
    from aswarm.agents.train import make_trainer

    t = make_trainer(TrainConfig(method="mappo", **SMALL))
    ts = jax.jit(t.init)(jax.random.PRNGKey(0))
    whole, m_whole = jax.jit(t.update_chunk, static_argnums=1)(ts, 1)
    _, k_roll, k_perm = jax.random.split(ts.key, 3)
    env_state, tr = jax.jit(t.rollout)(ts, k_roll)
    chex.assert_shape(tr.reward, (SMALL["rollout_steps"], SMALL["num_envs"], 1))
    halves, m_halves = jax.jit(t.learn)(ts, env_state, tr, k_perm)
    assert int(halves.update) == int(whole.update) == 1
    # Compiled apart, XLA may fuse the sums otherwise: the same numbers to float round-off.
    for a, b in zip(jax.tree.leaves(halves.params), jax.tree.leaves(whole.params)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(float(m_halves["train/loss"]), float(m_whole["train/loss"][0]), rtol=1e-4)


def test_loop_timing_and_the_time_a_curve_reached_its_target():
    from aswarm.analysis.train_bench import first_time_at

    # Chunks of 10 updates from update 20 (a resumed run): 30 s with the compile, then 8 s, 8 s, and a last,
    # shorter chunk of 2 updates that compiles its own length (5 s): only the 8 s chunks are steady.
    t = runner.loop_timing([(10, 30.0), (10, 8.0), (10, 8.0), (2, 5.0)], steps_per_update=100, start=20)
    assert t["updates"] == 32 and t["env_steps"] == 3200 and t["loop_s"] == 51.0
    assert t["first_chunk_s"] == 30.0 and t["first_chunk_updates"] == 10
    assert t["env_steps_per_s"] == pytest.approx(3200 / 51) and t["steady_env_steps_per_s"] == pytest.approx(125.0)
    assert t["chunk_ends"] == [[30, 30.0], [40, 38.0], [50, 46.0], [52, 51.0]]
    assert runner.loop_timing([(10, 30.0)], 100)["steady_env_steps_per_s"] is None
    # One chunk length for the whole loop where one from 10 down to 3 divides it (the race's 488 updates: 8; the GPU
    # file's 8M steps, 244 updates: 4).
    assert [runner.chunk_length(u, 10) for u in (488, 610, 487, 6, 1, 244)] == [8, 10, 10, 6, 10, 4]
    # Success per update from update 28; update 32 ended no episode and does not count towards the window of 3.
    succ = [0.0, 0.5, 1.0, 1.0, None, 0.9, 1.0, 1.0]
    rows = [{"update": 28 + i, "episodes": 0.0 if s is None else 4.0, "episode/success": s or 0.0}
            for i, s in enumerate(succ)]
    # Windows of the updates that ended episodes: 0.5 at update 30 (its chunk ends at update 30: 30 s), 0.83 at
    # 31 (chunk to 40: 38 s), 0.97 at 33, 34 and 35.
    assert first_time_at(rows, t["chunk_ends"], 0.4, window=3) == 30.0
    assert first_time_at(rows, t["chunk_ends"], 0.8, window=3) == 38.0
    assert first_time_at(rows, t["chunk_ends"], 0.95, window=3) == 38.0
    assert first_time_at(rows, t["chunk_ends"], 0.99, window=3) is None


def test_a_run_writes_its_timing_and_the_command_prints_it(mappo_run, capsys):
    from aswarm import cli

    run = mappo_run
    t = json.loads((run / runner.TIMING).read_text())
    assert t["updates"] == 4 and t["env_steps"] == 4 * 32 * 8 and t["first_chunk_updates"] == 2
    assert t["chunk_ends"][-1][0] == 4 and 0 < t["first_chunk_s"] <= t["loop_s"] <= t["train_s"]
    assert 0 <= t["host_s"] < t["loop_s"] and t["steady_env_steps_per_s"] > 0
    cli._print_timing(run)
    line = capsys.readouterr().out.strip()
    # (Minutes: the tiny run takes seconds, but a loaded machine has taken it past one.)
    assert re.match(r"trained 1,024 env steps in \d+ min \d+ s", line) and "after the first chunk" in line, line


def test_wall_times_round_to_the_second_before_splitting_minutes():
    # 659.6 s printed "10 min 60 s" when minutes and seconds were split before rounding.
    assert [runner.minutes_seconds(s) for s in (0.4, 59.4, 59.6, 659.6, 3600.2)] == [
        "0 min 0 s", "0 min 59 s", "1 min 0 s", "11 min 0 s", "60 min 0 s"]


def _fresh_state(config: TrainConfig, stacked: int = 0):
    """A train state's networks and normaliser as ``make_train``'s init lays them out (the rest is not read)."""
    from brax.training.acme import running_statistics

    from aswarm.agents.train import Agent, TrainState

    agent = Agent.build(config)
    params = agent.init_params(jax.random.PRNGKey(7))
    obs_norm = running_statistics.init_state(jax.ShapeDtypeStruct((agent.env.observation_size,), jnp.float32))
    if stacked:
        params, obs_norm = jax.tree.map(lambda x: jnp.stack([x] * stacked), (params, obs_norm))
    return TrainState(params=params, opt_state=None, obs_norm=obs_norm, env_state=None, key=None, update=None,
                      env_steps=None)


@pytest.mark.parametrize("stacked", [0, 2])
def test_init_from_copies_the_networks_that_fit_and_keeps_the_others_fresh(stacked):
    from aswarm.analysis import evaluate

    _, source = evaluate.load("pretrained:obstacles")  # 4 drones, joint critic over their 4 observations
    config = TrainConfig(scenario="obstacles", init_from="pretrained:obstacles",
                         env_overrides=(("num_agents", 8), ("max_neighbours", 3)))
    state = _fresh_state(config, stacked)
    lines = []
    out = runner.warm_start(state, config.init_from, stacked=bool(stacked), log=lines.append)
    for i in range(max(stacked, 1)):  # every trial of a stacked (sweep) state starts from the same networks
        row = functools.partial(jax.tree.map, lambda x, i=i: x[i] if stacked else x)
        chex.assert_trees_all_equal(row(out.params["actor"]), source["params"]["actor"])
        chex.assert_trees_all_equal(row(out.params["cbf"]), source["params"]["cbf"])
        chex.assert_trees_all_equal(row(out.obs_norm), source["obs_norm"])
    # The joint critic of 8 drones has another input width than the source's 4: it keeps its own weights.
    chex.assert_trees_all_equal(out.params["critic"], state.params["critic"])
    assert lines == ["init_from pretrained:obstacles: copied actor, cbf; fresh cost_critic, critic"]
    # A pooled critic from a joint one's checkpoint: other networks altogether, so it starts fresh too.
    pooled = dataclasses.replace(config, critic="pooled")
    runner.warm_start(_fresh_state(pooled), pooled.init_from, log=lines.append)
    assert lines[-1] == "init_from pretrained:obstacles: copied actor, cbf; fresh cost_critic, critic"


def test_init_from_a_policy_of_another_observation_layout_is_a_clear_error():
    # Two neighbour rows where the source observed three.
    config = TrainConfig(scenario="obstacles", init_from="pretrained:obstacles", env_overrides=(("max_neighbours", 2),))
    with pytest.raises(checkpoint.CheckpointError, match=r"invalid init_from='pretrained:obstacles'.*layout"):
        runner.warm_start(_fresh_state(config), config.init_from)
    with pytest.raises(checkpoint.CheckpointError, match="unknown shipped policy 'pretrained:nope'"):
        runner.warm_start(_fresh_state(config), "pretrained:nope")


def test_the_gain_target_spans_the_fitted_range_the_network_outputs():
    """On the firmware drone the filter's gains are fitted (scaled down) to its lag. The CBF loss's target must span
    the same range as the network: with the config's unfitted bounds, the target where no cost follows (2.0) lay
    above anything the network could output (1.47), which pinned it at its maximum in every state (session 30)."""
    from aswarm.agents import losses
    from aswarm.agents.train import make_trainer

    hover = dict(SMALL, env_overrides=())  # the default drone: firmware PID, rotor lag, fitted gains
    t = make_trainer(TrainConfig(method="attention_cbf", **hover))
    sf, cbf = TrainConfig().safety_filter, t.agent.cbf
    assert cbf.gain_max < sf.gain_max  # fitted: this test means something only where the range was scaled
    h = t.hparams({})
    assert (h["gain_min"], h["gain_max"]) == pytest.approx((cbf.gain_min, cbf.gain_max))
    target = losses.gain_target(jnp.array([0.0, 0.5, 3.0]), h["gain_min"], h["gain_max"])
    np.testing.assert_allclose(target, [cbf.gain_max, (cbf.gain_min + cbf.gain_max) / 2, cbf.gain_min], rtol=1e-6)
    # Swept bounds are the config's numbers, fitted the same way.
    swept = make_trainer(TrainConfig(method="attention_cbf", **hover), ("gain_max",))
    assert swept.hparams({"gain_max": 1.6})["gain_max"] == pytest.approx(1.6 * cbf.gain_max / sf.gain_max)
    # A filter not fitted to its drone keeps the config's numbers.
    unfitted = SafetyFilterConfig(fit_to_drone=False)
    plain = make_trainer(TrainConfig(method="attention_cbf", safety_filter=unfitted, **SMALL)).hparams({})
    assert (plain["gain_min"], plain["gain_max"]) == (sf.gain_min, sf.gain_max)

"""Recovery that matches the promise: damaged or foreign checkpoints, absurd inputs, one-line errors.

Every case was found by an attack on a tiny ``hover``/``mappo`` run; one such run (module fixture, three
checkpoints) serves them all, copied before a test damages or edits it.
"""

from __future__ import annotations

import json
import shutil
import time

import chex
import jax
import numpy as np
import pytest
from drones import GEOMETRIC

from aswarm import cli
from aswarm.agents.config import TrainConfig
from aswarm.analysis import evaluate
from aswarm.flight import bench
from aswarm.flight import runtime as fc
from aswarm.training import checkpoint, runner, sweep

TINY = TrainConfig(scenario="hover", method="mappo", num_envs=8, rollout_steps=16, updates_per_chunk=2,
                   total_steps=8 * 16 * 6, checkpoint_minutes=1e-6, actor_hidden=(8,), critic_hidden=(8,),
                   env_overrides=GEOMETRIC)
NOISE = "Event loop is closed"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A finished run with checkpoints at updates 2, 4 and 6 (one per chunk)."""
    return runner.train(TINY, tmp_path_factory.mktemp("recovery") / "run", progress=False)


def _copy(run, tmp_path, name="copy"):
    return shutil.copytree(run, tmp_path / name)


def _damage(step_dir, item="*"):
    """Truncate the data files of one step (what a full disk or a half-copied folder leaves)."""
    files = [f for f in step_dir.glob(f"{item}/**/d/*") if f.is_file()]
    assert files, step_dir
    for f in files:
        f.write_bytes(f.read_bytes()[:10])


def _one_line(text: str) -> str:
    """The lines of ``text`` that are not empty; the test fails unless there is exactly one."""
    lines = [x for x in text.splitlines() if x.strip()]
    assert len(lines) == 1, text
    return lines[0]


def _quiet(capsys) -> tuple[str, str]:
    time.sleep(0.5)  # tensorstore's threads reported the closed event loop after the error had returned
    out, err = capsys.readouterr()
    assert NOISE not in out + err
    return out, err


def _edit_train_config(run_dir, **fields):
    path = run_dir / "config.json"
    raw = json.loads(path.read_text())
    raw["train"].update(fields)
    path.write_text(json.dumps(raw))


def test_checkpoints_store_what_shapes_the_state(run):
    mngr = checkpoint.manager(run)
    assert mngr.all_steps() == [2, 4, 6]
    fp = checkpoint.stored_fingerprint(mngr, 6)
    assert fp["method"] == "mappo" and fp["actor_hidden"] == [8] and fp["critic_hidden"] == [8]
    assert fp["num_envs"] == 8 and fp["num_gates"] == 0 and fp["obs_size"] > 0
    assert set(fp) == set(checkpoint.STATE_KEYS)


def test_resume_skips_a_damaged_newest_checkpoint_in_one_line(run, tmp_path, capsys):
    copy = _copy(run, tmp_path)
    _damage(copy / "checkpoints" / "6")
    capsys.readouterr()
    runner.train(None, copy, resume=True, progress=False)
    out, err = _quiet(capsys)
    said = [x for x in (out + err).splitlines() if "cannot be restored" in x]
    assert len(said) == 1 and "checkpoint 6 " in said[0] and "resuming from checkpoint 4" in said[0], out + err
    assert (copy / checkpoint.UNREADABLE_DIR / "6").is_dir()
    assert checkpoint.manager(copy).all_steps()[-1] == 6
    # Update 6 trained again from 4 is the update 6 that was lost, bit for bit.
    chex.assert_trees_all_equal(evaluate.load(copy)[1], evaluate.load(run)[1])


def test_no_restorable_checkpoint_is_one_error_and_moves_nothing(run, tmp_path):
    from aswarm.agents.train import make_train

    copy = _copy(run, tmp_path)
    for step in (2, 4, 6):
        _damage(copy / "checkpoints" / str(step), "state")
    _, init, _, _ = make_train(TINY)
    like = jax.tree.map(lambda s: np.zeros(s.shape, s.dtype), jax.eval_shape(init, jax.random.PRNGKey(0)))
    with pytest.raises(checkpoint.CheckpointError, match=r"none of the checkpoints \(6, 4, 2\) can be restored"):
        checkpoint.restore_newest(checkpoint.manager(copy), like)
    assert checkpoint.manager(copy).all_steps() == [2, 4, 6]
    assert not (copy / checkpoint.UNREADABLE_DIR).exists()


@pytest.mark.parametrize("command", ["eval", "export"])
def test_eval_and_export_of_a_damaged_policy_are_one_line(run, tmp_path, capsys, command):
    copy = _copy(run, tmp_path)
    _damage(copy / "checkpoints" / "6", "policy")
    capsys.readouterr()
    extra = ["--episodes", "2"] if command == "eval" else ["--out", str(tmp_path / "bundle")]
    assert cli.main([command, "--checkpoint", str(copy), *extra]) == 2
    out, err = _quiet(capsys)
    line = _one_line(err)
    assert line.startswith(f"aswarm {command}: error: checkpoint ") and "cannot be restored" in line
    assert not (tmp_path / "bundle").exists()


@pytest.mark.parametrize("edit,named", [
    (dict(actor_hidden=[16]), "actor_hidden=[8]"),  # was a flax traceback, exit 1
    (dict(method="a2c"), "method=mappo"),  # was resumed without a word
])
def test_resume_refuses_a_checkpoint_of_another_configuration(run, tmp_path, capsys, edit, named):
    copy = _copy(run, tmp_path)
    _edit_train_config(copy, **edit)
    capsys.readouterr()
    assert cli.main(["train", "--resume", str(copy), "--quiet"]) == 2
    _, err = _quiet(capsys)
    line = _one_line(err)
    assert "was written for" in line and named in line and "refusing" in line, line
    assert checkpoint.manager(copy).all_steps() == [2, 4, 6]


def test_eval_refuses_a_policy_of_other_network_sizes(run, tmp_path, capsys):
    copy = _copy(run, tmp_path)
    _edit_train_config(copy, critic_hidden=[8, 8])
    capsys.readouterr()
    assert cli.main(["eval", "--checkpoint", str(copy), "--episodes", "2"]) == 2
    line = _one_line(_quiet(capsys)[1])
    assert "was written for critic_hidden=[8]" in line and "critic_hidden=[8, 8]" in line, line


def test_checkpoints_without_a_fingerprint_still_load(run, tmp_path):
    copy = _copy(run, tmp_path)
    for meta in (copy / "checkpoints").glob("*/_CHECKPOINT_METADATA"):
        raw = json.loads(meta.read_text())
        del raw["custom_metadata"]["fingerprint"]
        meta.write_text(json.dumps(raw))
    assert checkpoint.stored_fingerprint(checkpoint.manager(copy), 6) is None
    chex.assert_trees_all_equal(evaluate.load(copy)[1], evaluate.load(run)[1])
    # The policy shipped before the firmware drone was written before fingerprints existed.
    mngr = checkpoint.manager(evaluate.PRETRAINED_GEOMETRIC)
    assert checkpoint.stored_fingerprint(mngr, mngr.latest_step()) is None
    config, restored = evaluate.load(evaluate.PRETRAINED_GEOMETRIC)
    assert config.scenario == "race" and int(restored["update"]) == mngr.latest_step()
    # A policy copy keeps the fingerprint.
    small = checkpoint.copy_policy(run, tmp_path / "policy-only")
    assert checkpoint.stored_fingerprint(checkpoint.manager(small), 6) == checkpoint.stored_fingerprint(
        checkpoint.manager(run), 6)


def test_nan_at_the_first_update_says_no_checkpoint_was_written(tmp_path, monkeypatch):
    real = runner.make_train

    def poisoned(config, **kw):
        agent, init, chunk, train = real(config, **kw)

        def init_nan(key):  # the update chunk stays the fixture's program: a compile-cache hit
            ts = init(key)
            return ts.replace(params=jax.tree.map(lambda p: p * np.nan, ts.params))

        return agent, init_nan, chunk, train

    monkeypatch.setattr(runner, "make_train", poisoned)
    with pytest.raises(runner.TrainingDiverged) as e:
        runner.train(TINY, tmp_path / "nan", progress=False)
    msg = str(e.value)
    assert "at update 1;" in msg and "no checkpoint was written yet" in msg and "None" not in msg, msg


@pytest.mark.parametrize("argv,named", [
    (["--actor-hidden", "0"], "invalid actor_hidden=(0,)"),
    (["--actor-hidden", "64,0"], "invalid actor_hidden=(64, 0)"),
    (["--actor-hidden", "64,-3"], "invalid actor_hidden=(64, -3)"),
    (["--cbf-hidden", "0,64"], "invalid cbf_hidden=(0, 64)"),
    (["--actor-lr", "nan"], "--actor-lr"),  # was the whole usage of `aswarm train`, then the error
])
def test_bad_train_flags_are_one_line(tmp_path, capsys, argv, named):
    try:
        rc = cli.main(["train", *argv, "--out", str(tmp_path / "r")])
    except SystemExit as e:  # argparse's own errors exit from inside parse_args
        rc = e.code
    assert rc == 2
    line = _one_line(capsys.readouterr().err)
    assert line.startswith("aswarm train: error:") and named in line, line
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("hidden", [(0,), (64, 0), (64, -3)])
def test_zero_width_layers_are_refused_by_the_config(hidden):
    with pytest.raises(ValueError, match=r"invalid critic_hidden=.*allowed: layer widths > 0"):
        TrainConfig(critic_hidden=hidden)


HEAD = 'scenario = "hover"\ntotal_steps = 128\nseeds = [0]\n'


@pytest.mark.parametrize("text,message", [
    (HEAD + "[grid]\nactor_lr = [1e-3, 2e-3, 0.001]\n", "[grid] actor_lr: value 0.001 is listed twice"),
    (HEAD + "[grid]\nactor_hidden = [[8], [8]]\n", "value (8,) is listed twice"),
    (HEAD + "[grid]\nactor_lr = [" + ", ".join(f"{i}e-5" for i in range(1, 101)) + "]\n"
     "clip = [" + ", ".join(f"0.{i:03d}" for i in range(1, 101)) + "]\n",
     "10000 trials (10000 configurations x 1 seeds) is more than max_trials = 256"),
    ("max_trials = 1\n" + HEAD + "[grid]\nclip = [0.1, 0.2]\n", "2 trials"),
    ("max_trials = 0\n" + HEAD + "[grid]\nclip = [0.1]\n", "invalid max_trials = 0"),
])
def test_bad_sweep_grid_is_refused_before_compile(tmp_path, monkeypatch, capsys, text, message):
    def no_compile(*args, **kwargs):
        raise AssertionError("compiled before the sweep file was checked")

    monkeypatch.setattr(jax, "jit", no_compile)
    path = tmp_path / "bad.toml"
    path.write_text(text)
    assert cli.main(["sweep", str(path), "--out", str(tmp_path / "out")]) == 2
    assert message in _one_line(capsys.readouterr().err)
    assert not (tmp_path / "out").exists()


def test_many_trials_run_when_the_file_or_yes_allows(tmp_path):
    path = tmp_path / "big.toml"
    path.write_text(HEAD + "[grid]\nclip = [0.1, 0.2, 0.3]\n")
    assert len(sweep.load(path).trials) == 3
    path.write_text("max_trials = 2\n" + HEAD + "[grid]\nclip = [0.1, 0.2, 0.3]\n")
    with pytest.raises(ValueError, match="3 trials .* more than max_trials = 2; allowed: .* --yes"):
        sweep.load(path)
    assert len(sweep.load(path, yes=True).trials) == 3
    path.write_text("max_trials = 3\n" + HEAD + "[grid]\nclip = [0.1, 0.2, 0.3]\n")
    assert len(sweep.load(path).trials) == 3


def test_eval_in_batches_equals_one_program(run):
    config, agent, restored = evaluate.load_agent(run)
    key = jax.random.PRNGKey(10_000)
    args = (agent, restored["params"], restored["obs_norm"], agent.env, 4, key)
    rec, ended, rate = evaluate.rollout_episodes(*args)  # 4 <= EVAL_BATCH: one program, as before
    rec_b, ended_b, rate_b = evaluate.rollout_episodes(*args, batch=2)
    assert set(rec) == set(rec_b)
    for name in rec:
        a, b = np.asarray(rec[name]), np.asarray(rec_b[name])
        if np.issubdtype(a.dtype, np.floating):
            # The same episodes; XLA:CPU may vectorise a batch of 2 otherwise than one of 4, so sums can differ in
            # their last bits on some CPUs (an AMD EPYC: episode returns 1.4e-6 apart), never in what happened.
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6, err_msg=name)
        else:
            np.testing.assert_array_equal(a, b, err_msg=name)
    np.testing.assert_array_equal(np.asarray(ended), ended_b)
    assert float(rate) == pytest.approx(rate_b, rel=1e-6)
    with pytest.raises(ValueError, match="invalid batch=0"):
        evaluate.rollout_episodes(*args, batch=0)


def test_flight_controller_names_what_obstacles_may_be():
    bundle = bench.synthetic_bundle()
    ctl = fc.FlightController(bundle, 4)
    ctl.reset(gates=np.array(bundle.manifest["course"]["gates"]))
    pos = np.array([[3.0, -3.5, 1.0], [2.2, -3.5, 1.0], [1.4, -3.5, 1.0], [0.6, -3.5, 1.0]])
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (4, 1))
    assert np.all(np.isfinite(ctl.step(pos, quat, np.zeros(4), now=0.0).velocity))
    with pytest.raises(TypeError, match=r"obstacles is a ndarray: allowed: None or Obstacles\(pos="):
        ctl.step(pos, quat, np.full(4, 0.02), now=0.02, obstacles=np.zeros((3, 2)))

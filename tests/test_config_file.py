"""`aswarm train --config FILE`, `--help`'s field list and `--wandb` (offline, into a temporary folder)."""

import dataclasses
import json
import struct
import tomllib
from pathlib import Path

import pytest
from drones import GEOMETRIC, GEOMETRIC_FLAGS

from aswarm import cli, config_args, envs
from aswarm.agents.config import TrainConfig
from aswarm.core.safety import SafetyFilterConfig
from aswarm.training import checkpoint, run_config, runner, wandb_log

RACE = Path(__file__).parent.parent / "configs" / "race.toml"


def _captured_train(monkeypatch) -> list:
    """Make `aswarm train` hand its config to a list instead of training (nothing compiles)."""
    got = []

    def train(config, run_dir=None, **kw):
        got.append(config)
        return Path(run_dir or "runs/not-trained")  # no timing.json there: nothing to print

    monkeypatch.setattr(runner, "train", train)
    return got


def test_race_example_sets_every_field_and_equals_the_cli_defaults(monkeypatch):
    config = run_config.load_file(RACE)
    assert config == TrainConfig() and config.env_overrides == ()
    # Every field is in the file, explicitly: the example is also the list of what a file can set.
    doc = tomllib.loads(RACE.read_text())
    train_leaves = {k for k in config_args.leaf_types(TrainConfig) if k not in ("env", "env_overrides")}
    assert set(config_args.flatten({k: v for k, v in doc.items() if k != "env"}, train_leaves)) == train_leaves
    env_leaves = config_args.leaf_types(envs.EnvConfig)
    assert set(config_args.flatten(doc["env"], env_leaves)) == set(env_leaves)
    got = _captured_train(monkeypatch)
    assert cli.main(["train", "--config", str(RACE), "--quiet"]) == 0
    assert cli.main(["train", "--quiet"]) == 0
    assert got[0] == got[1] == TrainConfig()


def test_the_gpu_example_is_the_defaults_with_a_gpu_sized_batch():
    config = run_config.load_file(RACE.with_name("race_gpu.toml"))
    sized = dict(num_envs=2048, rollout_steps=16, minibatches=8, total_steps=12_000_000)
    assert config == dataclasses.replace(TrainConfig(), **sized)
    # A gradient step sees as many env steps as one of the defaults' (4,096): the GPU file takes more of them.
    per_step = config.num_envs * config.rollout_steps // config.minibatches
    assert per_step == TrainConfig().num_envs * TrainConfig().rollout_steps // TrainConfig().minibatches == 4096


def test_config_file_fields_and_flags_over_them(tmp_path, monkeypatch):
    path = tmp_path / "mine.toml"
    path.write_text('scenario = "hover"\nmethod = "mappo"\nactor_hidden = [32, 16]\ntotal_steps = 1_000\n'
                    "gain_min = 0.4\n"  # the safety filter's old flat name, as flags and sweep files take it
                    "[safety_filter]\nmargin = 0.2\n"
                    "[env]\nnum_agents = 2\narena_high = [4, 4, 2]\ncf.mass = 0.03\n"  # ints widen to floats
                    "[env.randomize]\nenabled = false\n")
    config = run_config.load_file(path)
    assert (config.scenario, config.method, config.actor_hidden, config.total_steps) == ("hover", "mappo", (32, 16),
                                                                                        1000)
    assert config.safety_filter == SafetyFilterConfig(margin=0.2, gain_min=0.4)
    env = config.env
    assert (env.num_agents, env.arena_high, env.cf.mass, env.randomize.enabled) == (2, (4.0, 4.0, 2.0), 0.03, False)
    assert env.episode_seconds == envs.preset("hover").episode_seconds  # unset: the preset's
    # The record: what the file asks that the preset does not hold, then --env.
    assert dict(config.env_overrides) == {"num_agents": 2, "arena_high": (4.0, 4.0, 2.0), "cf.mass": 0.03,
                                          "randomize.enabled": False}
    # Flags override the file, field by field: train fields, the filter's, and env fields.
    got = _captured_train(monkeypatch)
    assert cli.main(["train", "--config", str(path), "--method", "a2c", "--safety-filter.margin", "0.1",
                     "--env", "num_agents=3", "--env", "cf.mass=0.04", "--quiet"]) == 0
    flagged = got[0]
    assert (flagged.method, flagged.actor_hidden, flagged.safety_filter.margin, flagged.safety_filter.gain_min) == (
        "a2c", (32, 16), 0.1, 0.4)
    assert (flagged.env.num_agents, flagged.env.cf.mass, flagged.env.arena_high) == (3, 0.04, (4.0, 4.0, 2.0))
    assert dict(flagged.env_overrides) == {**dict(config.env_overrides), "cf.mass": 0.04, "num_agents": 3}
    # A file of train fields alone takes another --scenario; one with env fields was written for its own.
    only_train = tmp_path / "train.toml"
    only_train.write_text("seed = 4\n")
    assert cli.main(["train", "--config", str(only_train), "--scenario", "hover", "--quiet"]) == 0
    assert got[1] == TrainConfig(scenario="hover", seed=4)
    assert cli.main(["train", "--config", str(path), "--scenario", "race"]) == 2


@pytest.mark.parametrize("text,message", [
    ("actor_lrr = 1\n", "unknown train config field 'actor_lrr': allowed: action_std_scale, "),
    ('actor_lr = "fast"\n', "actor_lr: invalid value 'fast' (str); allowed: a finite number"),
    ("anneal_lr = 1\n", "anneal_lr: invalid value 1 (int); allowed: true or false"),
    ("gamma = 1.5\n", r"invalid gamma=1.5: must be in (0, 1]"),
    ('method = "magic"\n', "invalid method='magic': allowed: attention_cbf, "),
    ("[safety_filter]\nmargn = 0.1\n", "unknown train config field 'safety_filter.margn': allowed: safety_filter."),
    ("[env]\nnum_agents = 0\n", "invalid num_agents=0: must be between 1 and 64"),
    ("[env.cf]\nmas = 1\n", "env: unknown env config field 'cf.mas': allowed: cf.arm_length"),
    ("[env]\ntrack_radii = [1.0]\n", "env: track_radii: invalid value [1.0] (list); allowed: a list of 2 values"),
    ("[env]\ncf = 1\n", "env: invalid cf: a group of fields; allowed: cf.arm_length"),
    ("env = 3\n", "invalid env = 3; allowed: a table of env fields"),
    ('scenario = "hover"\n[env]\nscenario = "race"\n', "invalid env.scenario='race': must equal scenario='hover'"),
    ("x = \n", "not valid TOML: "),
])
def test_a_bad_config_file_is_one_line_naming_the_field_and_exit_code_2(tmp_path, capsys, monkeypatch, text,
                                                                         message):
    got = _captured_train(monkeypatch)
    path = tmp_path / "bad.toml"
    path.write_text(text)
    assert cli.main(["train", "--config", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("aswarm train: error: ") and message in err[0], err
    assert str(path) in err[0] and not got  # the file is named; nothing was built past the check


def test_a_run_folders_config_json_reproduces_its_config(tmp_path, monkeypatch, capsys):
    config = TrainConfig(scenario="hover", method="fixed_cbf", seed=7, devices=1, safety_filter=SafetyFilterConfig(
        margin=0.11, fit_to_drone=False), env_overrides=GEOMETRIC + (("cf.mass", 0.03), ("num_agents", 2)))
    runner.write_config(tmp_path, config)
    assert run_config.load_file(tmp_path / "config.json") == checkpoint.load_config(tmp_path) == config
    got = _captured_train(monkeypatch)
    assert cli.main(["train", "--config", str(tmp_path / "config.json"), "--seed", "8", "--quiet"]) == 0
    assert got[0] == dataclasses.replace(config, seed=8)
    # A preset edited since: the run's env as stored, and the record says what now differs from the preset.
    from aswarm.envs import presets

    hover = presets.SCENARIOS["hover"]
    monkeypatch.setitem(presets.SCENARIOS, "hover",
                        dataclasses.replace(hover, preset={**hover.preset, "episode_seconds": 9.0}))
    again = run_config.load_file(tmp_path / "config.json")
    assert again.env == config.env and again.env.episode_seconds == 6.0
    assert dict(again.env_overrides) == {**dict(config.env_overrides), "episode_seconds": 6.0}
    # Older runs read as `aswarm eval` reads them (the shipped geometric race policy predates the firmware drone).
    from aswarm.analysis import evaluate

    for folder in (evaluate.PRETRAINED, evaluate.PRETRAINED_GEOMETRIC):
        stored, loaded = checkpoint.load_config(folder), run_config.load_file(folder / "config.json")
        assert loaded.env == stored.env and dataclasses.replace(loaded, env_overrides=stored.env_overrides) == stored
    (tmp_path / "x.json").write_text(json.dumps({"train": {}, "env": {}, "extra": 1}))
    with pytest.raises(ValueError, match=r"x.json: unknown section 'extra' of a run's config; allowed: train, env"):
        run_config.load_file(tmp_path / "x.json")
    assert cli.main(["train", "--resume", str(tmp_path), "--config", str(tmp_path / "config.json")]) == 2
    assert "invalid --config with --resume" in capsys.readouterr().err


def test_help_lists_every_field_with_its_default(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["train", "--help"])
    assert e.value.code == 0
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps lines where it likes
    defaults = TrainConfig()
    for name, kind in config_args.field_types(TrainConfig).items():
        if config_args.is_flag(kind) and name != "env_overrides":
            assert f"--{name.replace('_', '-')} {config_args.kind_name(kind)} default {getattr(defaults, name)!r}" \
                in text, name
    for name in config_args.field_types(SafetyFilterConfig):
        assert f"--safety-filter.{name.replace('_', '-')}" in text, name
    epilog = text[text.index("environment fields (--env FIELD=VALUE"):]
    preset = envs.preset("race")
    for name, kind in config_args.leaf_types(envs.EnvConfig).items():
        if name != "scenario":
            value = preset
            for part in name.split("."):
                value = getattr(value, part)
            assert f" {name} {config_args.kind_name(kind)} {value!r}" in epilog, name
    for flag in ("--config FILE", "--wandb", "--wandb-project", "--wandb-entity", "--wandb-name", "--wandb-mode"):
        assert flag in text


# --- Weights & Biases -------------------------------------------------------------------------------------------


def _tfrecords(path: Path):
    """The records of a TFRecord file (TensorBoard's event files): length, its CRC, data, its CRC."""
    data, pos = path.read_bytes(), 0
    while pos < len(data):
        (n,) = struct.unpack("<Q", data[pos:pos + 8])
        yield data[pos + 12:pos + 12 + n]
        pos += 12 + n + 4


def tensorboard_scalars(tb_dir: Path) -> dict:
    """{tag: {step: value}} of every scalar in a run's tb/ folder."""
    from tensorboardX.proto import event_pb2

    out = {}
    for path in tb_dir.glob("events.out.tfevents.*"):
        for raw in _tfrecords(path):
            event = event_pb2.Event.FromString(raw)
            for v in event.summary.value:
                out.setdefault(v.tag, {})[event.step] = v.simple_value
    return out


def wandb_records(path: Path) -> list:
    """The records of an offline W&B run file (run-ID.wandb): a 7-byte header, then LevelDB's log format (32 KiB
    blocks of chunks: CRC, length, type (full, first, middle, last), data) around protobuf Records."""
    from wandb.proto import wandb_internal_pb2

    data = path.read_bytes()
    assert data[:4] == b":W&B"
    block, pos, parts, out = 32768, 7, b"", []
    while pos + 7 <= len(data):
        if block - pos % block < 7:  # a block's tail too short for a header is padding
            pos += block - pos % block
            continue
        _, n, kind = struct.unpack("<IHB", data[pos:pos + 7])
        if kind == 0:
            pos += block - pos % block
            continue
        parts += data[pos + 7:pos + 7 + n]
        pos += 7 + n
        if kind in (1, 4):
            out.append(wandb_internal_pb2.Record.FromString(parts))
            parts = b""
    return out


# test_train.py's small hover run (its programs are in the persistent compile cache): 2 updates.
TINY = ["--scenario", "hover", "--method", "mappo", "--num-envs", "32", "--rollout-steps", "8", "--minibatches", "2",
        "--epochs", "2", "--updates-per-chunk", "2", "--total-steps", str(32 * 8 * 2), *GEOMETRIC_FLAGS, "--quiet"]


@pytest.fixture(scope="module")
def wandb_run(tmp_path_factory):
    """(run folder, W&B home, stderr) of a tiny run trained with --wandb, with no API key: offline."""
    pytest.importorskip("wandb")
    tmp = tmp_path_factory.mktemp("wandb")
    with pytest.MonkeyPatch.context() as mp:
        for var in ("WANDB_DIR", "WANDB_CONFIG_DIR", "WANDB_CACHE_DIR", "WANDB_DATA_DIR"):
            mp.setenv(var, str(tmp / "wandb-home"))
        mp.delenv("WANDB_API_KEY", raising=False)
        mp.delenv("WANDB_MODE", raising=False)
        mp.setenv("NETRC", str(tmp / "no-netrc"))
        import contextlib
        import io

        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            code = cli.main(["train", *TINY, "--out", str(tmp / "run"), "--wandb", "--wandb-project", "tests",
                             "--wandb-name", "tiny"])
    assert code == 0
    return tmp / "run", tmp / "wandb-home", err.getvalue()


def test_wandb_offline_logs_what_tensorboard_gets_and_the_runs_config(wandb_run):
    run, home, err = wandb_run
    assert "no API key" in err  # offline without one, and it says so
    files = list(home.glob("wandb/offline-run-*/run-*.wandb"))
    assert len(files) == 1
    records = wandb_records(files[0])
    history = {}  # {key: {step: value}}
    for r in records:
        if r.WhichOneof("record_type") == "history":
            step = r.history.step.num
            for item in r.history.item:
                history.setdefault("/".join(item.nested_key) or item.key, {})[step] = json.loads(item.value_json)
    tb = tensorboard_scalars(run / "tb")
    assert len(tb) > 20 and "train/loss" in tb and "episode/success" in tb
    for tag, values in tb.items():  # every scalar TensorBoard got, at the same updates (float32 there)
        assert tag in history, tag
        assert {s: pytest.approx(v, rel=1e-6, abs=1e-6) for s, v in values.items()} == \
            {s: history[tag][s] for s in values}, tag
    assert sorted(history["train/loss"]) == [1, 2]
    (run_record,) = [r.run for r in records if r.WhichOneof("record_type") == "run"]
    assert (run_record.project, run_record.display_name, run_record.run_group) == ("tests", "tiny", "run")
    sent = {item.key: json.loads(item.value_json) for item in run_record.config.update}
    assert {k: sent[k] for k in ("train", "env")} == json.loads((run / "config.json").read_text())


def test_training_again_from_a_runs_config_json_gives_the_same_run(wandb_run, tmp_path):
    run = wandb_run[0]
    again = tmp_path / "again"
    assert cli.main(["train", "--config", str(run / "config.json"), "--quiet", "--out", str(again)]) == 0
    assert (again / "config.json").read_text() == (run / "config.json").read_text()
    assert runner.read_metrics(again) == runner.read_metrics(run)


def test_wandb_mode_and_a_missing_package(tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("WANDB_API_KEY", raising=False)
    monkeypatch.delenv("WANDB_MODE", raising=False)
    netrc = tmp_path / "netrc"
    monkeypatch.setenv("NETRC", str(netrc))
    assert wandb_log.resolve_mode(None) == "offline"  # no netrc file at all
    netrc.write_text("machine api.wandb.ai login user password " + "0" * 40 + "\n")
    netrc.chmod(0o600)
    assert wandb_log.resolve_mode(None) == "online"
    monkeypatch.setenv("WANDB_MODE", "offline")
    assert wandb_log.resolve_mode(None) == "offline" and wandb_log.resolve_mode("online") == "online"
    # Where and how a run starts: into the run folder unless WANDB_DIR says otherwise, named after it.
    import sys
    import types

    calls = []
    fake = types.SimpleNamespace(init=lambda **kw: calls.append(kw) or "run", Settings=dict)
    monkeypatch.setitem(sys.modules, "wandb", fake)
    monkeypatch.delenv("WANDB_DIR", raising=False)
    log = wandb_log.start(wandb_log.WandbOptions(entity="lab"), TrainConfig(), tmp_path / "race-1", resumed=True)
    assert log.run == "run" and calls[0]["dir"] == str(tmp_path / "race-1") and calls[0]["mode"] == "offline"
    assert (calls[0]["name"], calls[0]["group"], calls[0]["project"], calls[0]["entity"], calls[0]["job_type"]) == (
        "race-1", "race-1", "aswarm", "lab", "resume")
    assert calls[0]["config"] == json.loads(run_config.dumps(TrainConfig()))
    # Without the package: one line naming the extra, before anything is built.

    got = _captured_train(monkeypatch)
    monkeypatch.setitem(sys.modules, "wandb", None)
    assert cli.main(["train", "--wandb"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "aswarm train: error: --wandb needs the wandb package: pip install 'aswarm[wandb]'"]
    assert not got

"""``aswarm export``: round trip, manifest, atomic writes, refusals and clear errors."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import zipfile

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.training.acme import running_statistics
from flax import struct

from aswarm import cli, envs
from aswarm.agents.config import TrainConfig
from aswarm.agents.train import Agent
from aswarm.analysis import evaluate
from aswarm.analysis.step_response import characterise
from aswarm.flight import bundle as fb
from aswarm.flight import export
from aswarm.training import checkpoint, runner


@struct.dataclass
class PolicyState:
    """What ``checkpoint.save`` needs of a train state to write the policy item."""

    params: dict
    obs_norm: running_statistics.RunningStatisticsState
    update: jax.Array


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A run folder as ``aswarm train`` leaves it (config.json and an orbax checkpoint), without training.

    Compiling the trainer for a tiny run took ~100 s on 2 cores; the checkpoint format is the same.
    The normalizer gets non-trivial statistics so that its round trip means something.
    """
    config = TrainConfig(scenario="race", num_envs=8, rollout_steps=4, total_steps=64,
                         env_overrides=(("num_agents", 3),))
    agent = Agent.build(config)
    d = agent.env.observation_size
    rng = np.random.default_rng(0)
    params = jax.jit(agent.init_params)(jax.random.PRNGKey(3))
    norm = running_statistics.init_state(jax.ShapeDtypeStruct((d,), jnp.float32))
    norm = norm.replace(mean=jnp.asarray(rng.normal(size=d), jnp.float32),
                        std=jnp.asarray(rng.uniform(0.1, 3.0, d), jnp.float32))
    path = tmp_path_factory.mktemp("runs") / "race-run"
    path.mkdir()
    runner.write_config(path, config)
    checkpoint.save(checkpoint.manager(path), 7, PolicyState(params, norm, jnp.asarray(7, jnp.int32)))
    return path


@pytest.fixture(scope="module")
def exported(run_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("bundles") / "race"
    return export.export(run_dir, out)


def test_round_trip_is_bit_identical(run_dir, exported):
    config, restored = evaluate.load(run_dir)
    want = export.policy_arrays(restored["params"], restored["obs_norm"])
    b = fb.load_bundle(exported)
    assert set(b.arrays) == set(want)
    for name, a in want.items():
        got = b.arrays[name]
        assert got.dtype == np.float32 and got.shape == a.shape
        assert np.array_equal(got.view(np.uint32), a.view(np.uint32)), name  # bit for bit
    np.testing.assert_array_equal(b.arrays["obs_norm/std"], np.asarray(restored["obs_norm"].std))
    assert "actor/MLP_0/Dense_0/kernel" in b.arrays and "cbf/W_Q/kernel" in b.arrays
    assert not any(k.startswith("critic") for k in b.arrays)  # the flight side needs no critic


def test_npz_holds_plain_arrays_only(exported):
    with zipfile.ZipFile(exported / fb.NPZ) as z:
        assert all(n.endswith(".npy") for n in z.namelist())
    with np.load(exported / fb.NPZ, allow_pickle=False) as z:  # would raise on any object array
        assert all(z[k].dtype == np.float32 for k in z.files)


def test_manifest_describes_the_policy(run_dir, exported):
    m = json.loads((exported / fb.MANIFEST).read_text())
    env = envs.make("race", num_agents=3)
    assert m["format"] == fb.FORMAT and m["format_version"] == fb.FORMAT_VERSION
    assert m["scenario"] == {"name": "race", "kind": "track", "env_overrides": {"num_agents": 3}}
    assert m["observation"]["fields"] == env.obs_layout.describe()  # the simulator's layout, field by field
    assert m["observation"]["size"] == env.observation_size
    e = m["env"]
    assert (e["num_agents"], e["num_cylinders"], e["num_gates"], e["policy_freq"]) == (3, 8, 4, env.config.policy_freq)
    assert e["collision_radius"] == env.config.cf.collision_radius and e["arena_high"] == [8.0, 6.0, 3.0]
    assert m["action"]["unit"] == "m/s" and m["action"]["frame"] == "world" and m["action"]["high"] == 2.0
    assert m["control"]["rate_hz"] == env.config.policy_freq
    sf = m["safety_filter"]
    assert sf["enabled"] and sf["gain_source"] == "attention" and sf["margin"] == 0.13 and sf["rho"] == 1e6
    assert (sf["gate_half_opening"], sf["gate_bar"], sf["drone_radius"]) == (0.3, 0.05, 0.06)
    assert m["networks"]["cbf"]["activation"] == "gelu_tanh" and m["networks"]["actor"]["activation"] == "tanh"
    # The drone's velocity lag as measured on it: the flight runtime's model velocity estimate flies on it.
    lag = characterise(env.config)
    assert m["drone"]["velocity_lag"] == [lag.lag_xy, lag.lag_z] and 0.3 < lag.lag_xy < 0.4
    assert m["npz_sha256"] == hashlib.sha256((exported / fb.NPZ).read_bytes()).hexdigest()
    assert m["source"]["train_config_sha256"] == hashlib.sha256((run_dir / "config.json").read_bytes()).hexdigest()
    assert m["source"]["trained_updates"] == 7 and m["source"]["train_config"]["method"] == "attention_cbf"
    assert len(m["course"]["gates"]) == 4 and all(len(g) == 4 for g in m["course"]["gates"])


def test_flax_gelu_is_the_tanh_approximation_the_flight_side_computes():
    import flax.linen as nn

    from aswarm.flight.policy import gelu_tanh

    x = np.linspace(-6, 6, 1001)
    with jax.enable_x64(True):
        np.testing.assert_allclose(np.asarray(nn.gelu(jnp.asarray(x))), gelu_tanh(x), rtol=0, atol=1e-14)


def test_exported_networks_run_in_numpy_as_in_jax(run_dir, exported):
    """The exported actor and attention-CBF network against the checkpoint's, on random observations.

    (The whole runtime, filter included, is checked against ``Agent.act`` in tests/test_flight.py.)
    """
    from aswarm.flight import policy

    config, restored = evaluate.load(run_dir)
    agent = Agent.build(config)
    layout = agent.env.obs_layout
    rng = np.random.default_rng(1)
    obs = rng.normal(0.0, 3.0, (16, 3, layout.size))
    _, cyl, nbr = layout.split(obs)  # views: set the presence flags to 0 or 1
    cyl[..., -1] = rng.uniform(size=cyl.shape[:-1]) < 0.7
    nbr[..., -1] = rng.uniform(size=nbr.shape[:-1]) < 0.7
    b = fb.load_bundle(exported)
    with jax.enable_x64(True):
        o = jnp.asarray(obs)
        cmd = np.asarray(agent.policy(restored["params"], restored["obs_norm"], o, None)[0])
        gain = np.asarray(agent.cbf_params(restored["params"], restored["obs_norm"], o)[0][..., 1])
    nobs = policy.normalize(b.weights, obs)
    np.testing.assert_allclose(policy.actor_command(b.weights, nobs, 2.0), cmd, rtol=0, atol=1e-12)
    sf = b.safety_filter
    mine = policy.cbf_params(b.weights, b.layout, nobs, obs, gain_min=sf["gain_min"], gain_max=sf["gain_max"],
                             penalty_max=sf["penalty_max"])[1]
    np.testing.assert_allclose(mine, gain, rtol=0, atol=1e-12)


def test_existing_bundle_is_not_overwritten_without_force(run_dir, exported, tmp_path, capsys):
    before = (exported / fb.MANIFEST).read_bytes()
    with pytest.raises(fb.BundleError, match="already exists: allowed: a new --out folder, or --force"):
        export.export(run_dir, exported)
    assert (exported / fb.MANIFEST).read_bytes() == before
    assert cli.main(["export", "--checkpoint", str(run_dir), "--out", str(exported)]) == 2
    assert "already exists" in capsys.readouterr().err
    out = tmp_path / "copy"
    assert cli.main(["export", "--checkpoint", str(run_dir), "--out", str(out)]) == 0
    assert cli.main(["export", "--checkpoint", str(run_dir), "--out", str(out), "--force"]) == 0
    assert fb.load_bundle(out).arrays.keys() == fb.load_bundle(exported).arrays.keys()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["copy"]  # no temporary folders left behind
    other = tmp_path / "notes"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    with pytest.raises(fb.BundleError, match="is not a bundle: --force replaces only a bundle"):
        export.export(run_dir, other, force=True)
    assert (other / "keep.txt").read_text() == "mine"


def test_a_failed_write_leaves_nothing_behind(run_dir, tmp_path, monkeypatch):
    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(fb.np, "savez", boom)
    with pytest.raises(OSError, match="disk full"):
        export.export(run_dir, tmp_path / "b")
    assert list(tmp_path.iterdir()) == []


def test_unreadable_checkpoints_give_a_clear_error(tmp_path, capsys):
    with pytest.raises(checkpoint.CheckpointError, match="does not exist: give a run folder or 'pretrained'"):
        export.export(tmp_path / "nope", tmp_path / "b")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(checkpoint.CheckpointError, match="is not a run folder: config.json is missing"):
        export.export(empty, tmp_path / "b")
    (empty / "config.json").write_text("{not json")
    with pytest.raises(checkpoint.CheckpointError, match="is not a valid aswarm run config"):
        export.export(empty, tmp_path / "b")
    if not evaluate.PRETRAINED.exists():
        with pytest.raises(checkpoint.CheckpointError, match="pretrained policy is missing"):
            export.export("pretrained", tmp_path / "b")
    with pytest.raises(checkpoint.CheckpointError, match=r"unknown shipped policy 'pretrained:nope': allowed: "
                                                         r"pretrained, pretrained:"):
        export.export("pretrained:nope", tmp_path / "b")
    assert "pretrained:race-geometric" in evaluate.shipped()
    assert evaluate.run_folder("pretrained:race-geometric") == evaluate.PRETRAINED_GEOMETRIC
    assert cli.main(["export", "--checkpoint", str(tmp_path / "nope"), "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("aswarm export: error:") and "\n" not in err
    assert not (tmp_path / "b").exists()


def test_the_16_drone_policy_ships_trained_on_from_the_4_drone_one():
    config16, policy16 = evaluate.load("pretrained:obstacles16")
    assert (config16.env.num_agents, config16.critic, config16.init_from) == (16, "pooled", "pretrained:obstacles")
    assert "pretrained:obstacles16" in evaluate.shipped()
    _, policy4 = evaluate.load("pretrained:obstacles")
    actor16, actor4 = jax.tree.leaves(policy16["params"]["actor"]), jax.tree.leaves(policy4["params"]["actor"])
    assert [a.shape for a in actor16] == [a.shape for a in actor4]  # the same observation layout: it flies any size
    assert not all(np.array_equal(a, b) for a, b in zip(actor16, actor4))  # and it trained on
    # It flies with the deadlock escape (session 19, evaluation only: it trained without it), as does the lab one.
    assert config16.safety_filter.escape and evaluate.load("pretrained:lab")[0].safety_filter.escape


def test_the_rail_policy_ships_fine_tuned_from_the_dynamic_one_under_the_rail():
    config, policy = evaluate.load("pretrained:dynamic-rail")
    stored, base = evaluate.load("pretrained:dynamic")
    assert "pretrained:dynamic-rail" in evaluate.shipped() and config.init_from == "pretrained:dynamic"
    # The same scenes, drone and filter but the rail (session 49): only what it was fine-tuned under differs.
    assert config.env == stored.env
    assert config.safety_filter == dataclasses.replace(stored.safety_filter, rail_speed=0.2)
    mine, theirs = jax.tree.leaves(policy["params"]["actor"]), jax.tree.leaves(base["params"]["actor"])
    assert [a.shape for a in mine] == [a.shape for a in theirs]
    assert not all(np.array_equal(a, b) for a, b in zip(mine, theirs))


def test_the_lab_policy_ships_for_the_lab_room_as_it_stands():
    config, _ = evaluate.load("pretrained:lab")
    assert config.scenario == "lab" and "pretrained:lab" in evaluate.shipped()
    # Its room and drone are the preset's, field for field: a change to the preset (its cylinders' clearance from the
    # gates changed in session 18, the rotors' spin-down in session 22) needs a policy trained on the new one. The
    # reward (gate_bonus off since session 34) shapes training only, so it may differ: it trained with 10.
    assert config.env == envs.make("lab", gate_bonus=10.0).config
    # It trained with a discount that looks 4 s ahead, not the paper's 0.95 (0.8 s at 25 Hz): session 27.
    assert config.gamma == 0.99
    # The policy of before stays shipped, on its own drone (rotors that slow down with the spin-up's time constant).
    old, _ = evaluate.load("pretrained:lab-gamma95")
    before = dataclasses.replace(envs.preset("lab").cf, motor_tau_down=0.0)
    assert (old.env, old.gamma) == (envs.make("lab", cf=before, gate_bonus=10.0).config, 0.95)


def test_corrupt_checkpoint_gives_a_clear_error(run_dir, tmp_path):
    import shutil

    broken = tmp_path / "broken"
    shutil.copytree(run_dir, broken)
    for f in (broken / "checkpoints").rglob("*"):
        if f.is_file() and f.stat().st_size > 0:
            f.write_bytes(b"\x00" * 16)
    with pytest.raises(checkpoint.CheckpointError, match="cannot be restored"):
        export.export(broken, tmp_path / "b")
    assert not (tmp_path / "b").exists()


def test_a_mellinger_policy_tells_the_flight_side_to_stream_full_states(tmp_path):
    from aswarm.agents.train import make_env

    config = TrainConfig(scenario="race", num_envs=8, rollout_steps=4, total_steps=64,
                         env_overrides=(("num_agents", 3), ("controller", "mellinger")))
    runner.write_config(tmp_path, config)
    m = export.build_manifest(config, make_env(config), source="test", trained_updates=0,
                              config_text=(tmp_path / "config.json").read_text())
    d = m["drone"]
    assert d["controller"] == "mellinger" and d["firmware_params"] == {"stabilizer.controller": 2}
    assert d["setpoint"] == "full_state" and d["reference_leash"] == 0.3 and d["mellinger"]["kp_xy"] == 0.4
    # Its velocity lag is Mellinger's, measured: quicker than the PID's 0.34 s.
    assert 0.15 < d["velocity_lag"][0] < 0.3


def test_a_k_nearest_policy_exports_for_another_swarm_size_and_flies_it(tmp_path, capsys):
    from aswarm.flight.runtime import FlightController

    out = tmp_path / "b8"
    assert cli.main(["export", "--checkpoint", "pretrained:obstacles", "--out", str(out), "--env", "num_agents=8",
                     "--env", "max_neighbours=3"]) == 0
    b = fb.load_bundle(out)
    assert b.num_agents == 8 and b.manifest["env"]["max_neighbours"] == 3
    assert b.manifest["source"]["export_env_overrides"] == ["max_neighbours=3", "num_agents=8"]
    assert b.manifest["source"]["env_config"]["num_agents"] == 8  # what `aswarm sitl` flies
    # The runtime flies 8 drones with it: finite commands within the limit, one per drone.
    ctl = FlightController(b, 8)
    ctl.reset(goals=np.stack([np.arange(8) * 0.5, np.full(8, 2.0), np.ones(8)], -1))
    pos = np.stack([np.arange(8) * 0.5, np.zeros(8), np.ones(8)], -1)
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (8, 1))
    step = ctl.step(pos, quat, np.zeros(8), now=0.0)
    assert step.velocity.shape == (8, 3) and np.all(np.isfinite(step.velocity))
    assert np.all(np.abs(step.velocity) <= b.manifest["env"]["max_speed"] + 1e-9)
    # A field that changes what the policy observes is refused in one line, and nothing is written.
    assert cli.main(["export", "--checkpoint", "pretrained:obstacles", "--out", str(tmp_path / "b3"), "--env",
                     "num_obstacles=3"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "the observation layouts differ" in err and not (tmp_path / "b3").exists()


def test_a_filter_that_sees_more_neighbours_than_the_policy_exports_and_flies_as_in_jax(tmp_path):
    """``filter_neighbours``: the 4-drone `obstacles` policy (3 neighbours) flown by 5 drones, its filter on all 4
    others and their accelerations (``filter_neighbour_accel``). The bundle says so, the runtime builds the filter's
    observation, and numpy equals ``Agent.act``, with the first-order look-ahead and with the second-order one."""
    from aswarm.flight import runtime

    extra = ["num_agents=5", "max_neighbours=3", "filter_neighbours=4", "filter_neighbour_accel=true"]
    out = tmp_path / "b5"
    assert cli.main(["export", "--checkpoint", "pretrained:obstacles", "--out", str(out),
                     *(a for o in extra for a in ("--env", o))]) == 0
    b = fb.load_bundle(out)
    assert b.manifest["env"]["filter_neighbours"] == 4 and b.manifest["env"]["filter_neighbour_accel"] is True
    assert (b.layout.num_neighbours, b.filter_layout.num_neighbours, b.filter_layout.neighbour_accel) == (3, 4, True)
    _, agent, st = evaluate.load_agent("pretrained:obstacles", None, extra)
    env = agent.env
    assert env.wide_filter and env.filter_layout == b.filter_layout
    s = jax.jit(env.reset)(jax.random.PRNGKey(3))
    obs, wide = np.asarray(s.obs, np.float64), np.asarray(s.filter_obs, np.float64)
    assert wide.shape == (5, b.filter_layout.size) and np.array_equal(wide[:, :b.layout.size], obs)
    # Under way the drones tilt (at rest every acceleration is 0): tilted attitudes and accelerations written in.
    rng = np.random.default_rng(4)
    quat = np.concatenate([np.ones((5, 1)), rng.uniform(-0.15, 0.15, (5, 2)), np.zeros((5, 1))], -1)
    wide[:, b.layout.own_slices["quat"]] = quat / np.linalg.norm(quat, axis=-1, keepdims=True)
    wide[:, b.layout.size:] = rng.uniform(-2.5, 2.5, (5, wide.shape[1] - b.layout.size))
    obs = wide[:, :b.layout.size]
    with jax.enable_x64(True):
        want = jax.jit(agent.act)(st["params"], st["obs_norm"], jnp.asarray(obs), None, jnp.asarray(wide))
    np.testing.assert_allclose(runtime.run_policy(b, wide).u, np.asarray(want), rtol=0, atol=1e-9)
    second = {"lookahead_xy": 0.207, "lookahead_accel": 0.039}
    _, agent2, _ = evaluate.load_agent("pretrained:obstacles", None, extra, filter_overrides=second)
    b2 = dataclasses.replace(b, safety=dataclasses.replace(b.safety, **second))
    with jax.enable_x64(True):
        want2 = jax.jit(agent2.act)(st["params"], st["obs_norm"], jnp.asarray(obs), None, jnp.asarray(wide))
    np.testing.assert_allclose(runtime.run_policy(b2, wide).u, np.asarray(want2), rtol=0, atol=1e-9)
    assert np.abs(np.asarray(want2) - np.asarray(want)).max() > 1e-3  # the accelerations moved the rows
    assert agent2.config.safety_filter.lookahead_xy == 0.207  # the second-order fit's own, not the drone's lag
    # The runtime builds the filter's observation from poses and flies all 5 drones with it.
    ctl = runtime.FlightController(b, 5)
    ctl.reset(goals=np.stack([np.arange(5) * 0.5, np.full(5, 2.0), np.ones(5)], -1))
    step = ctl.step(np.stack([np.arange(5) * 0.5, np.zeros(5), np.ones(5)], -1), np.tile([1.0, 0, 0, 0], (5, 1)),
                    np.zeros(5), now=0.0)
    assert step.velocity.shape == (5, 3) and np.all(np.isfinite(step.velocity))
    narrow, full = b.layout.size, b.filter_layout.size
    with pytest.raises(ValueError, match=f"observations of size {narrow}: this bundle.s are {full}"):
        runtime.run_policy(b, wide[:, :narrow])


def test_the_filter_keeps_apart_a_neighbour_the_policy_does_not_observe():
    """Three drones in a row along x, 0.5 m apart, the middle one (0) commanded at 1 m/s towards drone 2 at +x; drone 1
    at -x is nearer (0.45 m). A policy observing its one nearest sees drone 1 only: a filter on the policy's rows lets
    the command through; one on the 2 nearest slows it to what the reciprocal barrier allows (hand-derived below)."""
    from aswarm.core import observation
    from aswarm.core.layout import ObsLayout
    from aswarm.core.safety import SafetyFilterConfig
    from aswarm.flight import cbf

    pos = np.array([[0.0, 0.0, 1.0], [-0.45, 0.0, 1.0], [0.5, 0.0, 1.0]])
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (3, 1))
    zero = np.zeros((3, 3))
    goal = np.array([[[9.0, 0.0, 1.0]]] * 3)
    no_cyl = np.zeros((0, 2))
    r, margin, gain = 0.06, 0.1, 1.0
    sf = SafetyFilterConfig(margin=margin)

    def filtered(k: int) -> np.ndarray:
        obs = observation.observe(pos, quat, zero, zero, goal, np.zeros_like(goal), np.zeros(3, int), np.ones(3, bool),
                                  no_cyl, no_cyl, np.zeros(0), np.zeros(0, bool), r, (-5.0, -5.0, 0.0),
                                  (5.0, 5.0, 3.0), k)
        cmd = np.array([[1.0, 0.0, 0.0]] * 3)
        res = cbf.filter_from_obs(ObsLayout(0, k), obs, cmd, np.full(3, gain), 2.0, r, sf)
        return res.u[0]

    np.testing.assert_allclose(filtered(1), [1.0, 0.0, 0.0], atol=1e-6)  # drone 2 unseen: nothing holds it back
    # Drone 2's row: h = |d| - 2 r - margin = 0.5 - 0.22 = 0.28 m; drone 0 takes its share 0.5 of the gain's
    # allowance: u_x <= 0.5 * gain * h = 0.14 m/s (both at rest).
    h = 0.5 - 2 * r - margin
    np.testing.assert_allclose(filtered(2)[0], 0.5 * gain * h, atol=1e-5)

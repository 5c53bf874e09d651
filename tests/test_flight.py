"""The numpy flight runtime: JAX-free import, parity with the simulator and the JAX policy, safety, SITL, fly.

The JAX half records closed-loop race episodes once (module fixture) with a policy whose actor is
set by hand to fly at the current gate, so the drones bunch up at gates, pass cylinders and the
safety filter works on many states; a noisy copy of the rollout adds off-policy states.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import subprocess
import sys
import textwrap
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.training.acme import running_statistics

from aswarm import cli, envs
from aswarm.agents.config import TrainConfig
from aswarm.agents.train import Agent
from aswarm.analysis import evaluate
from aswarm.core import geometry, observation
from aswarm.core.safety import SafetyFilterConfig
from aswarm.envs.config import LEGACY_DRONE
from aswarm.flight import bench, estimator, export, sitl
from aswarm.flight import bundle as fb
from aswarm.flight import fly as ffly
from aswarm.flight import runtime as fc

B = 8  # worlds
SEED = 10_000
EPISODE_S = 4.0
# A wider gate than the race's 0.3 m: the hand-set actor aims at the gate centre from an angle, and the
# filter slows a drone closing on a bar, so with the real opening almost no drone passed in 4 s.
HALF_OPENING = 0.6
URIS = ",".join(f"radio://0/80/2M/E7E7E7E70{i}" for i in range(4))
BLOCKED = ("jax", "jaxlib", "flax", "mujoco", "brax", "optax", "orbax", "chex", "cflib", "motioncapture")


# ------------------------------------------------------------------ fixtures
def gate_seeking(params: dict, d: int, rng: np.random.Generator):
    """Actor flying at the current gate, cmd = 2 tanh(3 tanh(tanh(-0.25 (p - g)))); a random normalizer.

    p - g is the observed target_rel. The first layer undoes the normalizer on those 3 inputs; the
    other units stay random. The CBF head is scaled up so that the class-K gains spread over part of
    their range.
    """
    mean = rng.normal(0.0, 0.1, d).astype(np.float32)
    std = rng.uniform(0.5, 2.0, d).astype(np.float32)
    p = jax.tree.map(np.array, params)
    mlp = p["actor"]["params"]["MLP_0"]
    k0, b0 = mlp["Dense_0"]["kernel"], mlp["Dense_0"]["bias"]
    k1, b1 = mlp["Dense_1"]["kernel"], mlp["Dense_1"]["bias"]
    k2, b2 = mlp["Dense_2"]["kernel"], mlp["Dense_2"]["bias"]
    for j in range(3):
        k0[:, j], k1[:, j], k2[:, j] = 0.0, 0.0, 0.0
        k0[j, j], b0[j] = -0.25 * std[j], -0.25 * mean[j]
        k1[j, j], b1[j] = 1.0, 0.0
        k2[j, j], b2[j] = 3.0, 0.0
    p["cbf"]["params"]["MLP_0"]["Dense_2"]["kernel"] *= 3.0
    norm = running_statistics.init_state(jax.ShapeDtypeStruct((d,), jnp.float32))
    norm = norm.replace(mean=jnp.asarray(mean), std=jnp.asarray(std))
    return jax.tree.map(jnp.asarray, p), norm


def rollout(sim, act, params, obs_norm, noise: float, rng) -> SimpleNamespace:
    """Closed loop of the JAX policy (``Agent.act``, float32), recording every state it acts on."""
    env = sim.env
    n = env.num_agents
    state, sensed = sim.reset(jax.random.PRNGKey(SEED))
    keys = ("obs", "pos", "quat", "vel", "ang_vel", "target", "finished", "time", "u")
    rec = {k: [] for k in keys}
    ended = np.zeros(B, bool)
    first = None
    for k in range(env.config.max_steps + 1):
        done = np.asarray(sensed.done) > 0
        metrics = jax.device_get(sensed.metrics)
        first = {m: np.asarray(v) for m, v in metrics.items()} if first is None else first
        new = done & ~ended
        first = {m: np.where(new, np.asarray(metrics[m]), first[m]) for m in first}
        ended |= new
        if k == env.config.max_steps or (noise == 0 and ended.all()):
            break
        u = act(params, obs_norm, state.obs)
        qpos = np.asarray(state.data.qpos).reshape(B, n, 7)
        qvel = np.asarray(state.data.qvel).reshape(B, n, 6)
        for name, v in (("obs", state.obs), ("pos", qpos[..., :3]), ("quat", qpos[..., 3:]), ("vel", qvel[..., :3]),
                        ("ang_vel", qvel[..., 3:]), ("target", state.tracker.target),
                        ("finished", state.tracker.finished), ("time", state.data.time), ("u", u)):
            rec[name].append(np.asarray(v))
        cmd = np.asarray(u) + noise * rng.normal(size=(B, n, 3))
        state, sensed = sim.step(state, jnp.asarray(np.clip(cmd, -2.0, 2.0), jnp.float32))
    out = {k: np.stack(v) for k, v in rec.items()}  # [T, B, ...]
    return SimpleNamespace(**out, metrics=first, ended=ended, layout=jax.device_get(state.layout))


@pytest.fixture(scope="module")
def race(tmp_path_factory):
    # Exact poses: the runtime is checked against the simulator's own observations (SITL adds noise itself). The
    # geometric drone: the hand-set gate-seeking actor was tuned on it, and what is compared (numpy against JAX,
    # runtime against simulator) does not depend on the drone (SITL on the firmware drone: experiments/robustness.py).
    overrides = (("episode_seconds", EPISODE_S), ("gate_half_opening", HALF_OPENING),
                 *((k, v) for k, v in LEGACY_DRONE.items()))
    # The filter margin the hand-set actor was tuned with (the default is 0.13 since issue #12), and the neighbours'
    # reference (released by closing speed since session 41, the filter holds back this actor's four drones, which
    # converge on the same gate ignoring each other, to 4 % of the track in 4 s, under the check below).
    config = TrainConfig(scenario="race", method="attention_cbf", env_overrides=overrides,
                         safety_filter=SafetyFilterConfig(margin=0.1, neighbour_release=0.0))
    sim = sitl.simulator(envs.make("race", **dict(overrides)).config, B)
    env = sim.env
    agent = Agent.build(config, env)
    rng = np.random.default_rng(0)
    params, obs_norm = gate_seeking(jax.jit(agent.init_params)(jax.random.PRNGKey(1)), env.observation_size, rng)
    path = export.export_policy(config, params, obs_norm, tmp_path_factory.mktemp("b") / "bundle", env=env,
                                source="test: gate-seeking actor")
    act = jax.jit(agent.act)
    clean = rollout(sim, act, params, obs_norm, 0.0, rng)
    noisy = rollout(sim, act, params, obs_norm, 0.8, rng)
    return SimpleNamespace(config=config, env=env, agent=agent, params=params, obs_norm=obs_norm, path=path,
                           bundle=fb.load_bundle(path), clean=clean, noisy=noisy)


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """A race-sized bundle with random weights, written without JAX."""
    b = bench.synthetic_bundle()
    path = tmp_path_factory.mktemp("s") / "bundle"
    fb.write_bundle(path, dict(b.arrays), {k: v for k, v in b.manifest.items() if k not in ("arrays", "npz_sha256")})
    return fb.load_bundle(path)


# ------------------------------------------------------------------ no JAX on the flight side
def test_flight_package_imports_no_jax_flax_mujoco_or_brax(synthetic):
    code = textwrap.dedent(f"""
        import importlib.abc, sys
        BLOCKED = {BLOCKED!r}
        class Block(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in BLOCKED:
                    raise ImportError("blocked: " + name)
        sys.meta_path.insert(0, Block())
        import numpy as np
        import aswarm.flight, aswarm.flight.fly, aswarm.flight.bench, aswarm.flight.record, aswarm.flight.links
        from aswarm.flight import FlightController, load_bundle
        b = load_bundle({str(synthetic.path)!r})
        ctl = FlightController(b, 4)
        ctl.reset(gates=np.array(b.manifest["course"]["gates"]))
        out = ctl.step(np.array([[3.0, -3.5, 1.0], [2.2, -3.5, 1.0], [1.4, -3.5, 1.0], [0.6, -3.5, 1.0]]),
                       np.tile([1.0, 0, 0, 0], (4, 1)), np.zeros(4), now=0.0)
        assert np.all(np.isfinite(out.velocity))
        bad = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
        assert not bad, bad
        print("ok")
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0 and run.stdout.strip() == "ok", run.stderr


# ------------------------------------------------------------------ parity with the simulator and JAX
def _states(race):
    """All recorded drone-states of both rollouts, as [S, n, ...] (S = steps x worlds)."""
    cat = {k: np.concatenate([getattr(r, k).reshape((-1,) + getattr(r, k).shape[2:]) for r in (race.clean, race.noisy)])
           for k in ("obs", "pos", "quat", "vel", "ang_vel", "target", "finished", "time", "u")}
    world = np.concatenate([np.tile(np.arange(B), len(r.time)) for r in (race.clean, race.noisy)])
    return SimpleNamespace(**cat, world=world)


def test_numpy_observation_equals_the_simulators(race):
    s = _states(race)
    lay = race.clean.layout  # the same layouts in both rollouts (same reset keys)
    n = race.env.num_agents
    normals = np.broadcast_to(geometry.horizontal(lay.gate_yaw)[:, None], lay.waypoints.shape)
    cyl_pos, cyl_vel = geometry.cylinders_at(lay.cyl_center[s.world], lay.cyl_axis[s.world],
                                             lay.cyl_amplitude[s.world], lay.cyl_omega[s.world],
                                             lay.cyl_phase[s.world], s.time)
    obs = observation.observe(s.pos.astype(float), s.quat, s.vel, s.ang_vel, lay.waypoints[s.world], normals[s.world],
                          s.target, ~s.finished, cyl_pos, cyl_vel, lay.cyl_radius[s.world], lay.cyl_present[s.world],
                          race.env.config.cf.collision_radius, race.env.config.arena_low, race.env.config.arena_high)
    assert obs.shape == s.obs.shape and s.obs.shape[1:] == (n, race.env.observation_size)
    assert s.target.max() >= 1, "no drone passed a gate: the gate fields were not exercised"
    np.testing.assert_allclose(obs, s.obs, rtol=0, atol=2e-5)


@pytest.mark.parametrize("k, accel", [(2, False), (6, False), (2, True)])
def test_numpy_observation_of_the_k_nearest_neighbours_equals_the_simulators(k, accel):
    """With ``accel`` (``filter_neighbour_accel``) the filter's observation carries each of those neighbours'
    accelerations from their attitudes after the policy's columns, the same in both."""
    from aswarm.envs.dynamics import DroneState

    n = 5
    env = envs.make("race", num_agents=n, max_neighbours=k, filter_neighbours=0,  # the policy's rows alone
                    filter_neighbour_accel=accel)
    s = jax.jit(env.reset)(jax.random.PRNGKey(1))
    rng = np.random.default_rng(0)
    pos = rng.uniform(-1.5, 1.5, (n, 3)) + [0.0, 0.0, 1.6]
    half = rng.uniform(-0.15, 0.15, (n, 2))  # tilted up to 17° about x and y
    quat = np.stack([np.ones(n), half[:, 0], half[:, 1], np.zeros(n)], -1)
    quat /= np.linalg.norm(quat, axis=-1, keepdims=True)
    vel, ang = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    finished = np.array([False, True, False, False, False])  # drone 1 is no neighbour
    tr = s.tracker.replace(finished=jnp.asarray(finished))
    drones = DroneState(*(jnp.asarray(x, jnp.float32) for x in (pos, quat, vel, ang)))
    want = jax.jit(env._observe)(drones, s.layout, tr, jnp.zeros(()))
    lay = jax.tree.map(np.asarray, s.layout)
    normals = np.broadcast_to(geometry.horizontal(lay.gate_yaw)[None], lay.waypoints.shape)
    got = observation.observe(pos, quat, vel, ang, lay.waypoints, normals, np.asarray(tr.target), ~finished,
                          lay.cyl_center, np.zeros_like(lay.cyl_center), lay.cyl_radius, lay.cyl_present,
                          env.config.cf.collision_radius, env.config.arena_low, env.config.arena_high,
                          max_neighbours=k, neighbour_accel=accel)
    assert got.shape == (n, env.filter_layout.size) and env.wide_filter == accel
    np.testing.assert_allclose(got, np.asarray(want), rtol=0, atol=2e-5)
    nbr = env.filter_layout.split(got)[2]  # [n, k, 7]: nearest first, then absent rows
    if accel:  # each row's acceleration is its drone's: found by position
        acc = env.filter_layout.neighbour_accels(got)
        tilt = geometry.tilt_accel(quat)[:, :2]
        for i in range(n):
            for j in range(k):
                if nbr[i, j, 6] > 0:
                    other = np.argmin(np.linalg.norm(pos - (pos[i] + nbr[i, j, :3]), axis=-1))
                    np.testing.assert_allclose(acc[i, j], tilt[other], atol=1e-12)
                else:
                    assert np.all(acc[i, j] == 0)
        assert np.abs(acc).max() > 0.5
    present = nbr[..., 6]
    assert np.all(np.diff(present, axis=-1) <= 0)  # present rows first
    assert np.all(present.sum(-1) == np.minimum(k, np.where(finished, 4, 3)))
    dist = np.linalg.norm(nbr[..., :3], axis=-1)
    assert all(np.all(np.diff(d[p > 0]) >= 0) for d, p in zip(dist, present))  # nearest first


def test_numpy_policy_and_filter_match_jax_on_recorded_states(race):
    """Normalizer + actor + attention gain + CBF filter against ``Agent.act`` on every recorded state.

    JAX runs in float32 and the numpy side in float64. Against JAX in float64 (same weights, same
    algorithm) the numpy runtime agrees to rounding; against the float32 run the gap is the float32
    solver's own rounding, largest where the QP is infeasible and the slack is large.
    """
    s = _states(race)
    pol = fc.run_policy(race.bundle, s.obs.astype(np.float64))
    active = pol.intervened
    err32 = np.abs(pol.u - s.u).max(-1)
    with jax.enable_x64(True):
        u64 = np.asarray(jax.jit(race.agent.act)(race.params, race.obs_norm, jnp.asarray(s.obs, jnp.float64)))
    err64 = np.abs(pol.u - u64).max()
    print(f"\n{err32.size} drone-states, filter active on {active.sum()} ({100 * active.mean():.0f} %); "
          f"max |numpy - jax float64| = {err64:.1e}; numpy - jax float32: max {err32.max():.1e}, "
          f"{100 * np.mean(err32 <= 1e-5):.2f} % within 1e-5")
    assert err32.size >= 5000 and active.mean() > 0.2
    assert err64 < 1e-9
    assert np.mean(err32 <= 1e-5) > 0.99 and err32.max() < 1e-4
    assert np.all(pol.converged)


# The numpy QP against the shared reference solver and OSQP: tests/test_cbf_filter.py.


def test_sitl_matches_jax_closed_loop_within_noise(race):
    """Same episodes (same keys) flown by the numpy runtime from poses only, and by JAX from true states."""
    r = sitl.run_sitl(race.path, episodes=B, seed=SEED)
    ref = evaluate.summarize(race.clean.metrics)
    print(f"\nSITL: success {r['success_rate']:.2f} collision {r['collision_rate']:.2f} progress {r['progress']:.3f} "
          f"| JAX: success {ref['success_rate']:.2f} collision {ref['collision_rate']:.2f} "
          f"progress {ref['progress']:.3f}; runtime {r['runtime_ms_per_step']:.2f} ms/step for {B} worlds")
    for name in ("success", "collision"):
        lo, hi = ref[f"{name}_ci95"]
        assert lo <= r[f"{name}_rate"] <= hi, (name, r[f"{name}_rate"], (lo, hi))
    assert ref["progress"] > 0.05, "the reference policy passed no gate: nothing to compare"
    assert abs(r["progress"] - ref["progress"]) < 0.1
    assert r["episodes_ended"] == B and 0 < r["filter_intervention_rate"] < 1


def test_sitl_with_noise_and_latency_and_its_cli(race, capsys):
    # 48 ms: one control step (40 ms) of old poses, and the command 2 onboard-controller ticks (4 ms at 250 Hz)
    # late; on the firmware drone (100 Hz) 50 ms is a step and a tick.
    assert sitl.split_latency(48.0, race.env.config) == (1, 2)
    assert sitl.split_latency(50.0, envs.preset("race")) == (1, 1)
    r = sitl.run_sitl(race.path, episodes=B, seed=SEED + 1, noise=0.003, latency_ms=48.0, mass_scale=1.1,
                      thrust_scale=0.9)
    assert (r["noise"], r["latency_ms"], r["mass_scale"], r["thrust_scale"]) == (0.003, 48.0, 1.1, 0.9)
    assert 0.0 <= r["collision_rate"] <= 1.0
    assert np.isfinite(r["progress"]) and r["control_steps"] > 0
    assert "SITL episodes" in sitl.format_table(r)
    assert cli.main(["sitl", "--bundle", str(race.path), "--episodes", str(B), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["episodes"] == B and set(out) >= {"success_rate", "collision_ci95", "runtime_ms_per_step"}
    assert cli.main(["sitl", "--bundle", str(race.path), "--estimator-window", "1"]) == 2
    assert "invalid window=1: must be an integer >= 2" in capsys.readouterr().err
    assert cli.main(["sitl", "--bundle", str(race.path), "--accel-noise", "0"]) == 2
    assert "invalid accel_noise=0.0: must be a finite number > 0" in capsys.readouterr().err
    with pytest.raises(ValueError, match=r"invalid latency=-10.0 ms: allowed: a multiple >= 0 of the onboard"):
        sitl.run_sitl(race.path, episodes=B, latency_ms=-10.0)
    with pytest.raises(ValueError, match=r"invalid latency=15.0 ms: .* tick, 4 ms"):
        sitl.run_sitl(race.path, episodes=B, latency_ms=15.0)
    with pytest.raises(ValueError, match=r"invalid mass_scale=0.0"):
        sitl.run_sitl(race.path, episodes=B, mass_scale=0.0)
    with pytest.raises(ValueError, match="observation layout does not transfer"):
        sitl.run_sitl(race.path, episodes=B, env_overrides=["num_agents=3"])


def test_sitl_flies_a_bundle_exported_before_a_field_was_added(race, tmp_path):
    import shutil

    old = tmp_path / "old"
    shutil.copytree(race.path, old)
    manifest = json.loads((old / "manifest.json").read_text())
    del manifest["source"]["env_config"]["randomize"]["velocity_window"]  # added in issue #12's fifth session
    (old / "manifest.json").write_text(json.dumps(manifest))
    a, b = (sitl.run_sitl(p, episodes=B, seed=SEED) for p in (race.path, old))
    assert (a["success_rate"], a["collision_rate"], a["progress"]) == (b["success_rate"], b["collision_rate"],
                                                                       b["progress"])


# ------------------------------------------------------------------ estimator
def _qexp(r):
    a = np.linalg.norm(r)
    return np.concatenate([[np.cos(a / 2)], np.sin(a / 2) * r / a])


def test_estimator_recovers_velocity_and_body_rate_despite_jitter_and_sign_flips():
    rng = np.random.default_rng(0)
    v, w = np.array([0.7, -1.1, 0.3]), np.array([0.4, -1.5, 2.2])
    q0 = _qexp(np.array([0.3, -0.2, 1.0]))
    cfg = estimator.EstimatorConfig(velocity="window")
    st = estimator.init((1,), cfg)
    for k in range(8):
        t = 0.02 * k + rng.uniform(0, 0.004)  # jittered timestamps
        q = estimator.quat_mul(q0, _qexp(w * t)) * (-1) ** k  # the sign of a mocap quaternion is arbitrary
        st, acc, glitch = estimator.update(st, np.array([t]), (v * t + 1.0)[None], q[None], np.ones(1, bool), cfg)
        assert acc[0] and not glitch[0]
    vel, ang = estimator.estimate(st, cfg)
    np.testing.assert_allclose(vel[0], v, atol=1e-9)
    np.testing.assert_allclose(ang[0], w, atol=1e-9)  # body frame: q(t) = q0 ⊗ exp(w t / 2)


def test_estimator_averages_noise_rejects_glitches_and_repeats():
    rng = np.random.default_rng(1)
    cfg = estimator.EstimatorConfig(window=6, velocity="window")
    st = estimator.init((1,), cfg)
    q = np.array([[1.0, 0, 0, 0]])
    errs, diffs, prev = [], [], None
    for k in range(200):
        t = 0.01 * k
        p = np.array([[0.5 * t, 0.0, 1.0]]) + rng.normal(0, 0.001, (1, 3))
        st, _, _ = estimator.update(st, np.array([t]), p, q, np.ones(1, bool), cfg)
        if k >= 6:
            errs.append(estimator.estimate(st, cfg)[0][0] - [0.5, 0, 0])
            diffs.append((p - prev)[0] / 0.01 - [0.5, 0, 0])
        prev = p
    assert np.std(errs) < 0.3 * np.std(diffs)  # the fit is much quieter than a finite difference
    t_last = st.t[0, -1]
    st2, acc, glitch = estimator.update(st, np.array([t_last + 0.01]), np.array([[5.0, 0, 1]]), q,
                                        np.ones(1, bool), cfg)
    assert glitch[0] and not acc[0] and np.array_equal(st2.pos, st.pos)  # a 5 m jump in 10 ms: rejected
    st3, acc, _ = estimator.update(st, np.array([t_last]), np.array([[0.0, 0, 1]]), q, np.ones(1, bool), cfg)
    assert not acc[0] and np.array_equal(st3.pos, st.pos)  # a repeated frame is not a new sample


def _lagging_drone(cmd, dt, tau, noise, rng, steps=60):
    """Poses of a drone whose velocity follows the command ``cmd(k)`` [n, 3] as v' = (u - v) / tau exactly
    (fine Euler steps), sampled every ``dt`` with Gaussian noise: yields (t, noisy pos, true vel, command)."""
    p, v, sub = np.zeros((1, 3)) + [0.0, 0.0, 1.0], np.zeros((1, 3)), 100
    for k in range(steps):
        u = cmd(k)
        yield k * dt, p + rng.normal(0.0, noise, p.shape), v.copy(), u
        for _ in range(sub):
            v = v + (u - v) / tau * (dt / sub)
            p = p + v * (dt / sub)


def test_model_estimate_follows_a_lagging_drone_without_the_windows_lag():
    # A drone that follows its commands with the modelled lag: the model estimate carries the velocity through a
    # 1 m/s step, where the window's line fit lags it by about half its window: 60 ms at 25 Hz times the step's
    # initial acceleration (1 m/s / 0.34 s = 2.9 m/s^2), about 0.18 m/s early in the step.
    tau = np.array([0.34, 0.34, 0.22])
    model = estimator.EstimatorConfig(velocity="model", lag=(0.34, 0.22))
    window = estimator.EstimatorConfig(velocity="window", window=4)
    sm, sw = estimator.init((1,), model), estimator.init((1,), window)
    q = np.array([[1.0, 0, 0, 0]])
    err_m, err_w = [], []
    step_at = 20
    prev_u = np.zeros((1, 3))
    for t, p, v, u in _lagging_drone(lambda k: np.array([[1.0, -0.5, 0.3]]) * (k >= step_at), 0.04, tau, 0.0,
                                     np.random.default_rng(0)):
        sm, _, _ = estimator.update(sm, np.array([t]), p, q, np.ones(1, bool), model, commands=prev_u)
        sw, _, _ = estimator.update(sw, np.array([t]), p, q, np.ones(1, bool), window)
        prev_u = u  # the command sent now is flown until the next pose
        if t > 0.04 * (step_at + 1):
            err_m.append(np.abs(estimator.estimate(sm, model)[0] - v).max())
            err_w.append(np.abs(estimator.estimate(sw, window)[0] - v).max())
    assert max(err_m) < 0.01  # the model is exact here: only the Euler steps of the true drone differ
    assert max(err_w) > 0.1  # the line fit's lag through the step
    # The angular rate is the window's in both.
    np.testing.assert_array_equal(estimator.estimate(sm, model)[1], estimator.estimate(sw, window)[1])


def test_model_estimate_carries_old_poses_to_now_with_the_commands_sent_since():
    # Poses two control steps old (80 ms) and a command that changes every step: the update integrates each pose
    # interval under the commands flown in it, and predict() carries the newest pose to the present.
    tau, dt, late = np.array([0.34, 0.34, 0.22]), 0.04, 2
    model = estimator.EstimatorConfig(velocity="model", lag=(0.34, 0.22))
    st = estimator.init((1,), model)
    sent = estimator.Commands.empty((), 1, 5)
    q = np.array([[1.0, 0, 0, 0]])
    truth = list(_lagging_drone(lambda k: np.array([[np.sin(0.3 * k), 0.5 * np.cos(0.2 * k), 0.2]]), dt, tau, 0.0,
                                np.random.default_rng(0)))
    for k in range(late, len(truth)):
        t_pose, p_pose, _, _ = truth[k - late]
        st, _, _ = estimator.update(st, np.array([t_pose]), p_pose, q, np.ones(1, bool), model, sent)
        now, p_now, v_now, u_now = truth[k]
        p_est, v_est = estimator.predict(st, np.array(now), sent, model)
        if k > 10:
            np.testing.assert_allclose(v_est[0], v_now[0], atol=5e-3, err_msg=f"step {k}")
            np.testing.assert_allclose(p_est[0], p_now[0], atol=1e-3, err_msg=f"step {k}")
        sent = sent.sent(np.array(now), u_now)
    # Without the history (the last command as if flown throughout) the velocity is off in these turns.
    p_bad, v_bad = estimator.predict(st, np.array(now), u_now, model)
    assert np.abs(v_bad[0] - v_now[0]).max() > 0.02


def test_model_estimate_is_quieter_than_the_line_fit_on_noisy_poses():
    rng = np.random.default_rng(2)
    model = estimator.EstimatorConfig(velocity="model", lag=(0.34, 0.22), pos_noise=0.005)
    window = estimator.EstimatorConfig(velocity="window", window=4)
    sm, sw = estimator.init((1,), model), estimator.init((1,), window)
    q = np.array([[1.0, 0, 0, 0]])
    err_m, err_w, prev_u = [], [], np.zeros((1, 3))
    for t, p, v, u in _lagging_drone(lambda k: np.array([[0.5 * np.sin(0.2 * k), 0.3, 0.0]]), 0.04,
                                     np.array([0.34, 0.34, 0.22]), 0.005, rng, steps=300):
        sm, _, _ = estimator.update(sm, np.array([t]), p, q, np.ones(1, bool), model, commands=prev_u)
        sw, _, _ = estimator.update(sw, np.array([t]), p, q, np.ones(1, bool), window)
        prev_u = u
        if t > 1.0:
            err_m.append(estimator.estimate(sm, model)[0][0] - v[0])
            err_w.append(estimator.estimate(sw, window)[0][0] - v[0])
    rms_m, rms_w = (float(np.sqrt(np.mean(np.square(e)))) for e in (err_m, err_w))
    # The line through 4 poses 40 ms apart, 5 mm noise: 5 mm / (0.04 s * sqrt(5)) = 0.056 m/s of noise per axis.
    assert 0.04 < rms_w < 0.08
    assert rms_m < 0.5 * rms_w


def test_model_estimate_rejects_bad_settings():
    for bad, match in ((dict(velocity="kalman"), "invalid velocity='kalman': allowed: model, window"),
                       (dict(lag=(0.3, -0.1)), "invalid lag"), (dict(accel_noise=0.0), "invalid accel_noise=0.0"),
                       (dict(pos_noise=float("nan")), "invalid pos_noise=nan")):
        with pytest.raises(ValueError, match=re.escape(match)):
            estimator.EstimatorConfig(**bad)


def test_the_model_estimate_takes_the_bundles_measured_lag(synthetic):
    assert synthetic.velocity_lag == estimator.FIRMWARE_PID_LAG
    assert fc.FlightController(synthetic, 4).estimation.lag == estimator.FIRMWARE_PID_LAG
    # A bundle from before the lag was recorded: what its fitted look-ahead implies (0.9 x the lag) ...
    m = json.loads(json.dumps(dict(synthetic.manifest)))
    del m["drone"]["velocity_lag"]
    m["safety_filter"] |= {"fit_lookahead": True, "lookahead_scale": 0.9, "lookahead_xy": 0.27, "lookahead_z": 0.18}
    old = fb.bundle_from(m, dict(synthetic.arrays))
    np.testing.assert_allclose(old.velocity_lag, (0.3, 0.2))
    # ... and without one the model has no drone to follow: a clear error, and the line fit still flies it.
    m["safety_filter"]["fit_lookahead"] = False
    older = fb.bundle_from(m, dict(synthetic.arrays))
    assert older.velocity_lag is None
    with pytest.raises(ValueError, match="does not record its drone's velocity lag.*--velocity-estimate window"):
        fc.FlightController(older, 4)
    fc.FlightController(older, 4, estimation=estimator.EstimatorConfig(velocity="window"))


# ------------------------------------------------------------------ safety on bad input
def _controller(bundle, **safety):
    ctl = fc.FlightController(bundle, 4, safety=fc.SafetyConfig(**safety))
    ctl.reset(gates=np.array(bundle.manifest["course"]["gates"]))
    return ctl


START = np.array([[3.0, -3.5, 1.0], [2.2, -3.5, 1.0], [1.4, -3.5, 1.0], [0.6, -3.5, 1.0]])
Q = np.tile([1.0, 0.0, 0.0, 0.0], (4, 1))


def _ok(out, max_speed=2.0):
    assert np.all(np.isfinite(out.velocity)) and np.all(np.abs(out.velocity) <= max_speed)


def _kinds(out):
    return {(e.drone, e.kind) for e in out.events}


def test_nan_or_missing_pose_hovers_that_drone_and_reports_it(synthetic):
    ctl = _controller(synthetic)
    for k in range(3):
        _ok(ctl.step(START + [0.01 * k, 0, 0], Q, np.full(4, 0.02 * k), now=0.02 * k))
    pos = START.copy()
    pos[1] = np.nan
    quat = Q.copy()
    quat[3] = 0.0  # a zero quaternion is no attitude
    ts = np.full(4, 0.06)
    ts[2] = np.nan  # no timestamp: missing
    out = ctl.step(pos, quat, ts, now=0.06)
    _ok(out)
    for d in (1, 2, 3):
        assert out.hover[d] and np.all(out.velocity[d] == 0) and (d, "invalid_pose") in _kinds(out)
    assert not out.hover[0] and np.any(out.velocity[0] != 0)
    assert (1, "invalid_pose") not in _kinds(ctl.step(pos, quat, ts, now=0.08))  # reported once, when it starts


def test_stale_pose_hovers_then_lands(synthetic):
    ctl = _controller(synthetic, stale_after=0.1, land_after=0.3)
    _ok(ctl.step(START, Q, np.zeros(4), now=0.0))
    seen = set()
    for k in range(1, 25):
        now = 0.02 * k
        ts = np.full(4, now)
        ts[0] = 0.0  # drone 0's mocap froze
        out = ctl.step(START, Q, ts, now=now)
        _ok(out)
        seen |= _kinds(out)
        if now > 0.1 + 1e-9:
            assert out.hover[0] and np.all(out.velocity[0] == 0)
        if now > 0.3 + 1e-9:
            assert out.land[0]
    assert {(0, "stale_pose"), (0, "land")} <= seen and not out.land[1:].any()


def test_drone_outside_the_geofence_gets_a_land_request(synthetic):
    ctl = _controller(synthetic)
    pos = START.copy()
    pos[2] = [20.0, 0.0, 1.0]  # beyond arena_high x = 8
    out = ctl.step(pos, Q, np.zeros(4), now=0.0)
    _ok(out)
    assert out.land[2] and np.all(out.velocity[2] == 0) and {(2, "geofence"), (2, "land")} <= _kinds(out)
    out = ctl.step(START, Q, np.full(4, 0.02), now=0.02)  # back inside: landing is latched until reset
    assert out.land[2] and np.all(out.velocity[2] == 0)


def test_nonfinite_command_is_replaced_by_hover(synthetic, monkeypatch):
    real = fc.run_policy

    def broken(bundle, obs, cyl_accel=None, applied=None):
        out = real(bundle, obs, cyl_accel, applied)
        u = out.u.copy()
        u[..., 1, :] = np.nan
        return fc.PolicyOutput(out.nominal, u, out.gain, out.intervened, out.converged)

    monkeypatch.setattr(fc, "run_policy", broken)
    out = _controller(synthetic).step(START, Q, np.zeros(4), now=0.0)
    _ok(out)
    assert out.hover[1] and (1, "nonfinite_command") in _kinds(out)


def test_random_garbage_never_gives_nan_or_unbounded_commands(synthetic):
    rng = np.random.default_rng(7)
    ctl = _controller(synthetic)
    for k in range(200):
        pos = START + rng.normal(0, 0.5, (4, 3))
        quat = Q + rng.normal(0, 0.1, (4, 4))
        ts = np.full(4, 0.02 * k)
        junk = rng.uniform(size=4)
        pos[junk < 0.1] = rng.choice([np.nan, np.inf, -np.inf, 1e12])
        quat[junk > 0.9] = rng.choice([np.nan, 0.0, 1e9])
        ts[(junk > 0.4) & (junk < 0.5)] = rng.choice([np.nan, -1.0, 0.0])
        obstacles = fc.Obstacles(pos=rng.uniform(-8, 8, (5, 2)), radius=np.full(5, 0.15),
                                 vel=rng.normal(0, 1, (5, 2)))
        _ok(ctl.step(pos, quat, ts, now=0.02 * k, obstacles=obstacles))


def test_old_poses_pass_gates_when_the_drone_does_not_a_step_late(synthetic, monkeypatch):
    # Drone 0 flies through gate 0 (centre (6, 0, 1), passage +y) on a first-order lag behind the runtime's commands;
    # the runtime sees poses one control step (40 ms) old. With the model estimate it switches to the next gate in
    # the step the drone crosses, as the simulator does; the line fit switches a step late, a drone already through.
    def straight(bundle, obs, cyl_accel=None, applied=None):
        u = np.zeros(obs.shape[:-1] + (3,))
        u[..., 0, 1] = 1.0
        off = np.zeros(obs.shape[:-1], bool)
        return fc.PolicyOutput(nominal=u, u=u, gain=np.ones(off.shape), intervened=off, converged=~off)

    monkeypatch.setattr(fc, "run_policy", straight)
    gates = np.array(synthetic.manifest["course"]["gates"])
    dt, tau = 0.04, np.array([0.34, 0.34, 0.22])
    switched = {}
    for velocity in ("model", "window"):
        ctl = fc.FlightController(synthetic, 4, estimation=estimator.EstimatorConfig(velocity=velocity))
        ctl.reset(gates=gates)
        p = np.array([[6.0, -1.0, 1.0], [0.0, -4.0, 1.0], [-2.0, -4.0, 1.0], [-4.0, -4.0, 1.0]])
        v, u = np.zeros((4, 3)), np.zeros((4, 3))
        poses = [(0.0, p.copy())]
        for k in range(1, 60):
            for _ in range(100):  # the drone flies the last command for one control period
                v = v + (u - v) / tau * (dt / 100)
                p = p + v * (dt / 100)
            poses.append((k * dt, p.copy()))
            t_pose, seen = poses[-2]
            out = ctl.step(seen, Q, np.full(4, t_pose), now=k * dt)
            u = out.velocity
            if out.target[0] == 1 and velocity not in switched:
                switched[velocity] = (k, p[0, 1])
    k_model, y_model = switched["model"]
    assert y_model >= 0 and poses[k_model - 1][1][0, 1] < 0  # the step the drone itself crossed the gate's plane
    assert switched["window"][0] == k_model + 1


def test_pose_noise_at_a_gate_plane_counts_no_pass_until_the_drone_comes_from_before_it(synthetic, monkeypatch):
    # Gate 0: centre (6, 0, 1), passage +y, half-opening 0.3. Drone 0 passes its plane 0.8 m to the side (outside the
    # opening: no pass, as in the simulator), comes back to the middle of the opening from the far side and sits on
    # the plane while its poses flicker ±3 mm across it: the simulator counts nothing there, nor may the runtime (it
    # did: a ghost sent on to the next gate). Once the drone has been 2 cm before the plane, passing 1 cm beyond it
    # through the opening counts.
    monkeypatch.setattr(fc, "run_policy", lambda bundle, obs, cyl_accel=None, applied=None: fc.PolicyOutput(
        nominal=np.zeros(obs.shape[:-1] + (3,)), u=np.zeros(obs.shape[:-1] + (3,)), gain=np.ones(obs.shape[:-1]),
        intervened=np.zeros(obs.shape[:-1], bool), converged=np.ones(obs.shape[:-1], bool)))
    ctl = fc.FlightController(synthetic, 4, estimation=estimator.EstimatorConfig(velocity="window"))
    ctl.reset(gates=np.array(synthetic.manifest["course"]["gates"]))
    assert tuple(ctl._gates[0, 0]) == (6.0, 0.0, 1.0, np.pi / 2)
    rest = np.array([[0.0, -4.0, 1.0], [-2.0, -4.0, 1.0], [-4.0, -4.0, 1.0]])
    path = ([(6.8, y, 1.0) for y in np.linspace(-0.5, 0.3, 9)]  # past the plane beside the frame
            + [(x, 0.3, 1.0) for x in np.linspace(6.7, 6.0, 8)]  # round to the middle, on the far side
            + [(6.0, y, 1.0) for y in (0.2, 0.1, 0.05, 0.01, 0.003, -0.001, 0.002, -0.003, 0.003, -0.002, 0.004)])
    # Before the plane (armed), then crawling up to it with the same flicker: a pass needs 1 cm beyond the plane.
    back = [(6.0, y, 1.0) for y in (-0.01, -0.025, -0.01, -0.005, 0.004, -0.002, 0.006, 0.003, 0.015, 0.1)]
    targets = []
    for k, p0 in enumerate(path + back):
        out = ctl.step(np.vstack([p0, rest]), Q, np.full(4, 0.04 * k), now=0.04 * k)
        targets.append(int(out.target[0]))
    assert targets[:len(path)] == [0] * len(path)
    assert targets[len(path):] == [0] * 8 + [1, 1]


GOALS = np.array([[0.0, 0.0, 1.0], [0.0, 3.0, 1.0], [0.0, -3.0, 1.0], [3.0, 3.0, 1.0]])


def _pass_beside_the_goal(monkeypatch, off, margin=None, steps=30):
    """Drone 0 flies straight along +x at 1.5 m/s, ``off`` m beside its goal (0, 0, 1), while every command asks it
    for (1.5, -1.5, 0), towards the goal: a drone that does not fly as the runtime's model has it (a gust, the
    filter of a real swarm). Poses are one control step (40 ms) old. Returns per step: the true distance to the goal,
    the predicted present's and whether the runtime finished the drone."""
    toward = np.array([1.5, -1.5, 0.0])

    def toward_the_goal(bundle, obs, cyl_accel=None, applied=None):
        u = np.broadcast_to(toward, obs.shape[:-1] + (3,)).copy()
        off = np.zeros(obs.shape[:-1], bool)
        return fc.PolicyOutput(nominal=u, u=u, gain=np.ones(off.shape), intervened=off, converged=~off)

    monkeypatch.setattr(fc, "run_policy", toward_the_goal)
    safety = fc.SafetyConfig() if margin is None else fc.SafetyConfig(goal_margin=margin)
    ctl = fc.FlightController(bench.synthetic_bundle(num_gates=0), 4, safety=safety)
    ctl.reset(goals=GOALS)
    start = np.array([[-1.0, off, 1.0], [-4.0, 3.0, 1.0], [-4.0, -3.0, 1.0], [-4.0, 4.0, 1.0]])
    truth, predicted, finished = [], [], []
    for k in range(steps):
        p = start + np.outer([1.0, 0, 0, 0], [1.5 * 0.04 * k, 0.0, 0.0])
        seen = start + np.outer([1.0, 0, 0, 0], [1.5 * 0.04 * max(k - 1, 0), 0.0, 0.0])
        out = ctl.step(seen, Q, np.full(4, 0.04 * max(k - 1, 0)), now=0.04 * k)
        truth.append(np.linalg.norm(p[0] - GOALS[0]))
        predicted.append(np.linalg.norm(out.position[0] - GOALS[0]))
        finished.append(bool(out.finished[0]))
    return np.array(truth), np.array(predicted), np.array(finished)


def test_a_goal_is_reached_on_measured_poses_not_on_the_prediction(monkeypatch):
    # 0.22 m beside the goal (radius 0.2) the drone never enters it, but the runtime's present, carried 40 ms on with
    # commands the drone does not fly, comes within 0.196 m: finishing on it stopped drones short of their goals (SITL,
    # 16 drones at 40 ms: 6 of 9 failed episodes in 400). On measured poses it is never finished.
    truth, predicted, finished = _pass_beside_the_goal(monkeypatch, 0.22)
    assert truth.min() > 0.2 and predicted.min() < 0.2 and not finished.any()
    # 0.15 m beside: the pose of step k is x = -1 + 0.06 (k - 1), first inside the radius less the 1 cm margin,
    # sqrt(x^2 + 0.15^2) < 0.19, at x = -0.1 (k = 16; 0.180 m), a step after the drone itself entered.
    truth, predicted, finished = _pass_beside_the_goal(monkeypatch, 0.15)
    assert np.argmax(finished) == 16 and finished[16:].all() and truth[15] < 0.2
    # The margin: a pass 0.195 m beside comes within 0.199 m of the goal (x = -0.04, the pose of step 17), which the
    # mocap's noise could as well have put outside it; with the margin that finishes nothing, without it step 17.
    truth, _, finished = _pass_beside_the_goal(monkeypatch, 0.195)
    assert truth.min() < 0.2 and not finished.any()
    assert np.argmax(_pass_beside_the_goal(monkeypatch, 0.195, margin=0.0)[2]) == 17
    with pytest.raises(ValueError, match=r"invalid goal_margin=0.2: allowed: 0 <= goal_margin < the bundle's goal "
                                         r"radius, 0.2 m"):
        fc.FlightController(bench.synthetic_bundle(num_gates=0), 4, safety=fc.SafetyConfig(goal_margin=0.2))
    with pytest.raises(ValueError, match="invalid goal_margin=-0.01"):
        fc.SafetyConfig(goal_margin=-0.01)


def test_command_accel_limit_of_the_bundle_ramps_every_command(synthetic):
    # The simulator's limit (EnvConfig.command_accel_limit): each command moves at most 5 m/s² / 25 Hz = 0.2 m/s
    # per axis from the last one sent, towards what the unlimited runtime sends (with the line-fit velocity its
    # estimates and targets do not depend on what it sent). Poses with gaps make some drones hover: the hover command
    # is ramped too.
    manifest = {**synthetic.manifest, "env": {**synthetic.env, "command_accel_limit": 5.0}}
    line = estimator.EstimatorConfig(velocity="window")
    limited, free = (fc.FlightController(b, 4, estimation=line)
                     for b in (dataclasses.replace(synthetic, manifest=manifest), synthetic))
    for ctl in (limited, free):
        ctl.reset(gates=np.array(synthetic.manifest["course"]["gates"]))
    rng = np.random.default_rng(3)
    last = np.zeros((4, 3))
    for k in range(40):
        pos = START + rng.normal(0, 0.3, (4, 3))
        ts = np.where(rng.uniform(size=4) < 0.1, np.nan, 0.04 * k)
        want = free.step(pos, Q, ts, now=0.04 * k).velocity
        got = limited.step(pos, Q, ts, now=0.04 * k).velocity
        np.testing.assert_allclose(got, last + np.clip(want - last, -0.2, 0.2), atol=1e-12)
        last = got
    assert np.abs(want).max() > 0.5  # the runtime asked for more than one step's change


def test_a_swarm_that_does_not_match_the_bundle_is_refused(synthetic):
    with pytest.raises(ValueError, match="trained for 4 drones, the swarm has 3"):
        fc.FlightController(synthetic, 3)
    with pytest.raises(ValueError, match="trained on scenario 'race', not 'lab'"):
        fc.FlightController(synthetic, 4, scenario="lab")
    ctl = fc.FlightController(synthetic, 4)
    with pytest.raises(ValueError, match="call reset"):
        ctl.step(START, Q, np.zeros(4))
    with pytest.raises(ValueError, match=r"invalid gates of shape \(2, 4\)"):
        ctl.reset(gates=np.zeros((2, 4)))
    with pytest.raises(ValueError, match="needs gates"):
        ctl.reset(goals=np.zeros((4, 3)))
    ctl.reset(gates=np.array(synthetic.manifest["course"]["gates"]))
    with pytest.raises(ValueError, match=r"positions has shape \(3, 3\)"):
        ctl.step(START[:3], Q, np.zeros(4))
    with pytest.raises(ValueError, match="9 obstacles but the policy observes at most 8"):
        ctl.step(START, Q, np.zeros(4), obstacles=fc.Obstacles(pos=np.zeros((9, 2)), radius=np.ones(9)))
    with pytest.raises(ValueError, match=r"invalid obstacles.accel=\[-1.0, 0.0\]: allowed: finite bounds >= 0"):
        ctl.step(START, Q, np.zeros(4), obstacles=fc.Obstacles(pos=np.full((2, 2), 5.0), radius=np.ones(2),
                                                               accel=np.array([-1.0, 0.0])))
    with pytest.raises(ValueError, match="invalid stale_after"):
        fc.SafetyConfig(stale_after=float("nan"))


def test_a_bundle_that_was_changed_or_is_not_understood_is_refused(synthetic, tmp_path):
    import shutil

    bad = tmp_path / "tampered"
    shutil.copytree(synthetic.path, bad)
    with open(bad / fb.NPZ, "r+b") as f:
        f.seek(200)
        f.write(b"\x00\x01")
    with pytest.raises(fb.BundleError, match="sha256"):
        fb.load_bundle(bad)
    newer = tmp_path / "newer"
    shutil.copytree(synthetic.path, newer)
    m = json.loads((newer / fb.MANIFEST).read_text())
    m["format_version"] = 99
    (newer / fb.MANIFEST).write_text(json.dumps(m))
    with pytest.raises(fb.BundleError, match="format_version 99 is not supported"):
        fb.load_bundle(newer)
    arrays = dict(synthetic.arrays)
    arrays["actor/MLP_0/Dense_0/kernel"] = arrays["actor/MLP_0/Dense_0/kernel"].copy()
    arrays["actor/MLP_0/Dense_0/kernel"][0, 0] = np.nan
    with pytest.raises(fb.BundleError, match="NaN or Inf"):
        fb.bundle_from(dict(synthetic.manifest), arrays)
    m = dict(synthetic.manifest)
    m["env"] = {**m["env"], "num_cylinders": 7}
    with pytest.raises(fb.BundleError, match="observation layout"):
        fb.bundle_from(m, dict(synthetic.arrays))
    with pytest.raises(fb.BundleError, match="is not a bundle"):
        fb.load_bundle(tmp_path)


# ------------------------------------------------------------------ fly --dry-run
def _replay_csv(path, steps=40, missing=(2, range(10, 14))):
    rows = [",".join(ffly.CSV_COLUMNS)]
    for k in range(steps):
        t = 0.01 * k
        for d in range(4):
            if d == missing[0] and k in missing[1]:
                rows.append(f"{t:.3f},{d},nan,nan,nan,nan,nan,nan,nan")
                continue
            x, y, z = START[d] + [0.5 * t, 0.0, 0.0]
            rows.append(f"{t:.3f},{d},{x:.4f},{y:.4f},{z:.4f},1,0,0,0")
    path.write_text("\n".join(rows) + "\n")
    return path


def test_fly_dry_run_replays_a_pose_log(synthetic, tmp_path, capsys):
    csv = _replay_csv(tmp_path / "poses.csv")
    args = ["fly", "--bundle", str(synthetic.path), "--uris", URIS, "--mocap", f"replay:{csv}", "--dry-run",
            "--record", str(tmp_path / "flight")]
    assert cli.main(args) == 0
    out = capsys.readouterr().out.splitlines()
    sends = [line for line in out if "send_velocity_world_setpoint" in line]
    # The sequence before the first setpoint (tests/test_fly_live.py checks it call by call).
    steps = [next(i for i, line in enumerate(out) if line.startswith(p)) for p in
             ("connect", "param all stabilizer.estimator=2", "reset estimators", "arm all", "takeoff all")]
    assert steps == sorted(steps) and steps[-1] < out.index(sends[0])
    assert (tmp_path / "flight.npz").is_file() and (tmp_path / "flight.json").is_file()
    rate = synthetic.manifest["control"]["rate_hz"]
    assert len(sends) == 4 * round(0.4 * rate)  # 0.4 s of poses at the bundle's control rate, 4 drones
    assert all("yawrate=0 deg/s" in line for line in sends)
    speeds = np.array([[float(w.split("=")[1]) for w in line.split() if w[:3] in ("vx=", "vy=", "vz=")]
                       for line in sends])
    assert np.all(np.isfinite(speeds)) and np.all(np.abs(speeds) <= 2.0)
    assert any("cf2 invalid_pose" in line for line in out)  # the gap in drone 2's log
    in_gap = math.ceil(0.10 * rate - 1e-9) / rate  # the first control tick inside drone 2's gap (0.10-0.13 s)
    assert any(line.startswith(f"t={in_gap:.3f} cf2") and "vx=+0.000 vy=+0.000 vz=+0.000" in line for line in sends)
    assert sum(line.startswith("land cf") for line in out) == 4 and out[-1].startswith("flight loop ended")


def _full_state_sends(synthetic, csv, leash):
    """Per control step, the (position, velocity) setpoints a dry run sends drone 0 of a Mellinger bundle."""
    m = dict(synthetic.manifest)
    m["drone"] = {**m["drone"], "controller": "mellinger", "setpoint": "full_state", "reference_leash": leash}
    lines = []
    ffly.fly(fb.bundle_from(m, dict(synthetic.arrays)), ffly.DryRunLink(URIS.split(","), lines.append),
             ffly.ReplaySource(csv, 4), plan=ffly.FlightPlan(realtime=False), log=lines.append)
    assert not any("send_velocity_world_setpoint" in line for line in lines)
    sends = [line for line in lines if " cf0 " in line and "send_full_state_setpoint" in line]
    nums = [[float(x) for x in re.findall(r"[-+]\d+\.\d+", line.split("setpoint", 1)[1])] for line in sends]
    return np.array(nums)[:, :3], np.array(nums)[:, 3:6]


def test_fly_streams_full_states_along_the_integrated_command_to_mellinger(synthetic, tmp_path):
    csv = _replay_csv(tmp_path / "poses.csv")
    period = 1.0 / synthetic.manifest["control"]["rate_hz"]
    pos, vel = _full_state_sends(synthetic, csv, leash=10.0)
    assert len(pos) == round(0.4 / period) and np.abs(vel).max() > 0.1
    # The setpoint is the reference plus half a step of the command; the reference moves a whole step of it:
    # consecutive setpoints are (v_k + v_k+1) / 2 * period apart (to the printed 1 mm).
    np.testing.assert_allclose(np.diff(pos, axis=0), (vel[:-1] + vel[1:]) / 2 * period, atol=2.5e-3)
    np.testing.assert_allclose(pos[0], START[0] + vel[0] * period / 2, atol=2e-3)  # from where the drone was
    # On a 1 cm leash the reference is dragged along by the drone (0.5 m/s in x in the replay, 0.18 m in these
    # 0.36 s), far beyond where the commands alone would take it.
    pos, vel = _full_state_sends(synthetic, csv, leash=0.01)
    commanded = np.sum(vel[:-1, 0]) * period
    assert abs(commanded) < 0.05 and pos[-1, 0] - pos[0, 0] > 0.1
    # A manifest that asks for full states without a leash is refused before take-off, in one line.
    m = dict(synthetic.manifest)
    m["drone"] = {**m["drone"], "setpoint": "full_state", "reference_leash": None}
    lines = []
    with pytest.raises(ValueError, match=r"invalid manifest drone.reference_leash=None: allowed: a number > 0"):
        ffly.fly(fb.bundle_from(m, dict(synthetic.arrays)), ffly.DryRunLink(URIS.split(","), lines.append),
                 ffly.ReplaySource(csv, 4), plan=ffly.FlightPlan(realtime=False), log=lines.append)
    assert not any(line.startswith("takeoff") for line in lines)


def test_fly_refuses_bad_input_and_stops_on_an_exception(synthetic, tmp_path, capsys):
    csv = _replay_csv(tmp_path / "poses.csv")
    base = ["fly", "--bundle", str(synthetic.path), "--mocap", f"replay:{csv}"]
    assert cli.main(base + ["--uris", URIS.rsplit(",", 1)[0], "--dry-run"]) == 2
    assert "3 URIs but the bundle was trained for 4 drones" in capsys.readouterr().err
    assert cli.main(base + ["--uris", URIS]) == 2  # a replay never drives real drones
    assert "cannot fly real drones" in capsys.readouterr().err
    (tmp_path / "bad.csv").write_text("t,drone,x,y,z\n0,0,1,2,3\n")
    assert cli.main(["fly", "--bundle", str(synthetic.path), "--uris", URIS, "--mocap",
                     f"replay:{tmp_path / 'bad.csv'}", "--dry-run"]) == 2
    assert "lacks column 'qw'" in capsys.readouterr().err

    lines = []

    class Failing(ffly.DryRunLink):
        def send_velocities(self, t, velocities, active):
            if t > 0.05:
                raise KeyboardInterrupt  # Ctrl-C in the middle of the loop
            super().send_velocities(t, velocities, active)

    with pytest.raises(KeyboardInterrupt):
        ffly.fly(synthetic, Failing(URIS.split(","), lines.append), ffly.ReplaySource(csv, 4),
                 plan=ffly.FlightPlan(realtime=False), log=lines.append)
    assert lines[-1] == "EMERGENCY STOP all"


def test_aswarm_fly_runs_without_jax(synthetic, tmp_path):
    csv = _replay_csv(tmp_path / "poses.csv", steps=10)
    code = textwrap.dedent(f"""
        import importlib.abc, sys
        class Block(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in {BLOCKED!r}:
                    raise ImportError("blocked: " + name)
        sys.meta_path.insert(0, Block())
        from aswarm import cli  # `aswarm fly`: the main command line hands over before importing JAX
        sys.exit(cli.main(["fly", "--bundle", {str(synthetic.path)!r}, "--uris", {URIS!r}, "--mocap",
                           "replay:{csv}", "--dry-run", "--record", {str(tmp_path / "flight")!r}]))
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    assert "send_velocity_world_setpoint" in run.stdout


# ------------------------------------------------------------------ cost
def test_runtime_step_cost_is_measured():
    times = bench.measure(num_agents=4, steps=60, conflict=True)
    assert set(times) >= {"estimate", "observe", "actor", "gain", "filter", "controller.step"}
    assert times["qp_fraction"].mean() > 0.5 and np.all(times["controller.step"] > 0)
    assert "controller.step" in bench.table(4, 40)

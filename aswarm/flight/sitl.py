"""``aswarm sitl``: the numpy flight runtime in closed loop against the MJX simulator.

The runtime (:class:`aswarm.flight.FlightController`, the very code that flies) sees what a mocap
system would give it: drone positions and attitudes with timestamps, optionally with Gaussian
position noise and latency, the cylinders' poses and the course (gates or goals). Latency comes in
milliseconds: whole control steps of it make the runtime see old poses, the rest delays its command on the
drone by whole onboard-controller ticks. The simulated drone can be heavier or lighter and its rotors push
more or less than the runtime (and the onboard controller's thrust map) expect; nothing else of the
training's randomisation is drawn. It estimates velocities itself, tracks its own gate progress, runs the policy and the
filter, and its setpoints drive ``env.step``. Episodes run vmapped and jitted over worlds, as
``aswarm eval`` runs them, from the same keys (so the same layouts for the same seed), and the
report has the same metrics.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from aswarm import config_args, envs
from aswarm.analysis import evaluate
from aswarm.analysis.protocol import EVAL_SEED
from aswarm.core.geometry import cylinder_accel_bound
from aswarm.envs.config import with_legacy_drone
from aswarm.envs.dynamics import drone_state
from aswarm.envs.randomization import Randomization
from aswarm.envs.scenarios import cylinders_at
from aswarm.flight import Bundle, FlightController, Obstacles, SafetyConfig, StepResult, load_bundle
from aswarm.flight.estimator import EstimatorConfig


class Sensed(NamedTuple):
    """What leaves the simulator each step ([B, ...] over worlds)."""

    pos: jax.Array  # [B, n, 3]
    quat: jax.Array  # [B, n, 4] wxyz
    time: jax.Array  # [B] s
    cyl_pos: jax.Array  # [B, M, 2]
    cyl_vel: jax.Array  # [B, M, 2]
    done: jax.Array  # [B]
    metrics: dict


class Simulator(NamedTuple):
    env: envs.SwarmEnv
    reset: callable  # key -> (state, Sensed)
    step: callable  # (state, action [B, n, 3]) -> (state, Sensed)


@functools.lru_cache(maxsize=4)
def simulator(config: envs.EnvConfig, episodes: int) -> Simulator:
    """Jitted, vmapped reset and step of ``episodes`` worlds (cached: tests and repeated runs compile once)."""
    env = envs.SwarmEnv(config)
    n = env.num_agents

    def sense(s: envs.State) -> Sensed:
        d = jax.vmap(lambda data: drone_state(data, n))(s.data)
        cyl_pos, cyl_vel = jax.vmap(cylinders_at)(s.layout, s.data.time)
        return Sensed(d.pos, d.quat, s.data.time, cyl_pos, cyl_vel, s.done, s.metrics)

    @jax.jit
    def reset(key):
        s = jax.vmap(env.reset)(jax.random.split(key, episodes))
        return s, sense(s)

    @jax.jit
    def step(s, action):
        s = jax.vmap(env.step)(s, action)
        return s, sense(s)

    return Simulator(env, reset, step)


def make_env(bundle: Bundle, scenario: str | None = None, env_overrides: list[str] | dict | None = None):
    """The bundle's training environment with ``env_overrides`` (nested ones dotted) applied, checked against the
    bundle.

    The training env is the one the run stored (the manifest's ``source.env_config``); another ``scenario``,
    or a bundle exported before the manifest held the full env, starts from the scenario's preset with the
    bundle's env overrides.
    """
    from aswarm.envs import registry

    trained = {k: config_args.as_tuples(v) for k, v in bundle.manifest["scenario"]["env_overrides"].items()}
    extra = dict(env_overrides) if isinstance(env_overrides, dict) else \
        config_args.parse_assignments(env_overrides or [], envs.EnvConfig)
    stored = bundle.manifest.get("source", {}).get("env_config")
    if stored is not None and scenario in (None, bundle.scenario):
        # Fields added since the export: as the bundle's env was without them.
        base = config_args.from_dict(envs.EnvConfig, with_legacy_drone(stored), "bundle source.env_config",
                                     require_all=True)
        env = envs.SwarmEnv(config_args.replace_fields(base, extra))
    else:
        env = envs.SwarmEnv(config_args.replace_fields(registry.preset(scenario or bundle.scenario),
                                                       {**trained, **extra}))
    if env.num_agents != bundle.num_agents or env.obs_layout.describe() != bundle.layout.describe():
        raise ValueError(f"the bundle was trained on {bundle.scenario!r} with {bundle.num_agents} drones and "
                         f"observations of size {bundle.layout.size}; scenario {env.config.scenario!r} has "
                         f"{env.num_agents} drones and size {env.observation_size}: the observation layout does not "
                         "transfer")
    return env


def exact_drone(env: envs.SwarmEnv, mass_scale: float = 1.0, thrust_scale: float = 1.0,
                latency_ticks: int = 0) -> envs.SwarmEnv:
    """The plant: one exact drone, "randomised" over ranges of one value each, so that its mass, thrust constant and
    command latency (in controller ticks, compiled in only where there is some) are the run's."""
    one = Randomization(mass=(mass_scale,) * 2, thrust_constant=(thrust_scale,) * 2, torque_constant=(1.0, 1.0),
                        motor_tau=(1.0, 1.0), gains=(1.0, 1.0), latency=(latency_ticks / env.ticks,) * 2,
                        mocap_noise=(0.0, 0.0), mocap_delay=(0, 0))
    return envs.SwarmEnv(dataclasses.replace(env.config, randomize=one))


def course(bundle: Bundle, layout) -> dict:
    """reset() arguments of the controller from a batch of simulator layouts (host arrays)."""
    if bundle.kind == "track":
        return {"gates": np.concatenate([layout.gate_pos, layout.gate_yaw[..., None]], -1)}
    return {"goals": layout.waypoints[:, :, 0]}


def split_latency(latency_ms: float, cfg: envs.EnvConfig) -> tuple[int, int]:
    """``latency_ms`` as (whole control steps of pose delay, onboard-controller ticks of command delay); a
    ``ValueError`` unless it is a whole number of ticks."""
    tick = 1000.0 / cfg.ctrl_freq
    ticks = latency_ms / tick
    if not (np.isfinite(latency_ms) and latency_ms >= 0) or abs(ticks - round(ticks)) > 1e-6:
        raise ValueError(f"invalid latency={latency_ms!r} ms: allowed: a multiple >= 0 of the onboard controller's "
                         f"tick, {tick:g} ms")
    per_step = cfg.ctrl_freq // cfg.policy_freq
    return int(round(ticks)) // per_step, int(round(ticks)) % per_step


def run_sitl(bundle: Bundle | str | Path, scenario: str | None = None, episodes: int = 200, seed: int = EVAL_SEED,
             noise: float = 0.0, latency_ms: float = 0.0, mass_scale: float = 1.0, thrust_scale: float = 1.0,
             env_overrides: list[str] | dict | None = None, estimation: EstimatorConfig = EstimatorConfig(),
             goal_margin: float = SafetyConfig.goal_margin, progress: bool = False,
             on_step: Callable[[Sensed, StepResult | None], None] | None = None) -> dict:
    """Fly ``episodes`` episodes; returns ``aswarm eval``'s metrics plus the runtime's own statistics.

    noise: standard deviation (m) of the Gaussian noise added to every position the runtime sees;
    latency_ms: what the runtime sees is this old, counting its command's way to the motors (:func:`split_latency`);
    mass_scale, thrust_scale: the simulated drone's mass and thrust constant over the nominal ones.
    goal_margin: the runtime's (``SafetyConfig.goal_margin``).
    on_step: called at every control step with the simulator's true state as it left the step before (host arrays)
    and the runtime's answer to what it saw of it, and once more after the last step with None for the answer: for
    traces (``experiments/sitl_trace.py``).
    """
    if episodes <= 0:
        raise ValueError(f"invalid episodes={episodes}: must be > 0")
    if not (np.isfinite(noise) and noise >= 0):
        raise ValueError(f"invalid noise={noise!r}: must be a finite number of metres >= 0")
    for name, v in (("mass_scale", mass_scale), ("thrust_scale", thrust_scale)):
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"invalid {name}={v!r}: allowed: a factor > 0 of the nominal value")
    b = bundle if isinstance(bundle, Bundle) else load_bundle(bundle)
    env = make_env(b, scenario, env_overrides)
    latency, ticks = split_latency(latency_ms, env.config)
    env = exact_drone(env, mass_scale, thrust_scale, ticks)
    cfg = env.config
    sim = simulator(cfg, episodes)
    state, sensed = sim.reset(jax.random.PRNGKey(seed))
    layout = jax.device_get(state.layout)
    # A pose is fresh for the controller if it is at most `latency` steps old: the stale limit
    # grows with the configured latency, or every drone would hover.
    safety = SafetyConfig(stale_after=max(0.1, (latency + 1.5) * cfg.dt), land_after=max(0.5, (latency + 5) * cfg.dt),
                          finished_are_neighbours=False, goal_margin=goal_margin)
    ctl = FlightController(b, env.num_agents, safety=safety, estimation=estimation)
    ctl.reset(**course(b, layout))
    # The moving cylinders' acceleration bounds, as a flight script gives them from its obstacles' known motion.
    accel = cylinder_accel_bound(layout.cyl_amplitude, layout.cyl_omega) if cfg.num_moving else None
    rng = np.random.default_rng(seed)
    seen = collections.deque(maxlen=latency + 1)
    n = env.num_agents
    ended = np.zeros(episodes, bool)
    rec: dict | None = None
    interventions = flying = 0.0
    runtime = 0.0
    steps = 0
    events = collections.Counter()
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=cfg.max_steps, unit="step", dynamic_ncols=True)
    for k in range(cfg.max_steps + 1):
        host = jax.device_get(sensed)
        done = np.asarray(host.done) > 0
        metrics = {name: np.asarray(v) for name, v in host.metrics.items()}
        if rec is None:
            rec = {name: np.zeros_like(v) for name, v in metrics.items()}
        first = done & ~ended
        for name, v in metrics.items():
            rec[name] = np.where(first, v, rec[name])
        ended |= first
        if k == cfg.max_steps or ended.all():
            if on_step is not None:
                on_step(host, None)
            break
        seen.append(host)
        old = seen[0]  # `latency` steps ago (the oldest there is at the start)
        pos = np.asarray(old.pos, np.float64)
        if noise > 0:
            pos = pos + rng.normal(0.0, noise, pos.shape)
        t0 = time.perf_counter()
        out = ctl.step(pos, old.quat, np.asarray(old.time)[:, None], now=np.asarray(host.time),
                       obstacles=Obstacles(pos=old.cyl_pos, radius=layout.cyl_radius, vel=old.cyl_vel,
                                           present=layout.cyl_present, accel=accel))
        runtime += time.perf_counter() - t0
        steps += 1
        if on_step is not None:
            on_step(host, out)
        live = ~ended
        interventions += float(np.sum(out.intervened[live]))
        flying += float(np.sum(live)) * n
        events.update(e.kind for e in out.events if live[e.world])
        state, sensed = sim.step(state, jnp.asarray(out.velocity, jnp.float32))
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    result = {"checkpoint": str(b.path), "method": b.safety_filter["method"], "scenario": cfg.scenario,
              "episodes": episodes, "seed": seed, "trained_updates": int(b.manifest["source"]["trained_updates"]),
              "env_overrides": sorted(env_overrides or []) if not isinstance(env_overrides, dict)
              else sorted(f"{k}={v}" for k, v in env_overrides.items()),
              "episodes_ended": int(ended.sum())}
    result.update(evaluate.summarize(rec, interventions / max(flying, 1.0)))
    result.update(noise=noise, latency_ms=latency_ms, mass_scale=mass_scale, thrust_scale=thrust_scale,
                  control_steps=steps,
                  runtime_ms_per_step=1e3 * runtime / max(steps, 1), events=dict(sorted(events.items())))
    return result


def format_table(r: dict) -> str:
    lines = [evaluate.format_table(r).replace(" episodes (seed", " SITL episodes (seed", 1)]
    lines.append(f"  {'position noise':24s} {r['noise']:8.3f} m")
    lines.append(f"  {'latency':24s} {r['latency_ms']:8.0f} ms")
    lines.append(f"  {'mass, thrust constant':24s} {r['mass_scale']:8.2f} x, {r['thrust_scale']:.2f} x nominal")
    lines.append(f"  {'runtime per step':24s} {r['runtime_ms_per_step']:8.3f} ms  (all {r['episodes']} worlds)")
    shown = ", ".join(f"{k} {v}" for k, v in r["events"].items()) or "none"
    lines.append(f"  {'runtime events':24s} {shown}")
    return "\n".join(lines)


def replay_flight(bundle: Bundle | str | Path, flight: str | Path, out: str | Path, seed: int = EVAL_SEED,
                  estimation: EstimatorConfig = EstimatorConfig()) -> dict:
    """Fly a recorded flight's start in the simulator, through the same runtime, for a side-by-side.

    One episode of the bundle's training environment (the exact nominal drone, as :func:`run_sitl` flies it) whose
    layout is replaced by the flight's: the drones start where the record has them when its control loop started
    (after take-off), at rest and level; the gates (or goals) are the flight's course; the cylinders are the flight's
    obstacles where the record first has them at that moment, with their radii, static (a moving one is frozen where
    it was) and the rest absent. The episode runs until the simulator ends it (every drone finished or collided, or
    the episode's time limit) or as long as the flight's control loop, whichever is first. Mocap noise, latency, the
    take-off and the landing are not simulated; the simulator's clock is one control step (at rest) ahead of the
    record's, so its staggered releases come that much earlier. Writes a flight record (:mod:`aswarm.flight.record`)
    to ``out`` and returns the episode's metrics.
    """
    from aswarm.flight import record

    rec = record.load_record(flight)
    b = bundle if isinstance(bundle, Bundle) else load_bundle(bundle)
    a, meta = rec.arrays, rec.meta
    control = np.flatnonzero(a["phase"] == record.PHASES.index("control"))
    if not len(control):
        raise ValueError(f"flight record {flight} has no control steps (status {meta.get('status')!r}): nothing to "
                         "replay")
    first = int(control[0])
    p0 = np.asarray(a["pos"][first], np.float64)
    if not np.isfinite(p0).all():
        raise ValueError(f"flight record {flight}: not every drone had a pose when the control loop started")
    env = exact_drone(make_env(b))
    cfg = env.config
    n, M = env.num_agents, cfg.num_cylinders
    if p0.shape != (n, 3):
        raise ValueError(f"flight record {flight} has {p0.shape[0]} drones, the bundle {n}")
    sim = simulator(cfg, 1)
    state, _ = sim.reset(jax.random.PRNGKey(seed))
    lay = state.layout
    course = meta.get("course", {})
    changes = {"start_pos": jnp.asarray(p0[None], jnp.float32)}
    if b.kind == "track":
        gates = np.asarray(course["gates"], np.float32)
        changes.update(gate_pos=jnp.asarray(gates[None, :, :3]), gate_yaw=jnp.asarray(gates[None, :, 3]),
                       waypoints=jnp.broadcast_to(jnp.asarray(gates[None, None, :, :3]), lay.waypoints.shape))
    else:
        goals = np.asarray(course["goals"], np.float32)
        changes["waypoints"] = jnp.asarray(goals[None, :, None, :])
    xy = np.asarray(a["obstacle_xy"][first], np.float32)
    radii = np.asarray(meta.get("obstacle_radius", []), np.float32)
    m = min(len(radii), M)
    seen = np.zeros(M, bool)
    centre, radius = np.zeros((M, 2), np.float32), np.asarray(lay.cyl_radius[0]).copy()
    if m:
        seen[:m] = np.isfinite(xy[:m]).all(-1)
        centre[:m] = np.where(seen[:m, None], xy[:m], 0.0)
        radius[:m] = radii[:m]
    changes.update(cyl_center=jnp.asarray(centre[None]), cyl_radius=jnp.asarray(radius[None]),
                   cyl_present=jnp.asarray(seen[None]), cyl_amplitude=jnp.zeros((1, M)), cyl_omega=jnp.zeros((1, M)))
    lay = lay.replace(**changes)
    qpos = np.concatenate([p0, np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))], -1).reshape(1, -1)
    data = state.data.replace(qpos=jnp.asarray(qpos, state.data.qpos.dtype), qvel=jnp.zeros_like(state.data.qvel))
    onboard = state.onboard
    if onboard.reference is not None:  # Mellinger's integrated reference starts where the drones are
        onboard = onboard.replace(reference=jnp.broadcast_to(jnp.asarray(p0, jnp.float32), onboard.reference.shape))
    state = state.replace(layout=lay, data=data, onboard=onboard)
    state, sensed = sim.step(state, jnp.zeros((1, n, 3)))  # one zero step: the sensed state of the new layout

    ctl = FlightController(b, n, safety=SafetyConfig(finished_are_neighbours=False), estimation=estimation)
    ctl.reset(**course_from_meta(b, course))
    t_end = float(a["time"][control[-1]])
    release = np.asarray(meta.get("release_times") or np.zeros(n), np.float64)
    rows = collections.defaultdict(list)
    t_start = float(np.asarray(sensed.time)[0])
    for _ in range(cfg.max_steps):
        host = jax.device_get(sensed)
        t = float(np.asarray(host.time)[0]) - t_start
        if bool(np.asarray(host.done)[0] > 0) or t > t_end + 1e-6:
            break
        pos = np.asarray(host.pos[0], np.float64)
        res = ctl.step(pos, np.asarray(host.quat[0], np.float64), np.full(n, t), now=t,
                       obstacles=Obstacles(pos=np.asarray(host.cyl_pos[0]), radius=radius, present=seen),
                       hold=t < release - 1e-9)
        for name, v in (("time", t), ("pos", pos), ("quat", host.quat[0]), ("raw", res.nominal),
                        ("filtered", res.velocity), ("intervened", res.intervened), ("hover", res.hover),
                        ("land", res.land), ("target", res.target), ("released", t >= release - 1e-9),
                        ("obstacle_xy", np.asarray(host.cyl_pos[0])[:m])):
            rows[name].append(np.asarray(v))
        state, sensed = sim.step(state, jnp.asarray(res.velocity[None], jnp.float32))
    T = len(rows["time"])
    arrays = {k: np.stack(v) for k, v in rows.items()}
    arrays.update(phase=np.full(T, record.PHASES.index("control"), np.int8), pose_age=np.zeros((T, n)),
                  estimate=np.full((T, n, 3), np.nan), vbat=np.full((T, n), np.nan), supervisor=np.full((T, n), -1),
                  latency=np.full(T, np.nan), lateness=np.full(T, np.nan),
                  pose_times=np.zeros(0))
    metrics = {k: float(np.asarray(v)[0]) for k, v in jax.device_get(sensed.metrics).items()}
    meta_out = {**{k: meta.get(k) for k in ("scenario", "kind", "names", "uris", "course", "obstacles",
                                             "obstacle_radius", "gate_half_opening", "release_times")},
                "format": "aswarm-flight-record", "version": 1, "status": "sitl", "reason": "",
                "mocap": f"SITL of {flight}", "bundle": str(b.path), "rate_hz": b.rate_hz, "metrics": metrics,
                "events": [], "sequence": [], "timing": {}}
    record.write_record(out, arrays, meta_out)
    return {"steps": T, "seconds": T / b.rate_hz, "record": str(out), **metrics}


def course_from_meta(bundle: Bundle, course: dict) -> dict:
    """reset() arguments of the controller from a flight record's course."""
    if bundle.kind == "track":
        return {"gates": np.asarray(course["gates"], np.float64)}
    return {"goals": np.asarray(course["goals"], np.float64)}

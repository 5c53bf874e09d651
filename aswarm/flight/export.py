"""``aswarm export``: a checkpoint's policy as a numpy bundle for the flight side (``aswarm.flight``).

The bundle holds what the deterministic, filtered policy (``Agent.act``) needs and nothing of
JAX: the actor, the observation normalizer and the attention-CBF network as plain float32 arrays in
``policy.npz``, and ``manifest.json`` with the scenario, the swarm, the observation layout field by
field, the action's bounds and units, the control rate, the safety filter's parameters, the
training config's sha256 and the npz's sha256. See ``aswarm/flight/bundle.py`` for the format.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from pathlib import Path

import jax
import numpy as np

from aswarm.agents.config import TrainConfig
from aswarm.agents.networks import ACTIVATIONS
from aswarm.analysis.step_response import characterise
from aswarm.core.geometry import cylinder_accel_bound
from aswarm.core.layout import ObsLayout
from aswarm.core.safety import manifest_fields
from aswarm.envs.presets import SCENARIOS
from aswarm.envs.swarm_env import SwarmEnv
from aswarm.flight import bundle as fb

# The firmware's stabilizer.controller of each onboard controller model that the firmware has.
FIRMWARE_CONTROLLER = {"pid": 1, "mellinger": 2}


def policy_arrays(params: dict, obs_norm) -> dict[str, np.ndarray]:
    """Flat ``{name: float32 array}`` of the actor, the attention-CBF network and the normalizer.

    Names are the flax paths without the ``params`` level: ``actor/MLP_0/Dense_0/kernel``,
    ``cbf/W_Q/kernel``, and ``obs_norm/mean``, ``obs_norm/std`` (a standard deviation, as brax stores it).
    """
    out = {}
    for net in ("actor", "cbf"):
        for path, leaf in jax.tree_util.tree_flatten_with_path(params[net]["params"])[0]:
            name = "/".join([net] + [str(getattr(k, "key", k)) for k in path])
            out[name] = np.asarray(leaf, np.float32)
    out["obs_norm/mean"] = np.asarray(obs_norm.mean, np.float32)
    out["obs_norm/std"] = np.asarray(obs_norm.std, np.float32)
    return out


def config_json(config: TrainConfig, env: SwarmEnv) -> str:
    """The training config as ``runner.write_config`` writes ``config.json`` (its sha256 goes in the manifest),
    with ``env``'s config as its env section."""
    from aswarm.training import run_config

    payload = {**run_config.payload(config), "env": dataclasses.asdict(env.config)}
    return json.dumps(payload, indent=2, default=str)


def _activation(name: str) -> str:
    if name not in ACTIVATIONS:
        raise ValueError(f"activation {name!r} has no flight-side equivalent: allowed: {', '.join(ACTIVATIONS)}")
    # flax's nn.gelu defaults to the tanh approximation; say so, the flight side computes exactly that.
    return "gelu_tanh" if name == "gelu" else name


def build_manifest(config: TrainConfig, env: SwarmEnv, *, source: str, trained_updates: int,
                   config_text: str) -> dict:
    """The manifest of ``config``'s policy on ``env`` (without arrays and hash, added when written)."""
    from aswarm.agents.train import Agent

    agent = Agent.build(config, env)
    ec = env.config
    geo = env.geometry
    env_fields = dict(num_agents=ec.num_agents, num_cylinders=ec.num_cylinders, num_gates=ec.num_gates,
                      max_neighbours=ec.max_neighbours, filter_neighbours=ec.filter_neighbours,
                      filter_neighbour_accel=ec.filter_neighbour_accel,
                      max_speed=ec.max_speed, command_accel_limit=ec.command_accel_limit, policy_freq=ec.policy_freq,
                      collision_radius=ec.cf.collision_radius,
                      arena_low=list(ec.arena_low), arena_high=list(ec.arena_high),
                      gate_half_opening=ec.gate_half_opening, gate_bar=ec.gate_bar, goal_radius=ec.goal_radius,
                      episode_seconds=ec.episode_seconds, safety_margin=ec.safety_margin,
                      # m/s²: how hard the moving cylinders the policy trained among could accelerate (their
                      # amplitude ω²; 0 without); give moving obstacles' bounds in flight as Obstacles(accel=...)
                      moving_accel_bound=float(cylinder_accel_bound(
                          ec.moving_amplitude, 2 * math.pi / ec.moving_period * max(ec.moving_speed_scale)))
                      if ec.num_moving else 0.0)
    course = {"gates": [[*map(float, p), float(y)] for p, y in zip(geo.gate_pos, geo.gate_yaw)],
              "gates_meaning": "nominal (x, y, z) m and yaw rad of each gate in order; episodes jitter them",
              "start_center": [float(v) for v in geo.start_center],
              "goal_center": [float(v) for v in geo.goal_center]}
    networks = {
        "actor": {"hidden": list(agent.actor.hidden), "activation": _activation(agent.actor.activation),
                  "out": 6, "out_meaning": "[loc (3) | scale (3)] of a tanh-Gaussian; the command is "
                                           "tanh(loc) * max_speed"},
        "cbf": {"embed": agent.cbf.embed, "hidden": list(agent.cbf.hidden), "state_hidden": agent.cbf.state_hidden,
                "activation": _activation(agent.cbf.activation), "penalty_max": agent.cbf.penalty_max,
                "gain_min": agent.cbf.gain_min, "gain_max": agent.cbf.gain_max},
    }
    # The SafetyFilterConfig field by field (core.safety.from_manifest reads it back), then the env's part.
    safety = {"method": config.method, "enabled": config.uses_filter,
              "gain_source": "attention" if config.uses_attention else "fixed",
              **manifest_fields(agent.config.safety_filter), "penalty_max": config.penalty_max,
              "drone_radius": ec.cf.collision_radius, "gate_half_opening": ec.gate_half_opening,
              "gate_bar": ec.gate_bar,
              "rows": "cylinders M | observed neighbours (n-1, or max_neighbours) | floor 1 | walls 5 (x low, x high, "
                      "y low, y high, ceiling) | gate frame 5 | previous gate 5 (gate rows where a gate is observed)"}
    # The onboard controller the policy was trained on, the firmware parameters that select it on the drone
    # (stabilizer.controller: 1 is controller_pid, 2 Mellinger) and the setpoints it is streamed: velocities, or
    # for Mellinger full states along the integrated command (core.command); the geometric controller has no
    # firmware counterpart. Its measured velocity lag is the flight runtime's model of it (velocity="model").
    drone_lag = characterise(ec)
    drone = {"controller": ec.controller, "motor_tau": ec.cf.motor_tau,
             "motor_tau_down": ec.cf.motor_tau_down, "mass": ec.cf.mass,
             "velocity_lag": [drone_lag.lag_xy, drone_lag.lag_z],
             "firmware_params": {"stabilizer.controller": FIRMWARE_CONTROLLER[ec.controller]}
             if ec.controller in FIRMWARE_CONTROLLER else {},
             "setpoint": "full_state" if ec.controller == "mellinger" else "velocity",
             "pid": dataclasses.asdict(ec.pid) if ec.controller == "pid" else None}
    if ec.controller == "mellinger":
        drone.update(mellinger=dataclasses.asdict(ec.mellinger), reference_leash=ec.reference_leash)
    manifest = fb.make_manifest(
        scenario=ec.scenario, kind=SCENARIOS[ec.scenario].kind, env=env_fields,
        env_overrides={k: list(v) if isinstance(v, tuple) else v for k, v in config.env_overrides},
        course=course, layout=ObsLayout(env.obs_layout.num_cylinders, env.obs_layout.num_neighbours),
        networks=networks, safety_filter=safety, train_config=json.loads(config_text)["train"],
        train_config_sha256=hashlib.sha256(config_text.encode()).hexdigest(), source=source, drone=drone,
        trained_updates=trained_updates)
    # The full env the policy was trained on, as the run stored it: `aswarm sitl` flies on exactly this.
    manifest["source"]["env_config"] = dataclasses.asdict(ec)
    return manifest


def export_policy(config: TrainConfig, params: dict, obs_norm, out_dir: str | Path, *, force: bool = False,
                  source: str = "", trained_updates: int = 0, config_text: str | None = None,
                  env: SwarmEnv | None = None, export_env_overrides: list[str] | None = None) -> Path:
    """Write the bundle of in-memory ``params`` and ``obs_norm`` (as restored from a checkpoint) for ``env`` (default:
    the run's own)."""
    from aswarm.agents.train import make_env

    env = env or make_env(config)
    if env.obs_layout.describe() != ObsLayout(env.obs_layout.num_cylinders,
                                                 env.obs_layout.num_neighbours).describe():
        raise ValueError("the simulator's observation layout differs from aswarm.core.layout's: update the flight "
                         "runtime together with the environment")
    text = config_text if config_text is not None else config_json(config, env)
    manifest = build_manifest(config, env, source=source, trained_updates=trained_updates, config_text=text)
    if export_env_overrides:
        manifest["source"]["export_env_overrides"] = list(export_env_overrides)
    arrays = policy_arrays(params, obs_norm)
    out = fb.write_bundle(out_dir, arrays, manifest, force=force)
    fb.load_bundle(out)  # what the flight side will do: fail here, not at the field
    return out


def export(checkpoint: str | Path, out_dir: str | Path, force: bool = False,
           env_overrides: list[str] | None = None) -> Path:
    """Export a run folder's latest checkpoint (or a shipped policy, ``"pretrained[:NAME]"``) to the bundle folder
    ``out_dir``.

    ``env_overrides`` ("FIELD=VALUE") change the environment the bundle flies, as ``aswarm eval --env`` does, where
    the policy's observation layout stays the same (a ValueError says why otherwise): above all another number of
    drones for a policy observing its K nearest (``num_agents=16``, with ``max_neighbours=3`` for a 4-drone policy
    trained observing all 3 others). The manifest records them under ``source.export_env_overrides``.
    """
    from aswarm.analysis import evaluate

    out = Path(out_dir)
    if out.exists() and not force:  # before the slow restore
        raise fb.BundleError(f"bundle {out} already exists: allowed: a new --out folder, or --force to overwrite it")
    env = None
    if env_overrides:
        config, agent, restored = evaluate.load_agent(checkpoint, None, list(env_overrides))
        env = agent.env
    else:
        config, restored = evaluate.load(checkpoint)
    run_dir = evaluate.run_folder(checkpoint)
    cfg_file = run_dir / "config.json"
    text = cfg_file.read_text() if cfg_file.is_file() else None
    return export_policy(config, restored["params"], restored["obs_norm"], out, force=force, source=str(checkpoint),
                         trained_updates=int(restored["update"]), config_text=text, env=env,
                         export_env_overrides=sorted(env_overrides or []))

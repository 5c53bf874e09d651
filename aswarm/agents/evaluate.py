"""Evaluation of a trained policy over vmapped episodes with unseen seeds."""

from __future__ import annotations

import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from brax.training.acme import running_statistics

from aswarm import config_args, envs
from aswarm.agents import checkpoint
from aswarm.agents.train import Agent

PRETRAINED = Path(__file__).resolve().parent.parent / "pretrained" / "race"


def wilson(successes: float, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a rate."""
    if n == 0:
        return (math.nan, math.nan)
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return (max(0.0, centre - half), min(1.0, centre + half))


def rollout_episodes(agent: Agent, params, obs_norm, env: envs.SwarmEnv, episodes: int, key: jax.Array):
    """Run ``episodes`` worlds to their end with the deterministic, filtered policy.

    Returns the metrics of each episode ([episodes] arrays) and per-step safety statistics.
    """
    reset = jax.vmap(env.reset)
    step = jax.vmap(env.step)

    def run(key):
        state = reset(jax.random.split(key, episodes))
        recorded = jax.tree.map(jnp.zeros_like, state.metrics)
        ended = jnp.zeros(episodes, bool)

        def body(carry, _):
            s, rec, ended, interventions, flying = carry
            cmd, _, _ = agent.policy(params, obs_norm, s.obs, None)
            safe, intervened, _ = agent.safe_command(params, obs_norm, s.obs, cmd)
            s = step(s, safe)
            first = (s.done > 0) & ~ended
            rec = jax.tree.map(lambda r, m: jnp.where(first, m, r), rec, s.metrics)
            live = ~ended
            interventions = interventions + jnp.sum(intervened * live[:, None])
            flying = flying + jnp.sum(live) * env.num_agents
            return (s, rec, ended | first, interventions, flying), None

        init = (state, recorded, ended, jnp.zeros(()), jnp.zeros(()))
        (_, rec, ended, interventions, flying), _ = jax.lax.scan(body, init, None, length=env.config.max_steps)
        return rec, ended, interventions / jnp.maximum(flying, 1.0)

    return jax.jit(run)(key)


def load(checkpoint_dir: str | Path):
    """(config, {params, obs_norm, update}) of a run folder or 'pretrained'."""
    run_dir = PRETRAINED if str(checkpoint_dir) == "pretrained" else Path(checkpoint_dir)
    if run_dir == PRETRAINED and not run_dir.exists():
        raise checkpoint.CheckpointError("no pretrained policy ships yet (the race does not train to a useful "
                                         "policy yet, see README): give a run folder from `aswarm train`")
    if not run_dir.exists():
        raise checkpoint.CheckpointError(f"checkpoint {checkpoint_dir!s} does not exist: give a run folder or "
                                         "'pretrained'")
    config = checkpoint.load_config(run_dir)
    agent = Agent.build(config)
    like = {"params": agent.init_params(jax.random.PRNGKey(0)),
            "obs_norm": running_statistics.init_state(jax.ShapeDtypeStruct((agent.env.observation_size,), jnp.float32)),
            "update": jnp.zeros((), jnp.int32)}
    return config, checkpoint.restore(checkpoint.manager(run_dir), like, item="policy")


def evaluate_checkpoint(checkpoint_dir, scenario: str | None = None, episodes: int = 1000, seed: int = 10_000,
                        env_overrides: list[str] | None = None) -> dict:
    if episodes <= 0:
        raise ValueError(f"invalid episodes={episodes}: must be > 0")
    config, restored = load(checkpoint_dir)
    overrides = dict(config.env_overrides)
    overrides.update(config_args.parse_assignments(env_overrides or [], envs.EnvConfig))
    env = envs.make(scenario or config.scenario, **overrides)
    trained = envs.make(config.scenario, **dict(config.env_overrides))
    if env.observation_size != trained.observation_size or env.num_agents != trained.num_agents:
        raise ValueError(
            f"checkpoint was trained on {config.scenario!r} with {trained.num_agents} drones and observations of "
            f"size {trained.observation_size}; scenario {env.config.scenario!r} has {env.num_agents} drones and "
            f"size {env.observation_size}: the centralized critic and observation layout do not transfer")
    agent = Agent.build(config, env)
    rec, ended, intervention_rate = rollout_episodes(agent, restored["params"], restored["obs_norm"], env, episodes,
                                                     jax.random.PRNGKey(seed))
    rec = {k: np.asarray(v) for k, v in rec.items()}
    n = episodes
    out = {"checkpoint": str(checkpoint_dir), "method": config.method, "scenario": env.config.scenario,
           "episodes": n, "seed": seed, "trained_updates": int(restored["update"]),
           "episodes_ended": int(np.sum(np.asarray(ended)))}
    for name in ("success", "collision"):
        k = float(rec[name].sum())
        out[f"{name}_rate"] = k / n
        out[f"{name}_ci95"] = wilson(k, n)
    out["drone_collision_rate"] = float(rec["drone_collision"].mean())
    for name in ("min_clearance", "mean_separation", "mission_time", "mean_speed", "progress"):
        out[name] = float(rec[name].mean())
    out["min_clearance_worst"] = float(rec["min_clearance"].min())
    out["filter_intervention_rate"] = float(intervention_rate)
    return out


def format_table(r: dict) -> str:
    lines = [f"{r['method']} on {r['scenario']}: {r['episodes']} episodes (seed {r['seed']}, "
             f"{r['trained_updates']} updates trained)"]
    for name in ("success", "collision"):
        lo, hi = r[f"{name}_ci95"]
        rate = 100 * r[name + "_rate"]
        lines.append(f"  {name + ' rate':22s} {rate:6.1f} %   95% CI [{100 * lo:.1f}, {100 * hi:.1f}]")
    for name, unit in (("drone_collision_rate", ""), ("progress", ""), ("min_clearance", "m"),
                       ("min_clearance_worst", "m"), ("mean_separation", "m"), ("mission_time", "s"),
                       ("mean_speed", "m/s"), ("filter_intervention_rate", "")):
        shown = "   (none)" if name.startswith("min_clearance") and r[name] >= 999 else f"{r[name]:8.3f} {unit}"
        lines.append(f"  {name:24s} {shown}")
    return "\n".join(lines)

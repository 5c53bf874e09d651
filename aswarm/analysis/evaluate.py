"""Evaluation of a trained policy over vmapped episodes with unseen seeds.

``evaluate_checkpoint`` runs the episodes, :func:`summarize` turns their per-episode metrics into the
report (rates with 95 % Wilson intervals), :func:`write_report` writes it as JSON and CSV.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from brax.training.acme import running_statistics

from aswarm import config_args, envs
from aswarm.agents.config import TrainConfig
from aswarm.agents.train import Agent
from aswarm.analysis.protocol import EVAL_SEED
from aswarm.envs.collisions import KINDS
from aswarm.files import write_atomic
from aswarm.training import checkpoint

PRETRAINED = Path(__file__).resolve().parent.parent / "pretrained" / "race"
# The race policy shipped before the firmware drone (issue #12), trained on the geometric controller: kept as the
# reference the shared core's refactor was checked against (tests/test_pretrained.py) and as a run folder written
# before fingerprints, nested filter settings and the firmware drone (the tests of reading old runs).
PRETRAINED_GEOMETRIC = PRETRAINED.parent / "race-geometric"
# Reports of the shipped policy go here (relative to the working directory), not into the package.
PRETRAINED_REPORT_DIR = Path("runs") / "eval"
COLLISION_KINDS = KINDS[1:]  # obstacle, drone, gate, floor, bounds
# Progress lines per batch of episodes, where a caller asks for them (rollout_with_filter_stats).
PROGRESS_LINES = 5
# Most episodes evaluated at once: a vmapped world holds its whole MJX state, and a million episodes in one
# program ran out of memory. Above the 1000 of the published tables, so their numbers come from one program.
EVAL_BATCH = 4096
# m/s: a drone-step's filter QP counts as infeasible (no command satisfied every barrier row) when its shared
# slack exceeds this. A feasible QP leaves a slack of ~1e-6 m/s per m/s of correction (the quadratic penalty,
# rho = 1e6, see cbf_filter.filter_velocity), so corrections up to the 2 m/s command bound stay 50x below it.
INFEASIBLE_SLACK = 1e-4


class FilterStats(NamedTuple):
    """The safety filter over the flying drone-steps of a rollout."""

    intervention_rate: float  # share where the filter changed the command
    infeasible_rate: float  # share where its QP had no command satisfying every row (slack > INFEASIBLE_SLACK)
    escape_rate: float = 0.0  # share where its deadlock escape chose the command (SafetyFilterConfig.escape)


def wilson(successes: float, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a rate."""
    if n == 0:
        return (math.nan, math.nan)
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return (max(0.0, centre - half), min(1.0, centre + half))


def rollout_with_filter_stats(agent: Agent, params, obs_norm, env: envs.SwarmEnv, episodes: int, key: jax.Array,
                              batch: int = EVAL_BATCH, progress: Callable[[str], None] | None = None
                              ) -> tuple[dict, jax.Array, FilterStats]:
    """Run ``episodes`` worlds to their end with the deterministic, filtered policy (a batch stops at its last
    episode's end, or at the clock).

    Returns the metrics of each episode ([episodes] arrays), which episodes ended, and the filter's
    :class:`FilterStats` over the drone-steps of worlds still running. Episode i starts from
    ``split(key, episodes)[i]``; at most ``batch`` worlds run at once (memory grows with them), so up to
    ``batch`` episodes are one program, as they always were. ``progress`` is handed a line
    (``episodes 1-4096 of 10000: step 150 of 750``) :data:`PROGRESS_LINES` times per batch of episodes, from inside
    the program: a batch of the race's 10,000 episodes runs for minutes.
    """
    shown = {"first": 0, "last": min(batch, episodes)}  # the batch running now (the host runs them in turn)

    def report(t):
        progress(f"episodes {shown['first'] + 1}-{shown['last']} of {episodes}: step {int(t)} of "
                 f"{env.config.max_steps}")

    def report_end(t):
        if int(t) < env.config.max_steps:  # (at the clock the last line above said so)
            progress(f"episodes {shown['first'] + 1}-{shown['last']} of {episodes}: all ended by step {int(t)} of "
                     f"{env.config.max_steps}")

    every = max(1, env.config.max_steps // PROGRESS_LINES)
    reset = jax.vmap(env.reset)
    step = jax.vmap(env.step)

    # The policy's arrays are arguments, not constants folded into the program: evaluating another checkpoint of
    # the same configuration then runs the same program (a persistent-cache hit, not a compile), and XLA does
    # not have to carry the weights through its passes.
    def run(params, obs_norm, keys):
        state = reset(keys)
        recorded = jax.tree.map(jnp.zeros_like, state.metrics)
        ended = jnp.zeros(keys.shape[0], bool)

        def body(carry):
            t, s, rec, ended, interventions, infeasible, escapes, flying = carry
            t = t + 1
            cmd, _, _ = agent.policy(params, obs_norm, s.obs, None)
            res = agent.filter_commands(params, obs_norm, s.obs, cmd, env.cylinder_accel(s), s.filter_obs,
                                        env.applied_command(s))
            s = step(s, res.u)
            first = (s.done > 0) & ~ended
            rec = jax.tree.map(lambda r, m: jnp.where(first, m, r), rec, s.metrics)
            live = ~ended
            interventions = interventions + jnp.sum(res.intervened * live[:, None])
            infeasible = infeasible + jnp.sum((res.slack > INFEASIBLE_SLACK) * live[:, None])
            escapes = escapes + jnp.sum(res.escaped * live[:, None])
            flying = flying + jnp.sum(live) * env.num_agents
            if progress is not None:  # (static: without it the program has no callback)
                jax.lax.cond(t % every == 0, lambda: jax.debug.callback(report, t), lambda: None)
            return t, s, rec, ended | first, interventions, infeasible, escapes, flying

        # The batch stops when its last episode has ended, not at the clock: nothing is recorded or counted after
        # (every sum above is masked by ~ended), so the same episodes give the same outcomes, sooner (XLA may fuse
        # this loop a little otherwise than a scan: a closed loop carries that on into a mean's last digits,
        # BENCHMARKS.md, "Evaluation").
        def running(carry):
            t, ended = carry[0], carry[3]
            return (t < env.config.max_steps) & ~jnp.all(ended)

        init = (jnp.zeros((), jnp.int32), state, recorded, ended, jnp.zeros(()), jnp.zeros(()), jnp.zeros(()),
                jnp.zeros(()))
        t, _, rec, ended, interventions, infeasible, escapes, flying = jax.lax.while_loop(running, body, init)
        if progress is not None:
            jax.debug.callback(report_end, t)
        return rec, ended, interventions, infeasible, escapes, flying

    if batch <= 0:
        raise ValueError(f"invalid batch={batch}: must be > 0")
    if episodes <= batch:
        def one(params, obs_norm, key):
            rec, ended, interventions, infeasible, escapes, flying = run(params, obs_norm,
                                                                         jax.random.split(key, episodes))
            per = jnp.maximum(flying, 1.0)
            return rec, ended, interventions / per, infeasible / per, escapes / per

        rec, ended, intervention_rate, infeasible_rate, escape_rate = jax.jit(one)(params, obs_norm, key)
        return rec, ended, FilterStats(intervention_rate, infeasible_rate, escape_rate)
    keys = jax.random.split(key, episodes)
    run_batch = jax.jit(run)
    parts = []
    for i in range(0, episodes, batch):
        shown.update(first=i, last=min(i + batch, episodes))
        parts.append(run_batch(params, obs_norm, keys[i:i + batch]))
        if progress is not None:  # the batches in turn, so that each line names the batch it comes from
            jax.block_until_ready(parts[-1])
    rec = jax.tree.map(lambda *xs: np.concatenate([np.asarray(x) for x in xs]), *[p[0] for p in parts])
    ended = np.concatenate([np.asarray(p[1]) for p in parts])
    # Counts summed in float64 on the host: float32 stops counting drone-steps exactly past 2**24.
    interventions = sum(float(p[2]) for p in parts)
    infeasible = sum(float(p[3]) for p in parts)
    escapes = sum(float(p[4]) for p in parts)
    flying = max(sum(float(p[5]) for p in parts), 1.0)
    return rec, ended, FilterStats(interventions / flying, infeasible / flying, escapes / flying)


def rollout_episodes(agent: Agent, params, obs_norm, env: envs.SwarmEnv, episodes: int, key: jax.Array,
                     batch: int = EVAL_BATCH):
    """(metrics of each episode, which ended, filter intervention rate): :func:`rollout_with_filter_stats`
    without the other filter statistics."""
    rec, ended, stats = rollout_with_filter_stats(agent, params, obs_norm, env, episodes, key, batch)
    return rec, ended, stats.intervention_rate


def shipped() -> list[str]:
    """The names of the shipped policies: 'pretrained' (the race) and 'pretrained:NAME' for the others."""
    others = sorted(p.name for p in PRETRAINED.parent.iterdir() if (p / "config.json").is_file() and p != PRETRAINED)
    return ["pretrained"] + [f"pretrained:{name}" for name in others]


def run_folder(checkpoint_dir: str | Path) -> Path:
    """The folder of a run, or of a shipped policy: 'pretrained' is the race policy, 'pretrained:NAME' another
    (``aswarm/pretrained/NAME``); a one-line CheckpointError for a name that is not shipped."""
    text = str(checkpoint_dir)
    if text == "pretrained":
        if not PRETRAINED.exists():
            raise checkpoint.CheckpointError("the pretrained policy is missing from this install (it ships in "
                                             "aswarm/pretrained/race): give a run folder from `aswarm train`")
        return PRETRAINED
    if text.startswith("pretrained:"):
        folder = PRETRAINED.parent / text.split(":", 1)[1]
        if folder == PRETRAINED or not (folder / "config.json").is_file():
            raise checkpoint.CheckpointError(f"unknown shipped policy {text!r}: allowed: {', '.join(shipped())}")
        return folder
    return Path(checkpoint_dir)


def is_shipped(checkpoint_dir: str | Path) -> bool:
    return str(checkpoint_dir) == "pretrained" or str(checkpoint_dir).startswith("pretrained:")


def load(checkpoint_dir: str | Path):
    """(config, {params, obs_norm, update}) of a run folder, 'pretrained' or 'pretrained:NAME'."""
    run_dir = run_folder(checkpoint_dir)
    if not run_dir.exists():
        raise checkpoint.CheckpointError(f"checkpoint {checkpoint_dir!s} does not exist: give a run folder or "
                                         "'pretrained'")
    config = checkpoint.load_config(run_dir)
    agent = Agent.build(config)
    # Only the structure is needed, and evaluating the initializers eagerly took seconds: zeros of their shapes.
    shapes = jax.eval_shape(agent.init_params, jax.random.PRNGKey(0))
    like = {"params": jax.tree.map(lambda x: np.zeros(x.shape, x.dtype), shapes),
            "obs_norm": running_statistics.init_state(jax.ShapeDtypeStruct((agent.env.observation_size,), jnp.float32)),
            "update": jnp.zeros((), jnp.int32)}
    mngr = checkpoint.manager(run_dir, fingerprint=checkpoint.fingerprint(config, agent.env))
    return config, checkpoint.restore(mngr, like, item="policy")


def eval_env_config(config: TrainConfig, scenario: str | None = None,
                    env_overrides: list[str] | None = None) -> envs.EnvConfig:
    """The env a run's policy is evaluated on (see :func:`load_agent`), without loading its networks."""
    extra = config_args.parse_assignments(env_overrides or [], envs.EnvConfig)
    if scenario is None or scenario == config.scenario:
        return config_args.replace_fields(config.env, extra)
    from aswarm.envs import registry

    return config_args.replace_fields(registry.preset(scenario), {**dict(config.env_overrides), **extra})


def load_agent(checkpoint_dir: str | Path, scenario: str | None = None,
               env_overrides: list[str] | None = None,
               filter_overrides: dict | None = None) -> tuple[TrainConfig, Agent, dict]:
    """(config, agent on the evaluation env, {params, obs_norm, update}) of a checkpoint.

    The evaluation env is the training env as the run stored it (``config.env``) with ``env_overrides``
    ("FIELD=VALUE", nested ones dotted: "cf.mass=0.03") applied; another ``scenario`` starts from that
    scenario's preset (the only description of its course) with the run's and these overrides. A ValueError
    says why when the networks cannot run on it. ``filter_overrides`` ({SafetyFilterConfig field: value}) replace
    fields of the agent's filter as fitted to its drone (so a look-ahead given here is the one flown).
    """
    config, restored = load(checkpoint_dir)
    trained = envs.SwarmEnv(config.env)
    env_config = eval_env_config(config, scenario, env_overrides)
    env = trained if env_config == config.env else envs.SwarmEnv(env_config)
    # The actor and the filter run per drone on its own observation row, so a policy flies any number of drones
    # whose rows have its layout (max_neighbours fixes the neighbour rows); the centralized critics, which do
    # depend on the number of drones, are not used here.
    if env.obs_layout != trained.obs_layout:
        hint = ("" if env.config.max_neighbours else
                "; for another number of drones, train with --env max_neighbours=K and evaluate with the same K")
        raise ValueError(
            f"checkpoint was trained on {config.scenario!r} with {trained.num_agents} drones, observing "
            f"{trained.obs_layout.num_cylinders} cylinders and {trained.obs_layout.num_neighbours} neighbours; "
            f"scenario {env.config.scenario!r} with {env.num_agents} drones gives {env.obs_layout.num_cylinders} "
            f"and {env.obs_layout.num_neighbours}: the observation layouts differ{hint}")
    agent = Agent.build(config, env)
    if filter_overrides:
        safety = dataclasses.replace(agent.config.safety_filter, **filter_overrides)
        agent = Agent.build(dataclasses.replace(agent.config, safety_filter=safety), env)
    return config, agent, restored


def summarize(rec: dict, intervention_rate: float = 0.0, infeasible_rate: float | None = None) -> dict:
    """The report's figures from per-episode metrics ``rec`` ({name: [episodes]}, as ``SwarmEnv._metrics``).

    Rates come with 95 % Wilson intervals (``*_ci95``). ``mission_time`` is the mean over *successful*
    episodes only (None when none succeeded): a failed episode has no mission time. Every other figure is
    the mean over all episodes; ``min_clearance_worst`` is the minimum. ``filter_infeasible_rate`` is None
    where the caller did not measure it (the flight runtime does not report the filter's slack).
    """
    rec = {k: np.asarray(v, dtype=np.float64) for k, v in rec.items()}
    n = int(np.size(rec["success"]))
    if n == 0:
        raise ValueError("invalid episodes=0: summarize needs at least one episode")
    out: dict = {}
    for name in ("success", "collision") + tuple(f"collision_{k}" for k in COLLISION_KINDS):
        k = float(rec[name].sum())
        out[f"{name}_rate"] = k / n
        out[f"{name}_ci95"] = wilson(k, n)
    out["drone_success_rate"] = float(rec["drone_success"].mean())
    out["drone_collision_rate"] = float(rec["drone_collision"].mean())
    won = rec["success"] > 0.5
    out["successful_episodes"] = int(won.sum())
    out["mission_time"] = float(rec["mission_time"][won].mean()) if won.any() else None
    for name in ("progress", "min_clearance", "mean_separation", "mean_speed", "episode_return"):
        out[name] = float(rec[name].mean())
    out["min_clearance_worst"] = float(rec["min_clearance"].min())
    out["filter_intervention_rate"] = float(intervention_rate)
    out["filter_infeasible_rate"] = None if infeasible_rate is None else float(infeasible_rate)
    return out


def evaluate_checkpoint(checkpoint_dir, scenario: str | None = None, episodes: int = 1000, seed: int = EVAL_SEED,
                        env_overrides: list[str] | None = None, with_method: str | None = None,
                        progress: Callable[[str], None] | None = None) -> dict:
    """Evaluate a checkpoint; ``with_method`` runs its networks as another method would (e.g. a policy trained
    without a safety layer under ``fixed_cbf``'s filter): every method has the same parameter tree. ``progress``:
    see :func:`rollout_with_filter_stats`."""
    if episodes <= 0:
        raise ValueError(f"invalid episodes={episodes}: must be > 0")
    config, agent, restored = load_agent(checkpoint_dir, scenario, env_overrides)
    if with_method is not None:
        config = dataclasses.replace(config, method=with_method)
        agent = Agent.build(config, agent.env)
    env = agent.env
    rec, ended, stats = rollout_with_filter_stats(agent, restored["params"], restored["obs_norm"], env, episodes,
                                                  jax.random.PRNGKey(seed), progress=progress)
    out = {"checkpoint": str(checkpoint_dir), "method": config.method, "scenario": env.config.scenario,
           "num_agents": env.num_agents, "episodes": episodes, "seed": seed, "trained_updates": int(restored["update"]),
           "env_overrides": sorted(env_overrides or []), "episodes_ended": int(np.sum(np.asarray(ended)))}
    out.update(summarize({k: np.asarray(v) for k, v in rec.items()}, float(stats.intervention_rate),
                         float(stats.infeasible_rate)))
    return out


def report_dir(checkpoint_dir: str | Path, out: str | Path | None = None) -> Path:
    """Where ``aswarm eval`` writes its files: ``out``, else the run folder, else ``runs/eval`` for 'pretrained'
    (``runs/eval/NAME`` for 'pretrained:NAME')."""
    if out is not None:
        return Path(out)
    if str(checkpoint_dir).startswith("pretrained:"):
        return PRETRAINED_REPORT_DIR / str(checkpoint_dir).split(":", 1)[1]
    return PRETRAINED_REPORT_DIR if str(checkpoint_dir) == "pretrained" else Path(checkpoint_dir)


def _flat(result: dict) -> dict:
    """One CSV row: intervals split into ``_lo``/``_hi``, lists as JSON, None as empty."""
    row = {}
    for k, v in result.items():
        if k.endswith("_ci95"):
            row[k + "_lo"], row[k + "_hi"] = v
        elif isinstance(v, (list, tuple, dict)):
            row[k] = json.dumps(v)
        else:
            row[k] = "" if v is None else v
    return row


def write_report(result: dict, out_dir: str | Path) -> tuple[Path, Path]:
    """Write ``eval_<scenario>.json`` and ``.csv`` (one header row, one value row) into ``out_dir``."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"invalid --out {str(out_dir)!r}: is a file; allowed: a folder")
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = f"eval_{result['scenario']}"
    row = _flat(result)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(row), lineterminator="\n")
    writer.writeheader()
    writer.writerow(row)
    json_path, csv_path = out_dir / f"{stem}.json", out_dir / f"{stem}.csv"
    write_atomic(json_path, json.dumps(result, indent=2) + "\n")
    write_atomic(csv_path, buf.getvalue())
    return json_path, csv_path


def format_table(r: dict) -> str:
    lines = [f"{r['method']} on {r['scenario']}: {r['episodes']} episodes (seed {r['seed']}, "
             f"{r['trained_updates']} updates trained)"]

    def rate_line(label: str, name: str) -> str:
        lo, hi = r[f"{name}_ci95"]
        return f"  {label:24s} {100 * r[name + '_rate']:6.1f} %   95% CI [{100 * lo:.1f}, {100 * hi:.1f}]"

    lines += [rate_line("success rate", "success"), rate_line("collision rate", "collision")]
    lines += [rate_line(f"  by {kind}", f"collision_{kind}") for kind in COLLISION_KINDS
              if f"collision_{kind}_rate" in r]
    for name, unit in (("drone_collision_rate", ""), ("progress", ""), ("min_clearance", "m"),
                       ("min_clearance_worst", "m"), ("mean_separation", "m"), ("mission_time", "s"),
                       ("mean_speed", "m/s"), ("filter_intervention_rate", ""), ("filter_infeasible_rate", "")):
        if name == "filter_infeasible_rate" and name not in r:  # a report written before it was measured
            continue
        v = r.get(name)
        if name.startswith("min_clearance") and v is not None and v >= 999:
            shown = "   (none)"
        elif v is None and name == "filter_infeasible_rate":
            shown = "   (not measured)"
        elif v is None:
            shown = "   (no successful episode)"
        else:
            shown = f"{v:8.3f} {unit}"
        if name == "mission_time" and v is not None and "successful_episodes" in r:
            shown += f"   (mean of the {r['successful_episodes']} successful episodes)"
        lines.append(f"  {name:24s} {shown}")
    return "\n".join(lines)

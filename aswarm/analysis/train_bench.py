"""``aswarm bench --trainer``: where training time goes, and the wall time of ``aswarm train`` itself.

Two measurements, written to BENCHMARKS.md between the ``train-bench`` markers:

- :func:`profile`: one update split into its stages (the environment alone, the policy, the safety filter,
  the learner), each jitted on its own on the layout ``aswarm train`` uses, beside the whole update as the
  host loop runs it. Stages are timed apart, so XLA fuses less than in the real update: the shares are a
  profile, their sum is not the update.
- :func:`end_to_end`: :func:`aswarm.training.runner.train` exactly as ``aswarm train`` calls it (progress bar,
  metrics log, TensorBoard, checkpoints, curves), its wall time, its compile, the env-steps/s of its chunks,
  the wall time at which its training curve first held the target success, and the final policy on unseen
  episodes (``aswarm eval``'s protocol). A throughput benchmark that skips the host loop measured 7,167
  env-steps/s where the user's run showed 5.0-6.9k (issue #15): this one times the user's run.
"""

from __future__ import annotations

import dataclasses
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np

from aswarm import envs

START, END = "<!-- train-bench:start -->", "<!-- train-bench:end -->"


def _median_time(fn: Callable, *args, repeat: int) -> float:
    """Seconds per call of ``fn(*args)`` after one compiling call, the median of ``repeat``."""
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _env_rollout(env: envs.SwarmEnv, config) -> Callable:
    """The rollout's environment half alone: ``rollout_steps`` steps of random commands in the run's worlds."""
    wenv = envs.wrap_for_training(env, config.num_envs)
    shape = (config.num_envs, env.num_agents, env.action_size)

    def run(state, key):
        def step(s, k):
            return wenv.step(s, jax.random.uniform(k, shape, minval=-1.0, maxval=1.0) * env.config.max_speed), None

        return jax.lax.scan(step, state, jax.random.split(key, config.rollout_steps))[0]

    return jax.jit(run)


def _program(config, key: jax.Array):
    """(trainer, state, jitted chunk, mesh): the trainer laid out over the devices as ``aswarm train`` lays it."""
    from aswarm.agents.train import make_trainer
    from aswarm.training import sharding

    mesh = sharding.training_mesh(config.num_envs, config.devices)
    trainer = make_trainer(config, shard_rows=sharding.rows_constraint(mesh))
    init_fn, chunk_fn = sharding.sharded_fns(trainer.init, trainer.update_chunk,
                                             jax.eval_shape(trainer.init, key), mesh, stacked=False)
    return trainer, init_fn(key), chunk_fn, mesh


def profile(config, repeat: int = 3) -> dict:
    """Seconds per update of each stage (see the module's docstring), on the devices ``aswarm train`` would
    use; ``{"stages": {name: s}, "devices": d}``."""
    from aswarm.agents.train import make_trainer
    from aswarm.training import sharding

    trainer, ts, _, mesh = _program(config, jax.random.PRNGKey(config.seed))
    k = jax.random.PRNGKey(1)
    env_s = _median_time(_env_rollout(trainer.agent.env, config), ts.env_state, k, repeat=repeat)
    stages = {"environment (random commands)": env_s}
    rollout = jax.jit(trainer.rollout)
    if config.uses_filter:
        # The same networks without the filter: the policy's share, then the filter's on top.
        bare = make_trainer(dataclasses.replace(config, method="attention_penalty"),
                            shard_rows=sharding.rows_constraint(mesh))
        policy_s = _median_time(jax.jit(bare.rollout), ts, k, repeat=repeat)
        stages["policy"] = policy_s - env_s
        stages["safety filter"] = _median_time(rollout, ts, k, repeat=repeat) - policy_s
    else:
        stages["policy"] = _median_time(rollout, ts, k, repeat=repeat) - env_s
    env_state, tr = rollout(ts, k)
    stages["learner (GAE, epochs x minibatches, metrics)"] = _median_time(jax.jit(trainer.learn), ts, env_state, tr,
                                                                          k, repeat=repeat)
    return {"stages": stages, "devices": int(mesh.devices.size)}


def first_time_at(rows: list[dict], chunk_ends: list, target: float, window: int = 5,
                  name: str = "episode/success") -> float | None:
    """Wall seconds since the loop started (at the end of the chunk holding it: ``timing.json``'s
    ``chunk_ends``) of the first update where the mean of ``name`` over ``window`` consecutive updates that
    ended episodes reached ``target``; None if it never did."""
    kept = [r for r in rows if r.get("episodes", 1) > 0]
    values = np.array([r[name] for r in kept], np.float64)
    for i in range(window - 1, len(kept)):
        if values[i - window + 1:i + 1].mean() >= target:
            return next(float(t) for u, t in chunk_ends if u >= kept[i]["update"])
    return None


def end_to_end(config, out: Path, target: float = 0.99, episodes: int = 1000, progress: bool = True) -> dict:
    """Train ``config`` as ``aswarm train`` does into ``out`` (a new folder) and measure it (module docstring)."""
    from aswarm.analysis import evaluate
    from aswarm.training import runner

    t0 = time.monotonic()
    run_dir = runner.train(config, out, progress=progress)
    wall = time.monotonic() - t0
    rows = runner.read_metrics(run_dir)
    timing = json.loads((run_dir / runner.TIMING).read_text())
    result = {"run": str(run_dir), "wall_s": wall, **timing, "target": target,
              "target_reached_s": first_time_at(rows, timing["chunk_ends"], target),
              "final_train_success": rows[-1]["episode/success"]}
    if episodes:
        ev = evaluate.evaluate_checkpoint(run_dir, episodes=episodes)
        result.update(eval_episodes=episodes, eval_success=ev["success_rate"], eval_collision=ev["collision_rate"])
    return result


def _minutes(s: float | None) -> str:
    from aswarm.training import runner

    return "never" if s is None else runner.minutes_seconds(s)


def format_profile(p: dict, whole: dict) -> list[str]:
    """The profile's table; ``whole``: :func:`time_trainer` of the same config (the whole update's row)."""
    total = sum(p["stages"].values())
    lines = ["| stage | s / update | share of the stages |", "|---|---:|---:|"]
    lines += [f"| {name} | {s:.3f} | {s / total:.0%} |" for name, s in p["stages"].items()]
    lines += [f"| sum of the stages | {total:.3f} | 100% |",
              f"| the whole update (one jitted chunk, as the host loop runs it) | {whole['s_per_update']:.3f} | "
              f"{whole['env_steps_per_s']:,.0f} env-steps/s |"]
    return lines


def format_end_to_end(r: dict) -> list[str]:
    lines = ["| measure | value |", "|---|---:|",
             f"| wall time of `aswarm train` (compile, logs, checkpoints, curves) | {_minutes(r['wall_s'])} |",
             f"| of which the first chunk (compile + {r['first_chunk_updates']} updates) | "
             f"{r['first_chunk_s']:.0f} s |",
             f"| env-steps/s over the chunks after the first | {r['steady_env_steps_per_s']:,.0f} |",
             f"| env-steps/s over the whole run | {r['env_steps_per_s']:,.0f} |",
             f"| training success first held at {r['target']:.0%} (5 updates) | {_minutes(r['target_reached_s'])} |"]
    if "eval_episodes" in r:
        lines.append(f"| final policy on {r['eval_episodes']} unseen episodes: success / collision episodes | "
                     f"{r['eval_success']:.1%} / {r['eval_collision']:.1%} |")
    return lines


def time_trainer(config, updates: int = 3) -> dict:
    """Throughput of the whole update alone (rollout and learner, no host loop), compile apart, laid out as
    ``aswarm train`` does (its worlds over ``config.devices``, 0: every device that divides them)."""
    _, ts, fn, mesh = _program(config, jax.random.PRNGKey(0))
    t0 = time.perf_counter()
    ts, _ = fn(ts, updates)  # compiles; a second call would recompile if the state's types drifted
    jax.block_until_ready(ts)
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    ts, _ = fn(ts, updates)
    jax.block_until_ready(ts)
    run_s = time.perf_counter() - t0
    return {"env_steps_per_s": updates * config.steps_per_update / run_s, "compile_s": compile_s,
            "s_per_update": run_s / updates, "devices": int(mesh.devices.size)}


# The whole-update table's rows: (method, what differs, TrainConfig overrides); the first is the defaults.
VARIANTS = (
    ("attention_cbf", "default sizes", {}),
    ("attention_cbf", "default sizes", {"devices": 1}),  # the peer of the row above: one device
    ("attention_cbf", "paper CBF MLP [1024, 256], embed 3", {"cbf_hidden": (1024, 256), "cbf_embed": 3}),
    ("attention_penalty", "default sizes, no filter", {}),
    ("mappo", "default sizes", {}),
)


def main(args) -> int:
    """``aswarm bench --trainer``: the profile, the whole-update table and (unless ``--skip-run``) the timed
    ``aswarm train`` run with its evaluation, into BENCHMARKS.md."""
    from aswarm.agents.config import TrainConfig
    from aswarm.analysis.bench import machine, write_section

    config = TrainConfig(scenario=args.scenario)
    command = f"aswarm bench --trainer --scenario {args.scenario}" + (" --skip-run" if args.skip_run else "")
    lines = ["## Training time (`make bench-train`)", "", f"Command: `{command}`  ", f"Machine: {machine()}  ",
             f"Date: {time.strftime('%Y-%m-%d')}  ", ""]
    if not args.skip_run:
        stamp = time.strftime("%Y%m%d-%H%M%S")
        out = Path(args.run_dir) if args.run_dir else Path("runs") / f"bench-{args.scenario}-{stamp}"
        print(f"timing `aswarm train --scenario {args.scenario}` into {out} (the default budget), then "
              f"{args.episodes} unseen episodes", flush=True)
        r = end_to_end(config, out, episodes=args.episodes)
        lines += [f"`aswarm train --scenario {args.scenario}` with the defaults ({config.total_steps:,} env steps, "
                  f"{r['devices']} device(s)), timed as the user runs it, into `{out}`:", ""]
        lines += format_end_to_end(r) + [""]
        (out / "bench.json").write_text(json.dumps(r, indent=1))
    table, timed = [], []
    for method, label, over in VARIANTS:
        r = time_trainer(dataclasses.replace(config, method=method, **over))
        timed.append(r)
        print(f"  {method:18s} {label:38s} {r['devices']} device(s) {r['env_steps_per_s']:10,.0f} env-steps/s",
              flush=True)
        table.append(f"| {method} | {label} | {r['devices']} | {r['env_steps_per_s']:,.0f} | {r['s_per_update']:.2f} "
                     f"| {r['compile_s']:.0f} |")
    p = profile(config)
    lines += [f"Where one update's time goes ({config.num_envs} worlds x {config.rollout_steps} steps, "
              f"{config.epochs} epochs x {config.minibatches} minibatches, {p['devices']} device(s); each stage "
              "jitted and timed on its own):", ""]
    # The table's first row is the profiled config itself (the defaults): its whole update closes the profile.
    lines += format_profile(p, timed[0]) + ["", "The whole update of each method, no host loop, compile apart:", "",
                                         "| method | networks | devices | env-steps/s | s / update | compile s |",
                                         "|---|---|---:|---:|---:|---:|"] + table
    write_section(args.out, "\n".join(lines), START, END)
    print(f"wrote {args.out}")
    return 0

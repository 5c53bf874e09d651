"""The host loop around the jitted trainer: progress, logs, checkpoints, resume, faults, plots."""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import jax
import numpy as np

from aswarm.agents.config import TrainConfig
from aswarm.agents.train import make_train
from aswarm.training import checkpoint, run_config, sharding, wandb_log


class TrainingDiverged(RuntimeError):
    """A loss or parameter became NaN or Inf (in every trial of the program)."""


# Flags that may change when a run resumes: the budget (extends the run; with anneal_lr the rates then fall to 0
# over the new budget) and host-loop settings. Anything else changes shapes or the algorithm of a state that
# is already half-trained.
RESUMABLE = ("total_steps", "checkpoint_minutes", "updates_per_chunk")
DIVERGED = "DIVERGED"  # file in a run folder whose loss or parameters became NaN/Inf


def default_run_dir(config: TrainConfig) -> Path:
    return Path("runs") / f"{config.scenario}-{config.method}-{time.strftime('%Y%m%d-%H%M%S')}"


def write_config(run_dir: Path, config: TrainConfig) -> None:
    """``config.json``: the training config and the run's full resolved env (``config.env``, ``run_config``)."""
    run_config.write(run_dir, config)


def _finite(tree) -> bool:
    return all(bool(np.all(np.isfinite(np.asarray(x)))) for x in jax.tree.leaves(tree)
               if np.issubdtype(np.asarray(x).dtype, np.floating))


def finite_rows(tree) -> np.ndarray:
    """[K] whether every float leaf of trial k (leading axis) is finite."""
    ok = None
    for x in jax.tree.leaves(tree):
        x = np.asarray(x)
        if np.issubdtype(x.dtype, np.floating) and x.size:
            f = np.isfinite(x).reshape(x.shape[0], -1).all(-1)
            ok = f if ok is None else ok & f
    return ok


# --- the host loop, shared by a run and a sweep group ---------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Program:
    """A compiled trainer laid out over ``mesh``: one run (``stacked=False``: state and metrics without a trial
    axis) or the K trials of a sweep group (``stacked=True``: a leading trial axis everywhere)."""

    env: object  # the SwarmEnv (its shapes go into the checkpoints' fingerprint)
    init_fn: Callable  # (*init_args) -> state
    chunk_fn: Callable  # (state, k) -> (state, metrics {name: [k]} or {name: [K, k]}); donates the state
    init_args: tuple
    mesh: object
    stacked: bool


@dataclasses.dataclass(frozen=True)
class LoopResult:
    state: object  # the state on the devices after the last chunk
    start: int  # the update it started (or resumed) at
    update: int  # the update it stopped at
    diverged: tuple[bool, ...]  # per trial: loss or parameters became NaN/Inf
    timing: dict  # wall seconds of this call's loop and its first chunk (the compile), env-steps/s (see run_loop)


TIMING = "timing.json"  # a run folder's wall time and throughput, as `aswarm train` prints them at the end


def minutes_seconds(seconds: float) -> str:
    """``seconds`` as "M min S s", rounded to the second first (659.6 s is "11 min 0 s", not "10 min 60 s")."""
    whole = int(round(seconds))
    return f"{whole // 60} min {whole % 60} s"


def chunk_length(updates: int, per_chunk: int) -> int:
    """Updates per chunk for a loop of ``updates``: the largest length from ``per_chunk`` down to a quarter of it
    (at least 2) that divides them, else ``per_chunk``. Each chunk length is its own compiled program (a scan
    length): a shorter last chunk cost the race's 4M-step run a second compile of 29 s out of its 8 min on the CPU,
    and 244 updates on a GPU (chunks of 10, then 4) 31 s of 94, where a chunk's host round trip costs milliseconds."""
    for k in range(per_chunk, max(2, (per_chunk + 3) // 4) - 1, -1):
        if updates % k == 0:
            return k
    return per_chunk


def loop_timing(chunks: list[tuple[int, float]], steps_per_update: int, start: int = 0) -> dict:
    """Wall time and throughput of a loop's ``chunks`` ([(updates, seconds)], in order, from update ``start``).
    The first chunk holds the compile, and a shorter last chunk compiles its own length: the steady throughput
    is that of the chunks after the first of the first one's length (None where there are none).
    ``chunk_ends``: [update, wall seconds since the loop started] at the end of each chunk (wall time stays out
    of ``metrics.jsonl``, which the same seed and config reproduce byte for byte)."""
    updates = sum(k for k, _ in chunks)
    seconds = sum(t for _, t in chunks)
    rest = [(k, t) for k, t in chunks[1:] if k == chunks[0][0]]
    rest_k, rest_s = sum(k for k, _ in rest), sum(t for _, t in rest)
    return {"updates": updates, "env_steps": updates * steps_per_update, "loop_s": seconds,
            "first_chunk_updates": chunks[0][0] if chunks else 0, "first_chunk_s": chunks[0][1] if chunks else 0.0,
            "env_steps_per_s": updates * steps_per_update / seconds if seconds > 0 else None,
            "steady_env_steps_per_s": rest_k * steps_per_update / rest_s if rest_k and rest_s > 0 else None,
            "chunk_ends": [[start + int(u), round(float(t), 3)] for u, t in
                           zip(np.cumsum([k for k, _ in chunks]), np.cumsum([t for _, t in chunks]))]}


EPISODE_SHOWN = ("episode/episode_return", "episode/success", "episode/collision")


def chunk_episode_means(metrics: dict, previous: dict | None) -> dict:
    """Per trial, the chunk's episode metrics weighted by the episodes each update ended.

    A trial that ended no episode in the chunk keeps its previous values: when every world times out
    together (a swarm that does not finish yet), most updates end none, and showing their zeros would
    hide the chunk's real figures.
    """
    ended = np.asarray(metrics["episodes"], np.float64)  # [trials, k]
    count = ended.sum(-1)
    out = {}
    for name in EPISODE_SHOWN:
        mean = (np.asarray(metrics[name], np.float64) * ended).sum(-1) / np.maximum(count, 1.0)
        before = previous[name] if previous is not None else np.full_like(mean, np.nan)
        out[name] = np.where(count > 0, mean, before)
    return out


def truncate_log(path: Path, update: int) -> None:
    """Drop log rows past the restored update (they will be produced again); atomic, as every log write is."""
    if not path.exists():
        return
    rows = [r for r in path.read_text().splitlines() if r and json.loads(r)["update"] <= update]
    tmp = path.with_suffix(".tmp")
    tmp.write_text("".join(r + "\n" for r in rows))
    tmp.replace(path)


def append_rows(path: Path, metrics: dict, trial: int, first: int, steps_per_update: int) -> list[dict]:
    """Append trial ``trial``'s rows of ``metrics`` ({name: [K, k]}) for updates first+1 .. first+k to the log."""
    k = len(next(iter(metrics.values()))[trial])
    rows = []
    for j in range(k):
        row = {name: float(v[trial, j]) for name, v in metrics.items()}
        row.update(update=first + j + 1, env_steps=(first + j + 1) * steps_per_update)
        rows.append(row)
    with path.open("a") as f:
        f.write("".join(json.dumps(r) + "\n" for r in rows))
    return rows


def run_loop(program: Program, config: TrainConfig, ckpt_dir: Path, trial_dirs: list[Path], *,
             progress: bool = True, max_updates: int | None = None, desc: str | None = None,
             tensorboard: bool = False, log: Callable[[str], None] | None = None,
             label: str | None = None, on_chunk: Callable[[int, dict], bool] | None = None,
             wandb: wandb_log.WandbOptions | None = None) -> LoopResult:
    """Train ``program`` from its newest checkpoint in ``ckpt_dir`` (or from init) to ``config.num_updates``.

    One metrics log per trial (``trial_dirs[i]/metrics.jsonl``, truncated atomically to the restored update),
    one checkpoint policy (every ``checkpoint_minutes`` and at the end, into ``ckpt_dir/checkpoints``), one NaN
    policy: a trial whose loss or parameters become NaN/Inf is marked (a ``DIVERGED`` file naming the update)
    and the others train on; when every trial has, the loop stops with :class:`TrainingDiverged` before
    logging or saving that chunk, so the last good checkpoint is kept. ``max_updates`` stops after that many
    updates in this call (tests, interrupted-run checks). Only process 0 writes logs. ``log`` gets the lines
    prefixed with ``label`` (resumed, diverged) and the checkpoint fallback's (default: stderr). ``wandb`` also
    sends the rows TensorBoard gets (trial 0's) to Weights & Biases.
    ``on_chunk(update, metrics)`` is called after each chunk's rows are logged; when it returns True the loop
    saves a checkpoint there and stops early (a search that has pruned every trial of the program).
    """
    from tensorboardX import SummaryWriter
    from tqdm import tqdm

    primary = jax.process_index() == 0
    mngr = checkpoint.manager(ckpt_dir, fingerprint=checkpoint.fingerprint(config, program.env))
    ts = program.init_fn(*program.init_args)
    shardings = sharding.state_shardings(program.mesh, ts, stacked=program.stacked)
    if mngr.latest_step() is not None:
        # Restored on the host, then laid out again: the same on one device, many, or many hosts.
        restored = checkpoint.restore_newest(mngr, sharding.fetch(ts), log=log)
        ts = jax.tree.map(sharding.put, restored, shardings)
        start = int(np.asarray(restored.update).reshape(-1)[0])
        good = finite_rows(restored.params) if program.stacked else [_finite(restored.params)]
        if label and log:
            log(f"{label}: resumed at update {start}")
    else:
        start, good = 0, [True] * len(trial_dirs)
        if config.init_from:
            started = warm_start(sharding.fetch(ts), config.init_from, stacked=program.stacked, log=log)
            ts = jax.tree.map(sharding.put, started, shardings)
    if primary:
        for d, ok in zip(trial_dirs, good):
            truncate_log(d / "metrics.jsonl", start)
            if ok:  # the divergence it records came after the restored state: it may not happen again
                (d / DIVERGED).unlink(missing_ok=True)
    diverged = [not ok for ok in good]
    total = config.num_updates
    stop = total if max_updates is None else min(total, start + max_updates)
    wandb_run = wandb_log.start(wandb, config, trial_dirs[0], resumed=start > 0) if wandb and primary else None
    writer = SummaryWriter(str(trial_dirs[0] / "tb")) if tensorboard and primary else None
    finished = False
    bar = tqdm(total=total, initial=start, unit="upd", disable=not (progress and primary), dynamic_ncols=True,
               desc=desc)
    last_save, update = time.monotonic(), start
    shown = None
    chunks: list[tuple[int, float]] = []  # (updates, wall seconds) per chunk
    per_chunk = chunk_length(stop - start, config.updates_per_chunk)
    host_s = 0.0  # the loop's own time between chunks (logs, checks, checkpoints), the devices idle
    try:
        t_prev = time.monotonic()
        while update < stop:
            k = min(per_chunk, stop - update)
            new_ts, metrics = program.chunk_fn(ts, k)  # donates ts
            metrics = sharding.fetch(metrics)
            t_ready = time.monotonic()  # the chunk has run: what follows until the next chunk is the host's
            if not program.stacked:
                metrics = {name: np.asarray(v)[None] for name, v in metrics.items()}  # [1, k]: one trial
            params = sharding.fetch(new_ts.params)
            loss = np.asarray(metrics["train/loss"])
            ok = np.isfinite(loss).all(-1) & (finite_rows(params) if program.stacked else np.array([_finite(params)]))
            bad_at = {}  # trial -> the first update whose loss is not finite (else the chunk's last)
            for i in np.flatnonzero(~ok):
                rows_bad = np.flatnonzero(~np.isfinite(loss[i]))
                bad_at[int(i)] = update + 1 + int(rows_bad[0]) if rows_bad.size else update + k
            for i, at in bad_at.items():
                if not diverged[i]:
                    diverged[i] = True
                    if primary:
                        (trial_dirs[i] / DIVERGED).write_text(f"loss or parameters became NaN/Inf at update {at}\n")
                    if label and log:
                        log(f"{label}: {trial_dirs[i].name} diverged at update {at}")
            if not ok.any():
                raise TrainingDiverged(f"loss or parameters became NaN/Inf at update {min(bad_at.values())}; "
                                       f"{checkpoint.last_good(mngr)}")
            ts = new_ts
            now = time.monotonic()
            sps = k * config.steps_per_update / (now - t_prev)
            chunks.append((k, now - t_prev))
            t_prev = now
            if primary:
                for i, d in enumerate(trial_dirs):
                    rows = append_rows(d / "metrics.jsonl", metrics, i, update, config.steps_per_update)
                    for row in rows if i == 0 else ():
                        for name, v in row.items() if writer is not None else ():
                            if name != "update":
                                writer.add_scalar(name, v, row["update"])
                        if wandb_run is not None:
                            wandb_run.log(row)
            update += k
            if on_chunk is not None and on_chunk(update, metrics):
                stop = update
            shown = chunk_episode_means(metrics, shown)
            if len(trial_dirs) == 1:
                bar.set_postfix(sps=f"{sps:,.0f}", ret=f"{shown['episode/episode_return'][0]:.1f}",
                                success=f"{shown['episode/success'][0]:.2f}",
                                coll=f"{shown['episode/collision'][0]:.2f}")
            else:
                bar.set_postfix(sps=f"{sps:,.0f}", best_success=f"{np.fmax.reduce(shown['episode/success']):.2f}")
            bar.update(k)
            if update >= stop or now - last_save > 60 * config.checkpoint_minutes:
                checkpoint.save(mngr, update, sharding.for_checkpoint(sharding.fetch(ts)))
                last_save = now
            host_s += time.monotonic() - t_ready
        finished = True
    finally:
        bar.close()
        if writer is not None:
            writer.close()
        if wandb_run is not None:
            wandb_run.close(ok=finished)
    return LoopResult(ts, start, update, tuple(diverged),
                      {**loop_timing(chunks, config.steps_per_update, start), "host_s": host_s})


# --- a single run ----------------------------------------------------------------------------------------------


def resume_config(stored: TrainConfig, changes: dict | None) -> TrainConfig:
    """The stored config with the flags that may change on resume applied; any other flag that differs is a
    one-line ValueError."""
    changes = {k: v for k, v in (changes or {}).items() if getattr(stored, k) != v}
    refused = [k for k in changes if k not in RESUMABLE]
    if refused:
        flag = "--" + refused[0].replace("_", "-")
        raise ValueError(f"invalid {flag} with --resume: the run was trained with {refused[0]}="
                         f"{getattr(stored, refused[0])!r} and it changes the algorithm or the state's shapes; "
                         f"allowed with --resume: {', '.join('--' + k.replace('_', '-') for k in RESUMABLE)}, --quiet")
    return dataclasses.replace(stored, **changes) if changes else stored


def train(config: TrainConfig | None, run_dir: Path | None = None, resume: bool = False, progress: bool = True,
          max_updates: int | None = None, changes: dict | None = None,
          wandb: wandb_log.WandbOptions | None = None) -> Path:
    """Train (or resume) into ``run_dir``; returns the run folder.

    A run is a sweep of one trial: the same host loop (:func:`run_loop`) on an unstacked state. With
    ``resume`` the config is the run's own (``config.json``, env as stored), with ``changes`` (flags given
    again) applied where :data:`RESUMABLE` allows. ``max_updates`` stops early after that many updates in this
    call (for tests and interrupted-run checks); the budget stays ``config.num_updates``. ``wandb`` logs the run
    to Weights & Biases as well (``wandb_log``).
    """
    t_begin = time.monotonic()
    run_dir = Path(run_dir) if run_dir else default_run_dir(config)
    if resume:
        stored = checkpoint.load_config(run_dir)
        latest = checkpoint.manager(run_dir).latest_step()
        if latest is None:
            raise checkpoint.CheckpointError(f"no checkpoint in {run_dir / 'checkpoints'}: nothing to resume")
        config = resume_config(stored, changes)
        if config.total_steps != stored.total_steps and config.num_updates <= latest:
            raise ValueError(f"invalid --total-steps={config.total_steps} with --resume: the run is at update "
                             f"{latest} ({latest * config.steps_per_update} env steps) already; allowed: more")
        if config != stored:
            write_config(run_dir, config)
    elif (run_dir / "checkpoints").exists() and any((run_dir / "checkpoints").iterdir()):
        raise ValueError(f"run folder {run_dir} already holds checkpoints: use --resume {run_dir} or another --out")
    mesh = sharding.training_mesh(config.num_envs, config.devices)
    # The number of devices changes the order of floating-point sums: record it, so a resume matches.
    config = dataclasses.replace(config, devices=int(mesh.devices.size))
    agent, init_fn, chunk_fn = train_program(make_train, config, mesh)
    run_dir.mkdir(parents=True, exist_ok=True)
    if not resume:
        write_config(run_dir, config)
    program = Program(agent.env, init_fn, chunk_fn, (jax.random.PRNGKey(config.seed),), mesh, stacked=False)
    result = run_loop(program, config, run_dir, [run_dir], progress=progress, max_updates=max_updates,
                      tensorboard=True, wandb=wandb)
    plot_curves(run_dir)
    timing = {**result.timing, "devices": config.devices, "resumed_at": result.start,
              "train_s": time.monotonic() - t_begin}
    if jax.process_index() == 0:
        tmp = run_dir / (TIMING + ".tmp")
        tmp.write_text(json.dumps(timing, indent=1) + "\n")
        tmp.replace(run_dir / TIMING)
    return run_dir


def warm_start(state, source: str, stacked: bool = False, log: Callable[[str], None] | None = None):
    """``state`` with the networks of checkpoint ``source`` where their shapes fit (``TrainConfig.init_from``).

    A network (a top-level entry of ``params``: actor, critic, cost_critic, cbf) is copied whole or not at all: half a
    critic is no warm start. The observation normaliser comes along with the actor. ``stacked`` (a sweep's
    state, one row per trial) gives every trial the same start. A CheckpointError when the actor does not fit:
    the run would learn from scratch while its config claims a warm start. ``log`` (default: stderr) gets the line
    saying what was copied.
    """
    from aswarm.analysis import evaluate

    log = log or (lambda line: print(line, file=sys.stderr))

    _, policy = evaluate.load(source)

    def fits(new, old) -> bool:
        return jax.tree.structure(new) == jax.tree.structure(old) and all(
            np.shape(a)[int(stacked):] == np.shape(b) for a, b in zip(jax.tree.leaves(new), jax.tree.leaves(old)))

    def take(new, old):
        return jax.tree.map(lambda a, b: np.broadcast_to(np.asarray(b, np.asarray(a).dtype), np.shape(a)), new, old)

    params, copied, fresh = dict(state.params), [], []
    # The Lagrange multiplier is no network: it starts where the config says (lagrange_init, which a sweep may vary).
    for name, net in ((k, v) for k, v in state.params.items() if k != "lagrange"):
        if name in policy["params"] and fits(net, policy["params"][name]):
            params[name] = take(net, policy["params"][name])
            copied.append(name)
        else:
            fresh.append(name)
    if "actor" not in copied or not fits(state.obs_norm, policy["obs_norm"]):
        raise checkpoint.CheckpointError(
            f"invalid init_from={source!r}: its actor or observation normaliser does not fit this run's "
            "(another observation layout: scenario, cylinders or max_neighbours differ)")
    target = {k: params[k] for k in state.target}  # target critics start where their critics do
    log(f"init_from {source}: copied {', '.join(sorted(copied))}; fresh {', '.join(sorted(fresh)) or 'none'}")
    return state.replace(params=params, obs_norm=take(state.obs_norm, policy["obs_norm"]), target=target)


@functools.lru_cache(maxsize=4)
def train_program(make: Callable, config: TrainConfig, mesh) -> tuple:
    """(agent, jitted init, jitted chunk) of ``config`` laid out over ``mesh``, built by ``make`` (``make_train``).

    Kept for the process's next run of the same config and layout (a resume, the same run again from Python):
    tracing and lowering the program took seconds each time even where the compiled program came from the
    persistent cache, and they are the same. The config is the whole key, so any change builds anew.
    """
    agent, init, update_chunk, _ = make(config, shard_rows=sharding.rows_constraint(mesh))
    like = jax.eval_shape(init, jax.random.PRNGKey(config.seed))
    return (agent, *sharding.sharded_fns(init, update_chunk, like, mesh, stacked=False))


def read_metrics(run_dir: Path) -> list[dict]:
    path = Path(run_dir) / "metrics.jsonl"
    return [json.loads(r) for r in path.read_text().splitlines() if r] if path.exists() else []


def plot_curves(run_dir: Path, out: Path | None = None, compare: Sequence[Path] = ()) -> Path | None:
    """The paper's Fig. 7 (reward, episode time, explained variance vs env steps) plus success and collision;
    with ``compare``, those runs' curves on the same axes (labelled by folder). Written to ``out``, by default
    the run's ``curves.png``; None for a run with no metrics yet."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [(Path(d), read_metrics(d)) for d in (run_dir, *compare)]
    if not runs[0][1]:
        return None
    panels = [("episode/episode_return", "mean episode return"), ("episode/mission_time", "episode time (s)"),
              ("train/explained_variance", "explained variance"), ("episode/success", "success rate"),
              ("episode/collision", "collision rate"), ("safety/intervention_rate", "filter intervention rate")]
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5))
    for i, (d, rows) in enumerate(runs):
        x = np.array([r["env_steps"] for r in rows])
        for ax, (name, _) in zip(axes.flat, panels):
            y = np.array([r.get(name, math.nan) for r in rows])
            ax.plot(x, y, lw=0.8, alpha=0.3, color=f"C{i % 10}")
            if len(y) >= 10:  # a moving mean over a twentieth of the run: episodes end in bursts
                w = max(1, len(y) // 20)
                ax.plot(x[w - 1:], np.convolve(np.nan_to_num(y), np.ones(w) / w, mode="valid"), color=f"C{i % 10}",
                        label=d.name if ax is axes.flat[0] and compare else None)
    for ax, (_, title) in zip(axes.flat, panels):
        ax.set_title(title)
        ax.set_xlabel("env steps")
        ax.grid(alpha=0.3)
    if compare:
        axes.flat[0].legend(fontsize=8)
    fig.suptitle(" vs ".join(d.name for d, _ in runs))
    fig.tight_layout()
    from aswarm.analysis.plots import save_figure

    out = save_figure(fig, Path(out) if out is not None else Path(run_dir) / "curves.png", dpi=110)
    plt.close(fig)
    return out

"""The host loop around the jitted trainer: progress, logs, checkpoints, resume, faults, plots."""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import jax
import numpy as np

from aswarm.agents.config import TrainConfig
from aswarm.agents.train import make_train
from aswarm.training import checkpoint, sharding


class TrainingDiverged(RuntimeError):
    """A loss or parameter became NaN or Inf."""


def default_run_dir(config: TrainConfig) -> Path:
    return Path("runs") / f"{config.scenario}-{config.method}-{time.strftime('%Y%m%d-%H%M%S')}"


def write_config(run_dir: Path, config: TrainConfig, env_config) -> None:
    payload = {"train": dataclasses.asdict(config), "env": dataclasses.asdict(env_config)}
    tmp = run_dir / "config.json.tmp"
    tmp.write_text(json.dumps(payload, indent=2, default=str))
    tmp.replace(run_dir / "config.json")


def _finite(tree) -> bool:
    return all(bool(np.all(np.isfinite(np.asarray(x)))) for x in jax.tree.leaves(tree)
               if np.issubdtype(np.asarray(x).dtype, np.floating))


def train(config: TrainConfig, run_dir: Path | None = None, resume: bool = False, progress: bool = True,
          max_updates: int | None = None) -> Path:
    """Train (or resume) into ``run_dir``; returns the run folder.

    ``max_updates`` stops early after that many updates in this call (for tests
    and interrupted-run checks); the budget stays ``config.num_updates``.
    """
    from tensorboardX import SummaryWriter
    from tqdm import tqdm

    run_dir = Path(run_dir) if run_dir else default_run_dir(config)
    if resume:
        config = checkpoint.load_config(run_dir)
    elif (run_dir / "checkpoints").exists() and any((run_dir / "checkpoints").iterdir()):
        raise ValueError(f"run folder {run_dir} already holds checkpoints: use --resume {run_dir} or another --out")
    mesh = sharding.training_mesh(config.num_envs, config.devices)
    # The number of devices changes the order of floating-point sums: record it, so a resume matches.
    config = dataclasses.replace(config, devices=int(mesh.devices.size))
    agent, init, update_chunk, _ = make_train(config, shard_rows=sharding.rows_constraint(mesh))
    run_dir.mkdir(parents=True, exist_ok=True)
    if not resume:
        write_config(run_dir, config, agent.env.config)
    mngr = checkpoint.manager(run_dir)
    key = jax.random.PRNGKey(config.seed)
    init_fn, chunk_fn = sharding.sharded_fns(init, update_chunk, jax.eval_shape(init, key), mesh, stacked=False)
    ts = init_fn(key)
    if resume:
        layout = sharding.state_shardings(mesh, ts, stacked=False)
        ts = jax.tree.map(sharding.put, checkpoint.restore(mngr, sharding.fetch(ts)), layout)
        _truncate_log(run_dir / "metrics.jsonl", int(ts.update))
    start = int(ts.update)
    total = config.num_updates
    stop = total if max_updates is None else min(total, start + max_updates)
    writer = SummaryWriter(str(run_dir / "tb"))
    bar = tqdm(total=total, initial=start, unit="upd", disable=not progress, dynamic_ncols=True)
    last_save = time.monotonic()
    log = (run_dir / "metrics.jsonl").open("a")
    try:
        t_prev = time.monotonic()
        while int(ts.update) < stop:
            k = min(config.updates_per_chunk, stop - int(ts.update))
            new_ts, metrics = chunk_fn(ts, k)  # donates ts
            metrics = jax.device_get(metrics)
            if not (_finite(metrics["train/loss"]) and _finite(new_ts.params)):
                bad = int(new_ts.update) - k + int(np.argmax(~np.isfinite(metrics["train/loss"])))
                raise TrainingDiverged(
                    f"loss or parameters became NaN/Inf at update {bad}; the last good checkpoint "
                    f"(update {mngr.latest_step()}) in {run_dir / 'checkpoints'} is kept")
            ts = new_ts
            now = time.monotonic()
            sps = k * config.steps_per_update / (now - t_prev)
            t_prev = now
            first = int(ts.update) - k
            for i in range(k):
                row = {name: float(v[i]) for name, v in metrics.items()}
                row.update(update=first + i + 1, env_steps=(first + i + 1) * config.steps_per_update)
                log.write(json.dumps(row) + "\n")
                for name, v in row.items():
                    if name not in ("update",):
                        writer.add_scalar(name, v, row["update"])
            log.flush()
            last = {name: float(v[-1]) for name, v in metrics.items()}
            bar.set_postfix(sps=f"{sps:,.0f}", ret=f"{last['episode/episode_return']:.1f}",
                            success=f"{last['episode/success']:.2f}", coll=f"{last['episode/collision']:.2f}")
            bar.update(k)
            done = int(ts.update) >= stop
            if done or now - last_save > 60 * config.checkpoint_minutes:
                checkpoint.save(mngr, int(ts.update), sharding.for_checkpoint(sharding.fetch(ts)))
                last_save = now
    finally:
        bar.close()
        log.close()
        writer.close()
    plot_curves(run_dir)
    return run_dir


def _truncate_log(path: Path, update: int) -> None:
    """Drop log rows past the restored update (they will be produced again)."""
    if not path.exists():
        return
    rows = [r for r in path.read_text().splitlines() if r and json.loads(r)["update"] <= update]
    tmp = path.with_suffix(".tmp")
    tmp.write_text("".join(r + "\n" for r in rows))
    tmp.replace(path)


def read_metrics(run_dir: Path) -> list[dict]:
    path = Path(run_dir) / "metrics.jsonl"
    return [json.loads(r) for r in path.read_text().splitlines() if r] if path.exists() else []


def plot_curves(run_dir: Path) -> Path | None:
    """The paper's Fig. 7 (reward, episode time, explained variance vs update) plus success and collision."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = read_metrics(run_dir)
    if not rows:
        return None
    u = np.array([r["update"] for r in rows])

    def series(name):
        return np.array([r.get(name, math.nan) for r in rows])

    panels = [("episode/episode_return", "mean episode return"), ("episode/mission_time", "episode time (s)"),
              ("train/explained_variance", "explained variance"), ("episode/success", "success rate"),
              ("episode/collision", "collision rate"), ("safety/intervention_rate", "filter intervention rate")]
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5))
    for ax, (name, title) in zip(axes.flat, panels):
        y = series(name)
        ax.plot(u, y, lw=0.8, alpha=0.4, color="C0")
        if len(y) >= 10:
            w = max(1, len(y) // 20)
            smooth = np.convolve(np.nan_to_num(y), np.ones(w) / w, mode="valid")
            ax.plot(u[w - 1:], smooth, color="C0")
        ax.set_title(title)
        ax.set_xlabel("update")
        ax.grid(alpha=0.3)
    fig.suptitle(f"{Path(run_dir).name}")
    fig.tight_layout()
    out = Path(run_dir) / "curves.png"
    tmp = out.with_name("curves.tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(out)
    return out

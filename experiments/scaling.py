"""Scaling study: env-steps/s and training-steps/s against worlds, drones and obstacles, with the cost growth.

    python experiments/scaling.py                       # the full study (~an hour on 2 CPU cores; quiet machine)
    python experiments/scaling.py --tiny                # a 2-point check of every axis that it runs

Each axis varies one quantity from the `obstacles` scenario (4 drones, 8 cylinders, 256 worlds):
- worlds 1 -> 4096: throughput should grow until the cores are busy, then flatten;
- drones 2 -> 16: every drone observes all n - 1 others and the collision checks are pairwise, so the cost
  of a world's step is expected to grow faster than linearly in n (the fit below says how much);
- drones_k3, the same with each drone observing its 3 nearest neighbours only (``max_neighbours=3``): the
  observation, attention and filter rows per drone stay fixed, so only the pairwise distances grow as n^2;
- obstacles 1 -> 32: each drone attends over M cylinders: linear in M expected.
The cost growth is the log-log slope of seconds per world-step (env) and per env-step (training)
against the varied quantity over the upper half of its range: 1 is linear, 2 quadratic.
Writes ``OUT/scaling.json``, ``OUT/scaling.md`` and ``OUT/scaling.png``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

SCENARIO = "obstacles"
BASE_WORLDS = 256
# 1 m between obstacle slots gives 36 slots: room for 32 cylinders.
BASE_ENV = {"obstacle_spacing": 1.0}


def _ints(text: str) -> list[int]:
    try:
        vals = [int(v) for v in text.split(",") if v]
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid list {text!r}: allowed: comma-separated positive integers") from None
    if min(vals, default=1) <= 0:
        raise argparse.ArgumentTypeError(f"invalid list {text!r}: allowed: comma-separated positive integers")
    return vals


def env_point(worlds: int, steps: int, **env) -> dict:
    from aswarm.analysis import bench

    row = bench.time_env(SCENARIO, worlds, steps, **{**BASE_ENV, **env})
    return {"env_steps_per_s": row.env_steps_per_s, "drone_steps_per_s": row.drone_steps_per_s,
            "compile_s": row.compile_s}


def train_point(worlds: int, rollout_steps: int, updates: int, **env) -> dict:
    from aswarm.agents.config import TrainConfig
    from aswarm.analysis import train_bench

    cfg = TrainConfig(scenario=SCENARIO, num_envs=worlds, rollout_steps=rollout_steps,
                      minibatches=2 if worlds * rollout_steps % 2 == 0 else 1,
                      env_overrides=tuple(sorted({**BASE_ENV, **env}.items())))
    r = train_bench.time_trainer(cfg, updates)
    return {"train_steps_per_s": r["env_steps_per_s"], "train_compile_s": r["compile_s"]}


def growth(xs: list[int], per_step_s: list[float]) -> float:
    """Log-log slope of the cost per step over the upper half of the range (1: linear, 2: quadratic)."""
    x, y = np.log(np.asarray(xs, float)), np.log(np.asarray(per_step_s, float))
    k = max(2, math.ceil(len(x) / 2))
    return float(np.polyfit(x[-k:], y[-k:], 1)[0]) if len(x) >= 2 else math.nan


def study(args, log=print) -> dict:
    axes = {"worlds": args.worlds, "drones": args.drones, "drones_k3": args.drones, "obstacles": args.obstacles}
    out: dict = {"scenario": SCENARIO, "base_worlds": args.base_worlds, "steps": args.steps, "axes": {}}
    for axis, values in axes.items():
        rows = []
        for v in values:
            worlds = v if axis == "worlds" else args.base_worlds
            env = ({"num_agents": v} if axis == "drones" else {"num_agents": v, "max_neighbours": 3}
                   if axis == "drones_k3" else {"num_obstacles": v} if axis == "obstacles" else {})
            t0 = time.perf_counter()
            row = {"value": v, "worlds": worlds, **env_point(worlds, args.steps, **env)}
            if args.train:
                row.update(train_point(worlds, args.rollout_steps, args.updates, **env))
            rows.append(row)
            log(f"{axis}={v}: {row['env_steps_per_s']:,.0f} env-steps/s"
                + (f", {row['train_steps_per_s']:,.0f} training-steps/s" if args.train else "")
                + f" ({time.perf_counter() - t0:.0f} s)")
        # Cost per world-step: one env step of one world. Along the worlds axis the batch shares the cores,
        # so its slope says how far the throughput is from flat (0 = perfect batching).
        xs = [r["value"] for r in rows]
        entry = {"rows": rows, "env_growth": growth(xs, [1 / r["env_steps_per_s"] for r in rows])}
        if args.train:
            entry["train_growth"] = growth(xs, [1 / r["train_steps_per_s"] for r in rows])
        out["axes"][axis] = entry
    return out


def to_markdown(res: dict) -> str:
    lines = [f"Scenario `{res['scenario']}` (obstacle_spacing 1 m), {res['base_worlds']} worlds unless varied, "
             f"{res['steps']} env steps per timed rollout.", ""]
    for axis, entry in res["axes"].items():
        train = "train_growth" in entry
        lines += [f"**{axis}**: cost per world-step grows as {axis}^{entry['env_growth']:.2f} (env)"
                  + (f", ^{entry['train_growth']:.2f} (training)" if train else ""), "",
                  f"| {axis} | env-steps/s | drone-steps/s |" + (" training-steps/s |" if train else ""),
                  "|---:|---:|---:|" + ("---:|" if train else "")]
        for r in entry["rows"]:
            lines.append(f"| {r['value']} | {r['env_steps_per_s']:,.0f} | {r['drone_steps_per_s']:,.0f} |"
                         + (f" {r['train_steps_per_s']:,.0f} |" if train else ""))
        lines.append("")
    return "\n".join(lines)


def plot(res: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(res["axes"]), figsize=(5 * len(res["axes"]), 4.5))
    for ax, (axis, entry) in zip(axes, res["axes"].items()):
        xs = [r["value"] for r in entry["rows"]]
        ax.loglog(xs, [r["env_steps_per_s"] for r in entry["rows"]], "o-", label="env-steps/s (random actions)")
        if "train_growth" in entry:
            ax.loglog(xs, [r["train_steps_per_s"] for r in entry["rows"]], "s-", label="training-steps/s")
        title = f"{axis}: cost ~ {axis}^{entry['env_growth']:.2f}"
        ax.set_title(title + (f" (train ^{entry['train_growth']:.2f})" if "train_growth" in entry else ""))
        ax.set_xlabel(axis)
        ax.grid(alpha=0.3, which="both")
    axes[0].set_ylabel("steps per second")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--worlds", type=_ints, default=[1, 16, 64, 256, 1024, 4096])
    p.add_argument("--drones", type=_ints, default=[2, 4, 8, 16])
    p.add_argument("--obstacles", type=_ints, default=[1, 2, 4, 8, 16, 32])
    p.add_argument("--base-worlds", type=int, default=BASE_WORLDS, help="worlds on the drones and obstacles axes")
    p.add_argument("--steps", type=int, default=100, help="env steps per timed rollout")
    p.add_argument("--rollout-steps", type=int, default=16, help="training: env steps per update")
    p.add_argument("--updates", type=int, default=2, help="training: updates per timed call")
    p.add_argument("--no-train", dest="train", action="store_false", help="environment throughput only")
    p.add_argument("--tiny", action="store_true", help="two small points per axis: checks that the study runs")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "scaling")
    args = p.parse_args(argv)
    if args.tiny:
        args.worlds, args.drones, args.obstacles = [2, 4], [2, 3], [1, 2]
        args.base_worlds, args.steps, args.rollout_steps, args.updates = 4, 5, 4, 1
    from aswarm.training import sharding

    sharding.use_cpu_cores()  # training points are laid out as `aswarm train` lays them out
    args.out.mkdir(parents=True, exist_ok=True)
    res = study(args)
    (args.out / "scaling.json").write_text(json.dumps(res, indent=2))
    md = to_markdown(res)
    (args.out / "scaling.md").write_text(md + "\n")
    print(md)
    print(f"wrote {plot(res, args.out / 'scaling.png')}, scaling.json and scaling.md in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

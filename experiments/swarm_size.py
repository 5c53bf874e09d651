"""Swarm size: success, collisions and env-steps/s for 2, 4, 8 and 16 drones on `obstacles`.

    python experiments/swarm_size.py --checkpoint runs/obstacles-k3        # a policy trained with max_neighbours=3
    python experiments/swarm_size.py --checkpoint runs/obstacles-k3 --drones 2,4 --episodes 64   # quick look

The actor and the CBF filter run per drone on its own observation row. With ``max_neighbours=K`` that row holds
the K nearest drones whatever the swarm's size, so one policy, trained on 4 drones, flies 2, 8 or 16 (the
centralized critics, which depend on the number of drones, are needed only in training). Each size is evaluated
on unseen episodes of the same scenario with ``num_agents`` changed; its env-steps/s (random actions, 256
worlds, as ``aswarm bench``) shows what the larger swarm costs to simulate. Writes ``OUT/swarm_size.md`` and
``.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from aswarm.analysis.protocol import EVAL_SEED
from aswarm.files import write_atomic


def _ints(text: str) -> list[int]:
    try:
        vals = [int(v) for v in text.split(",") if v]
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid list {text!r}: allowed: comma-separated integers >= 1") from None
    if not vals or min(vals) < 1:
        raise argparse.ArgumentTypeError(f"invalid list {text!r}: allowed: comma-separated integers >= 1")
    return vals


def _pct(r: dict, name: str) -> str:
    lo, hi = r[f"{name}_ci95"]
    return f"{100 * r[name + '_rate']:.1f} [{100 * lo:.1f}, {100 * hi:.1f}]"


def table(rows: list[dict]) -> str:
    lines = ["| drones | episodes | success % [95 % CI] | drones finished % | collision % [95 % CI] | by kind | "
             "mean separation m | mission time s | env-steps/s | drone-steps/s |",
             "|---:|---:|---|---:|---|---|---:|---:|---:|---:|"]
    for r in rows:
        kinds = ", ".join(f"{k} {100 * r[f'collision_{k}_rate']:.1f}" for k in ("obstacle", "drone", "floor", "bounds")
                          if r[f"collision_{k}_rate"]) or "–"
        t = "–" if r["mission_time"] is None else f"{r['mission_time']:.1f}"
        lines.append(f"| {r['num_agents']} | {r['episodes']} | {_pct(r, 'success')} | "
                     f"{100 * r['drone_success_rate']:.1f} | {_pct(r, 'collision')} | {kinds} | "
                     f"{r['mean_separation']:.2f} | {t} | {r['env_steps_per_s']:,.0f} | "
                     f"{r['drone_steps_per_s']:,.0f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", required=True, help="an `obstacles` run folder trained with --env max_neighbours=K")
    p.add_argument("--drones", type=_ints, default=[2, 4, 8, 16])
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--seed", type=int, default=EVAL_SEED)
    p.add_argument("--bench-worlds", type=int, default=256, help="worlds of the env-steps/s measurement")
    p.add_argument("--out", type=Path, default=Path("experiments/results"))
    args = p.parse_args(argv)
    if args.episodes <= 0:
        p.error(f"invalid --episodes {args.episodes}: must be > 0")

    from aswarm.agents.train import make_env
    from aswarm.analysis import bench, evaluate
    from aswarm.training import checkpoint

    config = checkpoint.load_config(evaluate.run_folder(args.checkpoint))
    trained = make_env(config).config
    k = trained.max_neighbours
    if not k:
        p.error(f"invalid --checkpoint {args.checkpoint}: it observes every other drone, so it flies only the swarm "
                "size it was trained for; train with --env max_neighbours=K")
    rows = []
    t_start = time.perf_counter()
    for n in args.drones:
        t0 = time.perf_counter()
        r = evaluate.evaluate_checkpoint(args.checkpoint, episodes=args.episodes, seed=args.seed,
                                         env_overrides=[f"num_agents={n}"])
        speed = bench.time_env(config.scenario, args.bench_worlds, 100, **{**dict(config.env_overrides),
                                                                           "num_agents": n})
        rows.append({**r, "env_steps_per_s": speed.env_steps_per_s, "drone_steps_per_s": speed.drone_steps_per_s,
                     "wall_s": time.perf_counter() - t0})
        print(f"{n} drones: success {_pct(r, 'success')}, collision {_pct(r, 'collision')}, "
              f"{speed.env_steps_per_s:,.0f} env-steps/s", flush=True)

    args.out.mkdir(parents=True, exist_ok=True)
    wall = time.perf_counter() - t_start
    cmd = "python experiments/swarm_size.py " + " ".join(argv if argv is not None else sys.argv[1:])
    md = (f"# Swarm size on `{config.scenario}`\n\nCommand: `{cmd.strip()}`  \nPolicy: `{args.checkpoint}`, "
          f"trained with {trained.num_agents} drones observing their {k} nearest "
          f"neighbours ({config.method}, {config.total_steps:,} env steps). Evaluation seed {args.seed} (unseen in "
          f"training); env-steps/s with random actions at {args.bench_worlds} worlds. Wall time: {wall / 60:.1f} min "
          f"(2-core CPU).\n\n{table(rows)}\n")
    for suffix, text in ((".md", md), (".json", json.dumps(rows, indent=2, default=float) + "\n")):
        write_atomic(args.out / f"swarm_size{suffix}", text)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Moving-obstacle study: success and collisions of a trained policy and the MPC against 1, 2 and 3 moving cylinders.

    python experiments/moving_obstacles.py --checkpoint pretrained --checkpoint runs/race-moving
    python experiments/moving_obstacles.py --checkpoint pretrained --episodes 64 --mpc-episodes 32

The paper reports 100 % success with one moving obstacle and 95 % with three. Here the race track keeps its
8 cylinder slots (so a race policy's observation layout is unchanged) and ``k`` of them move across the racing
line (``num_moving = min_moving = k``, ``num_obstacles = 8 - k``); k = 0 is the plain race for reference.
Writes ``OUT/moving_obstacles.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from aswarm.analysis.protocol import EVAL_SEED

SLOTS = 8  # the race's cylinder slots


def overrides(k: int) -> dict[str, int]:
    return {"num_obstacles": SLOTS - k, "num_moving": k, "min_moving": k}


def _pct(r: dict, name: str) -> str:
    lo, hi = r[f"{name}_ci95"]
    return f"{100 * r[name + '_rate']:.1f} [{100 * lo:.1f}, {100 * hi:.1f}]"


def table(rows: list[dict]) -> str:
    lines = ["| method | moving cylinders | episodes | success % [95 % CI] | collision % [95 % CI] | "
             "by obstacle % | mission time s |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        t = "–" if r["mission_time"] is None else f"{r['mission_time']:.1f}"
        lines.append(f"| {r['label']} | {r['moving']} | {r['episodes']} | {_pct(r, 'success')} | "
                     f"{_pct(r, 'collision')} | {100 * r['collision_obstacle_rate']:.1f} | {t} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", action="append", default=None,
                   help="a race run folder or 'pretrained' (repeat for several; default: pretrained)")
    p.add_argument("--moving", default="0,1,2,3", help="comma-separated numbers of moving cylinders (<= 8)")
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--mpc-episodes", type=int, default=200, help="0 skips the MPC")
    p.add_argument("--seed", type=int, default=EVAL_SEED)
    p.add_argument("--out", type=Path, default=Path("experiments/results"))
    args = p.parse_args(argv)
    try:
        counts = [int(v) for v in args.moving.split(",") if v]
    except ValueError:
        p.error(f"invalid --moving {args.moving!r}: allowed: comma-separated integers from 0 to {SLOTS}")
    if not counts or min(counts) < 0 or max(counts) > SLOTS:
        p.error(f"invalid --moving {args.moving!r}: allowed: comma-separated integers from 0 to {SLOTS}")
    if args.episodes <= 0 or args.mpc_episodes < 0:
        p.error(f"invalid --episodes {args.episodes} / --mpc-episodes {args.mpc_episodes}: must be > 0 / >= 0")

    import jax

    from aswarm import envs
    from aswarm.analysis import evaluate
    from aswarm.baselines import mpc

    rows = []
    t_start = time.perf_counter()
    for k in counts:
        for ckpt in args.checkpoint or ["pretrained"]:
            t0 = time.perf_counter()
            r = evaluate.evaluate_checkpoint(ckpt, "race", args.episodes, args.seed,
                                             [f"{f}={v}" for f, v in overrides(k).items()])
            rows.append({**r, "label": f"{r['method']} ({ckpt})", "moving": k, "wall_s": time.perf_counter() - t0})
            print(f"{ckpt}, {k} moving: success {_pct(r, 'success')}, collision {_pct(r, 'collision')}", flush=True)
        if args.mpc_episodes:
            t0 = time.perf_counter()
            env = envs.make("race", **overrides(k))
            rec = mpc.rollout_mpc(env, mpc.MPCConfig(), args.mpc_episodes, jax.random.PRNGKey(args.seed))
            m = evaluate.summarize(rec)
            rows.append({**m, "label": "MPC (MPPI)", "moving": k, "episodes": args.mpc_episodes,
                         "wall_s": time.perf_counter() - t0})
            print(f"MPC, {k} moving: success {_pct(m, 'success')}, collision {_pct(m, 'collision')}", flush=True)

    args.out.mkdir(parents=True, exist_ok=True)
    wall = time.perf_counter() - t_start
    cmd = "python experiments/moving_obstacles.py " + " ".join(argv if argv is not None else sys.argv[1:])
    md = (f"# Moving obstacles on the race track\n\nCommand: `{cmd.strip()}`  \nWall time: {wall / 60:.1f} min "
          f"(2-core CPU). Evaluation seed {args.seed} (unseen in training).\n\n{table(rows)}\n")
    (args.out / "moving_obstacles.md").write_text(md)
    (args.out / "moving_obstacles.json").write_text(json.dumps(rows, indent=2, default=float) + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

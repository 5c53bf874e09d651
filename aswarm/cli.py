"""The ``aswarm`` command line."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _positive_ints(text: str) -> list[int]:
    try:
        vals = [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid list {text!r}: allowed: comma-separated positive integers") from None
    if not vals or min(vals) <= 0:
        raise argparse.ArgumentTypeError(f"invalid list {text!r}: allowed: comma-separated positive integers")
    return vals


def cmd_scenarios(args: argparse.Namespace) -> int:
    from aswarm.envs import scenarios

    rows = []
    for name, sc in scenarios.SCENARIOS.items():
        cfg = scenarios.preset(name)
        geo = scenarios.geometry(cfg)
        moving = f"{cfg.min_moving}-{cfg.num_moving}" if cfg.num_moving else "0"
        task = f"{cfg.num_gates} gates in order" if sc.kind == "track" else "goal point"
        length = f"{scenarios.track_length(cfg):.1f} m" if sc.kind == "track" else "-"
        rows.append((name, str(cfg.num_agents), str(cfg.num_obstacles), moving, task, length,
                     f"{cfg.episode_seconds:g} s", str(len(geo.slot_pos)), sc.description))
    head = ("scenario", "drones", "static", "moving", "task", "lap", "limit", "slots", "description")
    widths = [max(len(r[i]) for r in rows + [head]) for i in range(len(head) - 1)]
    for r in [head, *rows]:
        print("  ".join(c.ljust(w) for c, w in zip(r[:-1], widths)) + "  " + r[-1])
    print("\nOverride any field, e.g. num_agents=8 or num_obstacles=4 (aswarm.envs.make(name, **overrides)).")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from aswarm import bench

    return bench.main_trainer(args) if args.trainer else bench.main(args)


def cmd_train(args: argparse.Namespace) -> int:
    from aswarm import config_args, envs
    from aswarm.agents import runner
    from aswarm.agents.config import TrainConfig

    if args.resume:
        run_dir = runner.train(None, args.resume, resume=True, progress=not args.quiet)
    else:
        fields = config_args.overrides(args, TrainConfig)
        env_over = config_args.parse_assignments(args.env or [], envs.EnvConfig)
        config = TrainConfig(**fields, env_overrides=tuple(sorted(env_over.items())))
        envs.make(config.scenario, **env_over)  # fail on a bad env before compiling anything
        run_dir = runner.train(config, args.out, progress=not args.quiet)
    print(f"run folder: {run_dir}  (metrics.jsonl, tb/, checkpoints/, curves.png)")
    print(f"evaluate:   aswarm eval --checkpoint {run_dir} --episodes 1000")
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    import json

    from aswarm.agents import evaluate

    result = evaluate.evaluate_checkpoint(args.checkpoint, scenario=args.scenario, episodes=args.episodes,
                                          seed=args.seed, env_overrides=args.env or [])
    if args.json:
        print(json.dumps(result))
    else:
        print(evaluate.format_table(result))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="aswarm", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("scenarios", help="list the scenarios with their drones, obstacles and gates")
    s.set_defaults(func=cmd_scenarios)

    b = sub.add_parser("bench", help="environment throughput; writes BENCHMARKS.md")
    b.add_argument("--scenario", default="race")
    b.add_argument("--worlds", type=_positive_ints, default=[1, 64, 1024, 4096])
    b.add_argument("--steps", type=int, default=200, help="env steps per timed rollout")
    b.add_argument("--peer-venv", type=Path, default=Path(".venv-crazyflow"),
                   help="virtualenv holding crazyflow, created on first use")
    b.add_argument("--no-peer", action="store_true", help="skip the crazyflow comparison")
    b.add_argument("--out", type=Path, default=Path("BENCHMARKS.md"))
    b.add_argument("--trainer", action="store_true", help="end-to-end training throughput instead")
    b.set_defaults(func=cmd_bench)

    from aswarm import config_args
    from aswarm.agents.config import METHODS, TrainConfig

    t = sub.add_parser("train", help="train a swarm policy (MAPPO with attention-CBF by default)",
                       description="Every TrainConfig field is a flag; env fields go through --env FIELD=VALUE. "
                       f"Methods: {'; '.join(f'{k}: {v}' for k, v in METHODS.items())}.")
    t.add_argument("--out", type=Path, default=None, help="run folder (default runs/SCENARIO-METHOD-TIME)")
    t.add_argument("--resume", type=Path, default=None,
                   help="continue the run in this folder from its latest checkpoint")
    t.add_argument("--env", action="append", metavar="FIELD=VALUE", help="env config override, repeatable")
    t.add_argument("--quiet", action="store_true", help="no progress bar")
    config_args.add_fields(t, TrainConfig, skip=("env_overrides",))
    t.set_defaults(func=cmd_train)

    e = sub.add_parser("eval", help="evaluate a trained policy on unseen seeds")
    e.add_argument("--checkpoint", required=True, help="run folder, or 'pretrained'")
    e.add_argument("--scenario", default=None, help="default: the scenario it was trained on")
    e.add_argument("--episodes", type=int, default=1000)
    e.add_argument("--seed", type=int, default=10_000, help="evaluation seed (training seeds are small integers)")
    e.add_argument("--env", action="append", metavar="FIELD=VALUE", help="env config override, repeatable")
    e.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    e.set_defaults(func=cmd_eval)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except ValueError as e:  # config, input and checkpoint errors: one line, non-zero exit
        print(f"aswarm {args.command}: error: {e}", file=sys.stderr)
        return 2
    except RuntimeError as e:  # training diverged
        print(f"aswarm {args.command}: error: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())

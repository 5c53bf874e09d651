"""The paper's Table I on our simulator: every method, the same env-step budget and seeds, >= 1000 episodes.

    python experiments/paper_table.py                 # full budgets (hours on 2 CPU cores)
    python experiments/paper_table.py --quick         # tiny budgets: checks the pipeline end to end (CI)
    python experiments/paper_table.py --total-steps 3000000 --methods attention_cbf,mappo,mpc

Rows are methods, columns Case 1 (``obstacles``) success, Case 2 (``race``) success and the collision rate
(episodes with any collision, over both cases), each with its 95 % Wilson interval and the paper's figure
beside ours. Methods trained without a safety layer are also evaluated with the CBF filter at a fixed gain
(``+ filter`` rows), so the filter's own contribution shows. Writes ``paper_table.md`` and ``.csv`` into
``--out`` (default ``experiments/results``), and keeps each run folder under ``--runs``.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import sys
import time
from pathlib import Path

from aswarm.analysis.protocol import EVAL_SEED
from aswarm.files import write_atomic

SCENARIOS = ("obstacles", "race")
LEARNED = ("attention_cbf", "mappo", "a2c", "fixed_cbf", "attention_penalty", "mappo_lagrangian")
ALL_METHODS = LEARNED + ("mpc",)
NAMES = {"attention_cbf": "AttentionSwarm (attention-CBF)", "mappo": "MAPPO", "a2c": "A2C", "mpc": "MPC (MPPI)",
         "fixed_cbf": "ablation: CBF filter, fixed gain",
         "attention_penalty": "ablation: attention penalties, no filter",
         "mappo_lagrangian": "ablation: MAPPO-Lagrangian"}
# Table I of the paper: Case 1 success, Case 2 success, collision rate (%).
PAPER = {"attention_cbf": (100, 95, 0), "mappo": (50, 40, 30), "a2c": (40, 30, 30), "mpc": (60, 50, 15)}
QUICK = dict(total_steps=16 * 8 * 2, num_envs=16, rollout_steps=8, minibatches=2, updates_per_chunk=1)
QUICK_ENV = {"obstacles": [("episode_seconds", 1.0)], "race": [("episode_seconds", 1.0)]}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="tiny budgets and episodes: checks the pipeline only")
    p.add_argument("--methods", default=",".join(ALL_METHODS), help=f"comma-separated, from {', '.join(ALL_METHODS)}")
    p.add_argument("--scenarios", default=",".join(SCENARIOS))
    p.add_argument("--total-steps", type=int, default=None, help="env steps per method and scenario "
                   "(default: TrainConfig's default budget)")
    p.add_argument("--seed", type=int, default=0, help="training seed (evaluation uses unseen seeds)")
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--out", type=Path, default=Path("experiments/results"))
    p.add_argument("--runs", type=Path, default=Path("runs/paper_table"))
    p.add_argument("--env", action="append", default=[], metavar="FIELD=VALUE",
                   help="env field for every method and scenario, as aswarm train's --env (repeatable; nested "
                        "fields dotted: --env controller=geometric)")
    args = p.parse_args(argv)
    from aswarm import config_args
    from aswarm.envs.config import EnvConfig

    try:
        args.env = tuple(config_args.parse_assignments(args.env, EnvConfig).items())
    except ValueError as e:
        p.error(str(e))
    args.methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    args.scenarios = [s.strip() for s in args.scenarios.split(",") if s.strip()]
    for m in args.methods:
        if m not in ALL_METHODS:
            p.error(f"invalid method {m!r}: allowed: {', '.join(ALL_METHODS)}")
    for s in args.scenarios:
        if s not in SCENARIOS:
            p.error(f"invalid scenario {s!r}: allowed: {', '.join(SCENARIOS)}")
    if args.episodes <= 0:
        p.error(f"invalid --episodes {args.episodes}: must be > 0")
    if args.quick:
        args.episodes = min(args.episodes, 8)
    return args


def train_and_evaluate(method: str, scenario: str, args: argparse.Namespace) -> list[dict]:
    """One method on one scenario: train (learned methods) and evaluate, with the filter where it has none."""
    import jax

    from aswarm import config_args, envs
    from aswarm.agents.config import TrainConfig
    from aswarm.analysis import evaluate
    from aswarm.baselines import mpc
    from aswarm.training import runner

    env_overrides = args.env + (tuple(QUICK_ENV[scenario]) if args.quick else ())
    t0 = time.perf_counter()
    if method == "mpc":
        env = envs.SwarmEnv(config_args.replace_fields(envs.preset(scenario), dict(env_overrides)))
        mpc_config = mpc.MPCConfig(samples=16, horizon=5) if args.quick else mpc.MPCConfig()
        rec = mpc.rollout_mpc(env, mpc_config, args.episodes, jax.random.PRNGKey(EVAL_SEED + args.seed))
        result = evaluate.summarize({k: jax.device_get(v) for k, v in rec.items()})
        result.update(method=method, variant="", scenario=scenario, episodes=args.episodes, train_seconds=0.0,
                      eval_seconds=time.perf_counter() - t0)
        return [result]

    fields = dict(QUICK) if args.quick else {}
    if args.total_steps:
        fields["total_steps"] = args.total_steps
    config = TrainConfig(scenario=scenario, method=method, seed=args.seed, env_overrides=env_overrides, **fields)
    run_dir = args.runs / f"{scenario}-{method}-seed{args.seed}"
    logged = runner.read_metrics(run_dir) if (run_dir / "checkpoints").exists() else []
    done = bool(logged) and logged[-1]["update"] >= config.num_updates
    if not done:  # a finished run is reused; an interrupted one resumes
        resume = (run_dir / "checkpoints").exists() and any((run_dir / "checkpoints").iterdir())
        runner.train(None if resume else config, run_dir, resume=resume, progress=not args.quick)
    train_seconds = time.perf_counter() - t0
    rows = []
    variants = [("", None)] if config.uses_filter else [("", None), ("+ filter", "fixed_cbf")]
    for variant, as_method in variants:
        t1 = time.perf_counter()
        result = evaluate.evaluate_checkpoint(run_dir, episodes=args.episodes, seed=EVAL_SEED + args.seed,
                                              with_method=as_method)
        result.update(method=method, variant=variant, scenario=scenario, train_seconds=train_seconds,
                      eval_seconds=time.perf_counter() - t1)
        rows.append(result)
    return rows


def _pct(r: dict | None, name: str) -> str:
    if r is None:
        return "–"
    lo, hi = r[f"{name}_ci95"]
    return f"{100 * r[name + '_rate']:.1f} [{100 * lo:.0f}, {100 * hi:.0f}]"


def table(results: list[dict], args: argparse.Namespace) -> tuple[str, str]:
    """(markdown, csv) of the results, one row per method and variant."""
    from aswarm.analysis.evaluate import wilson

    keys = []
    for r in results:
        if (r["method"], r["variant"]) not in keys:
            keys.append((r["method"], r["variant"]))
    head = ("| method | Case 1 success % | Case 2 success % | collision % | paper (C1 / C2 / coll.) |\n"
            "|---|---:|---:|---:|---|")
    lines, rows = [head], []
    for method, variant in keys:
        by = {r["scenario"]: r for r in results if (r["method"], r["variant"]) == (method, variant)}
        n = sum(r["episodes"] for r in by.values())
        hits = sum(r["collision_rate"] * r["episodes"] for r in by.values())
        coll = {"collision_rate": hits / n, "collision_ci95": wilson(hits, n)} if n else None
        paper = PAPER.get(method) if not variant else None
        name = NAMES[method] + (f" {variant}" if variant else "")
        lines.append(f"| {name} | {_pct(by.get('obstacles'), 'success')} | {_pct(by.get('race'), 'success')} | "
                     f"{_pct(coll, 'collision')} | {' / '.join(map(str, paper)) if paper else '–'} |")
        row = {"method": method, "variant": variant}
        for s in SCENARIOS:
            r = by.get(s)
            row[f"{s}_success"] = r["success_rate"] if r else ""
            row[f"{s}_success_lo"], row[f"{s}_success_hi"] = r["success_ci95"] if r else ("", "")
            row[f"{s}_collision"] = r["collision_rate"] if r else ""
            row[f"{s}_train_s"] = round(r["train_seconds"], 1) if r else ""
        row["collision"] = coll["collision_rate"] if coll else ""
        row["paper_case1"], row["paper_case2"], row["paper_collision"] = paper if paper else ("", "", "")
        rows.append(row)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]))
    w.writeheader()
    w.writerows(rows)
    budget = "quick (pipeline check only)" if args.quick else f"{args.total_steps or 'default'} env steps"
    md = (f"# Table I on the aswarm simulator\n\nCommand: `python experiments/paper_table.py "
          f"{' '.join(sys.argv[1:])}`  \nBudget per method and scenario: {budget}; training seed {args.seed}; "
          f"{args.episodes} evaluation episodes per cell on unseen seeds. Cells: rate % [95 % Wilson interval]. "
          f"Collision: episodes with any collision, both cases pooled.\n\n" + "\n".join(lines) + "\n")
    return md, buf.getvalue()


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from aswarm.training import sharding

    sharding.use_cpu_cores()  # train as `aswarm train` does: the worlds split over the CPU cores
    results = []
    t0 = time.perf_counter()
    for scenario in args.scenarios:
        for method in args.methods:
            print(f"[{time.perf_counter() - t0:7.0f} s] {method} on {scenario}", flush=True)
            results.extend(train_and_evaluate(method, scenario, args))
    md, text = table(results, args)
    md += f"\nWall time: {time.perf_counter() - t0:.0f} s.\n"
    args.out.mkdir(parents=True, exist_ok=True)
    stem = "paper_table_quick" if args.quick else "paper_table"
    for suffix, content in ((".md", md), (".csv", text), (".json", json.dumps(results, indent=1, default=str))):
        write_atomic(args.out / f"{stem}{suffix}", content)
    print(md)
    if args.quick:  # the pipeline check: every cell was filled
        expected = {(m, s) for m in args.methods for s in args.scenarios}
        assert {(r["method"], r["scenario"]) for r in results} == expected
    return 0


if __name__ == "__main__":
    sys.exit(main())

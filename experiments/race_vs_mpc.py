"""Issue #13's speed target: the race policy's mission time against the MPC's, on the same episodes and drone.

    python experiments/race_vs_mpc.py                                   # the shipped race policy, 500 episodes
    python experiments/race_vs_mpc.py --checkpoint runs/race --episodes 1000 --seed 50000
    python experiments/race_vs_mpc.py --quick                           # 4 episodes, a short MPC: CI

Both fly the checkpoint's own environment (its drone model, its randomisation, its filter for the policy), from
the same resets: episode i of both is ``aswarm eval --seed S``'s episode i. The MPC is ``aswarm/baselines/mpc.py``
with its defaults, its model fitted to the drone's measured step responses (``MPCConfig.fit_to_drone``). Mission
time is compared on the episodes both finished (paired), with a 95 % interval of the mean difference (normal
approximation of the paired differences). Writes ``OUT/race_vs_mpc.md`` and ``.json`` (``_quick`` with
``--quick``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from aswarm.files import write_atomic

MATRIX_SEED = 50_000  # unseen by the shipped race policy's selection (seeds 10000 and 20000)
Z95 = 1.959963984540054


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default="pretrained", help="run folder or shipped name (default: pretrained)")
    p.add_argument("--episodes", type=int, default=500)
    p.add_argument("--seed", type=int, default=MATRIX_SEED)
    p.add_argument("--quick", action="store_true", help="4 episodes and a short MPC plan: a pipeline check")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = p.parse_args(argv)
    if args.episodes <= 0:
        p.error(f"invalid --episodes {args.episodes}: must be > 0")
    if args.quick:
        args.episodes = min(args.episodes, 4)
    return args


def paired(a: np.ndarray, b: np.ndarray) -> dict:
    """Mean of a - b with a 95 % normal interval (None where fewer than 2 pairs)."""
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    if d.size < 2:
        return {"pairs": int(d.size), "mean_diff": float(d.mean()) if d.size else None, "ci95": None}
    half = Z95 * d.std(ddof=1) / np.sqrt(d.size)
    return {"pairs": int(d.size), "mean_diff": float(d.mean()), "ci95": [float(d.mean() - half),
                                                                         float(d.mean() + half)]}


def compare(args: argparse.Namespace) -> dict:
    import jax

    from aswarm.analysis import evaluate
    from aswarm.baselines import mpc

    _, agent, restored = evaluate.load_agent(args.checkpoint, None, None)
    env = agent.env
    key = jax.random.PRNGKey(args.seed)
    t0 = time.perf_counter()
    rec, _, stats = evaluate.rollout_with_filter_stats(agent, restored["params"], restored["obs_norm"], env,
                                                       args.episodes, key)
    policy_rec = {k: np.asarray(v) for k, v in rec.items()}
    t_policy = time.perf_counter() - t0
    config = mpc.MPCConfig(samples=16, horizon=5) if args.quick else mpc.MPCConfig()
    t0 = time.perf_counter()
    mpc_rec = mpc.rollout_mpc(env, config, args.episodes, jax.random.fold_in(key, 1),
                              reset_keys=jax.random.split(key, args.episodes))
    mpc_rec = {k: np.asarray(v) for k, v in jax.device_get(mpc_rec).items()}
    t_mpc = time.perf_counter() - t0
    both = (policy_rec["success"] > 0.5) & (mpc_rec["success"] > 0.5)
    return {
        "checkpoint": str(args.checkpoint), "scenario": env.config.scenario, "controller": env.config.controller,
        "episodes": args.episodes, "seed": args.seed, "quick": args.quick,
        "policy": {**evaluate.summarize(policy_rec, float(stats.intervention_rate), float(stats.infeasible_rate)),
                   "wall_s": t_policy},
        "mpc": {**evaluate.summarize(mpc_rec), "wall_s": t_mpc},
        "mission_time_both": {"policy": float(policy_rec["mission_time"][both].mean()) if both.any() else None,
                              "mpc": float(mpc_rec["mission_time"][both].mean()) if both.any() else None,
                              "policy_minus_mpc": paired(policy_rec["mission_time"][both],
                                                         mpc_rec["mission_time"][both])},
    }


def _pct(r: dict, name: str) -> str:
    lo, hi = r[f"{name}_ci95"]
    return f"{100 * r[name + '_rate']:.1f} [{100 * lo:.1f}, {100 * hi:.1f}]"


def _s(v: float | None) -> str:
    return "–" if v is None else f"{v:.1f}"


def report(res: dict, command: str) -> str:
    both = res["mission_time_both"]
    diff = both["policy_minus_mpc"]
    ci = "–" if diff["ci95"] is None else f"[{diff['ci95'][0]:+.1f}, {diff['ci95'][1]:+.1f}]"
    lines = [
        "# Race mission time: the policy against the MPC (issue #13)", "",
        f"Command: `{command}`  ",
        f"Policy `{res['checkpoint']}` on its own drone (`{res['controller']}` controller), scenario "
        f"`{res['scenario']}`; {res['episodes']} episodes from seed {res['seed']}, the same resets for both.", "",
        "| flyer | success % [95 %] | collision-episode % [95 %] | mission time s (its successes) | wall s |",
        "|---|---|---|---:|---:|",
    ]
    for name, r in (("policy (attention-CBF + filter)", res["policy"]), ("MPC (MPPI)", res["mpc"])):
        lines.append(f"| {name} | {_pct(r, 'success')} | {_pct(r, 'collision')} | {_s(r['mission_time'])} | "
                     f"{r['wall_s']:.0f} |")
    lines += ["", f"On the {diff['pairs']} episodes both finished: policy {_s(both['policy'])} s, MPC "
              f"{_s(both['mpc'])} s; policy − MPC {_s(diff['mean_diff'])} s, 95 % interval {ci}.", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    command = "python experiments/race_vs_mpc.py " + " ".join(sys.argv[1:] if argv is None else argv)
    try:
        res = compare(args)
    except ValueError as e:  # a checkpoint that is not there, a bad scenario: one line
        print(f"error: {str(e).splitlines()[0]}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    stem = "race_vs_mpc_quick" if args.quick else "race_vs_mpc"
    for suffix, text in ((".json", json.dumps({"command": command.strip(), **res}, indent=1) + "\n"),
                         (".md", report(res, command.strip()))):
        write_atomic(args.out / f"{stem}{suffix}", text)
    print(report(res, command.strip()))
    return 0


if __name__ == "__main__":
    sys.exit(main())

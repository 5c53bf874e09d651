"""One trained policy evaluated under other safety-filter settings and env overrides, without retraining.

    python experiments/filter_variants.py --checkpoint pretrained --episodes 1000 \
        --variant '{}' --variant '{"lookahead_xy": 0.31}' --variant '{"env": ["command_accel_limit=5"]}'

Each variant is a JSON object: ``SafetyFilterConfig`` fields replace those of the policy's fitted filter, and
``"env"`` lists ``aswarm eval --env`` overrides. Every variant flies the same episodes (``--seed``, the
evaluation seed by default). Prints one line per variant: success, collisions by kind, mission time; and on
stderr, while a variant flies, which batch of episodes it is on and how far (a 16-drone variant over 10,000
episodes runs for an hour or more). The README's look-ahead and command-limit comparisons (issue #12) were made
with this.
"""

from __future__ import annotations

import argparse
import json
import sys
import time


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", required=True, help="run folder, or 'pretrained'")
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--seed", type=int, default=None, help="default: the evaluation seed")
    p.add_argument("--variant", action="append", required=True, metavar="JSON", help="repeatable")
    args = p.parse_args(argv)
    try:
        variants = [json.loads(v) for v in args.variant]
    except json.JSONDecodeError as e:
        p.error(f"invalid --variant: {e}; allowed: a JSON object such as '{{\"lookahead_xy\": 0.3}}'")
    if not all(isinstance(v, dict) for v in variants):
        p.error("invalid --variant: allowed: a JSON object of safety-filter fields and an optional \"env\" list")

    import jax
    import numpy as np

    from aswarm.analysis import evaluate
    from aswarm.analysis.protocol import EVAL_SEED

    seed = EVAL_SEED if args.seed is None else args.seed
    names = ("success_rate", "collision_rate", "collision_gate_rate", "collision_floor_rate",
             "collision_obstacle_rate", "collision_drone_rate", "collision_bounds_rate", "filter_intervention_rate",
             "filter_infeasible_rate", "filter_escape_rate")

    def progress(line: str) -> None:
        print(f"  {line} [{time.perf_counter() - t0:.0f} s]", file=sys.stderr, flush=True)

    for variant in variants:
        t0 = time.perf_counter()
        fields = dict(variant)
        overrides = fields.pop("env", [])
        _, agent, restored = evaluate.load_agent(args.checkpoint, env_overrides=overrides, filter_overrides=fields)
        rec, _, stats = evaluate.rollout_with_filter_stats(agent, restored["params"], restored["obs_norm"], agent.env,
                                                           args.episodes, jax.random.PRNGKey(seed),
                                                           progress=progress)
        s = evaluate.summarize({k: np.asarray(x) for k, x in rec.items()}, float(stats.intervention_rate),
                               float(stats.infeasible_rate))
        s["filter_escape_rate"] = float(stats.escape_rate)
        mission = "-" if s["mission_time"] is None else f"{s['mission_time']:.1f} s"  # None: no success
        print(json.dumps(variant), {k: round(s[k], 4) for k in names}, f"mission {mission}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

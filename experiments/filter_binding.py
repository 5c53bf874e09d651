"""Which of the safety filter's rows take a policy's speed: cylinders, neighbours, floor, walls or gate frames.

    python experiments/filter_binding.py --checkpoint pretrained --episodes 100 --seed 50000
    python experiments/filter_binding.py --checkpoint pretrained --filter '{"margin": 0.1}' --out /tmp/binding

Flies ``--episodes`` episodes as ``aswarm eval`` does (the deterministic policy, its filter, episode i from the i-th
key of the seed) and, on every step of every flying drone, takes the rows of the filter
(``core.barriers.obs_rows``, at the look-ahead point) binding at the command it let through (the QP's active set,
``FilterResult.active``). A step on which the filter changed the command counts for each group with a binding row,
and the speed it took away along the policy's command (``|c| − u · c / |c|``, at least 0) is split evenly among
those groups. Prints, per group, the share of flying drone-steps on which it was binding and the speed it took per
flying drone-step (the groups' speeds add up to the mean speed lost); ``--out`` also writes ``filter_binding.json``
(the share under its old key, ``tight_share``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from aswarm.analysis.protocol import add_replay_arguments, filter_argument

CHANGED = 1e-3  # m/s: the filter changed a command by more than this


def attribute(active, u, cmd, flying, bounds):
    """Per drone [n]: which groups have a row binding at ``u`` [n, G] where the filter changed ``cmd`` (flying drones
    only), and the speed it took along ``cmd`` [n]. ``active`` [n, m] the QP's binding rows; ``bounds`` the groups'
    row offsets."""
    import jax.numpy as jnp

    changed = flying & (jnp.linalg.norm(u - cmd, axis=-1) > CHANGED)
    groups = jnp.stack([jnp.any(active[:, a:z], -1) for a, z in zip(bounds[:-1], bounds[1:])], -1)
    speed = jnp.linalg.norm(cmd, axis=-1)
    lost = jnp.maximum(speed - jnp.sum(u * cmd, -1) / jnp.maximum(speed, 1e-6), 0.0)
    return changed[:, None] & groups, jnp.where(changed, lost, 0.0)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_replay_arguments(p, episodes=100)
    p.add_argument("--out", type=Path, default=None, help="folder for filter_binding.json")
    args = p.parse_args(argv)
    if args.episodes <= 0:
        p.error(f"invalid --episodes={args.episodes}: allowed: > 0")
    fields = filter_argument(p, args.filter)

    import jax
    import jax.numpy as jnp
    import numpy as np

    from aswarm.analysis import evaluate
    from aswarm.analysis.protocol import EVAL_SEED
    from aswarm.core import barriers
    from aswarm.files import write_atomic

    seed = EVAL_SEED if args.seed is None else args.seed
    _, agent, restored = evaluate.load_agent(args.checkpoint, args.scenario, args.env, fields)
    env, params, obs_norm = agent.env, restored["params"], restored["obs_norm"]
    cfg = env.config
    layout = env.filter_layout if env.wide_filter else env.obs_layout
    groups = barriers.row_groups(layout)
    bounds = [int(x) for x in np.cumsum([0] + [k for _, k in groups])]
    zeros = jnp.zeros(len(groups))

    def episode(key):
        def body(carry, _):
            s, acc = carry
            cmd, _, _ = agent.policy(params, obs_norm, s.obs, None)
            res = agent.filter_commands(params, obs_norm, s.obs, cmd, env.cylinder_accel(s), s.filter_obs,
                                        env.applied_command(s))
            flying = env.flying(s) & ~s.tracker.collided
            tight, lost = attribute(res.active, res.u, cmd, flying, bounds)
            share = tight / jnp.maximum(tight.sum(-1, keepdims=True), 1)
            acc = {"flying": acc["flying"] + flying.sum(), "changed": acc["changed"] + jnp.any(tight, -1).sum(),
                   "tight": acc["tight"] + tight.sum(0), "lost": acc["lost"] + (share * lost[:, None]).sum(0),
                   "asked": acc["asked"] + jnp.where(flying, jnp.linalg.norm(cmd, axis=-1), 0.0).sum(),
                   "let_through": acc["let_through"] + jnp.where(flying, jnp.linalg.norm(res.u, axis=-1), 0.0).sum()}
            return (env.step(s, res.u), acc), None

        acc0 = {"flying": 0.0, "changed": 0.0, "tight": zeros, "lost": zeros, "asked": 0.0, "let_through": 0.0}
        return jax.lax.scan(body, (env.reset(key), acc0), None, length=cfg.max_steps)[0][1]

    keys = jax.random.split(jax.random.PRNGKey(seed), args.episodes)
    acc = jax.tree.map(lambda x: np.asarray(x, np.float64).sum(0), jax.jit(jax.vmap(episode))(keys))
    n = acc["flying"]
    result = {"checkpoint": args.checkpoint, "scenario": cfg.scenario, "env": args.env, "filter": fields,
              "episodes": args.episodes, "seed": seed, "flying_drone_steps": int(n),
              "changed_share": acc["changed"] / n, "asked_mps": acc["asked"] / n,
              "let_through_mps": acc["let_through"] / n,
              "groups": {g: {"tight_share": t / n, "speed_taken_mps": s / n}
                         for (g, _), t, s in zip(groups, acc["tight"], acc["lost"])}}
    print(f"{args.checkpoint} {fields or ''}: {args.episodes} episodes of seed {seed}, {int(n)} flying drone-steps; "
          f"the filter changed {result['changed_share']:.1%} of them with a binding row; speed asked "
          f"{result['asked_mps']:.2f} m/s, let through {result['let_through_mps']:.2f} m/s")
    for g, v in result["groups"].items():
        print(f"  {g:11s} binding on {v['tight_share']:6.1%} of flying steps, took {v['speed_taken_mps']:.3f} m/s")
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        write_atomic(args.out / "filter_binding.json", json.dumps(result, indent=1))
        print(f"wrote {args.out / 'filter_binding.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

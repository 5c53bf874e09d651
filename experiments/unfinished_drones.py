"""Where the drones of a timed-out episode end: which drones did not finish, how far from their goals, and alone or
in a crowd (issue #13's 64-drone cell: are its time-outs a jam, the wall, or the policy?).

    python experiments/unfinished_drones.py --checkpoint pretrained:obstacles16 --episodes 8 --seed 50000 \\
        --env num_agents=64 --env max_neighbours=3 --env filter_neighbours=8 --env cf.motor_tau_down=0.108 \\
        --env episode_seconds=30

Flies each episode as ``aswarm plot`` does (the deterministic, filtered policy; episode i from the i-th key of the
seed, so ``aswarm plot --episode-index i`` draws it) and prints, per episode, the drones that neither finished nor
collided: where they stopped, their goal, the gap to it, the nearest drone still flying and how far they moved in
the last 2 s; then a summary by start line (the crossing's lines, front first). Prints only; nothing is written.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

STILL_WINDOW_S = 2.0  # s: "moved" is the distance flown over the episode's last this many seconds


def unfinished(pos: np.ndarray, goal: np.ndarray, finished: np.ndarray, collided: np.ndarray, flying: np.ndarray,
               steps_back: int) -> list[dict]:
    """One row per drone that neither finished nor collided. pos [T, n, 3] (every instant), goal [n, 3],
    finished, collided [n] and flying [T, n] bool; ``steps_back`` instants define "moved"."""
    end = pos[-1]
    rows = []
    for d in np.flatnonzero(~finished & ~collided):
        others = np.flatnonzero(flying[-1] & (np.arange(len(end)) != d))
        near = float(np.min(np.linalg.norm(end[others] - end[d], axis=-1))) if len(others) else float("inf")
        rows.append(dict(drone=int(d), pos=end[d], goal=goal[d], gap=float(np.linalg.norm(end[d] - goal[d])),
                         nearest=near, moved=float(np.linalg.norm(end[d] - pos[max(0, len(pos) - 1 - steps_back), d]))))
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--scenario", default=None)
    ap.add_argument("--episodes", type=int, default=8)
    ap.add_argument("--seed", type=int, default=50000)
    ap.add_argument("--env", action="append", default=[], metavar="FIELD=VALUE")
    args = ap.parse_args(argv)
    if args.episodes < 1:
        ap.error(f"invalid --episodes {args.episodes}: must be >= 1")

    import jax

    from aswarm.analysis import evaluate, plots
    from aswarm.envs.scenarios import CROSSING_LANES

    _, agent, restored = evaluate.load_agent(args.checkpoint, args.scenario, args.env)
    keys = jax.random.split(jax.random.PRNGKey(args.seed), args.episodes)
    by_line: dict[int, int] = {}
    for i in range(args.episodes):
        ep = plots.record_episode(agent, restored["params"], restored["obs_norm"], keys[i])
        steps_back = int(STILL_WINDOW_S * ep.policy_freq)
        rows = unfinished(ep.pos, ep.layout.waypoints[:, -1], ep.finished, ep.collided, ep.flying, steps_back)
        hit = np.flatnonzero(ep.collided)
        print(f"episode {i}: {ep.time[-1]:.1f} s, {int(ep.finished.sum())} of {ep.num_agents} finished, "
              f"collided {[(int(d), ep.collision_kind[d]) for d in hit]}, {len(rows)} still flying")
        if len(hit):  # an episode ends at its first collision: the others were cut short, not stuck
            continue
        for r in rows:
            line = r["drone"] // CROSSING_LANES
            by_line[line] = by_line.get(line, 0) + 1
            print(f"  drone {r['drone']} (line {line}): at {np.round(r['pos'], 2)}, goal {np.round(r['goal'], 2)}, "
                  f"{r['gap']:.2f} m short, nearest flying drone {r['nearest']:.2f} m, moved {r['moved']:.2f} m "
                  f"in the last {STILL_WINDOW_S:.0f} s")
    print("unfinished drones of the episodes without a collision, by start line (0 = front): "
          + (", ".join(f"line {k}: {v}" for k, v in sorted(by_line.items())) or "none"))
    return 0


if __name__ == "__main__":
    sys.exit(main())

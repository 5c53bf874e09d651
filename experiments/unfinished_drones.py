"""Where the drones of a timed-out episode end: which drones did not finish, how far from their goals, and alone or
in a crowd (issue #13's 64-drone cell: are its time-outs a jam, the wall, or the policy?).

    python experiments/unfinished_drones.py --checkpoint pretrained:obstacles16 --episodes 8 --seed 50000 \\
        --env num_agents=64 --env max_neighbours=3 --env filter_neighbours=8 --env cf.motor_tau_down=0.108 \\
        --env episode_seconds=30

Flies each episode as ``aswarm plot`` does (the deterministic, filtered policy; episode i from the i-th key of the
seed, so ``aswarm plot --episode-index i`` draws it) and prints, per episode, the drones that neither finished nor
collided: where they stopped, their goal, the gap to it, the nearest drone still flying and how far they moved in
the last 2 s; then a summary by start line (the crossing's lines, front first). Prints only; nothing is written.

With ``--failed-of N`` it first flies N episodes in one batch, as ``aswarm eval`` does, and then replays only those
that failed there, printing each drone's legs (the time from one waypoint to the next) and the slowest: where a
timed-out race lost its time (issue #15's main command)

    python experiments/unfinished_drones.py --checkpoint runs/race --failed-of 1000 --seed 10000

and ``--only 6,42`` replays just those episodes of the split (the failures such a run listed), legs included.
On a track each episode also says how often its drones crossed their gate's plane beside the opening (which does
not count: the drone must turn back through it), and each unfinished drone on which side of its gate's plane it
ended.

A replay flies alone, and XLA fuses a lone episode's arithmetic differently from a batch's, so after a few
hundred steps it can end otherwise (a time-out of the batch may finish alone, late): its legs say where the
episode was slow, not that it fails every time.
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


def legs(target: np.ndarray, time: np.ndarray, open_end: np.ndarray | None = None) -> list[list[tuple[int, float]]]:
    """Per drone, ``(waypoint, seconds)`` for each waypoint it reached: the time since it reached the one before
    (the first from the episode's start, so it holds the start stagger). target [T, n] waypoint index, time [T] s;
    ``open_end`` [n] bool: those drones (still flying at the end) also get the leg they were on, timed to the end."""
    out = []
    for d in range(target.shape[1]):
        step = np.flatnonzero(np.diff(target[:, d]) > 0) + 1
        starts = np.concatenate([[time[0]], time[step]])
        drone_legs = [(int(target[k - 1, d]), float(t - t0)) for k, t, t0 in zip(step, time[step], starts)]
        if open_end is not None and open_end[d]:
            drone_legs.append((int(target[-1, d]), float(time[-1] - starts[-1])))
        out.append(drone_legs)
    return out


def gate_sides(pos: np.ndarray, target: np.ndarray, gate_pos: np.ndarray, gate_yaw: np.ndarray,
               half_opening: float) -> tuple[np.ndarray, np.ndarray]:
    """(passed beside [n], side [T, n]) on a track: how often each drone crossed its current gate's plane forwards
    outside the opening (which the race does not count: the drone must come back through it), and its signed
    distance along that gate's direction of passage at every instant (> 0: past the plane without having passed;
    NaN once every gate is passed). pos [T, n, 3], target [T, n]; gate_pos [G, 3], gate_yaw [G]."""
    from aswarm.core import geometry as geo

    g = len(gate_pos)
    k = np.minimum(target, g - 1)
    normal, centre = geo.horizontal(np.asarray(gate_yaw))[k], np.asarray(gate_pos)[k]  # [T, n, 3]
    side = np.where(target < g, np.sum((pos - centre) * normal, axis=-1), np.nan)
    forward = (side[:-1] < 0) & (side[1:] >= 0) & (target[1:] == target[:-1])  # crossed, and not counted
    inside = geo.gate_crossed(pos[:-1], pos[1:], centre[:-1], normal[:-1], half_opening)
    return np.sum(forward & ~inside, axis=0), side


def sweep_gap(pos: np.ndarray, center: np.ndarray, axis: np.ndarray, amplitude: np.ndarray, radius: np.ndarray,
              present: np.ndarray, drone_radius: float) -> float:
    """Surface gap (m) from a drone at ``pos`` [3] to the nearest moving cylinder's swept band (the segment its centre
    sweeps, ``center`` ± ``amplitude`` ``axis`` [M, 2], widened by its radius): how far it waits from where a
    cylinder can be. inf without a moving cylinder."""
    from aswarm.core.geometry import point_segment_distance

    moving = (amplitude > 0) & present
    if not moving.any():
        return float("inf")
    reach = amplitude[moving, None] * axis[moving]
    gap = point_segment_distance(pos[None, :2], center[moving] - reach, center[moving] + reach)
    return float(np.min(gap - radius[moving] - drone_radius))


def failed_episodes(agent, restored, episodes: int, key) -> np.ndarray:
    """Indices of the episodes that did not succeed when ``episodes`` of ``key`` fly as one batch (``aswarm eval``)."""
    from aswarm.analysis import evaluate

    rec, _, _ = evaluate.rollout_with_filter_stats(agent, restored["params"], restored["obs_norm"], agent.env,
                                                   episodes, key)
    success = np.asarray(rec["success"])
    print(f"{episodes} episodes in one batch: {success.mean():.1%} success, {int((success < 1).sum())} failed")
    return np.flatnonzero(success < 1)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--scenario", default=None)
    ap.add_argument("--episodes", type=int, default=8)
    ap.add_argument("--seed", type=int, default=50000)
    ap.add_argument("--env", action="append", default=[], metavar="FIELD=VALUE")
    ap.add_argument("--failed-of", type=int, default=0, metavar="N",
                    help="fly N episodes as one batch and replay the failed ones (instead of the first --episodes)")
    ap.add_argument("--only", default=None, metavar="I,J,...",
                    help="replay only these episodes of the --episodes (or --failed-of) split, e.g. the failures "
                         "another run listed")
    args = ap.parse_args(argv)
    try:
        only = None if args.only is None else [int(i) for i in args.only.split(",")]
    except ValueError:
        ap.error(f"invalid --only={args.only!r}: allowed: episode numbers separated by commas, such as 6,42")
    if args.episodes < 1:
        ap.error(f"invalid --episodes {args.episodes}: must be >= 1")
    if args.failed_of < 0:
        ap.error(f"invalid --failed-of {args.failed_of}: must be >= 1 (or 0: replay the first --episodes)")
    count = args.failed_of or args.episodes
    if only is not None and not all(0 <= i < count for i in only):
        ap.error(f"invalid --only={args.only!r}: allowed: episode numbers from 0 to {count - 1}")

    import jax

    from aswarm.analysis import evaluate, plots
    from aswarm.envs.scenarios import CROSSING_LANES

    _, agent, restored = evaluate.load_agent(args.checkpoint, args.scenario, args.env)
    key = jax.random.PRNGKey(args.seed)
    keys = jax.random.split(key, count)
    if only is not None:
        chosen = np.asarray(only)
    else:
        chosen = failed_episodes(agent, restored, count, key) if args.failed_of else np.arange(count)
    by_line: dict[int, int] = {}
    far_side, track = 0, False
    slowest_at: dict[int, int] = {}
    for i in chosen:
        ep = plots.record_episode(agent, restored["params"], restored["obs_norm"], keys[i])
        steps_back = int(STILL_WINDOW_S * ep.policy_freq)
        rows = unfinished(ep.pos, ep.layout.waypoints[:, -1], ep.finished, ep.collided, ep.flying, steps_back)
        hit = np.flatnonzero(ep.collided)
        print(f"episode {i}: {ep.time[-1]:.1f} s, {int(ep.finished.sum())} of {ep.num_agents} finished, "
              f"collided {[(int(d), ep.collision_kind[d]) for d in hit]}, {len(rows)} still flying")
        if args.failed_of:
            for d, drone_legs in enumerate(legs(ep.target, ep.time, ep.flying[-1])):
                if drone_legs:
                    worst = max(drone_legs, key=lambda leg: leg[1])
                    slowest_at[worst[0]] = slowest_at.get(worst[0], 0) + 1
                    print(f"  drone {d} legs (waypoint: s) " + ", ".join(f"{w}: {t:.1f}" for w, t in drone_legs)
                          + (" (the last still open)" if ep.flying[-1, d] else "")
                          + f"; slowest to waypoint {worst[0]}")
        if len(hit):  # an episode ends at its first collision: the others were cut short, not stuck
            continue
        track = ep.kind == "track" and len(ep.layout.gate_pos) > 0
        if track:
            beside, side = gate_sides(ep.pos, ep.target, ep.layout.gate_pos, ep.layout.gate_yaw, ep.gate_half_opening)
            print(f"  passed beside their gate (not counted, so turned back): {int(beside.sum())} times, by drones "
                  f"{np.flatnonzero(beside).tolist()}")
        for r in rows:
            line = r["drone"] // CROSSING_LANES
            by_line[line] = by_line.get(line, 0) + 1
            where = (f", {side[-1, r['drone']]:+.2f} m from gate {int(ep.target[-1, r['drone']])}'s plane "
                     "(+: past it, not passed)" if track else "")
            far_side += int(track and side[-1, r["drone"]] > 0)
            lay = ep.layout
            band = sweep_gap(r["pos"], lay.cyl_center, lay.cyl_axis, lay.cyl_amplitude, lay.cyl_radius,
                             lay.cyl_present, ep.drone_radius)
            waits = f", {band:.2f} m from a moving cylinder's swept band" if np.isfinite(band) else ""
            print(f"  drone {r['drone']} (line {line}): at {np.round(r['pos'], 2)}, goal {np.round(r['goal'], 2)}, "
                  f"{r['gap']:.2f} m short{where}, nearest flying drone {r['nearest']:.2f} m, moved "
                  f"{r['moved']:.2f} m in the last {STILL_WINDOW_S:.0f} s{waits}")
    print("unfinished drones of the episodes without a collision, by start line (0 = front): "
          + (", ".join(f"line {k}: {v}" for k, v in sorted(by_line.items())) or "none"))
    if track:
        print(f"of those, past their gate's plane without having passed it: {far_side}")
    if args.failed_of:
        print("each drone's slowest leg, by the waypoint it led to: "
              + (", ".join(f"{k}: {v}" for k, v in sorted(slowest_at.items())) or "none"))
    return 0


if __name__ == "__main__":
    sys.exit(main())

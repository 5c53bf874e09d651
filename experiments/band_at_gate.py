"""Which episodes of a moving-cylinder cell put a moving cylinder's swept band across a gate's exit, and how an
evaluation's failed episodes fall among them (issue #13's 1.5x cells: their time-outs wait at such a gate).

    python experiments/band_at_gate.py --checkpoint pretrained:dynamic --episodes 300 --seed 50000 \\
        --env min_moving=1 --env max_moving=1 --env moving_period=2.6666666666666665 \\
        --failed-log experiments/results/moving_cost_horizon/unfinished_dynamic1_fast_stored.log

Draws each episode's layout as ``aswarm eval`` and ``experiments/unfinished_drones.py`` do (episode i from the
i-th key of the seed's split) and, per episode, the gap from each gate's centre to the nearest moving cylinder's
swept band (the segment its centre sweeps, widened by its radius) among the cylinders standing past that gate's
plane: the gate whose exit is nearest a band, and that gap. ``--failed-log`` reads the episodes an
``unfinished_drones.py --failed-of N`` run replayed ("episode i: ..." lines) and splits them by that gap.
Prints only; nothing is written, nothing is flown.
"""

from __future__ import annotations

import argparse
import re
import sys

import numpy as np


def exit_gaps(gate_pos: np.ndarray, gate_yaw: np.ndarray, center: np.ndarray, axis: np.ndarray,
              amplitude: np.ndarray, radius: np.ndarray, present: np.ndarray) -> np.ndarray:
    """[G] surface gap (m) from each gate's centre to the nearest swept band of a moving cylinder standing past the
    gate's plane (its sweep's centre on the side the gate is passed towards); inf where there is none.
    gate_pos [G, 3], gate_yaw [G]; center, axis [M, 2]; amplitude, radius, present [M]."""
    from aswarm.core.geometry import horizontal, point_segment_distance

    normal = horizontal(np.asarray(gate_yaw))[:, :2]  # [G, 2] direction of passage
    rel = center[None] - gate_pos[:, None, :2]  # [G, M, 2]
    past = np.sum(rel * normal[:, None], -1) > 0
    reach = (amplitude[:, None] * axis)[None]
    gap = point_segment_distance(gate_pos[:, None, :2], center[None] - reach, center[None] + reach) - radius
    return np.min(np.where(past & ((amplitude > 0) & present)[None], gap, np.inf), axis=-1)


def replayed(log: str) -> list[int]:
    """The episodes an ``unfinished_drones.py`` run replayed, from its "episode i: ..." lines."""
    return [int(m.group(1)) for m in re.finditer(r"^episode (\d+):", log, re.MULTILINE)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", required=True, help="the run whose env (with --env) draws the layouts")
    ap.add_argument("--episodes", type=int, default=300)
    ap.add_argument("--seed", type=int, default=50000)
    ap.add_argument("--env", action="append", default=[], metavar="FIELD=VALUE")
    ap.add_argument("--failed-log", default=None, help="an unfinished_drones.py --failed-of log of the same split")
    ap.add_argument("--near", type=float, default=1.5, help="m: a band this close to a gate's exit is 'at the gate'")
    args = ap.parse_args(argv)
    if args.episodes < 1:
        ap.error(f"invalid --episodes {args.episodes}: must be >= 1")
    if not args.near > 0:
        ap.error(f"invalid --near {args.near}: must be > 0 m")
    failed = None
    if args.failed_log:
        try:
            with open(args.failed_log) as f:
                failed = replayed(f.read())
        except OSError as e:
            ap.error(f"invalid --failed-log {args.failed_log!r}: {e.strerror}")
        if any(i >= args.episodes for i in failed):
            ap.error(f"invalid --failed-log: it lists episode {max(failed)}, beyond --episodes {args.episodes}")

    import jax

    from aswarm.analysis import evaluate

    _, agent, _ = evaluate.load_agent(args.checkpoint, None, args.env)
    keys = jax.random.split(jax.random.PRNGKey(args.seed), args.episodes)
    lay = jax.tree.map(np.asarray, jax.jit(jax.vmap(agent.env.reset))(keys).layout)
    gaps = np.stack([exit_gaps(lay.gate_pos[i], lay.gate_yaw[i], lay.cyl_center[i], lay.cyl_axis[i],
                               lay.cyl_amplitude[i], lay.cyl_radius[i], lay.cyl_present[i])
                     for i in range(args.episodes)])  # [E, G]
    gate, nearest = np.argmin(gaps, -1), np.min(gaps, -1)
    at_gate = nearest < args.near
    print(f"{args.episodes} episodes: {int(at_gate.sum())} with a moving band within {args.near} m past a gate "
          f"(by gate: {np.bincount(gate[at_gate], minlength=gaps.shape[1]).tolist()})")
    if failed is not None:
        bad = np.zeros(args.episodes, bool)
        bad[failed] = True
        for name, sel in (("with a band at a gate", at_gate), ("without", ~at_gate)):
            k = int(sel.sum())
            print(f"  {name}: {k} episodes, {int((bad & sel).sum())} failed ({(bad & sel).sum() / max(k, 1):.1%})")
        print("  failed episodes (gate, gap m): " + ", ".join(
            f"{i} ({gate[i]}, {nearest[i]:.2f})" for i in failed))
    return 0


if __name__ == "__main__":
    sys.exit(main())

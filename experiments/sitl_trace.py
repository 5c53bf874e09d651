"""Why SITL loses an episode the simulator alone would not: the flight runtime's view of each failed episode against
the simulator's truth (issue #13's 16-drone SITL row).

    python experiments/sitl_trace.py --bundle BUNDLE --episodes 400 --seed 50000 --noise 0.002 --latency 40 \\
        --env num_agents=16 --env max_neighbours=3 --env filter_neighbours=8 --env cf.motor_tau_down=0.108

(BUNDLE: ``aswarm export --checkpoint pretrained:obstacles16 --env num_agents=16 --env max_neighbours=3 --env
filter_neighbours=8 --out BUNDLE``, as the safety matrix exports it.) Flies ``aswarm sitl``'s episodes through the
same runtime and sorts every episode the simulator counts as failed without a collision:

- *finished by the runtime alone*: the runtime had finished every drone (a finished drone stops: it lands) while the
  simulator, on the drones' true positions, holds some unfinished. Printed per such drone: the closest its true path
  came to its goal at the control steps, and how far from the goal the runtime's present (its estimate carried to the
  step's time: ``StepResult.position``) was when it finished it;
- *time-out*: drones the runtime had not finished either, each with its distance to its goal, the speed the policy
  asked for and the speed the filter let through (held: a deadlock before a hazard).

Goal scenarios only (a track's gates are another test). Prints only; nothing is written.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from aswarm.core.barriers import ESCAPE_MIN_SPEED

# A drone is held where it asked for more than the deadlock escape's least speed and the filter let through less than
# this share of it.
HELD = 0.25


class Recorder:
    """``run_sitl``'s ``on_step``: the true positions, the runtime's finished flags, positions and commands, and each
    episode's outcome as the simulator recorded it on the step it ended."""

    def __init__(self) -> None:
        self.true_pos, self.finished, self.seen_pos, self.nominal, self.sent = [], [], [], [], []
        self.success = self.collision = None

    def __call__(self, sensed, out) -> None:
        done = np.asarray(sensed.done) > 0
        if self.success is None:
            self.success = np.full(done.shape, np.nan)
            self.collision = np.full(done.shape, np.nan)
        first = done & np.isnan(self.success)
        self.success[first] = np.asarray(sensed.metrics["success"])[first]
        self.collision[first] = np.asarray(sensed.metrics["collision"])[first]
        if out is None:  # after the last step: the clock's episodes end here
            return
        self.true_pos.append(np.asarray(sensed.pos, np.float32))
        self.finished.append(out.finished.copy())
        self.seen_pos.append(out.position.astype(np.float32))
        self.nominal.append(out.nominal.astype(np.float32))
        self.sent.append(out.velocity.astype(np.float32))


def classify(rec: Recorder, goals: np.ndarray, goal_radius: float) -> list[dict]:
    """One entry per episode failed without a collision: its kind and its drones (see the module docstring)."""
    true_pos, finished = np.stack(rec.true_pos), np.stack(rec.finished)  # [T, B, n, ...]
    seen_pos, nominal, sent = np.stack(rec.seen_pos), np.stack(rec.nominal), np.stack(rec.sent)
    true_gap = np.linalg.norm(true_pos - goals, axis=-1)  # [T, B, n]
    seen_gap = np.linalg.norm(seen_pos - goals, axis=-1)
    out = []
    for w in np.nonzero((rec.success < 0.5) & (rec.collision < 0.5))[0]:
        last = finished[-1, w]
        if last.all():
            drones = [{"drone": int(d), "closest_true": float(true_gap[:, w, d].min()),
                       "at_finish": float(seen_gap[np.argmax(finished[:, w, d]), w, d])}
                      for d in np.nonzero(true_gap[:, w].min(0) >= goal_radius)[0]]
            out.append({"episode": int(w), "kind": "finished by the runtime alone", "drones": drones})
        else:
            drones = []
            for d in np.nonzero(~last)[0]:
                asked = float(np.linalg.norm(nominal[-1, w, d, :2]))
                let = float(np.linalg.norm(sent[-1, w, d, :2]))
                drones.append({"drone": int(d), "to_goal": float(true_gap[-1, w, d]), "asked": asked, "let": let,
                               "held": asked > ESCAPE_MIN_SPEED and let < HELD * asked})
            out.append({"episode": int(w), "kind": "time-out", "drones": drones})
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--bundle", required=True)
    p.add_argument("--episodes", type=int, default=400)
    p.add_argument("--seed", type=int, default=50000)
    p.add_argument("--noise", type=float, default=0.002, metavar="METRES")
    p.add_argument("--latency", type=float, default=40.0, metavar="MS")
    p.add_argument("--env", action="append", default=[], metavar="FIELD=VALUE")
    p.add_argument("--goal-margin", type=float, default=None, metavar="METRES",
                   help="the runtime's SafetyConfig.goal_margin (default: its default)")
    args = p.parse_args(argv)
    import jax

    from aswarm.flight import load_bundle, sitl

    bundle = load_bundle(args.bundle)
    if bundle.kind == "track":
        print(f"invalid bundle {args.bundle}: its scenario has gates; allowed: a bundle of a goal scenario",
              file=sys.stderr)
        return 2
    rec = Recorder()
    env = sitl.make_env(bundle, None, args.env)
    margin = {} if args.goal_margin is None else {"goal_margin": args.goal_margin}
    result = sitl.run_sitl(bundle, None, args.episodes, args.seed, noise=args.noise, latency_ms=args.latency,
                           env_overrides=args.env, on_step=rec, **margin)
    # The episodes' goals: run_sitl's simulator (cached: its reset is not compiled again) from the same key.
    plant = sitl.exact_drone(env, latency_ticks=sitl.split_latency(args.latency, env.config)[1])
    state, _ = sitl.simulator(plant.config, args.episodes).reset(jax.random.PRNGKey(args.seed))
    goals = np.asarray(state.layout.waypoints[:, :, 0])
    failed = classify(rec, goals, env.config.goal_radius)
    print(f"{args.episodes} episodes: success {100 * result['success_rate']:.2f} %, collision episodes "
          f"{round(result['collision_rate'] * args.episodes)}, failed without a collision {len(failed)}")
    for kind in ("finished by the runtime alone", "time-out"):
        these = [f for f in failed if f["kind"] == kind]
        print(f"\n{kind}: {len(these)}")
        for f in these:
            for d in f["drones"]:
                if kind == "time-out":
                    print(f"  episode {f['episode']} drone {d['drone']}: {d['to_goal']:.2f} m from its goal, asked "
                          f"{d['asked']:.2f} m/s, let through {d['let']:.2f}{' (held)' if d['held'] else ''}")
                else:
                    print(f"  episode {f['episode']} drone {d['drone']}: its true path came within "
                          f"{d['closest_true']:.3f} m of its goal; the runtime's present was {d['at_finish']:.3f} m "
                          "from it when it finished it")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""What the firmware-faithful drone costs the trainer: end-to-end env-steps/s of the default race training on the
firmware drone with randomisation (the PID, and Mellinger), against the geometric drone of before issue #12, in one
process, alternating.

    python experiments/drone_cost_bench.py --rounds 3 --updates 10

Prints one Markdown row per drone (median over rounds) and their ratio.
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax

from aswarm.agents.config import TrainConfig
from aswarm.agents.train import make_train
from aswarm.envs.config import LEGACY_DRONE


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--updates", type=int, default=10, help="updates per timed chunk")
    args = p.parse_args()
    drones = {"firmware PID + randomisation (default)": (),
              "firmware Mellinger + randomisation": (("controller", "mellinger"),),
              "geometric (before issue #12)": tuple(LEGACY_DRONE.items())}
    programs, rates = {}, {name: [] for name in drones}
    for name, overrides in drones.items():
        config = TrainConfig(scenario="race", env_overrides=overrides, devices=1)
        _, init, chunk, _ = make_train(config)
        t0 = time.perf_counter()
        ts = jax.jit(init)(jax.random.PRNGKey(0))
        run = jax.jit(chunk, static_argnums=1)
        ts, _ = run(ts, args.updates)
        jax.block_until_ready(ts)
        programs[name] = (run, ts, config.steps_per_update, time.perf_counter() - t0)
    for _ in range(args.rounds):
        for name, (run, ts, per_update, compile_s) in programs.items():
            t0 = time.perf_counter()
            ts, _ = run(ts, args.updates)
            jax.block_until_ready(ts)
            rates[name].append(args.updates * per_update / (time.perf_counter() - t0))
            programs[name] = (run, ts, per_update, compile_s)
    print("| drone | env-steps/s (median) | compile + first chunk (s) |")
    print("|---|---:|---:|")
    for name in drones:
        print(f"| {name} | {statistics.median(rates[name]):,.0f} | {programs[name][3]:.0f} |")
    geometric = statistics.median(rates["geometric (before issue #12)"])
    for name in list(drones)[:2]:
        print(f"ratio {name} / geometric: {statistics.median(rates[name]) / geometric:.2f}")


if __name__ == "__main__":
    main()

"""Throughput of two checkouts in the same session (BENCHMARKS.md, "Issue #11: before and after").

Run it once per tree, alternating, each in a fresh process so that the package comes from that tree:

    git worktree add /tmp/old d3eaf8b
    for t in /tmp/old . /tmp/old .; do PYTHONPATH=$t .venv/bin/python experiments/before_after_bench.py $t train; done

Prints one JSON line: env-steps/s of the race env at 1024 worlds (``env``) and/or of the default trainer
(``train``, 10 updates after the compile, every CPU core a device as ``aswarm train`` lays it out). ``rollout
[WORLDS]``: the best of 10 of the trainer's environment half alone (one rollout of random commands, 256 worlds by
default, laid out as ``aswarm train`` lays them), in seconds; with
``XLA_FLAGS=--xla_force_host_platform_device_count=1`` and 128 worlds, one device's share of it.
"""

import json
import os
import sys

os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=2")

try:
    from aswarm.analysis import bench
except ImportError:  # trees from before the layout of issue #11
    from aswarm import bench
try:
    from aswarm.analysis.train_bench import time_trainer
except ImportError:  # trees from before issue #15 kept it in bench
    time_trainer = bench.time_trainer
from aswarm.agents.config import TrainConfig


def main() -> None:
    tree, which = sys.argv[1], (sys.argv[2] if len(sys.argv) > 2 else "both")
    out = {"tree": tree}
    if which in ("env", "both"):
        out["env_1024"] = bench.time_env("race", 1024, 100).env_steps_per_s
    if which in ("train", "both"):
        config = TrainConfig(scenario="race", method="attention_cbf")
        out["train"] = time_trainer(config, updates=10)["env_steps_per_s"]
    if which == "rollout":
        out["rollout_s"] = rollout_seconds(int(sys.argv[3]) if len(sys.argv) > 3 else 256)
    print(json.dumps(out), flush=True)


def rollout_seconds(worlds: int, repeat: int = 10) -> float:
    import time

    import jax

    from aswarm.analysis.train_bench import _env_rollout, _program

    config = TrainConfig(scenario="race", method="attention_cbf", num_envs=worlds)
    trainer, ts, _, _ = _program(config, jax.random.PRNGKey(0))
    run, key = _env_rollout(trainer.agent.env, config), jax.random.PRNGKey(1)
    jax.block_until_ready(run(ts.env_state, key))
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(run(ts.env_state, key))
        best = min(best, time.perf_counter() - t0)
    return best


if __name__ == "__main__":
    main()

"""The JaxMARL wrapper's throughput against the native env's, measured in the same run.

``python -m aswarm.analysis.interfaces_bench`` times one jitted rollout of each (``lax.scan`` over steps,
``vmap`` over worlds, random commands, auto-reset) and writes the section "JaxMARL wrapper vs native env" of
BENCHMARKS.md. The two rollouts draw the same commands; the wrapper's also splits a key per world and step, as
JaxMARL's API asks. Runs alternate and the best of each is kept, so load from other processes on a shared machine
hits both alike.
"""

from __future__ import annotations

import argparse
import datetime
import os
import time
from collections.abc import Callable
from pathlib import Path

import jax

from aswarm.analysis.bench import machine, write_section
from aswarm.envs import jaxmarl as marl
from aswarm.envs.swarm_env import SwarmEnv
from aswarm.envs.wrappers import wrap_for_training

START, END = "<!-- jaxmarl-bench:start -->", "<!-- jaxmarl-bench:end -->"
TARGET = 0.9  # the wrapper's share of the native env-steps/s (issue #16)


def _commands(key: jax.Array, worlds: int, env: SwarmEnv) -> jax.Array:
    return jax.random.uniform(key, (worlds, env.num_agents, 3), minval=-1.0, maxval=1.0) * env.config.max_speed


def native_rollout(env: SwarmEnv, worlds: int, steps: int) -> Callable:
    """A jitted ``run(key)``: ``steps`` env steps of ``worlds`` auto-resetting native worlds."""
    wenv = wrap_for_training(env, worlds)

    def run(key):
        def body(carry, _):
            state, k = carry
            k, ka = jax.random.split(k)
            state = wenv.step(state, _commands(ka, worlds, env))
            return (state, k), state.done.sum()

        (state, _), dones = jax.lax.scan(body, (wenv.reset(key), key), None, length=steps)
        return state.obs, dones.sum()

    return jax.jit(run)


def jaxmarl_rollout(menv: marl.SwarmMultiAgentEnv, worlds: int, steps: int) -> Callable:
    """The same rollout through the JaxMARL API: dict actions and observations, a step key per world."""

    def run(key):
        obs, state = jax.vmap(menv.reset)(jax.random.split(key, worlds))

        def body(carry, _):
            obs, state, k = carry
            k, ka, ks = jax.random.split(k, 3)
            cmd = _commands(ka, worlds, menv.env)
            actions = {a: cmd[:, i] for i, a in enumerate(menv.agents)}
            obs, state, _, dones, _ = jax.vmap(menv.step)(jax.random.split(ks, worlds), state, actions)
            return (obs, state, k), dones["__all__"].sum()

        (obs, _, _), dones = jax.lax.scan(body, (obs, state, key), None, length=steps)
        return obs, dones.sum()

    return jax.jit(run)


def compare(scenario: str = "obstacles", worlds: int = 256, steps: int = 200, repeats: int = 5,
            **overrides) -> dict:
    """Env-steps/s of both rollouts (best of ``repeats`` alternating runs) and compile seconds."""
    menv = marl.make(scenario, **overrides)
    load = [os.getloadavg()[0]]
    fns = {"native": native_rollout(menv.env, worlds, steps), "jaxmarl": jaxmarl_rollout(menv, worlds, steps)}
    compiled, compile_s, best = {}, {}, {}
    for name, fn in fns.items():
        t0 = time.perf_counter()
        compiled[name] = fn.lower(jax.random.PRNGKey(0)).compile()
        compile_s[name] = time.perf_counter() - t0
        jax.block_until_ready(compiled[name](jax.random.PRNGKey(1)))  # warm-up
    for r in range(repeats):
        for name, fn in compiled.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn(jax.random.PRNGKey(2 + r)))
            best[name] = min(best.get(name, float("inf")), time.perf_counter() - t0)
    rate = {name: worlds * steps / s for name, s in best.items()}
    load.append(os.getloadavg()[0])
    return dict(scenario=scenario, agents=menv.num_agents, worlds=worlds, steps=steps, repeats=repeats,
                steps_per_s=rate, compile_s=compile_s, load=load, ratio=rate["jaxmarl"] / rate["native"])


def section(result: dict, command: str) -> str:
    r = result
    verdict = "met" if r["ratio"] >= TARGET else "NOT met"
    load = ", ".join(f"{x:.1f}" for x in r["load"])
    rows = [f"| {label} | {r['steps_per_s'][k]:,.0f} | {r['compile_s'][k]:.1f} |"
            for k, label in (("native", "native `wrap_for_training`"), ("jaxmarl", "JaxMARL `SwarmMultiAgentEnv`"))]
    # Two trailing spaces: Markdown's line break, as in the other sections.
    head = [f"Command: `{command}`", f"Machine: {machine()}", f"Date: {datetime.date.today().isoformat()}",
            f"Scenario `{r['scenario']}`: {r['agents']} drones, {r['worlds']} worlds, {r['steps']} env steps of random "
            "commands with auto-reset inside one jitted `lax.scan` over `vmap`; best of "
            f"{r['repeats']} alternating runs, compile time apart; 1-minute load average before and after: {load} "
            f"on {os.cpu_count()} cores (other processes share this machine)."]
    return "\n".join([
        "## JaxMARL wrapper vs native env (issue #16)", "", "  \n".join(head), "",
        "| env | env-steps/s | compile s |", "|---|---:|---:|", *rows, "",
        f"The wrapper runs at **{100 * r['ratio']:.1f} %** of the native env-steps/s "
        f"(target ≥ {100 * TARGET:.0f} %: {verdict}).",
    ]) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m aswarm.analysis.interfaces_bench", description=__doc__.split("\n")[0])
    p.add_argument("--scenario", default="obstacles")
    p.add_argument("--worlds", type=int, default=256)
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", default="BENCHMARKS.md", help="the file whose section is written ('-': print only)")
    args = p.parse_args(argv)
    for name in ("worlds", "steps", "repeats"):
        if getattr(args, name) < 1:
            p.error(f"invalid --{name} {getattr(args, name)}: allowed: an integer >= 1")
    try:
        result = compare(args.scenario, args.worlds, args.steps, args.repeats)
    except ValueError as e:  # an unknown scenario, before anything compiles
        p.error(str(e))
    command = (f"python -m aswarm.analysis.interfaces_bench --scenario {args.scenario} --worlds {args.worlds} "
               f"--steps {args.steps} --repeats {args.repeats}")
    body = section(result, command)
    print(body)
    if args.out != "-":
        write_section(Path(args.out), body, START, END)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

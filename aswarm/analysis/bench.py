"""``aswarm bench``: environment throughput, written to BENCHMARKS.md.

Env-steps/s of a scenario inside ``lax.scan`` at several world counts,
compile time apart, and the same for crazyflow (a peer simulator) measured in
the same run when it is installed, as a ratio.
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from aswarm import envs


@dataclasses.dataclass
class Row:
    name: str
    worlds: int
    steps: int
    compile_s: float
    run_s: float
    agents: int
    sim_dt: float  # simulated seconds per env step: the policy's (ours) or the controller's (crazyflow) period

    @property
    def sim_seconds_per_s(self) -> float:
        """Simulated flight per wall second, summed over worlds: the rate that compares simulators stepping
        at different control rates (one of our env steps is 40 ms of flight, one of crazyflow's 10 ms)."""
        return self.env_steps_per_s * self.sim_dt

    @property
    def env_steps_per_s(self) -> float:
        return self.worlds * self.steps / self.run_s

    @property
    def drone_steps_per_s(self) -> float:
        return self.env_steps_per_s * self.agents


def rollout_fn(env, worlds: int, steps: int):
    """A jitted random-action rollout of ``steps`` env steps in ``worlds`` auto-resetting worlds."""
    wenv = envs.wrap_for_training(env, worlds)
    n = env.num_agents

    def run(key):
        state = wenv.reset(key)

        def body(carry, _):
            s, k = carry
            k, ka = jax.random.split(k)
            a = jax.random.uniform(ka, (worlds, n, 3), minval=-1.0, maxval=1.0) * env.config.max_speed
            s = wenv.step(s, a)
            return (s, k), s.done.sum()

        (state, _), dones = jax.lax.scan(body, (state, key), None, length=steps)
        return state.obs, dones.sum()

    return jax.jit(run)


def time_env(scenario: str, worlds: int, steps: int, **overrides) -> Row:
    env = envs.make(scenario, **overrides)
    fn = rollout_fn(env, worlds, steps)
    t0 = time.perf_counter()
    compiled = fn.lower(jax.random.PRNGKey(0)).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(jax.random.PRNGKey(1)))  # warm-up
    t0 = time.perf_counter()
    jax.block_until_ready(compiled(jax.random.PRNGKey(2)))
    return Row(f"aswarm {scenario}", worlds, steps, compile_s, time.perf_counter() - t0, env.num_agents,
               env.config.dt)


def time_stages(scenario: str, worlds: int, steps: int) -> dict[str, float]:
    """Seconds per env step of the batch for physics alone, physics + controller, and the whole step."""
    from aswarm.envs.dynamics import drone_state, physics_step
    from aswarm.envs.onboard_controller import velocity_controller

    env = envs.make(scenario)
    cfg = env.config
    n = env.num_agents
    wenv = envs.wrap_for_training(env, worlds)
    state0 = jax.jit(wenv.reset)(jax.random.PRNGKey(0))
    rpm = jnp.full((worlds, n, 4), cfg.cf.hover_rpm)

    def physics_only(data):
        def body(d, _):
            return jax.vmap(lambda x, r: physics_step(env.mjx_model, x, r, cfg.cf))(d, rpm), None
        return jax.lax.scan(body, data, None, length=steps * cfg.substeps)[0]

    def with_controller(data):
        def body(d, _):
            r = jax.vmap(lambda x: velocity_controller(drone_state(x, n), jnp.zeros((n, 3)), cfg.gains, cfg.cf))(d)
            return jax.vmap(lambda x, rr: physics_step(env.mjx_model, x, rr, cfg.cf))(d, r), None
        return jax.lax.scan(body, data, None, length=steps * cfg.substeps)[0]

    def full(state):
        def body(s, _):
            return wenv.step(s, jnp.zeros((worlds, n, 3))), None
        return jax.lax.scan(body, state, None, length=steps)[0]

    out = {}
    for name, fn, arg in (("mjx.step only", physics_only, state0.data), ("+ controller", with_controller, state0.data),
                          ("+ collisions, gates, obs, reward, auto-reset", full, state0)):
        f = jax.jit(fn)
        jax.block_until_ready(f(arg))
        t0 = time.perf_counter()
        jax.block_until_ready(f(arg))
        out[name] = (time.perf_counter() - t0) / steps
    return out


CRAZYFLOW_SCRIPT = Path(__file__).with_name("crazyflow_bench.py")


def time_crazyflow(worlds: int, steps: int, python: str | None = None, contacts: bool = False) -> Row | str:
    """Run the crazyflow benchmark in a subprocess (``contacts``: with its own collision check after every
    control step); returns a Row or why it could not run."""
    python = python or os.environ.get("ASWARM_CRAZYFLOW_PYTHON", sys.executable)
    cmd = [python, str(CRAZYFLOW_SCRIPT), "--worlds", str(worlds), "--steps", str(steps)]
    cmd += ["--contacts"] if contacts else []
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    except (OSError, subprocess.TimeoutExpired) as e:
        return f"crazyflow benchmark did not run: {e}"
    if out.returncode != 0:
        last = (out.stderr.strip().splitlines() or ["no output"])[-1]
        return f"crazyflow benchmark failed: {last}"
    r = json.loads(out.stdout.strip().splitlines()[-1])
    name = "crazyflow (state ctrl" + (", its collision check)" if contacts else ")")
    return Row(name, r["worlds"], r["steps"], r["compile_s"], r["run_s"], r["agents"], 1.0 / r["ctrl_freq"])


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    backend = jax.default_backend()
    if backend != "cpu":  # name the accelerator, not only its platform
        backend = f"{backend} ({jax.device_count()} x {jax.devices()[0].device_kind})"
    return f"{cpu}, {os.cpu_count()} cores, jax {jax.__version__} on {backend}"


def ensure_peer_venv(venv: Path) -> str | None:
    """Python of a virtualenv with crazyflow (created on first use), or None if it cannot be had."""
    python = venv / "bin" / "python"
    if not (venv / ".crazyflow-installed").exists():
        print(f"creating {venv} with crazyflow (first use) ...", flush=True)
        steps = [[sys.executable, "-m", "venv", str(venv)],
                 [str(python), "-m", "pip", "install", "-q", CRAZYFLOW_REQUIREMENT]]
        for cmd in steps:
            if subprocess.run(cmd, capture_output=True).returncode != 0:
                return None
        (venv / ".crazyflow-installed").touch()
    return str(python)


CRAZYFLOW_REQUIREMENT = "crazyflow>=0.4,<0.5"
START, END = "<!-- env-bench:start -->", "<!-- env-bench:end -->"


def write_section(path: Path, body: str, start: str = START, end: str = END) -> None:
    """Replace the marked section of ``path`` (or append it), leaving the rest of the file as it was."""
    text = path.read_text() if path.exists() else "# Benchmarks\n"
    block = f"{start}\n{body.rstrip()}\n{end}"
    if start in text and end in text:
        text = text[: text.index(start)] + block + text[text.index(end) + len(end):]
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)


def main(args) -> int:
    from aswarm.envs import make

    env = make(args.scenario)  # validates the scenario before any compile
    cfg = env.config
    rows: list[Row] = []
    print(f"{args.scenario}: {env.num_agents} drones, physics {cfg.sim_freq} Hz, controller {cfg.ctrl_freq} Hz, "
          f"policy {cfg.policy_freq} Hz ({cfg.substeps} MJX steps per env step)", flush=True)
    for w in args.worlds:
        r = time_env(args.scenario, w, args.steps)
        rows.append(r)
        print(f"  {w:5d} worlds: {r.env_steps_per_s:12,.0f} env-steps/s  {r.drone_steps_per_s:12,.0f} drone-steps/s"
              f"  (compile {r.compile_s:.1f} s)", flush=True)
    stage_worlds = 1024 if 1024 in args.worlds else max(args.worlds)
    stages = time_stages(args.scenario, stage_worlds, min(args.steps, 50))
    peers: list[Row] = []
    peer_note = "skipped (--no-peer)"
    if not args.no_peer:
        python = ensure_peer_venv(args.peer_venv)
        if python is None:
            peer_note = f"crazyflow could not be installed into {args.peer_venv}"
        else:
            peer_note = ""
            for contacts in (False, True):
                for w in args.worlds:
                    r = time_crazyflow(w, args.steps, python, contacts)
                    if isinstance(r, str):
                        peer_note = r
                        break
                    peers.append(r)
                    print(f"  {r.name} {w:5d} worlds: {r.env_steps_per_s:12,.0f} env-steps/s", flush=True)
    if peer_note:
        print(f"  crazyflow: {peer_note}")

    lines = [
        "## Environment throughput (`make bench`)",
        "",
        f"Command: `aswarm bench --scenario {args.scenario} --worlds {','.join(map(str, args.worlds))} "
        f"--steps {args.steps}`  ",
        f"Machine: {machine()}  ",
        f"Date: {time.strftime('%Y-%m-%d')}  ",
        f"Scenario `{args.scenario}`: {env.num_agents} drones, {cfg.num_cylinders} cylinders, {cfg.num_gates} gates; "
        f"physics (MJX, every sub-step) {cfg.sim_freq} Hz, onboard controller {cfg.ctrl_freq} Hz, policy "
        f"{cfg.policy_freq} Hz = {cfg.substeps} `mjx.step` per env step; random actions, auto-reset, "
        f"{args.steps} env steps inside one `lax.scan`, compile time apart.",
        "",
        "Ratios compare **simulated seconds per wall second** (env-steps/s times the simulated time of a step:",
        f"{cfg.dt * 1000:.0f} ms for ours, one control period for crazyflow), summed over worlds, against crazyflow",
        "without and with its own collision check in the same run. Ours always includes observations, collisions",
        "(every physics step), gates, rewards and auto-reset.",
        "",
        "| simulator | worlds | env-steps/s | simulated s / s | compile s | vs crazyflow | vs crazyflow + collisions |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    bare = {p.worlds: p for p in peers if "collision" not in p.name}
    checked = {p.worlds: p for p in peers if "collision" in p.name}

    def ratio(r: Row, peer: dict) -> str:
        p = peer.get(r.worlds)
        return f"{r.sim_seconds_per_s / p.sim_seconds_per_s:.2f}x" if p else "-"

    for r in rows + peers:
        lines.append(f"| {r.name} | {r.worlds} | {r.env_steps_per_s:,.0f} | {r.sim_seconds_per_s:,.0f} | "
                     f"{r.compile_s:.1f} | {ratio(r, bare)} | {ratio(r, checked)} |")
    if peer_note:
        lines += ["", f"crazyflow: {peer_note}."]
    total = list(stages.values())[-1]
    lines += [
        "",
        f"Where the time goes ({stage_worlds} worlds, seconds per batched env step, each stage timed on its own):",
        "",
        "| stage | s / env step | share |",
        "|---|---:|---:|",
    ]
    prev = 0.0
    for name, sec in stages.items():
        lines.append(f"| {name} | {sec - prev:.5f} | {(sec - prev) / total:.0%} |")
        prev = sec
    lines.append(f"| total | {total:.5f} | 100% |")
    write_section(args.out, "\n".join(lines))
    print(f"wrote {args.out}")
    return 0

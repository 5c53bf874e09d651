"""Standalone throughput benchmark of the peer simulator crazyflow (``pip install crazyflow``).

Runs under crazyflow's own interpreter (crazyflow 0.4 excludes jax 0.10.2), so it imports nothing
from ``aswarm``. It builds one ``crazyflow.Sim`` with ``--worlds`` worlds of 4 drones, the state
(position/velocity setpoint) controller at 100 Hz and analytic first-principles dynamics at 500 Hz,
then times ``--steps`` control steps; one control step is ``sim_freq // ctrl_freq`` physics steps.

Modes (the JSON ``note`` says which ran):
  scan:   crazyflow's functional API (``functional.state_control`` + the pure step function
          returned by ``Sim.build_step_fn``) inside one jitted ``jax.lax.scan`` over control steps,
          with a new setpoint per control step. Same structure as our scanned env-steps (default).
  nsteps: one call ``Sim.step(n_steps=steps * substeps)`` with a fixed setpoint (crazyflow's own
          fused scan, no per-step commands; upper bound).
  loop:   the pattern of crazyflow's own benchmark: per control step ``Sim.state_control`` +
          ``Sim.step(substeps)`` + ``block_until_ready`` from Python.

The last stdout line is one JSON object: worlds, steps, agents, compile_s, run_s, sim_freq, ctrl_freq,
crazyflow_version, note.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from typing import Any

AGENTS = 4
SIM_FREQ = 500
CTRL_FREQ = 100


def _import_crazyflow() -> tuple[Any, Any, Any, Any, Any]:
    """Import crazyflow (its mujoco.mjx import prints to stdout, so send that to stderr)."""
    try:
        with contextlib.redirect_stdout(sys.stderr):
            import crazyflow
            import crazyflow.sim.functional as cf_functional
            import jax
            import jax.numpy as jnp
            import mujoco
    except ImportError:
        print("crazyflow is not installed: pip install crazyflow", file=sys.stderr)
        sys.exit(1)
    # MuJoCo's default warning handler appends to ./MUJOCO_LOG.TXT; keep the caller's cwd clean.
    mujoco.set_mju_user_warning(lambda msg: print(f"MuJoCo warning: {msg}", file=sys.stderr))
    return crazyflow, cf_functional, jax, jnp, crazyflow.Control


def _setpoints(jnp: Any, base_pos: Any, t: Any) -> Any:
    """State commands [pos, vel, acc, quat(xyzw), ang_vel] of shape (W, 4, 16): hover 1 m up, small circle."""
    w, a = base_pos.shape[:2]
    offset = jnp.stack([0.1 * jnp.sin(t), 0.1 * jnp.cos(t), jnp.asarray(1.0, dtype=base_pos.dtype)])
    cmd = jnp.zeros((w, a, 16), dtype=base_pos.dtype)
    cmd = cmd.at[..., 0:3].set(base_pos + offset)
    return cmd.at[..., 12].set(1.0)  # identity quaternion, qw last


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, build the sim, compile, time the run and print the JSON result line."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", type=int, default=1024)
    parser.add_argument("--steps", type=int, default=200, help="control steps to time")
    parser.add_argument("--mode", choices=("scan", "nsteps", "loop"), default="scan")
    parser.add_argument("--device", default=None, help="jax platform for crazyflow (default: jax default backend)")
    parser.add_argument("--contacts", action="store_true",
                        help="scan mode: crazyflow's own collision check (its mjx sync and mjx.collision, as "
                             "Sim.contacts runs them) after every control step, any contact counted")
    args = parser.parse_args(argv)
    if args.worlds < 1 or args.steps < 1:
        parser.error("--worlds and --steps must be positive")

    crazyflow, F, jax, jnp, Control = _import_crazyflow()
    device = args.device or jax.default_backend()

    sim = crazyflow.Sim(
        n_worlds=args.worlds,
        n_drones=AGENTS,
        control=Control.state,
        freq=SIM_FREQ,
        state_freq=CTRL_FREQ,
        device=device,
    )
    sim_freq, ctrl_freq = int(sim.freq), int(sim.control_freq)
    substeps = sim_freq // ctrl_freq
    base_pos = sim.data.states.pos  # (W, 4, 3), drones laid out on a grid per world
    steps = args.steps

    if args.mode == "scan":
        step_fn = sim.build_step_fn()  # pure (data, n_steps) -> data, jitted, lax.scan over physics steps
        if args.contacts:
            from crazyflow.sim.sim import sync_sim2mjx

        def control_step(carry: Any, t: Any) -> tuple[Any, None]:
            data, mjx_data, hits = carry
            data = F.state_control(data, _setpoints(jnp, base_pos, t * (1.0 / ctrl_freq)))
            data = step_fn(data, n_steps=substeps)
            if args.contacts:
                data, mjx_data = sync_sim2mjx(data, mjx_data, sim.mjx_model)
                hits = hits + jnp.sum(mjx_data._impl.contact.dist < 0)
            return (data, mjx_data, hits), None

        @jax.jit
        def rollout(data: Any, mjx_data: Any) -> Any:
            carry = (data, mjx_data, jnp.zeros((), jnp.int32))
            return jax.lax.scan(control_step, carry, jnp.arange(steps, dtype=jnp.float32))[0]

        t0 = time.perf_counter()
        compiled = rollout.lower(sim.data, sim.mjx_data).compile()
        warm = jax.block_until_ready(compiled(sim.data, sim.mjx_data))
        compile_s = time.perf_counter() - t0
        del warm
        t0 = time.perf_counter()  # sim.data is untouched (no donation), so this restarts from the initial state
        final, _, hits = jax.block_until_ready(compiled(sim.data, sim.mjx_data))
        run_s = time.perf_counter() - t0
        how = "functional.state_control + Sim.build_step_fn() in one jitted lax.scan over control steps"
        if args.contacts:
            how += f", crazyflow's collision check after each ({int(hits)} contacts)"
    elif args.mode == "nsteps":
        sim.state_control(_setpoints(jnp, base_pos, jnp.float32(0.0)))
        t0 = time.perf_counter()
        sim.step(steps * substeps)
        jax.block_until_ready(sim.data)
        compile_s = time.perf_counter() - t0
        sim.reset()
        sim.state_control(_setpoints(jnp, base_pos, jnp.float32(0.0)))
        jax.block_until_ready(sim.data)
        t0 = time.perf_counter()
        sim.step(steps * substeps)
        jax.block_until_ready(sim.data)
        run_s = time.perf_counter() - t0
        final = sim.data
        how = f"one Sim.step(n_steps={steps * substeps}) call, fixed setpoint"
    else:
        cmds = [_setpoints(jnp, base_pos, jnp.float32(i / ctrl_freq)) for i in range(steps)]
        jax.block_until_ready(cmds)
        t0 = time.perf_counter()
        sim.state_control(cmds[0])
        sim.step(substeps)
        jax.block_until_ready(sim.data)
        compile_s = time.perf_counter() - t0
        sim.reset()
        jax.block_until_ready(sim.data)
        t0 = time.perf_counter()
        for cmd in cmds:
            sim.state_control(cmd)
            sim.step(substeps)
            jax.block_until_ready(sim.data)
        run_s = time.perf_counter() - t0
        final = sim.data
        how = f"Python loop of Sim.state_control + Sim.step({substeps}) + block_until_ready"

    z = float(jnp.mean(final.states.pos[..., 2]))
    if not jnp.all(jnp.isfinite(final.states.pos)):
        print("crazyflow produced non-finite positions", file=sys.stderr)
        return 2
    note = (
        f"mode={args.mode}: {how}; {substeps} physics steps per control step; "
        f"state controller, {sim.dynamics} dynamics, {sim.integrator} integrator, device={device}, "
        f"jax {jax.__version__}; mean z after run {z:.3f} m (setpoint 1.0)"
    )
    result = {
        "worlds": args.worlds,
        "steps": steps,
        "agents": AGENTS,
        "compile_s": round(compile_s, 4),
        "run_s": round(run_s, 6),
        "sim_freq": sim_freq,
        "ctrl_freq": ctrl_freq,
        "crazyflow_version": str(getattr(crazyflow, "__version__", "unknown")),
        "contacts": bool(args.contacts),
        "note": note,
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())

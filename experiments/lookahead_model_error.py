"""How far the drone that flies is from the single integrator its safety filter assumes, through a look-ahead point.

    python experiments/lookahead_model_error.py                        # 128 drones, 60 s of random commands
    python experiments/lookahead_model_error.py --drones 16 --seconds 10 --out /tmp/lookahead

The filter's rows hold for a point q that moves at the command, q' = u (``core.barriers.obs_rows``). Its look-ahead
q = p + c1 v makes that exact for a velocity that follows the command with a first-order lag (c1 the time constant);
a velocity with a second-order response, (1/w²) v'' + (2z/w) v' + v = u, needs q = p + c1 v + c2 a (c1 = 2z/w,
c2 = 1/w²; a the acceleration), for which q' = u again. Which does the simulated Crazyflie follow? One drone per world
(``obstacles`` without cylinders: the default drone, firmware PID, rotor lag, randomised latency and constants) flies
random piecewise-constant velocity commands (a new one every 0.2-1 s, up to 2 m/s horizontally, 0.3 vertically) until
its episode ends. Over the control steps it flew, the horizontal (Δp + c1 Δv + c2 Δa) / dt is fitted to the command
it flew (after the command acceleration limit) by least squares, with c2 = 0 and free, and the fit's error
|q' − u| reported: rms, 99th percentile, largest; beside them the filter's own look-ahead (0.9 times the drone's
measured 63 % rise time, c2 = 0). ``a`` is MJX's acceleration of the last physics step; a last fit takes, in its
place, the acceleration the drone's attitude gives (``aswarm.core.geometry.tilt_accel``: what motion capture sees
of every drone, its neighbours' too, without differentiating positions twice). Prints a table;
``--out`` also writes ``lookahead_model_error.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from aswarm.core.geometry import tilt_accel
from aswarm.files import write_atomic


def fit(p, v, a, u, dt: float, keep, filter_c1: float | None = None, tilt=None):
    """Least-squares look-ahead coefficients over horizontal steps, first order (c1) and second order (c1, c2).

    p, v, a, u [W, T, 3]: positions, velocities, accelerations after each control step and the command flown during
    it; keep [W, T] bool: steps to use (a step t uses samples t and t + 1, both kept). Returns
    {"first": (coeffs, errors), "second": ..., "none": (None, errors)} with errors the |q' − u| [N] of each fit, and
    "filter": ([filter_c1], errors) for a given first-order look-ahead, and "tilt" the second-order fit with the
    acceleration ``tilt`` [W, T, 3] (``aswarm.core.geometry.tilt_accel``) in place of ``a``.
    """
    dp, dv, da, dtilt = (np.diff(x, axis=1)[..., :2] / dt for x in (p, v, a, a if tilt is None else tilt))
    m = keep[:, 1:] & keep[:, :-1]
    target = (u[:, 1:, :2] - dp)[m].reshape(-1)
    dv, da, dtilt = (x[m].reshape(-1, 1) for x in (dv, da, dtilt))
    out = {"none": (None, np.linalg.norm(target.reshape(-1, 2), axis=-1))}
    if filter_c1 is not None:
        out["filter"] = (np.array([filter_c1]), np.linalg.norm((target - filter_c1 * dv[:, 0]).reshape(-1, 2), axis=-1))
    fits = [("first", dv), ("second", np.concatenate([dv, da], 1))]
    for name, x in fits + ([] if tilt is None else [("tilt", np.concatenate([dv, dtilt], 1))]):
        coeffs = np.linalg.lstsq(x, target, rcond=None)[0]
        out[name] = (coeffs, np.linalg.norm((target - x @ coeffs).reshape(-1, 2), axis=-1))
    return out


def commands(key, worlds: int, steps: int, hold: tuple[int, int], speed: float, climb: float):
    """[worlds, steps, 3] piecewise-constant random velocity commands, each held hold[0] to hold[1] control steps."""
    import jax
    import jax.numpy as jnp

    segments = steps // hold[0] + 1
    k_hold, k_dir, k_speed, k_climb = jax.random.split(key, 4)
    ends = jnp.cumsum(jax.random.randint(k_hold, (worlds, segments), hold[0], hold[1] + 1), -1)
    which = jax.vmap(lambda e: jnp.searchsorted(e, jnp.arange(steps), side="right"))(ends)
    ang = jax.random.uniform(k_dir, (worlds, segments), minval=-jnp.pi, maxval=jnp.pi)
    s = jax.random.uniform(k_speed, (worlds, segments), maxval=speed)
    vz = jax.random.uniform(k_climb, (worlds, segments), minval=-climb, maxval=climb)
    seg = jnp.stack([s * jnp.cos(ang), s * jnp.sin(ang), vz], -1)
    return jnp.take_along_axis(seg, which[..., None], 1)


def fly(worlds: int, seconds: float, seed: int):
    """(p, v, a, u, keep, dt, env config) of ``worlds`` single drones flying random commands; keep: the steps before
    an end."""
    import jax

    from aswarm import envs

    env = envs.make("obstacles", num_agents=1, num_obstacles=0)
    dt = 1.0 / env.config.policy_freq
    steps = round(seconds / dt)
    k_cmd, k_reset = jax.random.split(jax.random.PRNGKey(seed))
    cmd = commands(k_cmd, worlds, steps, (round(0.2 / dt), round(1.0 / dt)), 2.0, 0.3)

    def episode(key, cmd_seq):
        def body(s, c):
            s = env.step(s, c[None])
            return s, (s.data.qpos[:3], s.data.qvel[:3], s.data.qacc[:3], s.data.qpos[3:7],
                       env.applied_command(s)[0], s.done)

        return jax.lax.scan(body, env.reset(key), cmd_seq)[1]

    p, v, a, quat, u, done = map(np.asarray, jax.jit(jax.vmap(episode))(jax.random.split(k_reset, worlds), cmd))
    return p, v, a, tilt_accel(quat), u, ~np.cumsum(done, 1).astype(bool), dt, env.config


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drones", type=int, default=128, help="worlds of one drone each")
    ap.add_argument("--seconds", type=float, default=60.0, help="length of the command sequence")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, help="folder for lookahead_model_error.json")
    args = ap.parse_args(argv)
    if args.drones < 1 or args.seconds <= 0:
        ap.error(f"invalid --drones {args.drones} / --seconds {args.seconds}: allowed: >= 1 / > 0")
    from aswarm.analysis.step_response import characterise
    from aswarm.core.safety import SafetyFilterConfig

    p, v, a, tilt, u, keep, dt, config = fly(args.drones, args.seconds, args.seed)
    drone = characterise(config)
    fits = fit(p, v, a, u, dt, keep, SafetyFilterConfig().fitted(drone.lag_xy, drone.lag_z).lookahead_xy, tilt)
    rows = {}
    for name, (coeffs, err) in fits.items():
        rows[name] = {"coeffs_s": None if coeffs is None else [float(c) for c in coeffs],
                      "rms": float(np.sqrt(np.mean(err**2))), "p99": float(np.percentile(err, 99)),
                      "max": float(err.max()), "steps": int(err.size)}
    print(f"{args.drones} drones, {args.seconds:g} s of random commands, {rows['none']['steps']} control steps flown")
    print("| look-ahead | c1 (s) | c2 (s²) | rms m/s | p99 m/s | max m/s |\n|---|---:|---:|---:|---:|---:|")
    for name, label in (("none", "none (q = p)"), ("filter", "p + c1 v, the filter's look-ahead"),
                        ("first", "p + c1 v, fitted"), ("second", "p + c1 v + c2 a, fitted"),
                        ("tilt", "p + c1 v + c2 a_tilt, fitted (a from the attitude)")):
        r, c = rows[name], rows[name]["coeffs_s"] or []
        cols = [f"{x:.3f}" for x in c] + ["–"] * (2 - len(c))
        print(f"| {label} | {' | '.join(cols)} | {r['rms']:.3f} | {r['p99']:.3f} | {r['max']:.3f} |")
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        write_atomic(args.out / "lookahead_model_error.json",
                     json.dumps({"args": {k: str(x) if isinstance(x, Path) else x for k, x in vars(args).items()},
                                 "fits": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

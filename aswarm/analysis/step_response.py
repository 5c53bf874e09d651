"""Step responses of the onboard controller models, measured in the environment itself.

One drone, no obstacles, nothing randomised, the policy rate raised to the onboard controller's (one command per
controller tick), a constant velocity command from hover. What the safety filter and the MPC assume of the
drone (its velocity lag and its braking) comes from here (:func:`characterise`), not from hand-set numbers.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from aswarm.envs import registry
from aswarm.envs.config import EnvConfig
from aswarm.envs.randomization import OFF
from aswarm.envs.swarm_env import SwarmEnv


def probe_config(config: EnvConfig) -> EnvConfig:
    """``config``'s drone (controller, rates, constants, gains) alone in the hover arena, sampled at every
    controller tick, nothing randomised, and a goal too small to reach (a drone that arrives stops flying). The
    command steps as given (no acceleration limit): the lag measured is the drone's to the command it receives."""
    drone = {f: getattr(config, f)
             for f in ("controller", "sim_freq", "ctrl_freq", "cf", "gains", "pid", "mellinger", "reference_leash")}
    return registry.preset("hover", **drone, policy_freq=config.ctrl_freq, randomize=OFF, command_accel_limit=0.0,
                           episode_seconds=30.0,
                           goal_radius=1e-9, arena_low=(-50.0, -50.0, 0.0), arena_high=(50.0, 50.0, 20.0))


@functools.lru_cache(maxsize=8)
def _rollout(config: EnvConfig, seconds: float):
    env = SwarmEnv(config)
    steps = int(round(seconds * config.policy_freq))

    @jax.jit
    def run(start_vel, cmd):
        s = env.reset(jax.random.PRNGKey(0))
        d = s.data
        s = s.replace(data=d.replace(qvel=d.qvel.at[:3].set(start_vel)))

        def body(s, _):
            s = env.step(s, cmd[None])
            quat = s.data.qpos[3:7]
            tilt = 2 * jnp.arcsin(jnp.clip(jnp.linalg.norm(quat[1:3]), 0.0, 1.0))
            return s, (s.data.qvel[:3], tilt, s.onboard.rpm[0])

        return jax.lax.scan(body, s, None, length=steps)[1]

    return run, steps


def step_response(config: EnvConfig, cmd, start_vel=(0.0, 0.0, 0.0), seconds: float = 2.0) -> dict:
    """The drone of ``config`` (see :func:`probe_config`) commanded ``cmd`` (m/s) from ``start_vel``: time (s),
    velocity [T, 3] (m/s), tilt [T] (deg) and rotor speeds [T, 4] (RPM) after each controller tick."""
    probe = probe_config(config)
    run, steps = _rollout(probe, seconds)
    vel, tilt, rpm = jax.device_get(run(jnp.asarray(start_vel, jnp.float32), jnp.asarray(cmd, jnp.float32)))
    return {"t": np.arange(1, steps + 1) / probe.policy_freq, "vel": np.asarray(vel),
            "tilt": np.rad2deg(np.asarray(tilt)), "rpm": np.asarray(rpm)}


@dataclasses.dataclass(frozen=True)
class Characteristics:
    """What a velocity-command planner needs to know of the drone, measured on it."""

    lag_xy: float  # s, to 63 % of a 0 -> 1 m/s step in x
    lag_z: float  # s, the same in z
    accel_xy: float  # m/s^2, the highest horizontal acceleration (0.1 s mean) of a 0 -> 2 m/s step
    climb: float  # m/s^2, the same upwards, of a 0 -> 2 m/s step in z
    sink: float  # m/s^2 (> 0), the same downwards, of a 0 -> -2 m/s step
    stop_distance: float  # m flown from 2 m/s in x after a zero command


def _rise(t: np.ndarray, v: np.ndarray, target: float) -> float:
    hit = np.nonzero(v >= 0.632 * target)[0]
    return float(t[hit[0]]) if hit.size else float("inf")


def _peak_accel(r: dict, axis: int, sign: float, window: float = 0.1) -> float:
    dt = float(r["t"][1] - r["t"][0])
    v = np.concatenate([[0.0], sign * r["vel"][:, axis]])
    w = max(int(round(window / dt)), 1)
    return float(np.max(v[w:] - v[:-w]) / (w * dt))


@functools.lru_cache(maxsize=16)
def characterise(config: EnvConfig) -> Characteristics:
    """Step responses of ``config``'s drone (all from one compiled rollout), reduced to :class:`Characteristics`."""
    x, z = step_response(config, (1.0, 0.0, 0.0)), step_response(config, (0.0, 0.0, 1.0))
    fast = step_response(config, (2.0, 0.0, 0.0))
    up, down = step_response(config, (0.0, 0.0, 2.0)), step_response(config, (0.0, 0.0, -2.0))
    stop = step_response(config, (0.0, 0.0, 0.0), start_vel=(2.0, 0.0, 0.0), seconds=2.0)
    dt = float(stop["t"][0])
    # The drone flew at 2 m/s until the command changed; it moves on its velocity before each sample.
    distance = dt * (2.0 + float(np.sum(stop["vel"][:-1, 0])))
    return Characteristics(lag_xy=_rise(x["t"], x["vel"][:, 0], 1.0), lag_z=_rise(z["t"], z["vel"][:, 2], 1.0),
                           accel_xy=_peak_accel(fast, 0, 1.0), climb=_peak_accel(up, 2, 1.0),
                           sink=_peak_accel(down, 2, -1.0), stop_distance=distance)

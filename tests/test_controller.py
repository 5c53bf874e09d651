"""Onboard velocity controller: step responses and altitude hold, in MJX."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from aswarm.envs.crazyflie import CrazyflieParams
from aswarm.envs.dynamics import DroneState, drone_state, physics_model, physics_step, set_drone_state
from aswarm.envs.mjx_import import mjx
from aswarm.envs.onboard_controller import ControllerGains, velocity_controller

CF = CrazyflieParams()
SIM = 250


@functools.partial(jax.jit, static_argnums=1)
def fly(cmd, steps=2 * SIM):
    _, mx = physics_model(1, SIM, CF)
    s0 = DroneState(pos=jnp.array([[0.0, 0.0, 1.0]]), quat=jnp.array([[1.0, 0, 0, 0]]), vel=jnp.zeros((1, 3)),
                    ang_vel=jnp.zeros((1, 3)))
    d = set_drone_state(mjx.make_data(mx), s0)

    def body(d, _):
        rpm = velocity_controller(drone_state(d, 1), cmd[None], ControllerGains(), CF)
        d = physics_step(mx, d, rpm, CF)
        s = drone_state(d, 1)
        return d, (s.pos[0], s.vel[0], rpm[0])

    return jax.lax.scan(body, d, None, length=steps)[1]


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_velocity_step_settles_fast_without_overshoot(axis):
    target = 1.5
    pos, vel, rpm = (np.asarray(x) for x in fly(jnp.zeros(3).at[axis].set(target)))
    v = vel[:, axis]
    t = np.arange(1, len(v) + 1) / SIM
    outside = np.nonzero(np.abs(v - target) > 0.1 * target)[0]
    settle = t[outside[-1]] if len(outside) else 0.0
    assert settle < 1.0
    assert v.max() <= 1.2 * target
    saturated = (rpm >= CF.max_rpm * 0.999) | (rpm <= 1.0)
    late = saturated.any(1) & (t > settle)
    assert not late.any(), "motor saturation outlasts the transient"
    assert np.abs(vel[-1] - np.eye(3)[axis] * target).max() < 0.02


def test_holds_altitude_and_position_at_zero_command():
    pos, vel, _ = (np.asarray(x) for x in fly(jnp.zeros(3)))
    assert np.abs(pos[:, 2] - 1.0).max() < 1e-3
    assert np.abs(pos[:, :2]).max() < 1e-3


def test_recovers_from_a_tilted_start():
    _, mx = physics_model(1, SIM, CF)
    q = np.array([np.cos(0.25), np.sin(0.25), 0.0, 0.0])  # 0.5 rad roll
    s0 = DroneState(pos=jnp.array([[0.0, 0.0, 1.0]]), quat=jnp.asarray(q)[None], vel=jnp.zeros((1, 3)),
                    ang_vel=jnp.zeros((1, 3)))

    @jax.jit
    def run():
        def body(d, _):
            rpm = velocity_controller(drone_state(d, 1), jnp.zeros((1, 3)), ControllerGains(), CF)
            d = physics_step(mx, d, rpm, CF)
            return d, None
        return drone_state(jax.lax.scan(body, set_drone_state(mjx.make_data(mx), s0), None, length=SIM)[0], 1)

    s = run()
    assert abs(float(s.quat[0, 0])) > 0.999  # level again
    assert float(jnp.linalg.norm(s.vel)) < 0.05

"""Onboard cascaded velocity controller, as the Crazyflie firmware runs it.

World-frame velocity command -> desired acceleration -> desired attitude and
collective thrust -> body rates -> torques -> motor speeds. The attitude stage
is the geometric SO(3) law of Lee et al. (2010); gains are chosen for a
well-damped response at the default 250 Hz rate (see ``tests/test_controller.py``).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from aswarm.envs.crazyflie import CrazyflieParams
from aswarm.envs.dynamics import DroneState, drone_params, quat_to_rotmat
from aswarm.envs.params import DroneParams, GainParams


@dataclasses.dataclass(frozen=True)
class ControllerGains:
    kp_vel_xy: float = 4.0  # 1/s, velocity error -> horizontal acceleration
    kp_vel_z: float = 4.0  # 1/s
    max_tilt_deg: float = 30.0  # caps horizontal acceleration at g tan(tilt)
    max_climb_accel: float = 7.0  # m/s^2 above hover
    max_sink_accel: float = 5.0  # m/s^2 below hover
    kp_att: float = 16.0  # 1/s, attitude error -> body rate
    kp_att_yaw: float = 6.0  # 1/s
    kp_rate: float = 90.0  # 1/s, body-rate error -> angular acceleration
    max_rate: float = 10.0  # rad/s, body-rate command limit


def _vee(m: jax.Array) -> jax.Array:
    return jnp.stack([m[..., 2, 1], m[..., 0, 2], m[..., 1, 0]], -1)


def velocity_controller(
    state: DroneState,
    vel_cmd: jax.Array,
    gains: GainParams | ControllerGains,
    cf: DroneParams | CrazyflieParams,
    yaw_cmd: float | jax.Array = 0.0,
) -> jax.Array:
    """Motor speeds [n, 4] (RPM) that track world-frame velocities ``vel_cmd`` [n, 3].

    ``gains`` and ``cf`` are data (``EnvParams.gains``, ``EnvParams.cf``); the frozen config dataclasses are
    converted as ``EnvParams.from_config`` does."""
    cf = drone_params(cf)
    if not isinstance(gains, GainParams):
        gains = GainParams.from_gains(gains, cf.gravity)
    g = cf.gravity
    acc = jnp.concatenate(
        [gains.kp_vel_xy * (vel_cmd[:, :2] - state.vel[:, :2]), gains.kp_vel_z * (vel_cmd[:, 2:] - state.vel[:, 2:])],
        -1,
    )
    max_h = gains.max_accel_xy
    h_norm = jnp.linalg.norm(acc[:, :2], axis=-1, keepdims=True)
    acc_xy = acc[:, :2] * jnp.minimum(1.0, max_h / jnp.maximum(h_norm, 1e-9))
    acc_z = jnp.clip(acc[:, 2:], -gains.max_sink_accel, gains.max_climb_accel)
    force = cf.mass * jnp.concatenate([acc_xy, acc_z + g], -1)  # [n, 3] desired thrust vector

    rot = quat_to_rotmat(state.quat)  # [n, 3, 3]
    b3 = force / jnp.linalg.norm(force, axis=-1, keepdims=True)
    yaw = jnp.broadcast_to(jnp.asarray(yaw_cmd, force.dtype), force.shape[:1])
    b1c = jnp.stack([jnp.cos(yaw), jnp.sin(yaw), jnp.zeros_like(yaw)], -1)
    b2 = jnp.cross(b3, b1c)
    b2 = b2 / jnp.linalg.norm(b2, axis=-1, keepdims=True)
    rot_des = jnp.stack([jnp.cross(b2, b3), b2, b3], -1)

    err_mat = jnp.einsum("nji,njk->nik", rot_des, rot) - jnp.einsum("nji,njk->nik", rot, rot_des)
    e_rot = 0.5 * _vee(err_mat)  # body frame
    k_att = jnp.stack([gains.kp_att, gains.kp_att, gains.kp_att_yaw]).astype(force.dtype)
    rate_cmd = jnp.clip(-k_att * e_rot, -gains.max_rate, gains.max_rate)

    inertia = cf.inertia.astype(force.dtype)
    w = state.ang_vel
    # (inertia kp_rate) first: XLA folded the constants' product so before the gains were data.
    torque = (inertia * gains.kp_rate) * (rate_cmd - w) + jnp.cross(w, inertia * w)
    thrust = jnp.sum(force * rot[:, :, 2], -1, keepdims=True)  # projected on the current body z

    wrench = jnp.concatenate([thrust, torque], -1)
    motor_thrust = wrench @ jnp.asarray(cf.inv_mixer, force.dtype).T
    motor_thrust = jnp.clip(motor_thrust, 0.0, cf.max_motor_thrust)
    # Times the reciprocal: what XLA compiled the division by the constant kf into before kf was data.
    return jnp.sqrt(motor_thrust * (1.0 / cf.kf))

"""The Crazyflie firmware's Mellinger controller, ``controller_mellinger`` (``stabilizer.controller = 2``), in JAX.

Mellinger tracks full-state setpoints (position, velocity, acceleration, orientation): its position law only
runs when the setpoint's x mode is absolute, and a velocity setpoint (``send_velocity_world_setpoint``) falls
into its "unknown combination of modes" branch, which holds the height with no horizontal thrust. So on this
drone the velocity command reaches the firmware as a full-state setpoint whose position is the command
integrated over time (``aswarm.core.command.advance_reference``), its velocity the command, its acceleration
zero and its orientation level with yaw 0: what ``aswarm fly`` streams with ``send_full_state_setpoint``.

Read from Bitcraze's ``crazyflie-firmware`` (commit 2a18fc2, 2026-08-21):

- ``src/modules/src/controller/controller_mellinger.c``: every gain and limit below (``g_self``), the whole
  controller at ``ATTITUDE_RATE`` (500 Hz); position PID on the force, its direction the desired body z axis,
  the rotation error as the vee of ``Rdes^T R - R^T Rdes`` (no factor 1/2) with its y negated, the angular
  velocity D term on the measured rates, the moments clamped to +-32000, yaw output ``-M.z``, no torques and
  the integrals reset while the thrust is not positive;
- ``src/platform/interface/platform_defaults_cf2.h``: ``CF_MASS`` 0.029 kg, the mass the controller assumes
  (``ctrlMel.mass``; not the simulated drone's);
- ``src/utils/interface/physicalConstants.h``: ``GRAVITY_MAGNITUDE`` 9.81;
- ``src/modules/src/crtp_commander_generic.c``: ``fullStateDecoder`` (position, velocity and acceleration
  absolute; attitude rates from the packet, here 0; the orientation as a quaternion, here level).

The power distribution and the motors' thrust map are ``controller_pid``'s (``firmware_pid``): the same
``powerDistributionLegacy`` and battery-compensated map follow every legacy-mode controller.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from aswarm.envs.firmware_pid import power_distribution

MOMENT_LIMIT = 32000.0  # the moments' clamp before the power distribution


@struct.dataclass
class FirmwareMellinger:
    """Gains and limits of ``controller_mellinger`` (firmware defaults). A frozen dataclass in
    ``EnvConfig.mellinger``, and, its leaves as arrays, data in ``EnvParams.mellinger``."""

    mass: float = 0.029  # kg (CF_MASS): the feed-forward's mass, the firmware's, not the drone's
    gravity: float = 9.81  # m/s^2 (GRAVITY_MAGNITUDE)
    mass_thrust: float = 132000.0  # PWM per newton (massThrust)
    kp_xy: float = 0.4  # N/m
    kd_xy: float = 0.2  # N/(m/s)
    ki_xy: float = 0.05  # N/(m s)
    i_range_xy: float = 2.0  # m s
    kp_z: float = 1.25
    kd_z: float = 0.4
    ki_z: float = 0.05
    i_range_z: float = 0.4
    kr_xy: float = 70000.0  # PWM per unit of rotation error (kR_xy)
    kw_xy: float = 20000.0  # PWM per rad/s (kw_xy)
    ki_m_xy: float = 0.0
    i_range_m_xy: float = 1.0
    kr_z: float = 60000.0
    kw_z: float = 12000.0
    ki_m_z: float = 500.0
    i_range_m_z: float = 1500.0
    kd_omega_rp: float = 200.0  # PWM per rad/s^2, roll and pitch


@struct.dataclass
class MellingerState:
    """The controller's memory, one row per drone."""

    integ: jax.Array  # [n, 6] position error integrals (m s), then the rotation error integrals (s)
    prev_rates: jax.Array  # [n, 2] last roll and pitch rates (rad/s) in the firmware's frame, for the D term


def _rates(ang_vel: jax.Array) -> jax.Array:
    """[n, 3] body rates (rad/s, right-handed) -> roll and pitch rates as the controller reads them: (gyro.x,
    -gyro.y), the legacy frame in which nose up is positive pitch."""
    return ang_vel[:, :2] * jnp.array([1.0, -1.0], ang_vel.dtype)


def initial_state(ang_vel: jax.Array, hover: jax.Array, mel: FirmwareMellinger) -> MellingerState:
    """The memory of a drone that has been hovering at its setpoint: its z integral supplies what the
    feed-forward ``mass * gravity`` lacks for the thrust command ``hover`` (PWM units) that carries it, within
    the firmware's limit, as it would have settled to after take-off."""
    n = ang_vel.shape[0]
    z_integ = jnp.clip((hover / mel.mass_thrust - mel.mass * mel.gravity) / mel.ki_z, -mel.i_range_z, mel.i_range_z)
    integ = jnp.zeros((n, 6)).at[:, 2].set(z_integ)
    return MellingerState(integ=integ, prev_rates=_rates(ang_vel))


def control(state: MellingerState, rot: jax.Array, ang_vel: jax.Array, pos: jax.Array, vel: jax.Array,
            sp_pos: jax.Array, sp_vel: jax.Array, mel: FirmwareMellinger,
            dt: float) -> tuple[MellingerState, jax.Array]:
    """One tick (``1 / dt`` Hz, the firmware's 500) of ``controllerMellinger`` on a full-state setpoint
    (``sp_pos``, ``sp_vel`` [n, 3]; zero acceleration, level orientation, yaw 0, zero rates): motor commands
    [n, 4] (PWM units) for drones at ``pos``, ``vel`` [n, 3] with attitude ``rot`` [n, 3, 3] (body -> world)
    and body rates ``ang_vel`` [n, 3] (rad/s)."""
    r_err, v_err = sp_pos - pos, sp_vel - vel
    i_range = jnp.stack([mel.i_range_xy, mel.i_range_xy, mel.i_range_z])
    i_pos = jnp.clip(state.integ[:, :3] + r_err * dt, -i_range, i_range)
    kp = jnp.stack([mel.kp_xy, mel.kp_xy, mel.kp_z])
    kd = jnp.stack([mel.kd_xy, mel.kd_xy, mel.kd_z])
    ki = jnp.stack([mel.ki_xy, mel.ki_xy, mel.ki_z])
    weight = jnp.stack([jnp.zeros_like(mel.mass), jnp.zeros_like(mel.mass), mel.mass * mel.gravity])
    force = weight + kp * r_err + kd * v_err + ki * i_pos  # [n, 3] desired force (N)

    z_axis = rot[:, :, 2]
    thrust = mel.mass_thrust * jnp.sum(force * z_axis, -1)  # the force along the body z axis, in PWM units
    z_des = force / jnp.linalg.norm(force, axis=-1, keepdims=True)
    x_c = jnp.broadcast_to(jnp.array([1.0, 0.0, 0.0], force.dtype), force.shape)  # yaw 0
    y_des = jnp.cross(z_des, x_c)
    y_des = y_des / jnp.linalg.norm(y_des, axis=-1, keepdims=True)
    x_des = jnp.cross(y_des, z_des)
    rot_des = jnp.stack([x_des, y_des, z_des], -1)
    err = jnp.einsum("nji,njk->nik", rot_des, rot) - jnp.einsum("nji,njk->nik", rot, rot_des)
    e_rot = jnp.stack([err[:, 2, 1], -err[:, 0, 2], err[:, 1, 0]], -1)  # the vee, y in the firmware's frame

    rates = _rates(ang_vel)
    e_w = -jnp.stack([rates[:, 0], rates[:, 1], ang_vel[:, 2]], -1)  # the setpoint's rates are 0
    d_rp = -(rates - state.prev_rates) / dt
    i_range_m = jnp.stack([mel.i_range_m_xy, mel.i_range_m_xy, mel.i_range_m_z])
    i_m = jnp.clip(state.integ[:, 3:] - e_rot * dt, -i_range_m, i_range_m)
    k_r = jnp.stack([mel.kr_xy, mel.kr_xy, mel.kr_z])
    k_w = jnp.stack([mel.kw_xy, mel.kw_xy, mel.kw_z])
    k_im = jnp.stack([mel.ki_m_xy, mel.ki_m_xy, mel.ki_m_z])
    moment = -k_r * e_rot + k_w * e_w + k_im * i_m
    moment = moment.at[:, :2].add(mel.kd_omega_rp * d_rp)

    # No thrust: no torques, and the integrals start again (controllerMellingerReset).
    on = (thrust > 0)[:, None]
    out = jnp.where(on, jnp.clip(moment, -MOMENT_LIMIT, MOMENT_LIMIT), 0.0)
    motors = power_distribution(jnp.maximum(thrust, 0.0), out[:, 0], out[:, 1], -out[:, 2])
    integ = jnp.where(on, jnp.concatenate([i_pos, i_m], -1), 0.0)
    return MellingerState(integ=integ, prev_rates=rates), motors

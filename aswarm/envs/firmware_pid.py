"""The Crazyflie firmware's default controller, ``controller_pid``, in velocity mode, in JAX.

What a stock Crazyflie runs when it is streamed ``send_velocity_world_setpoint``: a velocity PID (100 Hz) that
outputs roll and pitch in degrees and a thrust in PWM units, an attitude PID and a body-rate PID (500 Hz)
whose outputs the legacy power distribution mixes into four motor commands, and the battery-compensated
map from a motor command to its thrust. Read from Bitcraze's ``crazyflie-firmware`` (commit 2a18fc2,
2026-08-21):

- ``src/platform/interface/platform_defaults_cf2.h``: every gain and limit below, ``THRUST_MAX``/``THRUST_MIN``;
- ``src/modules/src/controller/position_controller_pid.c``: ``velocityController`` (tilt limit times the
  1.1 ``rpLimitOverhead`` on the PID's output, then clamped to the limit; thrust = raw * 1000 + base, at least
  ``PID_VEL_THRUST_MIN``; the z PID's output limit 65535 / 2 / 1000);
- ``src/utils/src/pid.c``: ``pidUpdate`` (P on the error, D on the measurement, I clamped to its limit,
  output clamped where a limit is set; default integration limit 5000);
- ``src/modules/src/controller/attitude_pid_controller.c``: rate outputs saturated to int16;
- ``src/modules/src/controller/controller_pid.c``: ``control->yaw = -yaw output``; the rate loop reads
  ``(gyro.x, -gyro.y, gyro.z)`` and the estimators report ``pitch = -pitch`` (``kalman_core.c``: the legacy
  CF2 frame, nose up is positive pitch);
- ``src/modules/src/power_distribution_quadrotor.c``: ``powerDistributionLegacy`` and ``powerDistributionCap``;
- ``src/drivers/src/motors.c``: ``motorsCompensateBatteryVoltage``: a command c is ``c / 65535 * THRUST_MAX``
  newtons, and no thrust below ``THRUST_MIN``.

Angles are in degrees and rates in degrees per second inside, as in the firmware. The low-pass filters on
the D terms are off by default in the firmware (``ATTITUDE_RATE_LPF_ENABLE false``) or act on a zero gain
(the velocity loops' kd is 0), so there are none here. Firmware motor M1..M4 are this project's motors 0..3
(front-right counter-clockwise, rear-right, rear-left, front-left).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

PWM_MAX = 65535.0  # UINT16_MAX: motor commands and the thrust command
INT16_MAX = 32767.0  # the rate loop's outputs are saturated to int16


@struct.dataclass
class FirmwarePid:
    """Gains and limits of ``controller_pid`` (cf2 defaults). A frozen dataclass in ``EnvConfig.pid``, and,
    its leaves as arrays, data in ``EnvParams.pid`` (randomised within tolerances per episode)."""

    vel_xy_kp: float = 25.0  # deg of tilt per m/s (PID_VEL_X_KP, PID_VEL_Y_KP)
    vel_xy_ki: float = 1.0  # deg per m (PID_VEL_X_KI)
    vel_z_kp: float = 25.0  # thrust / 1000 per m/s (PID_VEL_Z_KP)
    vel_z_ki: float = 15.0  # (PID_VEL_Z_KI)
    vel_i_limit: float = 5000.0  # DEFAULT_PID_INTEGRATION_LIMIT
    max_tilt_deg: float = 20.0  # PID_VEL_ROLL_MAX, PID_VEL_PITCH_MAX
    tilt_overhead: float = 1.1  # rpLimitOverhead: the PID's own output limit, before the clamp to max_tilt_deg
    thrust_base: float = 36000.0  # PID_VEL_THRUST_BASE (PWM units)
    thrust_min: float = 20000.0  # PID_VEL_THRUST_MIN
    thrust_scale: float = 1000.0  # thrustScale
    att_kp: float = 6.0  # 1/s (PID_ROLL_KP, PID_PITCH_KP)
    att_ki: float = 3.0
    att_i_limit: float = 20.0
    yaw_kp: float = 6.0
    yaw_ki: float = 1.0
    yaw_kd: float = 0.35
    yaw_i_limit: float = 360.0
    rate_kp: float = 250.0  # PWM per deg/s (PID_ROLL_RATE_KP, PID_PITCH_RATE_KP)
    rate_ki: float = 500.0
    rate_kd: float = 2.5
    rate_i_limit: float = 33.3
    yaw_rate_kp: float = 120.0
    yaw_rate_ki: float = 16.7
    yaw_rate_i_limit: float = 166.7
    motor_thrust_max: float = 0.12  # N per motor at a command of 65535 (THRUST_MAX, legacy and 2.1+ propellers)
    motor_thrust_min: float = 0.012817578393224994  # N: commands below this give no thrust (THRUST_MIN)


@struct.dataclass
class PidState:
    """The controller's memory, one row per drone."""

    integ: jax.Array  # [n, 9] integrals: velocity x, y, z (m); roll, pitch, yaw (deg s); rates (deg)
    prev: jax.Array  # [n, 6] last measured roll, pitch, yaw (deg) and rates (deg/s), for the D terms
    attitude: jax.Array  # [n, 3] roll, pitch, yaw setpoints (deg), held between velocity-loop ticks
    thrust: jax.Array  # [n] thrust command (PWM units), held between velocity-loop ticks


def euler_deg(quat: jax.Array) -> jax.Array:
    """[n, 4] quaternions [w, x, y, z] -> [n, 3] roll, pitch, yaw (deg) as the firmware's estimators report
    them: ZYX Euler angles with the pitch negated (nose up is positive)."""
    w, x, y, z = jnp.moveaxis(quat, -1, 0)
    roll = jnp.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = jnp.arcsin(jnp.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = jnp.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return jnp.rad2deg(jnp.stack([roll, -pitch, yaw], -1))


def gyro_deg(ang_vel: jax.Array) -> jax.Array:
    """[n, 3] body rates (rad/s, right-handed) -> what the rate loop reads: (gyro.x, -gyro.y, gyro.z) in deg/s."""
    return jnp.rad2deg(ang_vel) * jnp.array([1.0, -1.0, 1.0], ang_vel.dtype)


def _wrap180(deg: jax.Array) -> jax.Array:
    return jnp.where(deg > 180.0, deg - 360.0, jnp.where(deg < -180.0, deg + 360.0, deg))


def hover_thrust(weight: jax.Array, thrust_gain: jax.Array, pid: FirmwarePid) -> jax.Array:
    """The thrust command (PWM units) that holds ``weight`` (N) up when every motor gives ``thrust_gain`` times
    the thrust the firmware's map promises (the drone's thrust constant over the nominal one)."""
    return weight / 4.0 / (pid.motor_thrust_max * thrust_gain) * PWM_MAX


def initial_state(quat: jax.Array, ang_vel: jax.Array, hover: jax.Array, pid: FirmwarePid) -> PidState:
    """The memory of a drone that has been hovering: its z integral holds the thrust ``hover`` (PWM units) that
    carries it, as it would have settled to after take-off; the other integrals are empty."""
    n = quat.shape[0]
    z_integ = (hover - pid.thrust_base) / (pid.thrust_scale * pid.vel_z_ki)
    integ = jnp.zeros((n, 9)).at[:, 2].set(z_integ)
    att = euler_deg(quat)
    prev = jnp.concatenate([att, gyro_deg(ang_vel)], -1)
    attitude = jnp.zeros((n, 3)).at[:, 2].set(att[:, 2])
    return PidState(integ=integ, prev=prev, attitude=attitude, thrust=jnp.broadcast_to(hover, (n,)).astype(jnp.float32))


def velocity_loop(state: PidState, quat: jax.Array, vel: jax.Array, cmd: jax.Array, pid: FirmwarePid,
                  dt: float) -> PidState:
    """``velocityController`` at ``1 / dt`` Hz: world velocity command ``cmd`` [n, 3] (m/s) -> roll and pitch
    setpoints (deg) and a thrust command (PWM units). The command is turned into the body-yaw frame as
    ``positionController`` does for a world setpoint."""
    yaw = jnp.deg2rad(euler_deg(quat)[:, 2])
    c, s = jnp.cos(yaw), jnp.sin(yaw)

    def to_body(v):
        return jnp.stack([v[:, 0] * c + v[:, 1] * s, -v[:, 0] * s + v[:, 1] * c, v[:, 2]], -1)

    err = to_body(cmd) - to_body(vel)
    integ = jnp.clip(state.integ[:, :3] + err * dt, -pid.vel_i_limit, pid.vel_i_limit)
    kp = jnp.stack([pid.vel_xy_kp, pid.vel_xy_kp, pid.vel_z_kp])
    ki = jnp.stack([pid.vel_xy_ki, pid.vel_xy_ki, pid.vel_z_ki])
    out = kp * err + ki * integ
    tilt_out = pid.max_tilt_deg * pid.tilt_overhead
    pitch = -jnp.clip(out[:, 0], -tilt_out, tilt_out)
    roll = -jnp.clip(out[:, 1], -tilt_out, tilt_out)
    z_out = PWM_MAX / 2.0 / pid.thrust_scale
    thrust = jnp.clip(out[:, 2], -z_out, z_out) * pid.thrust_scale + pid.thrust_base
    thrust = jnp.clip(jnp.maximum(thrust, pid.thrust_min), 0.0, PWM_MAX)
    attitude = jnp.stack([jnp.clip(roll, -pid.max_tilt_deg, pid.max_tilt_deg),
                          jnp.clip(pitch, -pid.max_tilt_deg, pid.max_tilt_deg), state.attitude[:, 2]], -1)
    return state.replace(integ=state.integ.at[:, :3].set(integ), attitude=attitude, thrust=thrust)


def attitude_loop(state: PidState, quat: jax.Array, ang_vel: jax.Array, pid: FirmwarePid,
                  dt: float) -> tuple[PidState, jax.Array]:
    """The attitude and rate PIDs and the power distribution at ``1 / dt`` Hz: motor commands [n, 4] in PWM
    units (0 to 65535), motor order 0..3 = firmware M1..M4."""
    att, gyro = euler_deg(quat), gyro_deg(ang_vel)
    prev_att, prev_gyro = state.prev[:, :3], state.prev[:, 3:]

    # Attitude PID: angle error -> rate setpoint (deg/s); D on the measured angle (only yaw has a kd).
    att_err = (state.attitude - att).at[:, 2].apply(_wrap180)
    att_i_lim = jnp.stack([pid.att_i_limit, pid.att_i_limit, pid.yaw_i_limit])
    att_integ = jnp.clip(state.integ[:, 3:6] + att_err * dt, -att_i_lim, att_i_lim)
    d_att = (-(att - prev_att)).at[:, 2].apply(_wrap180) / dt
    rate_des = (jnp.stack([pid.att_kp, pid.att_kp, pid.yaw_kp]) * att_err
                + jnp.stack([pid.att_ki, pid.att_ki, pid.yaw_ki]) * att_integ
                + jnp.stack([jnp.zeros_like(pid.yaw_kd), jnp.zeros_like(pid.yaw_kd), pid.yaw_kd]) * d_att)

    # Rate PID: rate error -> roll, pitch, yaw outputs (int16 range).
    rate_err = rate_des - gyro
    rate_i_lim = jnp.stack([pid.rate_i_limit, pid.rate_i_limit, pid.yaw_rate_i_limit])
    rate_integ = jnp.clip(state.integ[:, 6:] + rate_err * dt, -rate_i_lim, rate_i_lim)
    d_rate = -(gyro - prev_gyro) / dt
    out = (jnp.stack([pid.rate_kp, pid.rate_kp, pid.yaw_rate_kp]) * rate_err
           + jnp.stack([pid.rate_ki, pid.rate_ki, pid.yaw_rate_ki]) * rate_integ
           + jnp.stack([pid.rate_kd, pid.rate_kd, jnp.zeros_like(pid.rate_kd)]) * d_rate)  # yaw rate kd 0
    out = jnp.clip(out, -INT16_MAX, INT16_MAX)

    motors = power_distribution(state.thrust, out[:, 0], out[:, 1], -out[:, 2])  # control->yaw = -yaw output
    state = state.replace(integ=jnp.concatenate([state.integ[:, :3], att_integ, rate_integ], -1),
                          prev=jnp.concatenate([att, gyro], -1))
    return state, motors


def power_distribution(thrust: jax.Array, roll: jax.Array, pitch: jax.Array, yaw: jax.Array) -> jax.Array:
    """``powerDistributionLegacy`` then ``powerDistributionCap``: a controller's thrust and its roll, pitch and
    yaw outputs (``control_t``, PWM units) -> motor commands [n, 4] (0 to 65535), motor order 0..3 = M1..M4."""
    r, p = roll / 2.0, pitch / 2.0  # roll and pitch split over the two motors of a side
    t = thrust
    motors = jnp.stack([t - r + p + yaw, t - r - p - yaw, t + r - p + yaw, t + r + p - yaw], -1)
    # The cap: the excess of the highest motor over 65535 comes off all four.
    excess = jnp.maximum(jnp.max(motors, -1, keepdims=True) - PWM_MAX, 0.0)
    return jnp.clip(motors - excess, 0.0, PWM_MAX)


def motor_rpm(motors: jax.Array, pid: FirmwarePid, kf_nominal: float) -> jax.Array:
    """Motor commands (PWM units) -> the speeds (RPM) they settle at: the battery-compensated map gives
    ``c / 65535 * THRUST_MAX`` newtons (none below ``THRUST_MIN``), which the nominal drone's rotors make at
    ``sqrt(thrust / kf)``. A drone whose thrust constant differs gets other thrust at that speed."""
    thrust = motors / PWM_MAX * pid.motor_thrust_max
    thrust = jnp.where(thrust < pid.motor_thrust_min, 0.0, thrust)
    return jnp.sqrt(thrust / kf_nominal)

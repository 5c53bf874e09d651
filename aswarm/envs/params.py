"""Environment parameters as data, as gymnax does: what may vary per episode or per sweep trial.

:class:`~aswarm.envs.config.EnvConfig` fixes the shapes and the program (drones, cylinders, gates, rates,
scenario kind, neighbours, formation, reward kind); :class:`EnvParams` holds the numbers the compiled
program reads (the drone's physical constants, the onboard controller's gains and limits, reward weights,
the safety margin, the speed limit, moving-obstacle motion). ``SwarmEnv.reset(key, params)`` stores them in
the state and ``step`` reads them from there, so one compiled program serves many values and can be
vmapped over them (:func:`stack`).

Some fields are derived from others as the code before this split computed them, in float64 on the host
(``max_rpm`` from mass and kf, the horizontal acceleration limit from the tilt limit and gravity):
:meth:`EnvParams.from_config` computes them, so the default parameters give the same bits as the constants
compiled in before. Build parameters from a config (``from_config``) rather than replacing one field by hand:
replacing ``cf.mass`` alone leaves ``cf.max_rpm`` as it was.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from aswarm.envs.crazyflie import CrazyflieParams
from aswarm.envs.firmware_mellinger import FirmwareMellinger
from aswarm.envs.firmware_pid import FirmwarePid

if TYPE_CHECKING:  # imported for hints only: the config and the controller import this module
    from aswarm.envs.config import EnvConfig
    from aswarm.envs.onboard_controller import ControllerGains


def _f32(x) -> jax.Array:
    """A host float64 value rounded once to float32, as a constant compiled into the program was."""
    return jnp.asarray(np.asarray(x, np.float64), jnp.float32)


def _matrix(m: np.ndarray) -> tuple:
    """A float64 matrix as nested tuples (hashable, so it can be a static field)."""
    return tuple(tuple(float(x) for x in row) for row in m)


@struct.dataclass
class DroneParams:
    """The drone's physical constants as the controller and the physics read them."""

    mass: jax.Array  # [] kg; also replaces the MJX model's body mass in every physics step
    inertia: jax.Array  # [3] kg m^2, diagonal; also replaces the MJX model's body inertia
    kf: jax.Array  # [] N / RPM^2
    max_rpm: jax.Array  # [] derived: sqrt(thrust_to_weight * weight / (4 kf))
    max_motor_thrust: jax.Array  # [] N, derived: kf * max_rpm^2
    motor_tau: jax.Array  # [] s, rotor time constant (used where the config's cf.motor_tau > 0)
    motor_tau_down: jax.Array  # [] s, slowing down about hover (used where the config's cf.motor_tau_down > 0)
    km_scale: jax.Array  # [] the yaw-torque constant over the config's (domain randomisation)
    drag: jax.Array  # [3] linear rotor drag (used where the config's cf.drag is not zero)
    # Not data (params that differ in them do not fit the env): gravity is the MJX model's opt.gravity, and the
    # mixer (arm length and km / kf; varying kf varies km with it) multiplies as a [4, 4] constant: as data
    # it would be one matrix per world, a batched product that XLA sums in another order (other bits).
    gravity: float = struct.field(pytree_node=False, default=9.8)
    mixer: tuple = struct.field(pytree_node=False, default=())  # [4][4] per-motor thrusts -> [T, tau_x, tau_y, tau_z]
    inv_mixer: tuple = struct.field(pytree_node=False, default=())  # [4][4] its inverse: the controller's allocation

    @classmethod
    def from_crazyflie(cls, cf: CrazyflieParams) -> DroneParams:
        return cls(mass=_f32(cf.mass), inertia=_f32(cf.inertia), kf=_f32(cf.kf), max_rpm=_f32(cf.max_rpm),
                   max_motor_thrust=_f32(cf.max_motor_thrust), motor_tau=_f32(cf.motor_tau),
                   motor_tau_down=_f32(cf.motor_tau_down), km_scale=_f32(1.0),
                   drag=_f32(cf.drag), gravity=float(cf.gravity),
                   mixer=_matrix(cf.mixer()), inv_mixer=_matrix(np.linalg.inv(cf.mixer())))


@struct.dataclass
class GainParams:
    """The onboard controller's gains and limits (:class:`~aswarm.envs.onboard_controller.ControllerGains`)."""

    kp_vel_xy: jax.Array  # 1/s
    kp_vel_z: jax.Array  # 1/s
    max_accel_xy: jax.Array  # m/s^2, derived: gravity * tan(max_tilt_deg)
    max_climb_accel: jax.Array  # m/s^2 above hover
    max_sink_accel: jax.Array  # m/s^2 below hover
    kp_att: jax.Array  # 1/s
    kp_att_yaw: jax.Array  # 1/s
    kp_rate: jax.Array  # 1/s
    max_rate: jax.Array  # rad/s

    @classmethod
    def from_gains(cls, gains: ControllerGains, gravity: float) -> GainParams:
        return cls(kp_vel_xy=_f32(gains.kp_vel_xy), kp_vel_z=_f32(gains.kp_vel_z),
                   max_accel_xy=_f32(gravity * np.tan(np.deg2rad(gains.max_tilt_deg))),
                   max_climb_accel=_f32(gains.max_climb_accel), max_sink_accel=_f32(gains.max_sink_accel),
                   kp_att=_f32(gains.kp_att), kp_att_yaw=_f32(gains.kp_att_yaw), kp_rate=_f32(gains.kp_rate),
                   max_rate=_f32(gains.max_rate))


@struct.dataclass
class EnvParams:
    """Everything ``SwarmEnv.reset``/``step`` read that changes no shape; field names follow ``EnvConfig``."""

    cf: DroneParams
    gains: GainParams  # the geometric controller's
    pid: FirmwarePid  # the firmware controller's, as arrays
    mellinger: FirmwareMellinger  # the firmware's Mellinger controller's, as arrays
    reference_leash: jax.Array  # m, how far Mellinger's setpoint may lead or trail the drone
    max_speed: jax.Array  # m/s, per-axis clip of the velocity command
    safety_margin: jax.Array  # m; the cost grows as clearance falls below it
    progress_weight: jax.Array
    gate_bonus: jax.Array
    finish_bonus: jax.Array
    collision_penalty: jax.Array
    time_penalty_per_step: jax.Array  # derived: time_penalty * dt
    command_rate_penalty: jax.Array
    command_step_limit: jax.Array  # m/s, derived: command_accel_limit / policy_freq
    lateral_weight: jax.Array
    wrong_side_weight: jax.Array
    wrong_side_clearance: jax.Array
    paper_epsilon: jax.Array
    moving_amplitude: jax.Array  # m, read by reset (the layout of a new episode)
    moving_omega: jax.Array  # rad/s, derived: 2 pi / moving_period
    latency_ticks: jax.Array  # onboard-controller ticks the velocity command arrives late (whole numbers)
    mocap_noise: jax.Array  # m, standard deviation of the noise on every position the policy sees
    mocap_delay: jax.Array  # policy steps the poses the policy sees are old (whole numbers)

    @classmethod
    def from_config(cls, cfg: EnvConfig) -> EnvParams:
        """The parameters ``cfg`` sets, derived fields computed as the program compiled from it used to."""
        return cls(
            cf=DroneParams.from_crazyflie(cfg.cf), gains=GainParams.from_gains(cfg.gains, cfg.cf.gravity),
            max_speed=_f32(cfg.max_speed), safety_margin=_f32(cfg.safety_margin),
            progress_weight=_f32(cfg.progress_weight), gate_bonus=_f32(cfg.gate_bonus),
            finish_bonus=_f32(cfg.finish_bonus), collision_penalty=_f32(cfg.collision_penalty),
            time_penalty_per_step=_f32(cfg.time_penalty * cfg.dt),
            command_rate_penalty=_f32(cfg.command_rate_penalty),
            command_step_limit=_f32(cfg.command_accel_limit / cfg.policy_freq), lateral_weight=_f32(cfg.lateral_weight),
            wrong_side_weight=_f32(cfg.wrong_side_weight),
            wrong_side_clearance=_f32(cfg.wrong_side_clearance), paper_epsilon=_f32(cfg.paper_epsilon),
            moving_amplitude=_f32(cfg.moving_amplitude), moving_omega=_f32(2 * np.pi / cfg.moving_period),
            pid=jax.tree.map(_f32, cfg.pid), mellinger=jax.tree.map(_f32, cfg.mellinger),
            reference_leash=_f32(cfg.reference_leash), latency_ticks=_f32(0.0), mocap_noise=_f32(0.0),
            mocap_delay=_f32(0.0),
        )


def stack(params: list[EnvParams]) -> EnvParams:
    """One batch (leading axis) of parameters, e.g. one per world or per trial, to vmap ``reset`` over."""
    return jax.tree.map(lambda *xs: jnp.stack(xs), *params)


def check(params, default: EnvParams, batched: bool = False) -> EnvParams:
    """``params`` as float32 arrays of ``default``'s structure and shapes (after a leading batch axis when
    ``batched``); raise ``ValueError`` naming the first mismatch otherwise."""
    if jax.tree.structure(params) != jax.tree.structure(default):
        raise ValueError(f"invalid params of type {type(params).__name__}: allowed: EnvParams with the structure "
                         f"of env.default_params (EnvParams.from_config of a config with the same cf.gravity, "
                         f"cf.arm_length and cf.km / cf.kf)")
    paths = jax.tree_util.tree_flatten_with_path(default)[0]
    out = []
    for (path, want), got in zip(paths, jax.tree.leaves(params)):
        shape = np.shape(got)[1:] if batched else np.shape(got)
        if shape != np.shape(want) or (batched and not np.ndim(got)):
            name = jax.tree_util.keystr(path, simple=True, separator=".")
            raise ValueError(f"invalid params.{name} of shape {np.shape(got)}: allowed shape "
                             f"{('[batch] + ' if batched else '') + str(np.shape(want))}")
        out.append(jnp.asarray(got, jnp.float32))
    return jax.tree.unflatten(jax.tree.structure(default), out)

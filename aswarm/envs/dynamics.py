"""Rigid-body dynamics of the swarm: MJX is the physics of record.

Each drone is a MuJoCo free body. Motor speeds (RPM) become per-motor thrust
``kf * rpm^2`` and yaw torque ``km * rpm^2``; their resultant wrench about the
centre of mass is applied through ``xfrc_applied`` and ``mjx.step`` integrates
(semi-implicit Euler, sparse mass matrix: see ``shared/crazyflie.md``).

Conventions: quaternions are MuJoCo's ``[w, x, y, z]``; linear velocity is in
the world frame; angular velocity is in the **body** frame (MuJoCo's free-joint
``qvel``).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from aswarm.envs import scene
from aswarm.envs.crazyflie import CrazyflieParams
from aswarm.envs.mjx_import import mjx
from aswarm.envs.params import DroneParams


@struct.dataclass
class DroneState:
    """Kinematic state of every drone; leading axis is the drone."""

    pos: jax.Array  # [n, 3] world, m
    quat: jax.Array  # [n, 4] body->world, [w, x, y, z]
    vel: jax.Array  # [n, 3] world, m/s
    ang_vel: jax.Array  # [n, 3] body, rad/s


def quat_to_rotmat(q: jax.Array) -> jax.Array:
    """[..., 4] unit quaternions [w, x, y, z] -> [..., 3, 3] body->world rotations."""
    w, x, y, z = jnp.moveaxis(q, -1, 0)
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def drone_state(data: mjx.Data, num_agents: int) -> DroneState:
    qpos = data.qpos.reshape(num_agents, 7)
    qvel = data.qvel.reshape(num_agents, 6)
    return DroneState(pos=qpos[:, :3], quat=qpos[:, 3:], vel=qvel[:, :3], ang_vel=qvel[:, 3:])


def set_drone_state(data: mjx.Data, s: DroneState) -> mjx.Data:
    qpos = jnp.concatenate([s.pos, s.quat], -1).reshape(-1)
    qvel = jnp.concatenate([s.vel, s.ang_vel], -1).reshape(-1)
    return data.replace(qpos=qpos, qvel=qvel)


def drone_params(cf: DroneParams | CrazyflieParams) -> DroneParams:
    """``cf`` as data; a :class:`CrazyflieParams` is converted as ``EnvParams.from_config`` does."""
    return cf if isinstance(cf, DroneParams) else DroneParams.from_crazyflie(cf)


def motor_wrench(rpm: jax.Array, cf: DroneParams | CrazyflieParams) -> jax.Array:
    """[n, 4] motor RPM -> [n, 4] body-frame [thrust, tau_x, tau_y, tau_z]."""
    cf = drone_params(cf)
    rpm = jnp.clip(rpm, 0.0, cf.max_rpm)
    thrusts = cf.kf * rpm**2
    wrench = thrusts @ jnp.asarray(cf.mixer, dtype=rpm.dtype).T
    return wrench.at[:, 3].multiply(cf.km_scale)  # exact where km_scale is 1 (every undrawn drone)


def rotor_lag(rpm: jax.Array, target: jax.Array, tau: jax.Array, dt: float, tau_down: jax.Array | None = None,
              reference_rpm: float = 0.0) -> jax.Array:
    """Rotor speeds after ``dt`` s with ``target`` held: the exact solutions, so the step size changes nothing
    but where the response is sampled.

    Speeding up (and, without ``tau_down``, slowing down too) follows the first-order lag
    ``d rpm / dt = (target - rpm) / tau``. With ``tau_down`` a rotor slows down as the identified Crazyflie
    rotors do, ``d rpm / dt = k (target^2 - rpm^2)``: the propeller's drag torque, quadratic in its speed, brakes
    it, so it slows fastest from high speed; ``k = 1 / (2 reference_rpm tau_down)`` makes ``tau_down`` its time
    constant about ``reference_rpm``."""
    up = target + (rpm - target) * jnp.exp(-dt / tau)
    if tau_down is None:
        return up
    k = 1.0 / (2.0 * reference_rpm * tau_down)
    # From rpm > target: rpm(t) - target = 2 target (rpm - target) e / (rpm (1 - e) + target (1 + e)), with
    # e = exp(-2 k target t), divided through by target so that target = 0 (a motor cut) is the limit
    # rpm / (1 + k rpm t) rather than 0 / 0.
    x = 2.0 * k * target * dt
    e = jnp.exp(-x)
    xs = jnp.maximum(x, 1e-6)
    one_minus_e_per_target = 2.0 * k * dt * jnp.where(x > 1e-6, -jnp.expm1(-xs) / xs, 1.0 - 0.5 * x)
    down = target + 2.0 * (rpm - target) * e / (rpm * one_minus_e_per_target + 1.0 + e)
    return jnp.where(target >= rpm, up, down)


def rotor_drag(quat: jax.Array, vel: jax.Array, rpm: jax.Array, cf: DroneParams) -> jax.Array:
    """[n, 3] world-frame linear rotor drag, ``-drag * v_body * sum(2 pi rpm / 60)`` (gym-pybullet-drones' DRAG)."""
    rot = quat_to_rotmat(quat)
    v_body = jnp.einsum("nji,nj->ni", rot, vel)
    omega = jnp.sum(rpm, -1, keepdims=True) * (2 * jnp.pi / 60)
    return jnp.einsum("nij,nj->ni", rot, -cf.drag * v_body * omega)


def apply_wrench(data: mjx.Data, quat: jax.Array, wrench: jax.Array) -> mjx.Data:
    """Write body-frame wrenches [n, 4] of the drones into ``xfrc_applied`` (world frame)."""
    rot = quat_to_rotmat(quat)
    force = rot[:, :, 2] * wrench[:, :1]
    torque = jnp.einsum("nij,nj->ni", rot, wrench[:, 1:])
    # Body 0 is the world; drones are bodies 1..n in the physics model.
    xfrc = data.xfrc_applied.at[1:].set(jnp.concatenate([force, torque], -1))
    return data.replace(xfrc_applied=xfrc)


def with_drone(model: mjx.Model, cf: DroneParams) -> mjx.Model:
    """``model`` with every drone's mass and inertia from ``cf``, so they can be data (per world, per trial)
    while MJX stays the physics of record. Each drone is a root body: its subtree mass is its own."""
    n = model.nbody - 1  # body 0 is the world
    mass = jnp.broadcast_to(jnp.asarray(cf.mass, model.body_mass.dtype), (n,))
    body_mass = jnp.concatenate([model.body_mass[:1], mass])
    body_inertia = jnp.concatenate(
        [model.body_inertia[:1], jnp.broadcast_to(jnp.asarray(cf.inertia, model.body_inertia.dtype), (n, 3))])
    subtree = jnp.concatenate([jnp.sum(mass, keepdims=True), mass])
    return model.replace(body_mass=body_mass, body_inertia=body_inertia, body_subtreemass=subtree)


def physics_step(model: mjx.Model, data: mjx.Data, rpm: jax.Array, cf: DroneParams | CrazyflieParams,
                 drag: bool = False) -> mjx.Data:
    """One physics step with motor speeds ``rpm`` [n, 4] held constant; ``cf``'s mass and inertia replace
    the model's (:func:`with_drone`); ``drag``: add :func:`rotor_drag`."""
    cf = drone_params(cf)
    n = rpm.shape[0]
    quat = data.qpos.reshape(n, 7)[:, 3:]
    data = apply_wrench(data, quat, motor_wrench(rpm, cf))
    if drag:
        force = rotor_drag(quat, data.qvel.reshape(n, 6)[:, :3], rpm, cf)
        data = data.replace(xfrc_applied=data.xfrc_applied.at[1:, :3].add(force))
    return mjx.step(with_drone(model, cf), data)


@functools.lru_cache(maxsize=32)
def physics_model(num_agents: int, sim_freq: int, cf: CrazyflieParams = CrazyflieParams()):
    """(mujoco.MjModel, mjx.Model) of ``num_agents`` drones stepped at ``sim_freq`` Hz."""
    m = scene.build_model(num_agents, sim_freq, cf, physics_only=True)
    # Concrete arrays even when first asked for inside a jit trace: the cache would otherwise keep tracers, and
    # the next caller would get a leaked one. This process's first device: jax.devices()[0], MJX's default,
    # belongs to another host in multi-host runs.
    with jax.ensure_compile_time_eval():
        return m, mjx.put_model(m, device=jax.local_devices()[0])


@struct.dataclass
class Trajectory:
    """States after each physics step; leading axes [T, n]."""

    time: jax.Array  # [T] s
    pos: jax.Array  # [T, n, 3] world, m
    quat: jax.Array  # [T, n, 4] [w, x, y, z]
    vel: jax.Array  # [T, n, 3] world, m/s
    ang_vel: jax.Array  # [T, n, 3] body, rad/s


def simulate_rpm(
    initial: DroneState,
    rpm: jax.Array | np.ndarray,
    sim_freq: int = 250,
    cf: CrazyflieParams = CrazyflieParams(),
) -> Trajectory:
    """Open-loop flight of a swarm under given motor speeds, for cross-checking simulators.

    Args:
      initial: state of the ``n`` drones at t = 0 (quaternions ``[w, x, y, z]``).
      rpm: ``[T, n, 4]`` motor speeds in RPM, one row per physics step at
        ``sim_freq`` Hz, in the motor order of ``crazyflie.py``; clipped to
        ``[0, cf.max_rpm]``.
      sim_freq: physics rate in Hz.
      cf: drone constants.

    Returns:
      The :class:`Trajectory` after each of the ``T`` steps (time ``(k+1)/sim_freq``).
    """
    rpm = jnp.asarray(rpm, jnp.float32)
    if rpm.ndim != 3 or rpm.shape[2] != 4:
        raise ValueError(f"rpm must have shape [T, n_drones, 4], got {tuple(rpm.shape)}")
    n = rpm.shape[1]
    if initial.pos.shape != (n, 3):
        raise ValueError(f"initial.pos must have shape ({n}, 3) to match rpm, got {tuple(initial.pos.shape)}")
    _, mx = physics_model(n, sim_freq, cf)
    return _simulate(mx, initial, rpm, cf)


@functools.partial(jax.jit, static_argnums=(3,))
def _simulate(mx: mjx.Model, initial: DroneState, rpm: jax.Array, cf: CrazyflieParams) -> Trajectory:
    n = rpm.shape[1]
    data0 = mjx.make_data(mx, device=jax.local_devices()[0])
    data = set_drone_state(data0, jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), initial))

    def body(d, r):
        d = physics_step(mx, d, r, cf)
        s = drone_state(d, n)
        return d, Trajectory(time=d.time, pos=s.pos, quat=s.quat, vel=s.vel, ang_vel=s.ang_vel)

    return jax.lax.scan(body, data, rpm)[1]

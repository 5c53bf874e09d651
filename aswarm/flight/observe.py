"""Observations in numpy, built exactly as ``aswarm.envs.swarm_env.SwarmEnv._observe`` builds them.

Shapes: leading batch axes ``...`` (worlds), ``n`` drones, ``K`` waypoints, ``M`` cylinders.
The field tables live in :mod:`aswarm.obs_layout` (free of JAX, shared with the simulator), and
:func:`aswarm.flight.bundle.load_bundle` checks a bundle's layout against them.
"""

from __future__ import annotations

import numpy as np

from aswarm.obs_layout import CYL_FIELDS, MIN_TARGET_DIST, NBR_FIELDS, OWN_FIELDS, ObsLayout  # noqa: F401


def others(n: int) -> np.ndarray:
    """[n, n - 1] indices of every drone's neighbours, in the simulator's order."""
    return np.array([[j for j in range(n) if j != i] for i in range(n)], dtype=np.intp).reshape(n, n - 1)


def gate_normals(gate_yaw: np.ndarray) -> np.ndarray:
    """[..., G] yaw (rad) -> [..., G, 3] horizontal unit directions of passage."""
    return np.stack([np.cos(gate_yaw), np.sin(gate_yaw), np.zeros_like(gate_yaw)], -1)


def cylinders_at(center, axis, amplitude, omega, phase, t) -> tuple[np.ndarray, np.ndarray]:
    """Cylinder centres and velocities [..., M, 2] at time ``t`` [...] (as ``scenarios.cylinders_at``)."""
    arg = omega * np.asarray(t)[..., None] + phase
    pos = center + axis * (amplitude * np.sin(arg))[..., None]
    vel = axis * (amplitude * omega * np.cos(arg))[..., None]
    return pos, vel


def observe(pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, ang_vel: np.ndarray, waypoints: np.ndarray,
            normals: np.ndarray, target: np.ndarray, flying: np.ndarray, cyl_pos: np.ndarray, cyl_vel: np.ndarray,
            cyl_radius: np.ndarray, cyl_present: np.ndarray, collision_radius: float) -> np.ndarray:
    """Every drone's observation [..., n, D].

    pos, vel, ang_vel [..., n, 3] (world m, world m/s, body rad/s); quat [..., n, 4] wxyz;
    waypoints [..., n, K, 3] each drone's gate centres in order (or its goal, K = 1);
    normals [..., n, K, 3] the gates' directions of passage (0 for goals); target [..., n] int index of
    the current waypoint (may be K when finished); flying [..., n] bool (a drone that finished or was
    lost is not a neighbour); cyl_pos, cyl_vel [..., M, 2]; cyl_radius [..., M]; cyl_present [..., M] bool.
    """
    n = pos.shape[-2]
    K = waypoints.shape[-2]
    k = np.minimum(target, K - 1).reshape(-1)
    k_next = np.minimum(k + 1, K - 1)
    full = pos.shape[:-1] + (K, 3)
    wp = (waypoints if waypoints.shape == full else np.broadcast_to(waypoints, full)).reshape(-1, K, 3)
    rows = np.arange(wp.shape[0])

    def pick(a, i):
        return a[rows, i].reshape(pos.shape)

    nrm = (normals if normals.shape == full else np.broadcast_to(normals, full)).reshape(-1, K, 3)
    normal = pick(nrm, k)
    # The gate passed last (tracks only: a goal has no direction of passage).
    t_flat = np.asarray(target).reshape(-1)
    has_prev = ((t_flat >= 1) & (np.abs(nrm[rows, 0]).sum(-1) > 0)).reshape(pos.shape[:-1] + (1,))
    k_prev = np.maximum(t_flat - 1, 0)
    prev_rel = np.where(has_prev, pos - pick(wp, k_prev), 0.0)
    prev_normal = np.where(has_prev, pick(nrm, k_prev), 0.0)
    to_target = pick(wp, k) - pos
    direction = to_target / np.maximum(np.linalg.norm(to_target, axis=-1, keepdims=True), MIN_TARGET_DIST)
    own = np.concatenate([-to_target, normal, pos - pick(wp, k_next), direction, prev_rel, prev_normal,
                          pos[..., 2:3], quat, vel, ang_vel], -1)

    rel = cyl_pos[..., None, :, :] - pos[..., :, None, :2]  # [..., n, M, 2]
    gap = np.linalg.norm(rel, axis=-1) - cyl_radius[..., None, :] - collision_radius
    cyl = np.empty(rel.shape[:-1] + (6,))
    cyl[..., 0:2] = rel
    cyl[..., 2] = gap
    cyl[..., 3:5] = cyl_vel[..., None, :, :]
    cyl[..., 5] = 1.0
    cyl *= cyl_present[..., None, :, None]

    idx = others(n)
    nbr = np.concatenate([pos[..., idx, :] - pos[..., :, None, :], vel[..., idx, :] - vel[..., :, None, :],
                          np.ones(pos.shape[:-2] + idx.shape + (1,))], -1)
    nbr = np.where(flying[..., idx][..., None], nbr, 0.0)
    lead = pos.shape[:-2]
    return np.concatenate([own, cyl.reshape(*lead, n, -1), nbr.reshape(*lead, n, -1)], -1)


def gate_crossed(p_prev: np.ndarray, p_new: np.ndarray, gate_pos: np.ndarray, gate_yaw: np.ndarray,
                 half_opening: float) -> np.ndarray:
    """[...] true where the move p_prev -> p_new [..., 3] crosses the gate [..., 3], yaw [...] forwards, inside.

    The simulator's test (``collisions.gate_crossed``): the segment crosses the gate plane in the
    direction of passage and the crossing point lies inside the square opening.
    """
    normal = gate_normals(gate_yaw)
    s0 = np.sum((p_prev - gate_pos) * normal, -1)
    s1 = np.sum((p_new - gate_pos) * normal, -1)
    forward = (s0 < 0) & (s1 >= 0)
    if not forward.any():  # the common case, every control step: nothing more to compute
        return forward
    frac = s0 / np.where(forward, s0 - s1, 1.0)
    hit = p_prev + frac[..., None] * (p_new - p_prev) - gate_pos
    lateral = hit[..., 0] * -normal[..., 1] + hit[..., 1] * normal[..., 0]
    return forward & (np.abs(lateral) < half_opening) & (np.abs(hit[..., 2]) < half_opening)

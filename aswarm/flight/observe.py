"""Observations in numpy, built exactly as ``aswarm.envs.swarm_env.SwarmEnv._observe`` builds them.

Shapes: leading batch axes ``...`` (worlds), ``n`` drones, ``K`` waypoints, ``M`` cylinders.
The field tables live in :mod:`aswarm.core.layout` (free of JAX, shared with the simulator), and
:func:`aswarm.flight.bundle.load_bundle` checks a bundle's layout against them.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from aswarm.core.layout import CYL_FIELDS, MIN_TARGET_DIST, NBR_FIELDS, OWN_FIELDS, ObsLayout  # noqa: F401


@functools.lru_cache(maxsize=64)
def others(n: int) -> np.ndarray:
    """[n, n - 1] indices of every drone's neighbours, in the simulator's order (read-only, built once per n)."""
    idx = np.array([[j for j in range(n) if j != i] for i in range(n)], dtype=np.intp).reshape(n, n - 1)
    idx.setflags(write=False)
    return idx


def gate_normals(gate_yaw: np.ndarray) -> np.ndarray:
    """[..., G] yaw (rad) -> [..., G, 3] horizontal unit directions of passage."""
    return np.stack([np.cos(gate_yaw), np.sin(gate_yaw), np.zeros_like(gate_yaw)], -1)


def cylinders_at(center, axis, amplitude, omega, phase, t) -> tuple[np.ndarray, np.ndarray]:
    """Cylinder centres and velocities [..., M, 2] at time ``t`` [...] (as ``scenarios.cylinders_at``)."""
    arg = omega * np.asarray(t)[..., None] + phase
    pos = center + axis * (amplitude * np.sin(arg))[..., None]
    vel = axis * (amplitude * omega * np.cos(arg))[..., None]
    return pos, vel


# Where each own field lives in a row (the tables' order), and the waypoint offsets picked per drone.
_OWN = ObsLayout(0, 0).own_slices
# observe writes the first 6 own fields as 3 waypoints' (offset, direction): the current waypoint and
# its normal, the next one and the direction to the current one, the last passed and its normal.
_WAYPOINT_FIELDS = ("target_rel", "target_normal", "next_target_rel", "target_dir", "prev_gate_rel", "prev_gate_normal")
if [f[:2] for f in OWN_FIELDS[:6]] != [(name, 3) for name in _WAYPOINT_FIELDS]:
    raise ImportError(f"observe expects the own fields to start with {_WAYPOINT_FIELDS}, 3 numbers each")
_OWN_DIM, _CYL_DIM, _NBR_DIM = ObsLayout(0, 0).own_dim, ObsLayout(0, 0).cyl_dim, ObsLayout(0, 0).nbr_dim


@functools.lru_cache(maxsize=64)
def _picks(K: int) -> np.ndarray:
    """[K + 1, 3]: for each target 0..K (K: finished), the current waypoint, the next one and the one passed last."""
    t = np.arange(K + 1)
    pick = np.stack([np.minimum(t, K - 1), np.minimum(t + 1, K - 1), np.maximum(t - 1, 0)], -1)
    pick.setflags(write=False)
    return pick


def observe(pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, ang_vel: np.ndarray, waypoints: np.ndarray,
            normals: np.ndarray, target: np.ndarray, flying: np.ndarray, cyl_pos: np.ndarray, cyl_vel: np.ndarray,
            cyl_radius: np.ndarray, cyl_present: np.ndarray, collision_radius: float, arena_low, arena_high,
            max_neighbours: int = 0) -> np.ndarray:
    """Every drone's observation [..., n, D].

    pos, vel, ang_vel [..., n, 3] (world m, world m/s, body rad/s); quat [..., n, 4] wxyz;
    waypoints [..., n, K, 3] each drone's gate centres in order (or its goal, K = 1);
    normals [..., n, K, 3] the gates' directions of passage (0 for goals); target [..., n] int index of
    the current waypoint (may be K when finished); flying [..., n] bool (a drone that finished or was
    lost is not a neighbour); cyl_pos, cyl_vel [..., M, 2]; cyl_radius [..., M]; cyl_present [..., M] bool.
    arena_low, arena_high [3]: the arena box (m), whose walls and ceiling the row measures the drone against.
    ``max_neighbours`` as the env config's: 0 gives every other drone in index order, K the K nearest
    flying ones, nearest first, padded with absent rows.

    Every field is written straight into its place in one output array (this runs every control
    step, and numpy's cost is per operation: a concatenation of small parts costs as much as the parts).
    """
    lead, n = pos.shape[:-2], pos.shape[-2]
    K, M = waypoints.shape[-2], cyl_pos.shape[-2]
    B = math.prod(lead)
    P = B * n
    k_nbr = max_neighbours or n - 1
    out = np.empty((P, _OWN_DIM + M * _CYL_DIM + k_nbr * _NBR_DIM))
    p = pos.reshape(P, 3)

    # Own fields. The waypoints (and their normals) at the current target, the next and the last passed.
    full = lead + (n, K, 3)
    wp = (waypoints if waypoints.shape == full else np.broadcast_to(waypoints, full)).reshape(P, K, 3)
    nrm = (normals if normals.shape == full else np.broadcast_to(normals, full)).reshape(P, K, 3)
    t_flat = _worlds(target, lead, (n,)).reshape(P)
    pick = _picks(K)[t_flat]  # [P, 3]: k, k_next, k_prev
    rows = np.arange(P)[:, None]
    at, nrm_at = wp[rows, pick], nrm[rows, pick]  # [P, 3, 3]
    # The first own fields, as [P, 3 waypoints, (offset, direction)]: see _WAYPOINT_FIELDS.
    per_wp = out[:, :18].reshape(P, 3, 6)
    np.subtract(p[:, None, :], at, out=per_wp[:, :, :3])
    per_wp[:, ::2, 3:] = nrm_at[:, ::2]
    to_target = at[:, 0] - p
    dist = np.sqrt((to_target * to_target).sum(-1))
    np.divide(to_target, np.maximum(dist, MIN_TARGET_DIST)[:, None], out=per_wp[:, 1, 3:])
    # The gate passed last (tracks only: a goal has no direction of passage).
    has_prev = t_flat >= 1
    if has_prev.any():  # (else none: before the first gate)
        has_prev &= np.abs(nrm[:, 0]).sum(-1) > 0
    if not has_prev.all():
        if has_prev.any():
            per_wp[~has_prev, 2] = 0.0
        else:  # before the first gate, or goals
            per_wp[:, 2] = 0.0
    out[:, _OWN["altitude"]] = p[:, 2:3]
    out[:, _OWN["quat"]] = quat.reshape(P, 4)
    out[:, _OWN["vel"]] = vel.reshape(P, 3)
    out[:, _OWN["ang_vel"]] = ang_vel.reshape(P, 3)
    walls = out[:, _OWN["wall_clearance"]]
    low, high = np.asarray(arena_low, np.float64), np.asarray(arena_high, np.float64)
    np.subtract(p[:, 0:2], low[:2], out=walls[:, 0:4:2])
    np.subtract(high[:2], p[:, 0:2], out=walls[:, 1:4:2])
    np.subtract(high[2], p[:, 2], out=walls[:, 4])

    # Cylinders [B, n, M, 6], written in place through a view of the output.
    rows3 = out.reshape(B, n, -1)
    cyl = rows3[:, :, _OWN_DIM:_OWN_DIM + M * _CYL_DIM].reshape(B, n, M, _CYL_DIM)
    p3 = p.reshape(B, n, 3)
    rel = _worlds(cyl_pos, lead, (M, 2))[:, None] - p3[:, :, None, :2]
    cyl[..., 0:2] = rel
    gap = np.sqrt((rel * rel).sum(-1))
    gap -= _worlds(cyl_radius, lead, (M,))[:, None]
    np.subtract(gap, collision_radius, out=cyl[..., 2])
    cyl[..., 3:5] = _worlds(cyl_vel, lead, (M, 2))[:, None]
    cyl[..., 5] = 1.0
    present = _worlds(cyl_present, lead, (M,))
    if not present.all():  # (multiplying by 1 changes nothing)
        cyl *= present[:, None, :, None]

    # Neighbours [B, n, n - 1, 7]: zero for one that is not flying.
    view = rows3[:, :, _OWN_DIM + M * _CYL_DIM:].reshape(B, n, k_nbr, _NBR_DIM)
    nbr = view if not max_neighbours else np.empty((B, n, n - 1, _NBR_DIM))
    idx = others(n)
    pv = np.concatenate([p3, vel.reshape(B, n, 3)], -1)  # relative position and velocity in one go
    np.subtract(pv[:, idx], pv[:, :, None], out=nbr[..., 0:6])
    nbr[..., 6] = 1.0
    seen = _worlds(flying, lead, (n,))[:, idx]
    if not seen.all():
        nbr[~seen] = 0.0
    if max_neighbours:  # the K nearest flying ones, nearest first (swarm_env.nearest_rows), then absent rows
        dist = np.where(seen, np.sqrt((nbr[..., :3] ** 2).sum(-1)), np.inf)
        order = np.argsort(dist, axis=-1, kind="stable")[..., :k_nbr]
        keep = min(k_nbr, n - 1)
        view[:, :, :keep] = np.take_along_axis(nbr, order[..., None], axis=2)
        view[:, :, :keep] *= np.take_along_axis(seen, order, axis=2)[..., None]
        view[:, :, keep:] = 0.0
    return rows3.reshape(lead + (n, -1))


def _worlds(x: np.ndarray, lead: tuple[int, ...], tail: tuple[int, ...]) -> np.ndarray:
    """``x`` [..., *tail] as [B, *tail] over the flattened batch axes ``lead`` (broadcast only when needed)."""
    x = np.asarray(x)
    want = lead + tail
    return (x if x.shape == want else np.broadcast_to(x, want)).reshape((math.prod(lead),) + tail)


def gate_crossed(p_prev: np.ndarray, p_new: np.ndarray, gate_pos: np.ndarray, gate_yaw: np.ndarray,
                 half_opening: float) -> np.ndarray:
    """[...] true where the move p_prev -> p_new [..., 3] crosses the gate [..., 3], yaw [...] forwards, inside.

    The simulator's test (``collisions.gate_crossed``): the segment crosses the gate plane in the
    direction of passage and the crossing point lies inside the square opening.
    """
    return crossed_gate(p_prev, p_new, gate_pos, gate_normals(gate_yaw), half_opening)


def crossed_gate(p_prev: np.ndarray, p_new: np.ndarray, gate_pos: np.ndarray, normal: np.ndarray,
                 half_opening: float) -> np.ndarray:
    """:func:`gate_crossed` with the gates' directions of passage ``normal`` [..., 3] (:func:`gate_normals`) given."""
    s0 = ((p_prev - gate_pos) * normal).sum(-1)
    s1 = ((p_new - gate_pos) * normal).sum(-1)
    forward = (s0 < 0) & (s1 >= 0)
    if not forward.any():  # the common case, every control step: nothing more to compute
        return forward
    frac = s0 / np.where(forward, s0 - s1, 1.0)
    hit = p_prev + frac[..., None] * (p_new - p_prev) - gate_pos
    lateral = hit[..., 0] * -normal[..., 1] + hit[..., 1] * normal[..., 0]
    return forward & (np.abs(lateral) < half_opening) & (np.abs(hit[..., 2]) < half_opening)

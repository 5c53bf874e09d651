"""Every drone's observation, built once for the simulator (JAX, inside ``jit``) and the flight runtime (numpy).

Written against the array API, as :mod:`aswarm.core.geometry`: the namespace comes from the arguments,
arrays are built with ``stack``/``concat``/``where`` and never written in place. Each field is computed
under its name and the row is assembled in the order of the tables in :mod:`aswarm.core.layout`, so a
field is defined here once and placed by the tables alone.

Shapes: leading batch axes ``...`` (worlds), ``n`` drones, ``K`` waypoints, ``M`` cylinders.
"""

from __future__ import annotations

import functools

import numpy as np

from aswarm.core.geometry import namespace, norm, tilt_accel, wall_clearance
from aswarm.core.layout import CYL, MIN_TARGET_DIST, NBR, NBR_ACCEL, OWN


@functools.lru_cache(maxsize=64)
def others(n: int) -> np.ndarray:
    """[n, n - 1] indices of every drone's neighbours in index order (read-only, built once per n)."""
    idx = np.array([[j for j in range(n) if j != i] for i in range(n)], dtype=np.intp).reshape(n, n - 1)
    idx.setflags(write=False)
    return idx


def _full(xp, x, shape: tuple[int, ...]):
    """``x`` broadcast to ``shape`` (only when it differs: numpy's broadcast_to costs microseconds per call)."""
    return x if x.shape == shape else xp.broadcast_to(x, shape)


# (group name, the fields built) that matched the group's table. The names come from this module's code, not from
# its inputs, so each is checked once rather than every control step of the flight runtime.
_CHECKED: set[tuple[str, tuple[str, ...]]] = set()


def _assemble(xp, group, fields: dict, shape: tuple[int, ...]):
    """The fields of ``group`` (name -> [*shape, size]) concatenated in the table's order: [*shape, group.dim]."""
    key = (group.name, tuple(fields))
    if key not in _CHECKED:
        if fields.keys() != set(group.names):
            raise ValueError(f"the {group.name} fields built {sorted(fields)} differ from the table's "
                             f"{list(group.names)}")
        _CHECKED.add(key)
    return xp.concat([_full(xp, fields[name], shape + (size,)) for name, size, _ in group.fields], axis=-1)


def _all(x) -> bool:
    """True for a numpy array of flags that are all set: masking it with ``where`` would change nothing (numpy
    only; under jit the mask is always applied, so the traced program is the same whatever the flags)."""
    return isinstance(x, np.ndarray) and bool(x.all())


def nearest_rows(nbr, present, k: int):
    """Neighbour rows [..., n, m, D] -> the ``k`` nearest present ones, nearest first, then absent (zero)
    rows: [..., n, k, D]. ``present`` [..., n, m] bool. Ties keep index order."""
    xp = namespace(nbr)
    m = present.shape[-1]
    dist = xp.where(present, norm(NBR.get(nbr, "rel_pos")), xp.inf)
    order = xp.argsort(dist, axis=-1, stable=True)[..., :k]
    rows = xp.take_along_axis(nbr, order[..., None], axis=-2)
    rows = xp.where(xp.take_along_axis(present, order, axis=-1)[..., None], rows, 0.0)
    pad = xp.zeros(nbr.shape[:-2] + (max(k - m, 0), nbr.shape[-1]), dtype=nbr.dtype)
    return xp.concat([rows, pad], axis=-2)


def observe(pos, quat, vel, ang_vel, waypoints, normals, target, flying, cyl_pos, cyl_vel, cyl_radius, cyl_present,
            collision_radius: float, arena_low, arena_high, max_neighbours: int = 0, neighbour_accel: bool = False):
    """Every drone's observation [..., n, D] (numpy or JAX, as the arguments).

    pos, vel, ang_vel [..., n, 3] (world m, world m/s, body rad/s); quat [..., n, 4] wxyz;
    waypoints [..., n, K, 3] each drone's gate centres in order (or its goal, K = 1);
    normals [..., n, K, 3] the gates' directions of passage (0 for goals); target [..., n] int index of
    the current waypoint (may be K when finished); flying [..., n] bool (a drone that finished or was
    lost is not a neighbour); cyl_pos, cyl_vel [..., M, 2]; cyl_radius [..., M]; cyl_present [..., M] bool.
    arena_low, arena_high [3]: the arena box (m), whose walls and ceiling the row measures the drone against.
    ``max_neighbours``: 0 gives every other drone in index order, K the K nearest flying ones, nearest
    first, padded with absent rows. ``neighbour_accel``: after the neighbour rows, each one's acceleration from its
    attitude (:data:`aswarm.core.layout.NBR_ACCEL`, in the rows' order; the safety filter's second-order look-ahead).
    Arguments without the leading axes broadcast.
    """
    xp = namespace(pos)
    lead, n = pos.shape[:-2], pos.shape[-2]
    K, M = waypoints.shape[-2], cyl_pos.shape[-2]
    drones = lead + (n,)

    # The current waypoint, the next one and the gate passed last, gathered in one go: [..., n, 3 picks, 3].
    target = _full(xp, xp.asarray(target), drones)
    k = xp.minimum(target, K - 1)
    pick = xp.stack([k, xp.minimum(k + 1, K - 1), xp.maximum(target - 1, 0)], axis=-1)[..., None]
    wp = xp.take_along_axis(_full(xp, waypoints, drones + (K, 3)), pick, axis=-2)
    nrm = xp.take_along_axis(_full(xp, normals, drones + (K, 3)), pick, axis=-2)
    to_target = wp[..., 0, :] - pos
    # The gate just passed stays in view: a drone turning towards the next gate right after the plane can
    # still clip this frame from behind (it did, at low filter gains, see README). Goals have no normal.
    has_prev = ((target >= 1) & xp.any(nrm[..., 2, :] != 0, axis=-1))[..., None]
    dtype = pos.dtype
    low, high = xp.asarray(arena_low, dtype=dtype), xp.asarray(arena_high, dtype=dtype)
    own = _assemble(xp, OWN, {
        "target_rel": pos - wp[..., 0, :],
        "target_normal": nrm[..., 0, :],
        "next_target_rel": pos - wp[..., 1, :],
        "target_dir": to_target / xp.maximum(norm(to_target)[..., None], MIN_TARGET_DIST),
        "prev_gate_rel": xp.where(has_prev, pos - wp[..., 2, :], 0.0),
        "prev_gate_normal": xp.where(has_prev, nrm[..., 2, :], 0.0),
        "altitude": pos[..., 2:3],
        "quat": quat,
        "vel": vel,
        "ang_vel": ang_vel,
        "wall_clearance": wall_clearance(pos, low, high),
    }, drones)

    # Cylinders [..., n, M, 6]: all zero for one that is absent this episode.
    rel = cyl_pos[..., None, :, :] - pos[..., :, None, :2]
    gap = norm(rel) - cyl_radius[..., None, :] - collision_radius
    cyl = _assemble(xp, CYL, {"rel_xy": rel, "clearance": gap[..., None], "vel_xy": cyl_vel[..., None, :, :],
                              "present": xp.ones_like(gap)[..., None]}, drones + (M,))
    if not _all(cyl_present):
        cyl = xp.where(xp.asarray(cyl_present)[..., None, :, None], cyl, 0.0)

    # Neighbours [..., n, n - 1, 7] in index order: all zero for one that is not flying.
    idx = others(n)
    flat = idx.reshape(-1)

    def of_others(x):  # [..., n, 3] -> [..., n, n - 1, 3]
        return xp.reshape(xp.take(x, flat, axis=-2), drones + idx.shape[1:] + (x.shape[-1],))

    seen = xp.reshape(xp.take(_full(xp, xp.asarray(flying), drones), flat, axis=-1), drones + idx.shape[1:])
    rel_pos = of_others(pos) - pos[..., :, None, :]
    nbr = _assemble(xp, NBR, {"rel_pos": rel_pos, "rel_vel": of_others(vel) - vel[..., :, None, :],
                              "present": xp.ones_like(rel_pos[..., :1])}, drones + (n - 1,))
    if neighbour_accel:  # carried beside each row through the selection below, then split off
        accel = _assemble(xp, NBR_ACCEL, {"tilt_accel": of_others(tilt_accel(quat)[..., :2])}, drones + (n - 1,))
        nbr = xp.concat([nbr, accel], axis=-1)
    if not _all(seen):
        nbr = xp.where(seen[..., None], nbr, 0.0)
    if max_neighbours:
        nbr = nearest_rows(nbr, seen, max_neighbours)
    k_nbr = nbr.shape[-2]
    tail = []
    if neighbour_accel:
        nbr, accel = nbr[..., :NBR.dim], nbr[..., NBR.dim:]
        tail = [xp.reshape(accel, drones + (k_nbr * NBR_ACCEL.dim,))]
    return xp.concat([own, xp.reshape(cyl, drones + (M * CYL.dim,)), xp.reshape(nbr, drones + (k_nbr * NBR.dim,)),
                      *tail], axis=-1)

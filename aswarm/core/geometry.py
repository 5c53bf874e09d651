"""Gate and cylinder geometry, written once for numpy and JAX (the array API).

Every function asks its array arguments for their namespace (:func:`namespace`) and uses only that
namespace's functions, so the simulator calls it on traced JAX arrays inside ``jit``/``vmap`` and the
flight runtime calls it on numpy arrays in a process that has no JAX. Shapes broadcast over leading
axes ``...`` (worlds, drones). Arrays are built with ``stack``/``concat``/``where``, never updated in place.

Conventions: positions in metres, world frame, z up; a gate's ``yaw`` is its direction of passage
(rad, from +x towards +y); a gate's centre is the centre of its square opening.
"""

from __future__ import annotations

from types import ModuleType

import numpy as np

from aswarm.core.numpy_namespace import NUMPY

# Clearance reported for what is absent (an obstacle that does not exist this episode, a drone that left).
FAR = 1e3
# Segments of zero length are treated as points: |ab|^2 is floored here.
_MIN_SQ_LENGTH = 1e-12
# m/s²: the gravity the safety filter's second-order look-ahead tilts (:func:`tilt_accel`), the drone model's.
GRAVITY = 9.81
# The thrust axis' vertical component is floored here in :func:`tilt_accel`: a drone on its side is finite.
_MIN_UPRIGHT = 1e-3


def namespace(*xs) -> ModuleType:
    """The array namespace of the first argument that has one (numpy for Python scalars; for a numpy array,
    numpy with cheaper calls that return the same arrays, :mod:`aswarm.core.numpy_namespace`)."""
    for x in xs:
        if type(x) is np.ndarray:  # the flight runtime's, many times a control step: numpy with cheaper calls
            return NUMPY
        get = getattr(x, "__array_namespace__", None)
        if get is not None:
            return get()
    return np


def norm(x, axis: int = -1):
    """Euclidean norm over ``axis`` (the same operations as ``jnp.linalg.norm``, so the same bits)."""
    xp = namespace(x)
    return xp.sqrt(xp.sum(x * x, axis=axis))


def tilt_accel(quat, gravity: float = GRAVITY):
    """[..., 3] the acceleration a drone's attitude alone gives (quat [..., 4], body->world, [w, x, y, z]): its
    thrust along the body z axis R e_z, as large as holds its altitude, so horizontally g (R e_z)_xy / (R e_z)_z and
    vertically 0. What motion capture gives of every drone's acceleration without differentiating positions twice
    (``experiments/lookahead_model_error.py`` fits the safety filter's second-order look-ahead on it)."""
    xp = namespace(quat)
    w, x, y, z = (quat[..., i] for i in range(4))
    up = xp.maximum(1 - 2 * (x * x + y * y), _MIN_UPRIGHT)
    scale = gravity / up
    return xp.stack([scale * 2 * (x * z + w * y), scale * 2 * (y * z - w * x), xp.zeros_like(up)], axis=-1)


def horizontal(yaw):
    """[...] yaw (rad) -> [..., 3] horizontal unit vectors (a gate's direction of passage)."""
    xp = namespace(yaw)
    return xp.stack([xp.cos(yaw), xp.sin(yaw), xp.zeros_like(yaw)], axis=-1)


def gate_frames(gate_pos, gate_yaw, half_opening: float, bar: float):
    """Segments [..., 5, 2, 3] of each gate's frame: the 4 edges of the square and the post to the floor.

    gate_pos [..., 3], gate_yaw [...]. The bars' axes run ``half_opening + bar / 2`` from the centre.
    """
    xp = namespace(gate_pos, gate_yaw)
    c = half_opening + bar / 2
    lat = xp.stack([-xp.sin(gate_yaw), xp.cos(gate_yaw), xp.zeros_like(gate_yaw)], axis=-1)  # [..., 3]
    up = xp.asarray([0.0, 0.0, 1.0], dtype=gate_pos.dtype)
    corners = ((-c, -c), (c, -c), (c, c), (-c, c))
    pts = xp.stack([gate_pos + a * lat + b * up for a, b in corners], axis=-2)  # [..., 4, 3]
    nxt = xp.concat([pts[..., 1:, :], pts[..., :1, :]], axis=-2)  # each corner's successor
    edges = xp.stack([pts, nxt], axis=-2)  # [..., 4, 2, 3]
    foot = xp.concat([gate_pos[..., :2], xp.zeros_like(gate_pos[..., 2:])], axis=-1)
    post = xp.stack([gate_pos - c * up, foot], axis=-2)[..., None, :, :]  # [..., 1, 2, 3]
    return xp.concat([edges, post], axis=-3)


def closest_on_segment(p, a, b):
    """The point of segment ``a``-``b`` nearest to ``p`` [..., 3] (broadcasting over leading axes)."""
    xp = namespace(p, a, b)
    ab = b - a
    t = xp.clip(xp.sum((p - a) * ab, axis=-1) / xp.maximum(xp.sum(ab * ab, axis=-1), _MIN_SQ_LENGTH), 0.0, 1.0)
    return a + t[..., None] * ab


def point_segment_distance(p, a, b):
    return norm(p - closest_on_segment(p, a, b))


def cylinders_at(center, axis, amplitude, omega, phase, t):
    """Cylinder centres and velocities [..., M, 2] at time ``t`` [...].

    A moving cylinder oscillates along the unit ``axis`` [..., M, 2] about ``center`` [..., M, 2]:
    ``center + axis * amplitude * sin(omega t + phase)``; a static one has ``amplitude`` 0.
    """
    xp = namespace(center, t)
    arg = omega * xp.asarray(t)[..., None] + phase
    pos = center + axis * (amplitude * xp.sin(arg))[..., None]
    vel = axis * (amplitude * omega * xp.cos(arg))[..., None]
    return pos, vel


def cylinder_accel_bound(amplitude, omega):
    """[..., M] the largest acceleration (m/s²) of each cylinder of :func:`cylinders_at`: amplitude ω² (0 if static).
    The safety filter's rows for a moving cylinder hold against any motion within this bound."""
    return amplitude * omega * omega


def gate_crossed(p_prev, p_new, gate_pos, normal, half_opening: float):
    """[...] true where the move ``p_prev -> p_new`` [..., 3] crosses a gate forwards, inside its opening.

    gate_pos [..., 3] is the gate's centre, ``normal`` [..., 3] its direction of passage
    (:func:`horizontal` of its yaw). The move must cross the gate's plane along the normal and the
    crossing point must lie inside the square opening of half-width ``half_opening``.
    """
    xp = namespace(p_prev, p_new, gate_pos)
    s0 = xp.sum((p_prev - gate_pos) * normal, axis=-1)
    s1 = xp.sum((p_new - gate_pos) * normal, axis=-1)
    forward = (s0 < 0) & (s1 >= 0)
    if isinstance(forward, np.ndarray) and not forward.any():
        return forward  # the common case on the flight side, every control step: nothing more to compute
    frac = s0 / xp.where(forward, s0 - s1, 1.0)
    hit = p_prev + frac[..., None] * (p_new - p_prev) - gate_pos
    lateral = hit[..., 0] * -normal[..., 1] + hit[..., 1] * normal[..., 0]
    return forward & (xp.abs(lateral) < half_opening) & (xp.abs(hit[..., 2]) < half_opening)


def cylinder_clearance(pos, center, radius, height, present, r: float):
    """[..., n, M] gap between drone spheres (radius ``r``) and vertical cylinders standing on the floor.

    pos [..., n, 3]; center [..., M, 2]; radius, height, present [..., M]. FAR for absent cylinders.
    """
    xp = namespace(pos, center)
    d_xy = norm(pos[..., :, None, :2] - center[..., None, :, :]) - radius[..., None, :] - r
    above = pos[..., :, None, 2] - height[..., None, :] - r  # > 0: passes over the top
    gap = xp.where(above > 0, xp.maximum(above, d_xy), d_xy)
    return xp.where(present[..., None, :], gap, FAR)


def drone_clearance(pos, active, r: float):
    """[..., n, n] gap between drone spheres; FAR on the diagonal and for inactive drones."""
    xp = namespace(pos)
    n = pos.shape[-2]
    eye = xp.eye(n, dtype=pos.dtype)
    diff = pos[..., :, None, :] - pos[..., None, :, :]
    dist = xp.sqrt(xp.sum(diff**2, axis=-1) + eye)  # the identity keeps the gradient finite on the diagonal
    valid = active[..., :, None] & active[..., None, :] & (eye == 0)
    return xp.where(valid, dist - 2 * r, FAR)


def frame_distance(s, lat, vert, half_opening: float, bar: float, height):
    """Distance from points to the centre lines of a gate frame, in the gate's coordinates.

    ``s`` along the passage direction, ``lat`` sideways and ``vert`` up, from the centre of the opening;
    ``height`` is the centre's height above the floor. The frame is the square of centre-line half-size
    ``half_opening + bar / 2`` in the plane s = 0 and the post from its bottom edge down to the floor: the
    segments of :func:`gate_frames`, in closed form (two distances where the segments take five).
    """
    xp = namespace(s, lat, vert)
    c = half_opening + bar / 2
    al, av = xp.abs(lat), xp.abs(vert)
    far = xp.maximum(al, av)
    outside = xp.maximum(al - c, 0.0) ** 2 + xp.maximum(av - c, 0.0) ** 2
    in_plane_square = xp.where(far <= c, c - far, xp.sqrt(outside))
    below = xp.clip(vert, -height, -c)  # the post's nearest point, measured along vert
    in_plane_post = xp.sqrt(lat**2 + (vert - below) ** 2)
    return xp.sqrt(s**2 + xp.minimum(in_plane_square, in_plane_post) ** 2)


def gate_clearance(pos, gate_pos, normal, half_opening: float, bar: float, r: float):
    """[..., n, G] gap between drone spheres (radius ``r``) [..., n, 3] and the (round) bars of the gates' frames
    (:func:`gate_frames`) at gate_pos [..., G, 3] with directions of passage ``normal`` [..., G, 3]
    (:func:`horizontal` of their yaws)."""
    rel = pos[..., :, None, :] - gate_pos[..., None, :, :]
    nx, ny = normal[..., None, :, 0], normal[..., None, :, 1]
    along = rel[..., 0] * nx + rel[..., 1] * ny
    lat = rel[..., 1] * nx - rel[..., 0] * ny
    d = frame_distance(along, lat, rel[..., 2], half_opening, bar, gate_pos[..., None, :, 2])
    return d - bar / 2 - r


def out_of_bounds(pos, low, high):
    """[..., n] true where a drone centre left the arena box sideways or through the ceiling (the floor is
    checked apart, as a collision of its own)."""
    xp = namespace(pos)
    low = xp.asarray(low, dtype=pos.dtype)
    high = xp.asarray(high, dtype=pos.dtype)
    outside = (pos > high) | xp.concat([pos[..., :2] < low[:2], xp.zeros_like(pos[..., 2:]) > 0], axis=-1)
    return xp.any(outside, axis=-1)


def wall_clearance(pos, low, high):
    """[..., 5] gaps from drone centres [..., 3] to the arena's walls at x low, x high, y low, y high, and
    its ceiling (m)."""
    xp = namespace(pos)
    return xp.stack([pos[..., 0] - low[0], high[0] - pos[..., 0], pos[..., 1] - low[1], high[1] - pos[..., 1],
                     high[2] - pos[..., 2]], axis=-1)

"""Analytic collision checks and gate crossings (MJX contacts stay off).

Every drone is a sphere of radius ``r`` (``CrazyflieParams.collision_radius``).
A *clearance* is the gap between surfaces: negative means collision. Absent
obstacles and inactive drones get :data:`FAR`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

FAR = 1e3

NONE, OBSTACLE, DRONE, GATE, FLOOR, BOUNDS = range(6)
KINDS = ("none", "obstacle", "drone", "gate", "floor", "bounds")


def cylinder_clearance(pos: jax.Array, center: jax.Array, radius: jax.Array, height: jax.Array,
                       present: jax.Array, r: float) -> jax.Array:
    """[n, M] gap between drone spheres and vertical cylinders standing on the floor."""
    d_xy = jnp.linalg.norm(pos[:, None, :2] - center[None], axis=-1) - radius[None] - r
    above = pos[:, None, 2] - height[None] - r  # > 0: passes over the top
    gap = jnp.where(above > 0, jnp.maximum(above, d_xy), d_xy)
    return jnp.where(present[None], gap, FAR)


def drone_clearance(pos: jax.Array, active: jax.Array, r: float) -> jax.Array:
    """[n, n] gap between drone spheres; FAR on the diagonal and for inactive drones."""
    n = pos.shape[0]
    diff = pos[:, None] - pos[None]
    dist = jnp.sqrt(jnp.sum(diff**2, -1) + jnp.eye(n))  # eye keeps the gradient finite
    valid = active[:, None] & active[None] & ~jnp.eye(n, dtype=bool)
    return jnp.where(valid, dist - 2 * r, FAR)


def gate_frames(gate_pos: jax.Array, gate_yaw: jax.Array, half_opening: float, bar: float):
    """Segments [G, 5, 2, 3] of each gate's frame (4 edges and the post to the floor)."""
    c = half_opening + bar / 2
    lat = jnp.stack([-jnp.sin(gate_yaw), jnp.cos(gate_yaw), jnp.zeros_like(gate_yaw)], -1)  # [G, 3]
    up = jnp.array([0.0, 0.0, 1.0])
    corners = [(-c, -c), (c, -c), (c, c), (-c, c)]
    pts = jnp.stack([gate_pos + a * lat + b * up for a, b in corners], 1)  # [G, 4, 3]
    edges = jnp.stack([pts, jnp.roll(pts, -1, axis=1)], 2)  # [G, 4, 2, 3]
    foot = gate_pos.at[:, 2].set(0.0)
    post = jnp.stack([gate_pos - c * up, foot], 1)[:, None]  # [G, 1, 2, 3]
    return jnp.concatenate([edges, post], 1)


def closest_on_segment(p: jax.Array, a: jax.Array, b: jax.Array) -> jax.Array:
    """The point of segment ``a``-``b`` nearest to ``p`` (broadcasting over leading axes)."""
    ab = b - a
    t = jnp.clip(jnp.sum((p - a) * ab, -1) / jnp.maximum(jnp.sum(ab * ab, -1), 1e-12), 0.0, 1.0)
    return a + t[..., None] * ab


def point_segment_distance(p: jax.Array, a: jax.Array, b: jax.Array) -> jax.Array:
    return jnp.linalg.norm(p - closest_on_segment(p, a, b), axis=-1)


def gate_clearance(pos: jax.Array, frames: jax.Array, bar: float, r: float) -> jax.Array:
    """[n, G] gap between drone spheres and the (round) bars of the gate frames."""
    d = point_segment_distance(pos[:, None, None], frames[None, :, :, 0], frames[None, :, :, 1])
    return jnp.min(d, -1) - bar / 2 - r


def out_of_bounds(pos: jax.Array, low, high) -> jax.Array:
    """[n] true where a drone centre left the arena box (the floor is checked apart)."""
    low = jnp.asarray(low).at[2].set(-FAR)
    return jnp.any((pos < low) | (pos > jnp.asarray(high)), -1)


def gate_crossed(p_prev: jax.Array, p_new: jax.Array, gate_pos: jax.Array, gate_yaw: jax.Array,
                 half_opening: float) -> jax.Array:
    """[n] true where the step p_prev -> p_new crosses the gate plane forwards, inside the opening.

    ``gate_pos``/``gate_yaw`` are each drone's current gate ([n, 3], [n]).
    """
    normal = jnp.stack([jnp.cos(gate_yaw), jnp.sin(gate_yaw), jnp.zeros_like(gate_yaw)], -1)
    s0 = jnp.sum((p_prev - gate_pos) * normal, -1)
    s1 = jnp.sum((p_new - gate_pos) * normal, -1)
    forward = (s0 < 0) & (s1 >= 0)
    frac = s0 / jnp.where(forward, s0 - s1, 1.0)
    hit = p_prev + frac[:, None] * (p_new - p_prev) - gate_pos
    lateral = hit[:, 0] * -normal[:, 1] + hit[:, 1] * normal[:, 0]
    return forward & (jnp.abs(lateral) < half_opening) & (jnp.abs(hit[:, 2]) < half_opening)

"""Scenario presets and their per-episode layouts.

Host side (numpy, once per config) a :class:`Geometry` fixes the nominal track
and a list of obstacle *slots* spaced so that no two jittered obstacles can
overlap or touch a gate; a config asking for more obstacles than slots fails
here, before anything is compiled. Device side, :func:`sample_layout` draws a
:class:`Layout` from a key inside ``jit``: gate jitter, which slots hold
obstacles, their offsets, moving obstacles' phases, start positions.
"""

from __future__ import annotations

import hashlib
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from aswarm.core import geometry as core_geometry
from aswarm.envs.config import EnvConfig
from aswarm.envs.presets import SCENARIOS

# The crossing's start line holds at most this many drones across the arena; more stand in lines behind it.
CROSSING_LANES = 16
# m between the arena's wall and the last line of starts (or goals): a goal jittered the most (0.2 m at
# layout_jitter 1) still lies outside the safety filter's wall barrier (drone radius 0.06 + margin 0.13 m). At 0.3
# the 64-drone crossing's back line had goals 0.1 m from the wall and its drones timed out short of them (README).
CROSSING_WALL_GAP = 0.4


@struct.dataclass
class Layout:
    """One episode's layout. n drones, K waypoints, G gates, M cylinders."""

    start_pos: jax.Array  # [n, 3]
    waypoints: jax.Array  # [n, K, 3] gate centres (shared) or each drone's goal
    gate_pos: jax.Array  # [G, 3] centre of the opening
    gate_yaw: jax.Array  # [G] direction of passage, rad
    cyl_center: jax.Array  # [M, 2] nominal centre
    cyl_axis: jax.Array  # [M, 2] unit direction of motion
    cyl_amplitude: jax.Array  # [M] m; 0 for a static cylinder
    cyl_omega: jax.Array  # [M] rad/s
    cyl_phase: jax.Array  # [M] rad
    cyl_radius: jax.Array  # [M]
    cyl_height: jax.Array  # [M]
    cyl_present: jax.Array  # [M] bool


def cylinders_at(layout: Layout, t: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Cylinder centres [M, 2] and velocities [M, 2] at time ``t`` (:func:`aswarm.core.geometry.cylinders_at`)."""
    return core_geometry.cylinders_at(layout.cyl_center, layout.cyl_axis, layout.cyl_amplitude, layout.cyl_omega,
                                      layout.cyl_phase, t)


class Geometry(NamedTuple):
    """Nominal, host-side geometry of a scenario (numpy)."""

    gate_pos: np.ndarray  # [G, 3]
    gate_yaw: np.ndarray  # [G]
    gate_radial: np.ndarray  # [G, 2] direction of radial gate jitter
    start_center: np.ndarray  # [3]
    start_heading: np.ndarray  # [2] unit
    goal_center: np.ndarray  # [3] (crossing)
    slot_pos: np.ndarray  # [S, 2] obstacle slots
    slot_tangent: np.ndarray  # [S, 2] along the direction of travel
    slot_normal: np.ndarray  # [S, 2] across it: static offset and motion axis


def _ellipse(a: float, b: float, n: int = 4096):
    theta = np.linspace(0.0, 2 * np.pi, n + 1)
    pts = np.stack([a * np.cos(theta), b * np.sin(theta)], -1)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=-1))])
    return theta, arc


def _on_ellipse(a: float, b: float, theta: np.ndarray):
    p = np.stack([a * np.cos(theta), b * np.sin(theta)], -1)
    t = np.stack([-a * np.sin(theta), b * np.cos(theta)], -1)
    t = t / np.linalg.norm(t, axis=-1, keepdims=True)
    return p, t


def track_length(cfg: EnvConfig) -> float:
    """Length of the racing line from the start to the last gate (m); 0 without gates."""
    if cfg.num_gates == 0:
        return 0.0
    a, b = cfg.track_radii
    _, arc = _ellipse(a, b)
    return float(arc[-1] * (cfg.num_gates - 0.5) / cfg.num_gates)


def geometry(cfg: EnvConfig) -> Geometry:
    kind = SCENARIOS[cfg.scenario].kind
    if kind == "track":
        geo = _track_geometry(cfg)
    elif kind == "crossing":
        geo = _crossing_geometry(cfg)
    else:
        geo = _hover_geometry(cfg)
    need = cfg.num_cylinders
    if need > len(geo.slot_pos):
        raise ValueError(
            f"cannot place num_obstacles + num_moving = {need} cylinders in scenario {cfg.scenario!r}: "
            f"at most {len(geo.slot_pos)} fit with obstacle_spacing={cfg.obstacle_spacing}"
        )
    return geo


def _track_geometry(cfg: EnvConfig) -> Geometry:
    if cfg.num_gates == 0:
        raise ValueError(f"invalid num_gates=0 for scenario {cfg.scenario!r}: a track needs >= 1 gate")
    a, b = cfg.track_radii
    g = cfg.num_gates
    theta_g = 2 * np.pi * np.arange(g) / g
    gp, gt = _on_ellipse(a, b, theta_g)
    gate_pos = np.concatenate([gp, np.full((g, 1), cfg.track_height)], -1)
    gate_yaw = np.arctan2(gt[:, 1], gt[:, 0])
    radial = gp / np.linalg.norm(gp, axis=-1, keepdims=True)
    theta_s = -np.pi / g  # half a gate interval before gate 0
    sp, st = _on_ellipse(a, b, np.array([theta_s]))

    # Slots every obstacle_spacing metres along the line from the start to the last gate.
    theta, arc = _ellipse(a, b)
    arc_of = lambda th: np.interp(np.mod(th - theta_s, 2 * np.pi), theta, arc)  # noqa: E731
    end = arc_of(theta_g[-1])
    s = np.arange(cfg.gate_clearance, end - cfg.gate_clearance + 1e-9, cfg.obstacle_spacing)
    gate_s = arc_of(theta_g)
    s = s[np.all(np.abs(s[:, None] - gate_s[None]) >= cfg.gate_clearance, axis=1)]
    th = np.interp(s, arc, theta) + theta_s
    slot_pos, slot_t = _on_ellipse(a, b, th)
    slot_n = np.stack([-slot_t[:, 1], slot_t[:, 0]], -1)
    return Geometry(gate_pos, gate_yaw, radial, np.array([*sp[0], cfg.track_height]), st[0],
                    np.zeros(3), slot_pos, slot_t, slot_n)


def _crossing_geometry(cfg: EnvConfig) -> Geometry:
    lo, hi = np.array(cfg.arena_low), np.array(cfg.arena_high)
    x0, x1 = lo[0] + 1.5, hi[0] - 1.5
    # Obstacle grid in the middle band, clear of the start and goal lines.
    xs = np.arange(x0 + 1.5, x1 - 1.5 + 1e-9, cfg.obstacle_spacing)
    ys = np.arange(lo[1] + 1.0, hi[1] - 1.0 + 1e-9, cfg.obstacle_spacing)
    xs, ys = xs - (xs.mean() if len(xs) else 0), ys - (ys.mean() if len(ys) else 0)
    grid = np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)
    ones = np.ones_like(grid)
    return Geometry(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 2)), np.array([x0, 0.0, cfg.track_height]),
                    np.array([1.0, 0.0]), np.array([x1, 0.0, cfg.track_height]), grid,
                    ones * [1.0, 0.0], ones * [0.0, 1.0])


def _hover_geometry(cfg: EnvConfig) -> Geometry:
    z = np.zeros((0, 2))
    c = np.array([0.0, 0.0, cfg.track_height])
    return Geometry(np.zeros((0, 3)), np.zeros(0), z, c, np.array([1.0, 0.0]), c, z, z, z)


def _crossing_offsets(n: int, cfg: EnvConfig, geo: Geometry) -> np.ndarray:
    """[n, 2] (behind, lateral) offsets of the crossing's starts (and, mirrored, goals).

    One line across the arena of at most CROSSING_LANES drones (16 stand 0.33 m apart in the default arena); more
    stand in further lines behind it, start_spacing apart or closer, so the last line keeps CROSSING_WALL_GAP to the
    wall. A single line of 32 would put drones 0.16 m apart: touching at the start.
    """
    per_line = min(n, CROSSING_LANES)
    lines = math.ceil(n / per_line)
    line, lane = np.arange(n) // per_line, np.arange(n) % per_line
    width = cfg.arena_high[1] - cfg.arena_low[1] - 2.0
    lateral = (lane - (per_line - 1) / 2) * min(1.0, width / max(per_line - 1, 1))
    room = min(geo.start_center[0] - cfg.arena_low[0], cfg.arena_high[0] - geo.goal_center[0]) - CROSSING_WALL_GAP
    spacing = min(cfg.start_spacing, room / (lines - 1)) if lines > 1 else 0.0
    return np.stack([line * spacing, lateral], -1)


def _start_grid(n: int, spacing: float) -> np.ndarray:
    """[n, 2] (behind, lateral) offsets of a compact grid, front row at 0."""
    cols = math.ceil(math.sqrt(n))
    i = np.arange(n)
    row, col = i // cols, i % cols
    in_row = np.minimum(cols, n - row * cols)
    return np.stack([row * spacing, (col - (in_row - 1) / 2) * spacing], -1)


def sample_layout(key: jax.Array, cfg: EnvConfig, geo: Geometry, moving_amplitude, moving_omega) -> Layout:
    """Draw an episode's layout; pure and jittable (``cfg`` and ``geo`` are static). The moving cylinders'
    amplitude (m) and angular frequency (rad/s) are the env params' (data, ``EnvParams``)."""
    kind = SCENARIOS[cfg.scenario].kind
    j = cfg.layout_jitter
    n, m = cfg.num_agents, cfg.num_cylinders
    k_gate, k_slot, k_off, k_phase, k_count, k_start, k_goal = jax.random.split(key, 7)
    u = lambda k, shape, lim: jax.random.uniform(k, shape, minval=-lim, maxval=lim)  # noqa: E731

    # Gates: radial, height and yaw jitter.
    g = len(geo.gate_pos)
    kg = jax.random.split(k_gate, 3)
    gate_xy = jnp.asarray(geo.gate_pos[:, :2]) + jnp.asarray(geo.gate_radial) * u(kg[0], (g, 1), 0.3 * j)
    gate_z = geo.gate_pos[:, 2] + jax.random.uniform(kg[1], (g,), minval=-0.2 * j, maxval=0.3 * j)
    gate_pos = jnp.concatenate([gate_xy, gate_z[:, None]], -1)
    gate_yaw = jnp.asarray(geo.gate_yaw) + u(kg[2], (g,), np.deg2rad(10.0) * j)

    # Cylinders: a random subset of slots, jittered inside the slot.
    slots = jax.random.permutation(k_slot, len(geo.slot_pos))[:m]
    static = jnp.arange(m) < cfg.num_obstacles
    normal, tangent = jnp.asarray(geo.slot_normal)[slots], jnp.asarray(geo.slot_tangent)[slots]

    def offsets(k):
        ko = jax.random.split(k, 2)
        lateral = jnp.where(static, u(ko[0], (m,), cfg.obstacle_lateral * j), 0.0)
        along = u(ko[1], (m,), 0.2 * j)
        return jnp.asarray(geo.slot_pos)[slots] + normal * lateral[:, None] + tangent * along[:, None]

    # Draw 0 is from k_off itself, so a scenario whose slots are too far apart ever to break the gap rule
    # (the race) keeps the layouts it always had; later draws replace it only where it breaks the rule.
    # One vmapped draw, not a Python loop of them: each random call inlines a copy of the generator, and a loop
    # of 16 made this function the slowest part of the env to compile. The numbers are the loop's.
    keys = jax.vmap(jax.random.fold_in, (None, 0))(k_off, jnp.arange(1, cfg.layout_draws))
    draws = jax.vmap(offsets)(jnp.concatenate([k_off[None], keys]))
    pair = jnp.linalg.norm(draws[:, :, None] - draws[:, None, :], axis=-1) - 2 * cfg.obstacle_radius
    both = static[:, None] & static[None, :] & ~np.eye(m, dtype=bool)
    narrowest = jnp.min(jnp.where(both, pair, jnp.inf), axis=(1, 2), initial=jnp.inf)  # [draws]
    ok = narrowest >= cfg.min_obstacle_gap
    # The first draw that keeps every gap; if none does (a config packed too tightly), the widest.
    pick = jnp.where(jnp.any(ok), jnp.argmax(ok), jnp.argmax(narrowest))
    center = draws[pick]
    n_moving = jax.random.randint(k_count, (), cfg.min_moving, cfg.most_moving + 1)
    present = static | (jnp.arange(m) - cfg.num_obstacles < n_moving)
    omega = jnp.where(static, 0.0, moving_omega)
    if tuple(cfg.moving_speed_scale) != (1.0, 1.0):  # static: the default draws nothing (the layouts it always had)
        lo, hi = cfg.moving_speed_scale
        omega = omega * jax.random.uniform(jax.random.fold_in(k_phase, 1), (m,), minval=lo, maxval=hi)

    # Starts: behind the start point (a column or a grid), facing the direction of travel.
    heading = jnp.asarray(geo.start_heading)
    left = jnp.array([-heading[1], heading[0]])
    if kind == "crossing":
        offs = _crossing_offsets(n, cfg, geo)
    elif cfg.start_formation == "column":
        # Single file up to 4 drones; more fly in side-by-side files at most 4 deep, so the column stays
        # on the straight stretch behind the start.
        files = math.ceil(n / 4)
        row, lane = np.arange(n) // files, np.arange(n) % files
        offs = np.stack([row * cfg.start_spacing, (lane - (files - 1) / 2) * cfg.start_spacing], -1)
    else:
        offs = _start_grid(n, cfg.start_spacing)
    ks = jax.random.split(k_start, 2)
    start_xy = geo.start_center[:2] - offs[:, :1] * heading + offs[:, 1:] * left + u(ks[0], (n, 2), 0.1 * j)
    start_z = geo.start_center[2] + u(ks[1], (n, 1), 0.1 * j)
    start_pos = jnp.concatenate([start_xy, start_z], -1)

    if kind == "track":
        waypoints = jnp.broadcast_to(gate_pos, (n, g, 3))
    elif kind == "crossing":
        # Mirrored: a drone standing in a line behind the start has its goal in a line beyond the goal line.
        goal_xy = offs[:, :1] * heading + offs[:, 1:] * left
        goal = jnp.asarray(geo.goal_center) + jnp.concatenate([goal_xy, jnp.zeros((n, 1))], -1)
        waypoints = (goal + u(k_goal, (n, 3), 0.2 * j) * jnp.array([1.0, 1.0, 0.5]))[:, None]
    else:
        direction = jax.random.normal(k_goal, (n, 3))
        direction = direction / jnp.linalg.norm(direction, axis=-1, keepdims=True)
        waypoints = (start_pos + direction * (0.5 + 0.5 * j))[:, None]

    return Layout(
        start_pos=start_pos, waypoints=waypoints, gate_pos=gate_pos, gate_yaw=gate_yaw,
        cyl_center=center, cyl_axis=normal, cyl_amplitude=jnp.where(static, 0.0, moving_amplitude),
        cyl_omega=omega, cyl_phase=jax.random.uniform(k_phase, (m,), maxval=2 * np.pi),
        cyl_radius=jnp.full((m,), cfg.obstacle_radius), cyl_height=jnp.full((m,), cfg.obstacle_height),
        cyl_present=present,
    )


def layout_digest(cfg: EnvConfig, seed: int, count: int = 8) -> str:
    """A sha256 of the first ``count`` layouts drawn from ``seed`` under ``cfg`` (its default moving-cylinder
    amplitude and period): an edit of the layout code that changes what a config's episodes look like changes
    it, a comment or a refactor does not. Cached results key on it (the safety matrix's cells)."""
    geo = geometry(cfg)
    keys = jax.random.split(jax.random.PRNGKey(seed), count)
    draw = jax.jit(jax.vmap(lambda k: sample_layout(k, cfg, geo, cfg.moving_amplitude, 2 * np.pi / cfg.moving_period)))
    h = hashlib.sha256()
    for leaf in jax.tree.leaves(draw(keys)):
        # 5 decimals (10 um): the same layout drawn by another XLA build that rounds the last bit differently
        # keeps its digest.
        h.update(np.round(np.asarray(leaf, np.float64), 5).tobytes())
    return h.hexdigest()

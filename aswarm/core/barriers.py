"""Control-barrier-function rows of the safety filter, written once for numpy and JAX (the array API).

Model: each drone is a single integrator at the velocity level, ``ṗ ≈ u`` with ``u ∈ R^3`` the
world-frame velocity command. Every hazard ``j`` has a barrier ``h_j(p) ≥ 0`` (safe set) and the CBF
condition

    ḣ_j = ∇h_j · (u − v_j) ≥ −γ_j h_j,

with ``v_j`` the hazard's velocity and ``γ_j > 0`` a class-K gain (1/s). Each condition is a half-space
``a_j · u ≥ b_j``: one :class:`Rows` entry. The QP that finds the command closest to the policy's
within all of them is solved twice, by ``aswarm.agents.cbf_filter`` (JAX, fixed shape under ``jit``)
and ``aswarm.flight.cbf`` (numpy, early exit for latency); both take their rows from here.

Every barrier is a distance (clearance minus margin), so every ``∇h`` is a unit vector and ``γ`` has
one meaning for every hazard: the gap may close at most ``γ h`` m/s. Functions take leading batch axes
``...`` (worlds, drones) and, like :mod:`aswarm.core.geometry`, ask their arguments for their array
namespace and build arrays without in-place writes, so the simulator traces them inside ``jit``/``vmap``
and the flight runtime runs them in a process without JAX. Rows from observations
(:func:`obs_rows`) are laid out ``[cylinders M | neighbours K | floor 1 | walls 5 | gate frame 5 |
previous gate 5]``.

A drone whose command has an acceleration limit cannot take back a closing speed at once: for the
cylinders, :func:`cylinder_braking_rows` replaces the velocity condition by one on a braking-distance
barrier of relative degree 2 (``SafetyFilterConfig.braking``), and :func:`neighbour_braking_rows` does the same for
the other drones (``SafetyFilterConfig.neighbour_braking``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from aswarm.core import geometry
from aswarm.core.layout import CYL, NBR, OWN

# Below this length a direction is taken as zero (its row is ignored; keeps gradients finite).
EPS = 1e-9
# Inward normals of the arena's walls, in the order of the observation's wall_clearance field.
WALL_NORMALS = ((1.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, -1.0))
# m: the gap below which cylinder_braking_rows holds √(a/2h) at its value there (it grows without bound at contact).
BRAKING_MIN_GAP = 0.02
# Rows after the point hazards in obs_rows, by group: the floor, the 4 walls and the ceiling, and both gates' 5 bars.
FIXED_GROUPS = (("floor", 1), ("walls", 5), ("gate", 5), ("prev_gate", 5))
FIXED_ROWS = sum(k for _, k in FIXED_GROUPS)
# An observed gate direction of passage is a unit vector, an absent gate's is 0: tested against this |n|².
_GATE_PRESENT_SQ = 0.25
# The own fields of the current gate and of the one passed last: (offset, direction of passage).
_GATE_FIELDS = (("target_rel", "target_normal"), ("prev_gate_rel", "prev_gate_normal"))


def _gate_columns(which: int) -> np.ndarray:
    """[2 gates, 3] columns of an own row holding field ``which`` (0 offset, 1 direction) of both gates: the
    numpy path of obs_rows reads both gates in one go (see there)."""
    cols = [OWN.slice(fields[which]) for fields in _GATE_FIELDS]
    if any(sl.stop - sl.start != 3 for sl in cols):
        raise ImportError("obs_rows expects the gates' offsets and directions of passage as 3 numbers each")
    return np.array([np.arange(sl.start, sl.stop) for sl in cols])


_GATE_REL_COLS, _GATE_NORMAL_COLS = _gate_columns(0), _gate_columns(1)


class Rows(NamedTuple):
    """Linear CBF constraints ``A u ≥ b``: A [..., m, 3] (∇h_j), b [..., m], mask [..., m] (present rows),
    h [..., m] barrier values (m): clearance minus margin, negative inside the margin."""

    A: object
    b: object
    mask: object
    h: object


def unit(d):
    """(||d||, d/||d||) over the last axis; zero direction where d = 0 (keeps gradients finite)."""
    xp = geometry.namespace(d)
    sq = xp.sum(d * d, axis=-1)
    ok = sq > EPS**2
    if isinstance(ok, np.ndarray) and ok.all():  # numpy with no zero direction (in flight, most calls): the
        dist = np.sqrt(sq)  # values of the masked form below, without its three passes of masking
        return dist, d / dist[..., None]
    dist = xp.sqrt(xp.where(ok, sq, 1.0))
    return xp.where(ok, dist, 0.0), xp.where(ok[..., None], d / dist[..., None], 0.0)


def concat(parts) -> Rows:
    """The rows of ``parts`` one after the other."""
    xp = geometry.namespace(parts[0].A)
    return Rows(*(xp.concat(list(f), axis=-2 if i == 0 else -1) for i, f in enumerate(zip(*parts))))


def _rows_like(h, normals):
    """Constant unit normals [k, 3] for the rows of ``h`` [..., k] (an addition rather than ``broadcast_to``:
    numpy's costs ~10 µs a call, and the flight filter runs every control step)."""
    xp = geometry.namespace(h)
    return xp.zeros_like(h)[..., None] + xp.asarray(normals, dtype=h.dtype)


def cylinder_rows(pos, center, radius, vel, present, gamma, *, drone_radius: float, margin: float = 0.0,
                  motion: tuple | None = None) -> Rows:
    """Rows for vertical cylinders (infinite in z: conservative above a cylinder's top).

    pos [..., 3]; center, vel [..., M, 2] (cylinder xy position and velocity); radius, present [..., M];
    gamma [..., M] or broadcastable. h = ||p_xy − c|| − (R + r_d + margin): the distance form rather than
    the squared one, so that a drone may not approach a large cylinder faster than a small one at the
    same gap (the squared form's rate is γ(d² − R²)/2d).

    ``motion`` = (accel [..., M], lag) for cylinders that may move, ``center`` then being the look-ahead point
    c + τ v_c (τ = ``lag``): it moves at v_c + τ a_c, and the observation holds v_c but not the acceleration a_c.
    With |a_c| at most ``accel`` the row holds for any such motion: n · u ≥ n · v_c + τ accel − γ h.
    """
    xp = geometry.namespace(pos, center)
    dist, n_xy = unit(pos[..., None, :2] - center)  # [..., M], [..., M, 2]
    h = dist - (radius + drone_radius + margin)
    A = xp.concat([n_xy, xp.zeros_like(n_xy[..., :1])], axis=-1)
    b = xp.sum(n_xy * vel, axis=-1) - gamma * h
    if motion is not None:
        accel, lag = motion
        b = b + lag * accel
    return Rows(A, b, present, h)


def _braking_speed(h, decel):
    """(√(2 decel h), its slope √(decel / 2h)) of the braking barriers: the speed from which braking at ``decel``
    stops within the gap h (0 inside the barrier), and how fast it grows with h (h floored at BRAKING_MIN_GAP)."""
    xp = geometry.namespace(h)
    return xp.sqrt(2.0 * decel * xp.maximum(h, 0.0)), xp.sqrt(decel / (2.0 * xp.maximum(h, BRAKING_MIN_GAP)))


def cylinder_braking_rows(pos, cmd, center, radius, vel, present, gamma, *, accel, lag: float, decel: float,
                          dt: float, drone_radius: float, margin: float = 0.0) -> Rows:
    """Rows for vertical cylinders with relative degree 2: a braking-distance barrier on a drone whose command
    cannot change faster than ``decel`` (m/s², ``EnvConfig.command_accel_limit``).

    pos [..., 3] the drone's look-ahead point q, cmd [..., 3] the command it flies now (q̇ = cmd for a first-order
    lag); center, vel [..., M, 2] the cylinders' look-ahead points and velocities, accel [..., M] their acceleration
    bounds (0 for static ones), radius, present [..., M]; gamma [..., M] or broadcastable (1/s). With n the unit
    normal from the cylinder, h = ||q − c|| − (R + r_d + margin) and the worst-case opening speed
    w_n = n · (cmd − v_c) − τ accel (the cylinder's look-ahead point moves at v_c + τ a_c), the barrier is

        B = √(2 decel h) + w_n ≥ 0:

    closing at −w_n, braking at ``decel`` stops short of the cylinder as it moves now. With the command moving to u
    over one control step (u̇ ≈ (u − cmd)/dt), the cylinder's acceleration at its bound against the drone over that
    step, and Ḃ ≥ −γ B, the row is linear in u:

        n · u ≥ n · cmd + dt (accel − |w_⊥|²/d − √(decel/2h) w_n − γ B),

    |w_⊥|²/d the turning of n as the drone passes (it helps). At B = 0 and a still cylinder it asks for exactly
    ``decel`` of braking, which the command limit allows. It holds against the cylinder's acceleration step by step,
    not over the whole braking: B with decel − accel in place of decel would, and on the dynamic preset it left the
    drones almost no way past (README). h is floored at BRAKING_MIN_GAP in √(decel/2h).
    """
    xp = geometry.namespace(pos, center)
    dist, n_xy = unit(pos[..., None, :2] - center)
    h = dist - (radius + drone_radius + margin)
    w = cmd[..., None, :2] - vel
    n_w = xp.sum(n_xy * w, axis=-1)
    w_n = n_w - lag * accel
    perp_sq = xp.maximum(xp.sum(w * w, axis=-1) - n_w * n_w, 0.0)
    speed, slope = _braking_speed(h, decel)
    B = speed + w_n
    rate = accel - perp_sq / xp.maximum(dist, BRAKING_MIN_GAP) - slope * w_n
    b = xp.sum(n_xy * cmd[..., None, :2], axis=-1) + dt * (rate - gamma * B)
    A = xp.concat([n_xy, xp.zeros_like(n_xy[..., :1])], axis=-1)
    return Rows(A, b, present, h)


def neighbour_rows(pos, vel, nbr_pos, nbr_vel, present, gamma, *, drone_radius: float, margin: float = 0.0,
                   share=0.5, reference: float = 1.0, release: float = 0.0) -> Rows:
    """Rows for the other drones (spheres).

    pos, vel [..., 3] (this drone); nbr_pos, nbr_vel [..., K, 3]; present [..., K]; gamma [..., K] or
    broadcastable; share [] or [..., K]. h = ||p − q|| − (2 r_d + margin) and the pair condition is
    n · (u − u_k) ≥ −γ h with n = (p − q)/||p − q||. Responsibility is split: this drone keeps

        n · u ≥ n · ((1 − w) v + w v_k) − w γ h,      w = share ∈ (0, 1].

    If the neighbour applies the same rule with share 1 − w (w = 1/2 for both by default) and both see
    the same velocities, the two rows add up to the pair condition for any v, v_k: the split is sound
    without knowing the other's command. The reference (1 − w) v + w v_k (an ORCA-style reciprocal
    split) makes each drone take its share of the change from the current relative velocity; with
    v = v_k = 0 it reduces to the classic n · u ≥ −γ h / 2. share = 1 treats the neighbour as a
    non-cooperative moving obstacle. ``reference`` λ scales that reference, λ ((1 − w) v + w v_k): the rows add up
    for any λ both drones use; 0 is the classic form at any velocity, where a drone may always brake to rest along
    n and closes on the neighbour at no more than its share of γ h, whatever the neighbour's speed away.
    ``release`` r > 0 (m/s) lowers that scale with how fast the pair closes, c = n · (v_k − v) (the same for both
    drones), to λ max(0, 1 − c / r): a column flying at one speed (c = 0) keeps the current velocities as reference,
    so a follower may keep pace, while a pair that closes fast (a leader braking for a gate frame) falls to the
    classic form, where the leader may brake and the follower must. Both drones compute the same scale, so their
    rows still add up.
    """
    xp = geometry.namespace(pos, nbr_pos)
    dist, n = unit(pos[..., None, :] - nbr_pos)  # [..., K], [..., K, 3]
    h = dist - (2.0 * drone_radius + margin)
    share = xp.asarray(share)
    ref_vel = (1.0 - share)[..., None] * vel[..., None, :] + share[..., None] * nbr_vel
    if release > 0:  # (static, as the reference below)
        closing = xp.sum(n * (nbr_vel - vel[..., None, :]), axis=-1)
        ref_vel = (reference * xp.clip(1.0 - closing / release, 0.0, 1.0))[..., None] * ref_vel
    elif reference != 1.0:  # (static: the default traces as before)
        ref_vel = reference * ref_vel
    b = xp.sum(n * ref_vel, axis=-1) - share * gamma * h
    return Rows(n, b, present, h)


def closing_share(pos, vel, nbr_pos, nbr_vel, *, soft: float, least: float):
    """[..., K] this drone's share of each pair's neighbour row (``share`` of :func:`neighbour_rows`), split by
    closing speed rather than in halves.

    pos, vel [..., 3] this drone; nbr_pos, nbr_vel [..., K, 3]. With n the unit normal from the neighbour, this
    drone closes at c = max(0, −n · v) and the neighbour at c_k = max(0, n · v_k), and

        w = (c + s) / (c + c_k + 2 s),   clipped to [least, 1 − least],

    with s = ``soft`` (m/s) the speed below which the split stays near halves. The neighbour, seeing the same
    positions and velocities, computes 1 − w (c and c_k swap), so the pair's two rows still add up to the pair
    condition: the split stays sound. The drone that closes keeps the larger share: a drone ahead of a follower is
    no longer pushed on by it, but with :func:`neighbour_rows`' velocity reference a small share also holds the
    drone near its own velocity along n, so it may not brake much either (README, "Splitting a pair by closing
    speed": on the race it flew slower and hit more gate frames).
    """
    xp = geometry.namespace(pos, nbr_pos)
    _, n = unit(pos[..., None, :] - nbr_pos)
    own = xp.maximum(-xp.sum(n * vel[..., None, :], axis=-1), 0.0)
    other = xp.maximum(xp.sum(n * nbr_vel, axis=-1), 0.0)
    return xp.clip((own + soft) / (own + other + 2.0 * soft), least, 1.0 - least)


def neighbour_braking_rows(pos, cmd, nbr_pos, nbr_vel, present, gamma, *, decel: float, dt: float,
                           drone_radius: float, margin: float = 0.0, share=0.5) -> Rows:
    """Rows for the other drones with relative degree 2: :func:`cylinder_braking_rows`' barrier for a pair of drones
    that both brake, split as :func:`neighbour_rows` splits the velocity condition.

    pos [..., 3] this drone's look-ahead point, cmd [..., 3] the command it flies now; nbr_pos, nbr_vel [..., K, 3]
    the neighbours' look-ahead points and velocities; present [..., K]; gamma [..., K] or broadcastable; share []
    (this drone's part of the pair's braking, 1/2 when both follow the rule). With n the unit normal from the
    neighbour, h = ||q − q_k|| − (2 r_d + margin) and w = cmd − v_k (the neighbour's command is not observed: its
    velocity stands in), the pair closing at −n · w can stop within h when the two brake at ``decel`` each, which
    the split asks of a drone as decel / share of relative braking:

        B = √(2 (decel / share) h) + n · w ≥ 0,

    and Ḃ ≥ −γ B, with each drone taking ``share`` of the change of n · w over one control step, is the row

        n · u ≥ n · cmd − dt share (|w_⊥|²/d + √(decel / (2 share h)) n · w + γ B).

    At B = 0 it asks for exactly ``decel`` of braking, which the command limit allows. Two drones that both keep it
    and see each other's commands as they are (rather than their velocities) keep the pair's barrier; the velocity
    is exact for a drone flying a steady command and lags one that changes it. h is floored at BRAKING_MIN_GAP in
    √(·/h), as for the cylinders.
    """
    xp = geometry.namespace(pos, nbr_pos)
    dist, n = unit(pos[..., None, :] - nbr_pos)
    h = dist - (2.0 * drone_radius + margin)
    share = xp.asarray(share, dtype=pos.dtype)
    pair_decel = decel / share
    w = cmd[..., None, :] - nbr_vel
    n_w = xp.sum(n * w, axis=-1)
    perp_sq = xp.maximum(xp.sum(w * w, axis=-1) - n_w * n_w, 0.0)
    speed, slope = _braking_speed(h, pair_decel)
    B = speed + n_w
    rate = perp_sq / xp.maximum(dist, BRAKING_MIN_GAP) + slope * n_w + gamma * B
    b = xp.sum(n * cmd[..., None, :], axis=-1) - dt * share * rate
    return Rows(n, b, present, h)


def floor_row(pos, gamma, *, z_min: float) -> Rows:
    """One row for the floor: h = z − z_min (z_min: lowest allowed altitude of the drone centre)."""
    xp = geometry.namespace(pos)
    h = pos[..., 2:3] - z_min
    return Rows(_rows_like(h, ((0.0, 0.0, 1.0),)), -gamma * h, xp.ones(h.shape, dtype=bool), h)


def wall_rows(clearance, gamma, *, drone_radius: float, margin: float = 0.0, braking: tuple | None = None) -> Rows:
    """Rows for the arena's 4 side walls and its ceiling: ``clearance`` [..., 5] is the drone centre's distance
    to each (x low, x high, y low, y high, ceiling), h = clearance − (r_d + margin), ∇h the inward normal.

    ``braking`` = (cmd [..., 3], decel, dt): each wall's row also holds its braking barrier, :func:`gate_rows`' for a
    plane, whose normal does not turn: B = √(2 decel h) + n · cmd ≥ 0 and Ḃ ≥ −γ B give
    n · u ≥ n · cmd − dt (√(decel / 2h) n · cmd + γ B). Both rows share the normal, so the row takes the larger b:
    the braking barrier binds far off, where a fast drone must start braking, and the velocity row near, where √h
    would let the drone close at a speed only exact braking takes back (alone, the braking rows let the 1.5x moving
    cells' drones out of the arena 64 and 70 times as often as the velocity rows, README).
    """
    xp = geometry.namespace(clearance)
    h = clearance - (drone_radius + margin)
    A = _rows_like(h, WALL_NORMALS)
    present = xp.ones(h.shape, dtype=bool)
    if braking is None:
        return Rows(A, -gamma * h, present, h)
    cmd, decel, dt = braking
    n_c = xp.sum(A * cmd[..., None, :], axis=-1)
    speed, slope = _braking_speed(h, decel)
    return Rows(A, xp.maximum(-gamma * h, n_c - dt * (slope * n_c + gamma * (speed + n_c))), present, h)


def gate_rows(pos, gate_center, gate_normal, present, gamma, *, half_opening: float, bar: float,
              drone_radius: float, margin: float = 0.0, braking: tuple | None = None) -> Rows:
    """Rows for the frame of one gate: its 4 edges and the post to the floor (5 round bars).

    pos, gate_center (centre of the opening), gate_normal (horizontal direction of passage) [..., 3];
    present [...] bool; gamma [..., 5] or broadcastable. h = distance to the bar's axis − (bar/2 + r_d +
    margin), ∇h the unit vector from the nearest point of the bar to the drone: a drone flying through
    the middle of the opening sees only sideways normals and is not slowed.

    ``braking`` = (cmd [..., 3], decel, dt): the bars' rows are braking barriers instead, as
    :func:`cylinder_braking_rows`' for a still cylinder, B = √(2 decel h) + n · cmd ≥ 0 and Ḃ ≥ −γ B:

        n · u ≥ n · cmd − dt (|cmd_⊥|²/d + √(decel / 2h) n · cmd + γ B),

    with cmd_⊥ the command without its components along n and along the bar's axis e (n turns at cmd_⊥ / d
    beside a bar; at its ends, where the bar is a point, it turns faster, so this is the smaller, safe, value).
    """
    xp = geometry.namespace(pos, gate_center)
    yaw = xp.atan2(gate_normal[..., 1], gate_normal[..., 0])
    frames = geometry.gate_frames(gate_center, yaw, half_opening, bar)  # [..., 5, 2, 3]
    p = pos[..., None, :]
    dist, n = unit(p - geometry.closest_on_segment(p, frames[..., 0, :], frames[..., 1, :]))
    h = dist - (bar / 2 + drone_radius + margin)
    mask = xp.zeros(h.shape, dtype=bool) | present[..., None]
    if braking is None:
        return Rows(n, -gamma * h, mask, h)
    cmd, decel, dt = braking
    c = cmd[..., None, :]
    _, e = unit(frames[..., 1, :] - frames[..., 0, :])
    n_c, e_c = xp.sum(n * c, axis=-1), xp.sum(e * c, axis=-1)
    perp_sq = xp.maximum(xp.sum(c * c, axis=-1) - n_c * n_c - e_c * e_c, 0.0)
    speed, slope = _braking_speed(h, decel)
    B = speed + n_c
    rate = perp_sq / xp.maximum(dist, BRAKING_MIN_GAP) + slope * n_c + gamma * B
    return Rows(n, n_c - dt * rate, mask, h)


def barrier_rows(pos, vel, cyl_center, cyl_radius, cyl_vel, cyl_present, nbr_pos, nbr_vel, nbr_present, gamma, *,
                 drone_radius: float, margin: float = 0.0, floor_z: float = 0.0, neighbour_share=0.5) -> Rows:
    """Rows ``[cylinders M | neighbours K | floor 1]`` (m = M + K + 1) for drones at ``pos``.

    pos, vel [..., 3]: the drones' positions and velocities; cyl_center, cyl_vel [..., M, 2], cyl_radius,
    cyl_present [..., M]; nbr_pos, nbr_vel [..., K, 3], nbr_present [..., K] (the drone itself excluded);
    gamma: one class-K gain (1/s) per drone [...], or [..., m] in the rows' layout. Every barrier is a
    surface gap minus ``margin`` (the floor's: z − (floor_z + r_d + margin)).
    """
    return concat(_barrier_parts(pos, vel, cyl_center, cyl_radius, cyl_vel, cyl_present, nbr_pos, nbr_vel,
                                 nbr_present, gamma, drone_radius=drone_radius, margin=margin, floor_z=floor_z,
                                 neighbour_share=neighbour_share))


def _barrier_parts(pos, vel, cyl_center, cyl_radius, cyl_vel, cyl_present, nbr_pos, nbr_vel, nbr_present, gamma, *,
                   drone_radius: float, margin: float, floor_z: float, neighbour_share, neighbour_reference=1.0,
                   neighbour_release: float = 0.0, cyl_motion: tuple | None = None, cyl_braking: tuple | None = None,
                   nbr_braking: tuple | None = None, moving_gain_max: float = 0.0,
                   moving_margin: float = 0.0, moving_margin_time: float = 0.0, rail_speed: float = 0.0) -> list[Rows]:
    """:func:`barrier_rows` before its concatenation: [cylinder rows, neighbour rows, floor row]; with
    ``moving_gain_max`` > 0 and ``cyl_motion``, the rows of the cylinders with an acceleration bound > 0 (the moving
    ones) take at most that gain, and with ``moving_margin`` > 0 (m) keep that much more than ``margin``;
    ``moving_margin_time`` > 0 (s) adds that many seconds of the drone's closing speed on each moving cylinder
    (max(0, −n · (v − v_c)), v the drone's velocity: the margin is a state's, the row stays linear in u);
    ``rail_speed`` > 0 (m/s) takes each moving cylinder as moving on a straight line, its acceleration along its own
    velocity: the bound enters as accel |n · v_c/|v_c|| where |v_c| is at least that speed (any direction below it,
    where the observed velocity's direction is noise or the cylinder turns).
    ``cyl_braking`` = (cmd, decel, dt, lag) makes the cylinders' rows braking barriers (None: velocity rows);
    ``nbr_braking`` = (cmd, decel, dt, gain) adds the neighbours' braking rows as a fourth part, beside their
    velocity rows, with that class-K gain (1/s; 0: the neighbours' rows' own)."""
    xp = geometry.namespace(pos)
    M, K = cyl_center.shape[-2], nbr_pos.shape[-2]
    gamma = xp.asarray(gamma, dtype=pos.dtype)
    if gamma.ndim == pos.ndim - 1:
        gamma = gamma[..., None]
    if isinstance(gamma, np.ndarray) and gamma.shape[-1] == 1:
        # numpy, one gain per drone: it broadcasts in each product as it stands (the same values, no copies).
        g_cyl = g_nbr = g_floor = gamma
    else:
        # Broadcast and sliced per group, even for one gain per drone: the simulator's filter traces to the
        # program the shipped policy was evaluated with (a bare [..., 1] gain let XLA fuse it differently: not
        # the same bits).
        gamma = xp.broadcast_to(gamma, pos.shape[:-1] + (M + K + 1,))
        g_cyl, g_nbr, g_floor = gamma[..., :M], gamma[..., M:M + K], gamma[..., M + K:]
    if moving_gain_max > 0 and cyl_motion is not None:  # (a static choice: without it the rows trace as before)
        g_cyl = xp.where(cyl_motion[0] > 0, xp.minimum(g_cyl, xp.asarray(moving_gain_max, dtype=pos.dtype)), g_cyl)
    cyl_margin = margin
    if moving_margin > 0 and cyl_motion is not None:  # (static, as the gain cap above)
        cyl_margin = margin + (cyl_motion[0] > 0) * xp.asarray(moving_margin, dtype=pos.dtype)
    if (moving_margin_time > 0 or rail_speed > 0) and cyl_motion is not None:  # (static, as above)
        _, n_xy = unit(pos[..., None, :2] - cyl_center)  # each cylinder's normal, for both options below
    if moving_margin_time > 0 and cyl_motion is not None:
        closing = xp.maximum(-xp.sum(n_xy * (vel[..., None, :2] - cyl_vel), axis=-1), 0.0)
        cyl_margin = cyl_margin + (cyl_motion[0] > 0) * (xp.asarray(moving_margin_time, dtype=pos.dtype) * closing)
    if rail_speed > 0 and cyl_motion is not None:  # (static, as above; after the cap and the margins, which the
        # whole bound marks as moving)
        speed, heading = unit(cyl_vel)
        along = xp.where(speed >= rail_speed, xp.abs(xp.sum(n_xy * heading, axis=-1)), 1.0)
        cyl_motion = (cyl_motion[0] * along, cyl_motion[1])
    if cyl_braking is None:
        cyl = cylinder_rows(pos, cyl_center, cyl_radius, cyl_vel, cyl_present, g_cyl, drone_radius=drone_radius,
                            margin=cyl_margin, motion=cyl_motion)
    else:
        cmd, decel, dt, lag = cyl_braking
        accel = xp.zeros_like(cyl_radius) if cyl_motion is None else cyl_motion[0]
        cyl = cylinder_braking_rows(pos, cmd, cyl_center, cyl_radius, cyl_vel, cyl_present, g_cyl, accel=accel,
                                    lag=lag, decel=decel, dt=dt, drone_radius=drone_radius, margin=cyl_margin)
    parts = [cyl,
             neighbour_rows(pos, vel, nbr_pos, nbr_vel, nbr_present, g_nbr, drone_radius=drone_radius, margin=margin,
                            share=neighbour_share, reference=neighbour_reference, release=neighbour_release),
             floor_row(pos, g_floor, z_min=floor_z + drone_radius + margin)]
    if nbr_braking is not None:
        cmd, decel, dt, g_brake = nbr_braking
        g_brake = g_nbr if g_brake <= 0 else xp.asarray(g_brake, dtype=pos.dtype)
        parts.append(neighbour_braking_rows(pos, cmd, nbr_pos, nbr_vel, nbr_present, g_brake, decel=decel, dt=dt,
                                            drone_radius=drone_radius, margin=margin, share=neighbour_share))
    return parts


def obs_rows(layout, obs, gain, *, drone_radius: float, margin: float, gate_half_opening: float = 0.0,
             gate_bar: float = 0.0, floor_z: float = 0.0, neighbour_share=0.5,
             lookahead: tuple[float, float] = (0.0, 0.0), cyl_accel=None, braking: tuple | None = None,
             moving_gain_max: float = 0.0, moving_margin: float = 0.0, moving_margin_time: float = 0.0,
             rail_speed: float = 0.0, brake: tuple[bool, ...] = (True, False, False),
             braking_gain: float = 0.0, lookahead_accel: float = 0.0,
             closing_split: tuple[float, float] | None = None, neighbour_reference: float = 1.0,
             neighbour_release: float = 0.0) -> Rows:
    """Every drone's rows from what it observes: raw obs [..., n, D] -> A [..., n, m, 3], b, mask, h [..., n, m].

    Rows ``[cylinders M | neighbours K | floor 1 | walls 5 | current gate 5 | previous gate 5]``
    (m = M + K + 16). Everything the barriers need is in the observation (relative cylinder positions,
    their clearance and velocity, relative neighbour positions and velocities, altitude, wall clearances,
    the current and previous gates' centres and directions), so the simulator and the flight runtime
    filter from the very same rows. Positions are taken in a frame centred on the drone's horizontal
    position, with z its altitude above the floor. ``gain`` [..., n] is one class-K gain per drone,
    applied to all its rows. The gate rows are present when ``gate_bar > 0`` and the observation has
    that gate (non-zero direction). The gate passed last is kept: right after its plane a drone turning
    towards the next gate can clip its frame from behind. The walls keep the drone centre inside the
    arena: without them, swarms of 8 and 16 drones pushed their outer drones out of it (README).

    ``lookahead`` (τ_xy, τ_z) in s: every barrier is taken at the drone's look-ahead point q = p + τ v (and
    each moving hazard's at c + τ v_c) instead of its position. A drone whose velocity follows the command
    with a first-order lag τ (v̇ = (u − v)/τ) has q̇ = v + τ v̇ = u exactly, so the single-integrator rows
    above hold for q on the lagging drone; and p, the exponential average of q's past (ṗ = (q − p)/τ),
    stays in every convex safe set (floor, walls) that q keeps. (0, 0) is the plain single integrator.
    ``lookahead_accel`` c2 > 0 (s²) makes the horizontal point second order, q = p + τ_xy v + c2 a, with a each
    drone's acceleration from its attitude (:func:`aswarm.core.geometry.tilt_accel`: its own from its ``quat``, each
    neighbour's from the layout's ``neighbour_accel`` columns, which it then needs): the firmware drone behind its
    command limit is no first-order lag, and on it q' = u holds to 0.16 m/s rms with (τ_xy, c2) = (0.207, 0.039)
    where the best first-order point leaves 0.44 (``experiments/lookahead_model_error.py``).

    ``cyl_accel`` [..., n, M] (m/s², or None: the rows above, every cylinder holding its velocity): a bound on each
    cylinder's acceleration, for scenes where cylinders move. The observation holds each one's velocity but not its
    acceleration, so its row holds against the worst within the bound (:func:`cylinder_rows`' ``motion``; a static
    one, bound 0, keeps its row; nothing changes without a look-ahead, where the command acts at once).
    ``moving_gain_max`` > 0 (1/s): the rows of the cylinders whose bound is > 0 take at most this gain (a gain per
    hazard: conservative towards what moves); it needs ``cyl_accel``. ``moving_margin`` > 0 (m): those cylinders'
    rows keep that much more clearance than ``margin`` (their barrier binds that much sooner); it needs ``cyl_accel``.
    ``moving_margin_time`` > 0 (s): and that many seconds of the drone's closing speed on each of them more.
    ``rail_speed`` > 0 (m/s): each moving cylinder moves on a straight line, so its bound acts along its velocity
    (where it is at least that fast; :func:`_barrier_parts`).

    ``braking`` = (cmd [..., n, 3], decel, dt): the command each drone flies now, the command acceleration limit
    (m/s²) and the control period (s); the cylinders' rows are then :func:`cylinder_braking_rows` (relative degree
    2: the drone's speed towards a cylinder must leave room to brake at the limit), None the velocity rows above.
    ``brake`` = (cylinders, neighbours[, gate frames[, walls]]): which groups take braking rows when ``braking`` is
    given. The cylinders' and the gate frames' (:func:`gate_rows`' braking form) replace their velocity rows, the
    walls' (:func:`wall_rows`') make each wall's row the tighter of the two; the neighbours'
    (:func:`neighbour_braking_rows`) come on top of theirs, as K more rows after the previous gate's: the braking
    barrier bounds the closing speed from afar, where the velocity rows do not see it coming, and the velocity rows
    hold near, where the braking barrier's √h lets a pair close at a speed only exact braking on both sides would
    take back (alone, they collided in 98 % of the race-16 episodes, README). ``braking_gain`` (1/s, 0: the drone's
    gain) is the class-K gain of the neighbours' braking rows: B is a speed margin that braking alone keeps, so its
    gain can be far above the velocity rows'.

    ``closing_split`` = (soft, least): the neighbours' rows split each pair by :func:`closing_share` (taken at the
    look-ahead points) in place of ``neighbour_share``; None: ``neighbour_share``. ``neighbour_reference``,
    ``neighbour_release``: the neighbours' rows' reference velocity scale and the closing speed that lowers it
    (:func:`neighbour_rows`' ``reference`` and ``release``).
    """
    xp = geometry.namespace(obs)
    numpy = isinstance(obs, np.ndarray)
    own, cyl, nbr = layout.split(obs)
    alt = own[..., OWN.slice("altitude")]
    vel = OWN.get(own, "vel")
    zero = xp.zeros_like(alt)
    pos = xp.concat([zero, zero, alt], axis=-1)

    rel = CYL.get(cyl, "rel_xy")
    cyl_radius = geometry.norm(rel) - CYL.get(cyl, "clearance") - drone_radius
    cyl_vel = CYL.get(cyl, "vel_xy")
    nbr_vel = NBR.get(nbr, "rel_vel") + vel[..., None, :]
    nbr_pos = NBR.get(nbr, "rel_pos") + pos[..., None, :]
    clearance = OWN.get(own, "wall_clearance")
    at = pos
    if any(t != 0 for t in lookahead):  # (a static choice: the plain rows trace as they always did)
        tau_xy, tau_z = lookahead
        tau = xp.asarray((tau_xy, tau_xy, tau_z), dtype=obs.dtype)
        at = pos + tau * vel
        rel = rel + tau_xy * cyl_vel
        nbr_pos = nbr_pos + tau * nbr_vel
        normals = xp.asarray(WALL_NORMALS, dtype=obs.dtype)
        clearance = clearance + xp.sum(normals * (tau * vel)[..., None, :], axis=-1)
    if lookahead_accel > 0:  # (static, as the look-ahead above)
        own_accel = lookahead_accel * geometry.tilt_accel(OWN.get(own, "quat"))
        nbr_xy = layout.neighbour_accels(obs)
        at = at + own_accel
        nbr_pos = nbr_pos + lookahead_accel * xp.concat([nbr_xy, xp.zeros_like(nbr_xy[..., :1])], axis=-1)
        normals = xp.asarray(WALL_NORMALS, dtype=obs.dtype)
        clearance = clearance + xp.sum(normals * own_accel[..., None, :], axis=-1)

    def gate(p, q, rel_cols, normal_cols):  # gate_rows' (point q, centre, direction, present) for the columns' gates
        normal = own[..., normal_cols]
        present = (xp.sum(normal**2, axis=-1) > _GATE_PRESENT_SQ) & (gate_bar > 0)
        return q, p - own[..., rel_cols], normal, present

    # Under jit: one gate_rows call per gate (current, previous), as stacking them along an axis for one pass
    # changed the bits of the simulator's filter (another fusion of the compiled program). numpy computes value by
    # value, so there both gates go through one call, as [..., 2 gates, 3] (half the operations, every step).
    if numpy:
        gates = [gate(pos[..., None, :], at[..., None, :], _GATE_REL_COLS, _GATE_NORMAL_COLS)]
    else:
        gates = [gate(pos, at, OWN.slice(rel), OWN.slice(normal)) for rel, normal in _GATE_FIELDS]
    if closing_split is not None:  # (static: without it the rows trace as before)
        neighbour_share = closing_share(at, vel, nbr_pos, nbr_vel, soft=closing_split[0], least=closing_split[1])
    gamma = xp.asarray(gain, dtype=obs.dtype)[..., None]
    motion = None if cyl_accel is None else (xp.asarray(cyl_accel, dtype=obs.dtype), lookahead[0])
    points = _barrier_parts(at, vel, rel, cyl_radius, cyl_vel, CYL.present(cyl), nbr_pos, nbr_vel,
                            NBR.present(nbr), gamma, drone_radius=drone_radius, margin=margin, floor_z=floor_z,
                            neighbour_share=neighbour_share, neighbour_reference=neighbour_reference,
                            neighbour_release=neighbour_release, cyl_motion=motion,
                            cyl_braking=None if braking is None or not brake[0] else (*braking, lookahead[0]),
                            nbr_braking=None if braking is None or not brake[1] else (*braking, braking_gain),
                            moving_gain_max=moving_gain_max, moving_margin=moving_margin,
                            moving_margin_time=moving_margin_time, rail_speed=rail_speed)
    points, after = points[:3], points[3:]  # after: the neighbours' braking rows, if any, go last
    if not numpy:  # traced in barrier_rows' order (numpy: all the rows in one concatenation below)
        points = [concat(points)]
    wall_braking = braking if braking is not None and len(brake) > 3 and brake[3] else None
    walls = wall_rows(clearance, gamma, drone_radius=drone_radius, margin=margin, braking=wall_braking)
    gate_braking = None
    if braking is not None and len(brake) > 2 and brake[2]:  # (cmd, decel, dt), cmd shaped as the gates' points
        gate_braking = (braking[0][..., None, :] if numpy else braking[0], braking[1], braking[2])
    frames = [gate_rows(*g, gamma[..., None, :] if numpy else gamma, half_opening=gate_half_opening, bar=gate_bar,
                        drone_radius=drone_radius, margin=margin, braking=gate_braking) for g in gates]
    if numpy:
        frames = [_merge_gates(f) for f in frames]
    return concat([*points, walls, *frames, *after])


def sees_whole_swarm(layout, obs) -> bool:
    """Whether every drone's filter observes every other drone of its swarm (raw obs [..., n, D], the swarm on the
    second-to-last axis): then each pair's two drones both hold a row for the other, which a split of the pair in
    other parts than halves (``closing_split``) needs to add up to the pair condition. Where the filter sees only the
    nearest K of a larger swarm, a drone can hold a row for a neighbour that does not hold one for it."""
    return obs.ndim >= 2 and layout.num_neighbours >= obs.shape[-2] - 1


def filter_rows(layout, obs, gain, safety, *, drone_radius: float, gate_half_opening: float = 0.0,
                gate_bar: float = 0.0, cyl_accel=None, braking: tuple | None = None,
                whole_swarm: bool = False) -> Rows:
    """:func:`obs_rows` with the settings of ``safety`` (an ``aswarm.core.safety.SafetyFilterConfig``): the rows
    that both safety filters (JAX and numpy) solve and the tools that replay them read. ``cyl_accel`` and
    ``braking`` as :func:`obs_rows` takes them, already chosen by the caller from ``safety``'s flags.
    ``whole_swarm`` (:func:`sees_whole_swarm`, which the caller knows from the whole swarm's observation): the
    neighbours split by closing speed where ``safety.closing_split`` > 0; otherwise, or without it, by
    ``safety.neighbour_share``."""
    return obs_rows(layout, obs, gain, drone_radius=drone_radius, margin=safety.margin,
                    gate_half_opening=gate_half_opening, gate_bar=gate_bar, floor_z=safety.floor_z,
                    neighbour_share=safety.neighbour_share, lookahead=(safety.lookahead_xy, safety.lookahead_z),
                    cyl_accel=cyl_accel, braking=braking, moving_gain_max=safety.moving_gain_max,
                    moving_margin=safety.moving_margin, moving_margin_time=safety.moving_margin_time,
                    rail_speed=safety.rail_speed,
                    brake=(safety.braking, safety.neighbour_braking, safety.gate_braking, safety.wall_braking),
                    braking_gain=safety.neighbour_braking_gain,
                    lookahead_accel=safety.lookahead_accel,
                    closing_split=((safety.closing_split, safety.closing_share_min)
                                   if safety.closing_split > 0 and whole_swarm else None),
                    neighbour_reference=safety.neighbour_reference,
                    neighbour_release=safety.neighbour_release)


def row_groups(layout) -> tuple[tuple[str, int], ...]:
    """(name, number of rows) of each group of :func:`obs_rows`' rows in their order, for ``layout``'s cylinders and
    neighbours (the neighbours' braking rows, where there are any, come after these)."""
    return (("cylinders", layout.num_cylinders), ("neighbours", layout.num_neighbours), *FIXED_GROUPS)


def slack_weights(layout, static_weight: float, num_rows: int | None = None) -> np.ndarray:
    """[m] each row's share of the filter's shared slack in :func:`obs_rows`' layout: 1 for the cylinders and the
    neighbours, ``static_weight`` for the floor, the walls, the ceiling and the gate frames. Those hold still, and
    hovering keeps every one of them, so when no command satisfies every row (a fast cylinder, a crowd) they give
    way ``static_weight`` times less than the moving hazards: a drone is not pushed into the floor or a frame to
    spread the violation evenly. ``num_rows``: the rows' count where it goes past the gates' (the neighbours'
    braking rows, last), those rows weighing 1 as the neighbours' others."""
    m = layout.num_cylinders + layout.num_neighbours
    after = 0 if num_rows is None else num_rows - m - FIXED_ROWS
    return np.concatenate([np.ones(m), np.full(FIXED_ROWS, float(static_weight)), np.ones(after)])


def row_slack_weights(layout, rows: Rows, safety):
    """[..., m] each of ``rows``' share of the filter's shared slack (``rows`` as :func:`filter_rows` gives them), or
    None for equal shares (the program of before the weights, so stored policies keep their bits).

    :func:`slack_weights`' static weights, times clip(h / ``safety.proximity_slack``, ``proximity_slack_min``, 1)
    where ``proximity_slack`` > 0: of two rows that cannot both hold, the one whose hazard is farther (a larger
    barrier value h) gives way more. A fast cylinder's row asks a drone to match its speed while it is still metres
    off; a neighbour 0.3 m away leaves no such room, and under equal weights the two gave alike.
    """
    if safety.static_slack == 1 and safety.proximity_slack == 0:
        return None
    weight = slack_weights(layout, safety.static_slack, rows.b.shape[-1])
    if safety.proximity_slack > 0:
        xp = geometry.namespace(rows.b)
        near = xp.clip(rows.h / safety.proximity_slack, safety.proximity_slack_min, 1.0)
        weight = weight * xp.where(rows.mask, near, 1.0)  # (an absent row's h may be anything)
    return weight


def _merge_gates(rows: Rows) -> Rows:
    """Rows [..., g, 5] of g gates (A [..., g, 5, 3]) as the rows [..., 5 g] of one gate after the other."""
    lead, k = rows.b.shape[:-2], rows.b.shape[-2] * rows.b.shape[-1]
    return Rows(rows.A.reshape(lead + (k, 3)), *(f.reshape(lead + (k,)) for f in rows[1:]))


# m/s: a drone asked for less horizontal speed than this is hovering by choice, not stuck (no deadlock escape).
ESCAPE_MIN_SPEED = 0.2
# A hazard blocks the policy's direction where its row's horizontal normal points against it by more than this cosine.
_ESCAPE_FACING = 0.5


def escape_nominal(u_nom, u, rows: Rows, *, stuck: float, near: float, blockers: int | None = None):
    """The deadlock escape of ``SafetyFilterConfig.escape``: (nominal command [..., 3], stuck [...] bool).

    A drone is stuck where the QP's command ``u`` keeps less than ``stuck`` of the horizontal speed asked for
    (``u_nom``) along the asked direction while a hazard within ``near`` m (barrier value) faces that direction. For
    a CBF-QP the point where a cylinder's row and a wall's (or a frame's) meet ahead of the drone is an equilibrium:
    the policy asks forward, the projection cancels it. The escape asks for the same speed along the blocking
    hazard's horizontal tangent instead (the vertical part as asked), turning away from the other hazards within
    ``near`` (the closer, the more they count) or, with none, towards the asked direction, else counterclockwise
    (two drones meeting head on then both turn the same way). Only the first ``blockers`` rows (None: all) can block:
    :func:`obs_rows`' cylinders and neighbours, which a drone can go around (a gate's post it must pass beside, on
    the opening's side). Not stuck: ``u_nom`` unchanged. The caller filters the returned command through the same
    rows, so every barrier holds whichever nominal it started from.
    """
    xp = geometry.namespace(u_nom, rows.A)
    nrm, a_hat = unit(rows.A)
    near_rows = rows.mask & (nrm > EPS) & (rows.h < near)
    a_xy = a_hat[..., :2]
    a_len = geometry.norm(a_xy)
    horizontal = a_len > 0.5
    ask_xy = u_nom[..., :2]
    ask_speed = geometry.norm(ask_xy)
    ask_dir = ask_xy / xp.maximum(ask_speed, EPS)[..., None]
    facing = xp.sum(a_xy * ask_dir[..., None, :], axis=-1) / xp.maximum(a_len, EPS)  # [..., m] cos
    candidate = near_rows & horizontal & (facing < -_ESCAPE_FACING)
    if blockers is not None:
        candidate = candidate & (xp.arange(rows.A.shape[-2]) < blockers)
    progress = xp.sum(u[..., :2] * ask_dir, axis=-1)
    is_stuck = (ask_speed > ESCAPE_MIN_SPEED) & (progress < stuck * ask_speed) & xp.any(candidate, axis=-1)
    # The blocker: the candidate that faces the asked direction most squarely.
    blocker = xp.argmin(xp.where(candidate, facing, 2.0), axis=-1)
    pick = xp.arange(rows.A.shape[-2]) == blocker[..., None]  # [..., m]
    n_b = xp.sum(xp.where(pick[..., None], a_xy, 0.0), axis=-2)
    n_b = n_b / xp.maximum(geometry.norm(n_b), EPS)[..., None]
    tangent = xp.stack([-n_b[..., 1], n_b[..., 0]], axis=-1)  # counterclockwise around the blocker
    weight = xp.where(near_rows & ~pick, (near - rows.h) / near, 0.0)
    away = xp.sum(xp.sum(weight[..., None] * a_xy, axis=-2) * tangent, axis=-1)
    towards = xp.sum(ask_dir * tangent, axis=-1)
    side = xp.where(xp.abs(away) > 1e-3, xp.sign(away), xp.where(xp.abs(towards) > 1e-3, xp.sign(towards), 1.0))
    escape_xy = (side * ask_speed)[..., None] * tangent
    escape = xp.concat([escape_xy, u_nom[..., 2:]], axis=-1)
    return xp.where(is_stuck[..., None], escape, u_nom), is_stuck


def escape_from(u_nom, u, rows: Rows, layout, safety):
    """:func:`escape_nominal` with a :class:`~aswarm.core.safety.SafetyFilterConfig`'s settings for :func:`obs_rows`'
    rows of ``layout`` (its cylinders and neighbours can block): what both filters call."""
    return escape_nominal(u_nom, u, rows, stuck=safety.escape_stuck, near=safety.escape_near,
                          blockers=layout.num_cylinders + layout.num_neighbours)

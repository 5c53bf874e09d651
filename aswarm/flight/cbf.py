"""The CBF safety filter in numpy: the same barriers and the same QP as ``aswarm.agents.cbf_filter``.

Barriers (one row ``a_j · u ≥ b_j`` per hazard, see the JAX module for their derivation), rows laid
out ``[cylinders M | neighbours K | floor 1 | gate frame 5 | previous gate 5]``, and the QP

    min_{u, s}  ||u − u_nom||² + ρ s²
    s.t.        â_j · u + s ≥ b̂_j   (present rows, normalised to ||â_j|| = 1)
                −u_max ≤ u ≤ u_max.

The QP is strictly convex, so its solution is unique; it is found with the same Goldfarb–Idnani
dual active-set steps as the JAX solver (same row chosen at each step, same step budget, so even an
out-of-budget problem ends where the JAX one does), written here over a batch of problems in
float64. Every function takes leading batch axes ``...`` (worlds, drones).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from aswarm.flight.observe import ObsLayout

_EPS = 1e-9
_SLOTS = 4  # independent active rows in R^4 (velocity and scaled slack)


@dataclasses.dataclass(frozen=True)
class Rows:
    """Linear CBF constraints ``A u ≥ b``: A [..., m, 3], b [..., m], mask [..., m] (present rows), h [..., m]."""

    A: np.ndarray
    b: np.ndarray
    mask: np.ndarray
    h: np.ndarray

    @staticmethod
    def concat(parts: list[Rows]) -> Rows:
        return Rows(*(np.concatenate([getattr(p, f) for p in parts], -2 if f == "A" else -1)
                      for f in ("A", "b", "mask", "h")))


@dataclasses.dataclass(frozen=True)
class FilterResult:
    u: np.ndarray  # [..., 3] filtered command
    slack: np.ndarray  # [...] shared relaxation (m/s along the unit normals), 0 when feasible
    intervened: np.ndarray  # [...] bool: u_nom violated a row or the box
    correction_norm: np.ndarray  # [...] ||u − u_nom||
    converged: np.ndarray  # [...] bool: the active-set steps finished within the budget


def _unit(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(||d||, d/||d||) over the last axis; zero where d = 0."""
    sq = np.sum(d * d, -1)
    ok = sq > _EPS**2
    dist = np.sqrt(np.where(ok, sq, 1.0))
    return np.where(ok, dist, 0.0), np.where(ok[..., None], d / dist[..., None], 0.0)


# ------------------------------------------------------------------ geometry
def gate_frames(gate_pos: np.ndarray, gate_yaw: np.ndarray, half_opening: float, bar: float) -> np.ndarray:
    """Segments [..., 5, 2, 3] of a gate's frame (4 edges and the post to the floor), as ``collisions.gate_frames``."""
    c = half_opening + bar / 2
    lat = np.stack([-np.sin(gate_yaw), np.cos(gate_yaw), np.zeros_like(gate_yaw)], -1)
    up = np.array([0.0, 0.0, 1.0])
    pts = np.stack([gate_pos + a * lat + b * up for a, b in ((-c, -c), (c, -c), (c, c), (-c, c))], -2)
    edges = np.stack([pts, np.roll(pts, -1, axis=-2)], -2)  # [..., 4, 2, 3]
    foot = gate_pos.copy()
    foot[..., 2] = 0.0
    post = np.stack([gate_pos - c * up, foot], -2)[..., None, :, :]
    return np.concatenate([edges, post], -3)


def closest_on_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip(np.sum((p - a) * ab, -1) / np.maximum(np.sum(ab * ab, -1), 1e-12), 0.0, 1.0)
    return a + t[..., None] * ab


# ------------------------------------------------------------------ barriers
def cylinder_constraints(pos, center, radius, vel, present, gamma, *, drone_radius: float,
                         margin: float = 0.0) -> Rows:
    """pos [..., 3]; center, vel [..., M, 2]; radius, present [..., M]; gamma [..., M] or broadcastable."""
    dist, n_xy = _unit(pos[..., None, :2] - center)
    h = dist - (radius + drone_radius + margin)
    A = np.concatenate([n_xy, np.zeros_like(n_xy[..., :1])], -1)
    return Rows(A, np.sum(n_xy * vel, -1) - gamma * h, present, h)


def neighbour_constraints(pos, vel, nbr_pos, nbr_vel, present, gamma, *, drone_radius: float, margin: float = 0.0,
                          share: float = 0.5) -> Rows:
    """pos, vel [..., 3]; nbr_pos, nbr_vel [..., K, 3]; present [..., K]; responsibility ``share`` of the pair."""
    dist, n = _unit(pos[..., None, :] - nbr_pos)
    h = dist - (2.0 * drone_radius + margin)
    ref_vel = (1.0 - share) * vel[..., None, :] + share * nbr_vel
    return Rows(n, np.sum(n * ref_vel, -1) - share * gamma * h, present, h)


def floor_constraint(pos, gamma, *, z_min: float) -> Rows:
    h = pos[..., 2:3] - z_min
    A = np.broadcast_to(np.array([0.0, 0.0, 1.0]), h.shape + (3,))
    return Rows(A, -gamma * h, np.ones(h.shape, bool), h)


def gate_constraints(pos, gate_center, gate_normal, present, gamma, *, half_opening: float, bar: float,
                     drone_radius: float, margin: float = 0.0) -> Rows:
    """The 5 round bars of one gate's frame: pos, gate_center, gate_normal [..., 3]; present [...]; gamma [..., 1]."""
    yaw = np.arctan2(gate_normal[..., 1], gate_normal[..., 0])
    frames = gate_frames(gate_center, yaw, half_opening, bar)  # [..., 5, 2, 3]
    p = pos[..., None, :]
    dist, n = _unit(p - closest_on_segment(p, frames[..., 0, :], frames[..., 1, :]))
    h = dist - (bar / 2 + drone_radius + margin)
    return Rows(n, -gamma * h, np.broadcast_to(present[..., None], h.shape), h)


def barrier_constraints(pos, vel, cyl_center, cyl_radius, cyl_vel, cyl_present, nbr_pos, nbr_vel, nbr_present,
                        gamma, *, drone_radius: float, margin: float = 0.0, floor_z: float = 0.0,
                        neighbour_share: float = 0.5) -> Rows:
    """Rows ``[cylinders M | neighbours K | floor 1]``; gamma [...] one gain per drone, or [..., M + K + 1]."""
    M, K = cyl_center.shape[-2], nbr_pos.shape[-2]
    gamma = np.broadcast_to(np.asarray(gamma, float)[..., None] if np.ndim(gamma) == pos.ndim - 1 else gamma,
                            pos.shape[:-1] + (M + K + 1,))
    return Rows.concat([
        cylinder_constraints(pos, cyl_center, cyl_radius, cyl_vel, cyl_present, gamma[..., :M],
                             drone_radius=drone_radius, margin=margin),
        neighbour_constraints(pos, vel, nbr_pos, nbr_vel, nbr_present, gamma[..., M:M + K],
                              drone_radius=drone_radius, margin=margin, share=neighbour_share),
        floor_constraint(pos, gamma[..., M + K:], z_min=floor_z + drone_radius + margin),
    ])


# ------------------------------------------------------------------ the QP
def _active_set(G: np.ndarray, h: np.ndarray, valid: np.ndarray, x0: np.ndarray, max_iter: int, tol: float):
    """Goldfarb–Idnani for min ½||x − x0||² s.t. G x ≥ h (valid rows); P problems: G [P, C, 4], h [P, C].

    Each step either adds the most violated row (first index on ties) after a full step, or drops
    the first active row whose multiplier reaches zero first after a partial step, exactly as the
    JAX loop; a problem whose chosen row is still being added when the budget ends is ``pending``.
    The active normals sit in 4 slots (rows of N, zero when unused), so the Gram matrix plus the
    identity on unused slots is invertible and gives zero coordinates there. As in the JAX solver,
    a final Newton step puts a finished problem back exactly onto its active set: when the QP is
    infeasible the scaled slack reaches 1e3-1e4 and the steps' rounding would otherwise show in u.
    """
    P = G.shape[0]
    ar = np.arange(P)
    x = x0.copy()
    N = np.zeros((P, _SLOTS, 4))
    idx = np.zeros((P, _SLOTS), np.intp)
    used = np.zeros((P, _SLOTS), bool)
    unused = np.ones((P, _SLOTS))  # 1.0 on free slots: the identity added to the Gram matrix
    lam = np.zeros((P, _SLOTS))
    free = valid.copy()  # rows that may be added: valid and not active
    g_sq = np.einsum("pcd,pcd->pc", G, G)
    p = np.zeros(P, np.intp)
    pending = np.zeros(P, bool)
    lam_p = np.zeros(P)
    diag = np.arange(_SLOTS)
    for _ in range(max_iter):
        gaps = (G @ x[:, :, None])[:, :, 0]
        gaps -= h
        cand = np.where(free, gaps, np.inf)
        first = cand.argmin(1)
        work = pending | (cand[ar, first] < -tol)
        if not work.any():
            break
        p = np.where(pending, p, first)
        lam_p *= pending
        pending = work
        g = G[ar, p]
        gram = N @ N.transpose(0, 2, 1)
        gram[:, diag, diag] += unused
        r = np.linalg.solve(gram, N @ g[:, :, None])  # g's coordinates on the active normals
        z = g - (r.transpose(0, 2, 1) @ N)[:, 0]  # primal direction: g with its active part removed
        r = r[:, :, 0]
        zz = np.einsum("pd,pd->p", z, z)
        z_zero = (zz < 1e-12 * g_sq[ar, p]) | used.all(1)
        t_full = np.divide(-gaps[ar, p], zz, out=np.full(P, np.inf), where=~z_zero)
        ratio = np.divide(lam, r, out=np.full(r.shape, np.inf), where=used & (r > 0))
        k = ratio.argmin(1)
        t_part = ratio[ar, k]
        t = np.minimum(t_full, t_part)
        go = pending & (t < np.inf)  # no finite step: infeasible (impossible with the slack); stop
        t[~go] = 0.0
        x += (t * ~z_zero)[:, None] * z
        lam_p += t
        add = go & (t_full <= t_part)
        lam -= t[:, None] * r
        np.maximum(lam, 0.0, out=lam)
        drop = ar[go & ~add]
        if drop.size:
            kd = k[drop]
            used[drop, kd] = False
            unused[drop, kd] = 1.0
            lam[drop, kd] = 0.0
            N[drop, kd] = 0.0
            free[drop, idx[drop, kd]] = True
        put = ar[add]
        if put.size:
            slot = unused[put].argmax(1)
            pp = p[put]
            N[put, slot] = g[put]
            idx[put, slot] = pp
            used[put, slot] = True
            unused[put, slot] = 0.0
            lam[put, slot] = lam_p[put]
            free[put, pp] = False
            pending[put] = False
        pending &= go
    fix = used & ~pending[:, None]
    Nf = N * fix[:, :, None]
    gram = Nf @ Nf.transpose(0, 2, 1)
    gram[:, diag, diag] += ~fix
    d = (np.take_along_axis(h, idx, 1) - (Nf @ x[:, :, None])[:, :, 0]) * fix
    x += (np.linalg.solve(gram, d[:, :, None]).transpose(0, 2, 1) @ Nf)[:, 0]
    return x, pending


# Below this many problems the steps run in Python floats, one problem at a time: each array
# operation costs about a microsecond whatever its size, and one step over a batch takes ~60 of them,
# while a problem's own step (a Gram matrix of at most 4 x 4) takes ~15 us in plain Python.
SCALAR_MAX_PROBLEMS = 8


def _chol_solve(a: list, b: list) -> list:
    """y with a y = b for a small symmetric positive definite ``a`` (lists of floats)."""
    k = len(b)
    L = [[0.0] * k for _ in range(k)]
    for i in range(k):
        for j in range(i + 1):
            v = a[i][j] - sum(L[i][q] * L[j][q] for q in range(j))
            L[i][j] = math.sqrt(v) if i == j else v / L[j][j]
    y = [0.0] * k
    for i in range(k):
        y[i] = (b[i] - sum(L[i][q] * y[q] for q in range(i))) / L[i][i]
    for i in reversed(range(k)):
        y[i] = (y[i] - sum(L[q][i] * y[q] for q in range(i + 1, k))) / L[i][i]
    return y


def _active_set_one(G: np.ndarray, h: np.ndarray, valid: np.ndarray, x0: np.ndarray, max_iter: int, tol: float):
    """:func:`_active_set` for one problem (G [C, 4], h [C]) in Python floats: the same steps, slot by slot."""
    Gl = G.tolist()
    free = valid.copy()
    x = x0.tolist()
    slots: list = [None] * _SLOTS  # (row, normal, multiplier) of the active rows
    pending, p, lam_p = False, 0, 0.0
    for _ in range(max_iter):
        gaps = G @ np.array(x) - h
        cand = np.where(free, gaps, np.inf)
        first = int(cand.argmin())
        if not pending:
            if not cand[first] < -tol:
                break
            p, lam_p, pending = first, 0.0, True
        g = Gl[p]
        act = [i for i in range(_SLOTS) if slots[i] is not None]
        normals = [slots[i][1] for i in act]
        if act:
            gram = [[sum(u * v for u, v in zip(a, c)) for c in normals] for a in normals]
            r = _chol_solve(gram, [sum(u * v for u, v in zip(a, g)) for a in normals])
            z = [g[d] - sum(ri * nrm[d] for ri, nrm in zip(r, normals)) for d in range(4)]
        else:
            r, z = [], list(g)
        zz = sum(v * v for v in z)
        z_zero = len(act) == _SLOTS or zz < 1e-12 * sum(v * v for v in g)
        t_full = math.inf if z_zero else -float(gaps[p]) / zz
        t_part, k = math.inf, -1
        for j, i in enumerate(act):
            if r[j] > 0 and slots[i][2] / r[j] < t_part:
                t_part, k = slots[i][2] / r[j], i
        t = min(t_full, t_part)
        if t == math.inf:  # infeasible (impossible with the slack): stop, as the JAX loop idles
            pending = False
            break
        if not z_zero:
            x = [xd + t * zd for xd, zd in zip(x, z)]
        lam_p += t
        for j, i in enumerate(act):
            row, nrm, lam = slots[i]
            slots[i] = (row, nrm, max(lam - t * r[j], 0.0))
        if t_full <= t_part:
            slots[slots.index(None)] = (p, g, lam_p)
            free[p] = False
            pending = False
        else:
            free[slots[k][0]] = True
            slots[k] = None
    act = [sl for sl in slots if sl is not None]
    if act and not pending:  # the final Newton step onto the active set (see _active_set)
        normals = [sl[1] for sl in act]
        gram = [[sum(u * v for u, v in zip(a, c)) for c in normals] for a in normals]
        y = _chol_solve(gram, [float(h[sl[0]]) - sum(u * v for u, v in zip(sl[1], x)) for sl in act])
        x = [x[d] + sum(yi * nrm[d] for yi, nrm in zip(y, normals)) for d in range(4)]
    return np.array(x), pending


def _solve(u_nom: np.ndarray, a_hat: np.ndarray, b_hat: np.ndarray, valid_rows: np.ndarray, u_max: np.ndarray,
           rho: float, max_iter: int, tol: float) -> FilterResult:
    """The QP on unit rows: u_nom [P, 3], a_hat [P, m, 3], b_hat [P, m], valid_rows [P, m], u_max [3]."""
    P, m = b_hat.shape
    # Which commands already satisfy everything (the common case in flight: nothing else to do).
    row_gap = (a_hat @ u_nom[:, :, None])[:, :, 0] - b_hat
    safe = ~((valid_rows & (row_gap < -tol)).any(1) | (np.abs(u_nom) - u_max > tol).any(1))
    u = u_nom.copy()
    slack = np.zeros(P)
    converged = np.ones(P, bool)
    bad = np.flatnonzero(~safe)
    if bad.size:
        # x = (u, √ρ s): rows [â, 1/√ρ] ≥ b̂, then the box as u_k ≥ −u_max and −u_k ≥ −u_max.
        Q = bad.size
        G = np.zeros((Q, m + 6, 4))
        G[:, :m, :3] = a_hat[bad]
        G[:, :m, 3] = 1.0 / np.sqrt(rho)
        G[:, m:, :3] = _BOX
        h = np.empty((Q, m + 6))
        h[:, :m] = b_hat[bad]
        h[:, m:] = -np.concatenate([u_max, u_max])
        valid = np.ones((Q, m + 6), bool)
        valid[:, :m] = valid_rows[bad]
        x0 = np.zeros((Q, 4))
        x0[:, :3] = u_nom[bad]
        if Q <= SCALAR_MAX_PROBLEMS:
            out = [_active_set_one(G[i], h[i], valid[i], x0[i], max_iter, tol) for i in range(Q)]
            x, pending = np.stack([o[0] for o in out]), np.array([o[1] for o in out])
        else:
            x, pending = _active_set(G, h, valid, x0, max_iter, tol)
        # Out of budget: the dual iterate can leave the box; clipping keeps the command flyable.
        u[bad] = np.clip(x[:, :3], -u_max, u_max)
        slack[bad] = np.maximum(x[:, 3] / np.sqrt(rho), 0.0)
        gaps = (G @ x[:, :, None])[:, :, 0] - h
        converged[bad] = ~pending & ~(valid & (gaps < -10 * tol)).any(1)
    corr = np.sqrt(((u - u_nom) ** 2).sum(-1))
    return FilterResult(u=u, slack=slack, intervened=~safe, correction_norm=corr, converged=converged)


_BOX = np.concatenate([np.eye(3), -np.eye(3)])


def filter_velocity(u_nom: np.ndarray, A: np.ndarray, b: np.ndarray, mask: np.ndarray, u_max, *, rho: float = 1e6,
                    max_iter: int = 16, tol: float = 1e-6) -> FilterResult:
    """Closest velocity to ``u_nom`` [..., 3] with ``A u ≥ b`` (rows where ``mask``) and ``|u_k| ≤ u_max``.

    A [..., m, 3]; b, mask [..., m]; u_max scalar or [3]. Rows are normalised to unit ‖a_j‖ (rows with
    a_j ≈ 0 are ignored). A command that satisfies every row and the box (to ``tol``) is returned
    unchanged; only the other problems go through the active-set steps.
    """
    u_nom = np.asarray(u_nom, np.float64)
    lead, m = u_nom.shape[:-1], A.shape[-2]
    P = int(np.prod(lead, dtype=np.int64))
    nrm, a_hat = _unit(np.asarray(A, np.float64).reshape(P, m, 3))
    valid_rows = np.asarray(mask, bool).reshape(P, m) & (nrm > _EPS)
    b_hat = np.where(valid_rows, np.asarray(b, np.float64).reshape(P, m) / np.where(valid_rows, nrm, 1.0), 0.0)
    res = _solve(u_nom.reshape(P, 3), a_hat, b_hat, valid_rows, np.broadcast_to(np.asarray(u_max, float), (3,)),
                 rho, max_iter, tol)
    return _reshape(res, lead)


def _reshape(res: FilterResult, lead: tuple[int, ...]) -> FilterResult:
    return FilterResult(u=res.u.reshape(*lead, 3), slack=res.slack.reshape(lead),
                        intervened=res.intervened.reshape(lead), correction_norm=res.correction_norm.reshape(lead),
                        converged=res.converged.reshape(lead))


# ------------------------------------------------------------------ from observations
_CORNERS = np.array([(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)])  # (lateral, up) of a gate's corners


def filter_from_obs(layout: ObsLayout, obs: np.ndarray, cmd: np.ndarray, gain: np.ndarray, u_max: float,
                    drone_radius: float, margin: float, gate_half_opening: float = 0.0, gate_bar: float = 0.0, *,
                    rho: float = 1e6, max_iter: int = 16, tol: float = 1e-6, floor_z: float = 0.0,
                    neighbour_share: float = 0.5) -> FilterResult:
    """Filter commands [..., n, 3] using only what each drone observes (raw obs [..., n, D]); gain [..., n].

    As ``cbf_filter.filter_from_obs``: positions in a frame centred on the drone's horizontal
    position with z its altitude; one gain per drone for all its rows; gate rows present when
    ``gate_bar > 0`` and the observation has a gate (non-zero direction of passage). The rows are
    those of :func:`barrier_constraints` and :func:`gate_constraints`, built here directly as unit
    rows from the relative positions in the observation (fewer array operations for the same
    numbers: this runs every control step).
    """
    lead = obs.shape[:-1]
    P = int(np.prod(lead, dtype=np.int64))
    M, K = layout.num_cylinders, layout.num_neighbours
    obs = np.asarray(obs, np.float64).reshape(P, -1)
    own, cyl, nbr = layout.split(obs)
    f = layout.own_slices
    alt = own[:, f["altitude"]][:, 0]
    vel = own[:, f["vel"]]
    gamma = np.asarray(gain, np.float64).reshape(P, 1)

    # Cylinders and neighbours: the hazard's offset to the drone (the drone sits at (0, 0, alt)),
    # its velocity of reference and the share of the gap this drone closes (see the JAX module).
    d = np.zeros((P, M + K, 3))
    d[:, :M, :2] = -cyl[:, :, 0:2]
    d[:, M:] = -nbr[:, :, 0:3]
    ref = np.zeros((P, M + K, 3))
    ref[:, :M, :2] = cyl[:, :, 3:5]
    ref[:, M:] = vel[:, None, :] + neighbour_share * nbr[:, :, 3:6]
    sq = (d * d).sum(-1)
    ok = sq > _EPS**2
    dist = np.sqrt(np.where(ok, sq, 1.0))
    n_pt = d * (ok / dist)[:, :, None]
    h_pt = np.empty((P, M + K))
    # h = ||p_xy − c|| − (R + r + margin) with R = ||rel|| − clearance − r: the clearance less the margin.
    h_pt[:, :M] = cyl[:, :, 2] - margin
    h_pt[:, M:] = dist[:, M:] - (2.0 * drone_radius + margin)
    share = np.concatenate([np.ones(M), np.full(K, neighbour_share)])
    b_pt = (n_pt * ref).sum(-1) - share * gamma * h_pt
    present = np.concatenate([cyl[:, :, 5], nbr[:, :, 6]], 1) > 0.5

    # The current gate's frame and the one passed last: 4 edges and the post each, as round bars.
    n_cur, h_cur, on_cur = _gate_rows(own[:, f["target_rel"]], own[:, f["target_normal"]], alt,
                                      gate_half_opening, gate_bar, drone_radius, margin)
    n_prev, h_prev, on_prev = _gate_rows(own[:, f["prev_gate_rel"]], own[:, f["prev_gate_normal"]], alt,
                                         gate_half_opening, gate_bar, drone_radius, margin)

    # Rows [cylinders M | neighbours K | floor 1 | gate 5 | previous gate 5]; a row with no direction is ignored.
    a_hat = np.concatenate([n_pt, np.broadcast_to(_UP, (P, 1, 3)), n_cur, n_prev], 1)
    b_hat = np.concatenate([b_pt, gamma * (floor_z + drone_radius + margin - alt[:, None]), -gamma * h_cur,
                            -gamma * h_prev], 1)
    valid = np.concatenate([present & ok, np.ones((P, 1), bool), on_cur, on_prev], 1)
    res = _solve(np.asarray(cmd, np.float64).reshape(P, 3), a_hat, b_hat, valid, np.full(3, float(u_max)), rho,
                 max_iter, tol)
    return _reshape(res, lead)


def _gate_rows(rel: np.ndarray, normal: np.ndarray, alt: np.ndarray, half_opening: float, bar: float,
               drone_radius: float, margin: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit rows [P, 5, 3], barrier values [P, 5] and validity [P, 5] of one gate's 5 bars.

    rel [P, 3] drone minus gate centre and normal [P, 3] as observed; the drone sits at (0, 0, alt).
    """
    P = rel.shape[0]
    center = -rel
    center[:, 2] += alt
    yaw = np.arctan2(normal[:, 1], normal[:, 0])
    c = half_opening + bar / 2
    lat = np.stack([-np.sin(yaw), np.cos(yaw), np.zeros(P)], -1)
    corners = center[:, None, :] + c * _CORNERS[None, :, :1] * lat[:, None, :]
    corners[:, :, 2] += c * _CORNERS[:, 1]
    a = np.concatenate([corners, center[:, None, :]], 1)  # segment starts [P, 5, 3]
    a[:, 4, 2] -= c
    e = np.concatenate([np.roll(corners, -1, axis=1), center[:, None, :]], 1)  # segment ends
    e[:, 4, 2] = 0.0
    pos = np.zeros((P, 1, 3))
    pos[:, 0, 2] = alt
    ab = e - a
    t = np.clip(((pos - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0.0, 1.0)
    dg = pos - (a + t[:, :, None] * ab)
    sq = (dg * dg).sum(-1)
    ok = sq > _EPS**2
    dist = np.sqrt(np.where(ok, sq, 1.0))
    on = ((normal * normal).sum(-1) > 0.25) & (bar > 0)
    return dg * (ok / dist)[:, :, None], np.where(ok, dist, 0.0) - (bar / 2 + drone_radius + margin), on[:, None] & ok


_UP = np.array([0.0, 0.0, 1.0])

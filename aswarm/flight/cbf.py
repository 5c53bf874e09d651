"""The CBF safety filter in numpy: the rows of ``aswarm.core.barriers`` and the same QP as ``aswarm.agents.cbf_filter``.

Rows (one ``a_j · u ≥ b_j`` per hazard, built by :func:`aswarm.core.barriers.obs_rows`, shared with the
JAX filter) are laid out ``[cylinders M | neighbours K | floor 1 | walls 5 | gate frame 5 | previous gate 5]``,
and the QP is

    min_{u, s}  ||u − u_nom||² + ρ s²
    s.t.        â_j · u + s ≥ b̂_j   (present rows, normalised to ||â_j|| = 1)
                −u_max ≤ u ≤ u_max.

The QP is strictly convex, so its solution is unique; it is found with the same Goldfarb–Idnani
dual active-set steps as the JAX solver (same row chosen at each step, same step budget, so even an
out-of-budget problem ends where the JAX one does), written here over a batch of problems in
float64. Every function takes leading batch axes ``...`` (worlds, drones).
"""

from __future__ import annotations

import bisect
import dataclasses
import functools
import math

import numpy as np

from aswarm.core import barriers, command
from aswarm.core.layout import ObsLayout
from aswarm.core.safety import SafetyFilterConfig

_SLOTS = 4  # independent active rows in R^4 (velocity and scaled slack)


@dataclasses.dataclass(frozen=True)
class FilterResult:
    u: np.ndarray  # [..., 3] filtered command
    slack: np.ndarray  # [...] shared relaxation (m/s along the unit normals), 0 when feasible
    intervened: np.ndarray  # [...] bool: u_nom violated a row or the box
    correction_norm: np.ndarray  # [...] ||u − u_nom||
    converged: np.ndarray  # [...] bool: the active-set steps finished within the budget
    escaped: np.ndarray | None = None  # [...] bool: the deadlock escape chose the nominal (filter_from_obs)


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


# Up to this many problems the steps run in Python floats (_active_set_scalar): each array operation
# costs about a microsecond whatever its size, and one step over a batch takes ~60 of them, while a
# problem's own step (a Gram matrix of at most 4 x 4) takes a few microseconds in plain Python.
SCALAR_MAX_PROBLEMS = 8


def _dot(a: list, b: list) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]


def _sum_sq(v: list) -> float:
    acc = 0.0
    for e in v:
        acc += e * e
    return acc


def _cholesky_row(L: list, a: list) -> list:
    """The next row of the Cholesky factor ``L`` (its rows so far) of a Gram matrix whose new last row is ``a``."""
    new = []
    for j, row in enumerate(L):
        acc = 0.0
        for q in range(j):
            acc += new[q] * row[q]
        new.append((a[j] - acc) / row[j])
    new.append(math.sqrt(a[len(L)] - _sum_sq(new)))
    return new


def _cholesky(normals: list) -> list:
    """Cholesky factor (rows, lists of floats) of the Gram matrix of a few 4-vectors."""
    L: list = []
    for i, a in enumerate(normals):
        L.append(_cholesky_row(L, [_dot(a, c) for c in normals[:i + 1]]))
    return L


# The sums below are accumulated term by term in a fixed order (as sum() would): plain loops, as
# these run a few times per step of a 4-variable problem, where generators cost more than the sums.
def _forward(L: list, b: list) -> list:
    """y with L y = b."""
    y: list = []
    for i, row in enumerate(L):
        acc = 0.0
        for q in range(i):
            acc += row[q] * y[q]
        y.append((b[i] - acc) / row[i])
    return y


def _backward(L: list, y: list) -> list:
    """r with Lᵀ r = y."""
    k = len(y)
    r = list(y)
    for i in range(k - 1, -1, -1):
        acc = 0.0
        for q in range(i + 1, k):
            acc += L[q][i] * r[q]
        r[i] = (r[i] - acc) / L[i][i]
    return r


def _combination(c: list, v: list) -> tuple:
    """Σ c_i v_i of 4-vectors v_i (at least one)."""
    a, u = c[0], v[0]
    s0, s1, s2, s3 = a * u[0], a * u[1], a * u[2], a * u[3]
    for i in range(1, len(c)):
        a, u = c[i], v[i]
        s0 += a * u[0]
        s1 += a * u[1]
        s2 += a * u[2]
        s3 += a * u[3]
    return s0, s1, s2, s3


class _Steps:
    """One problem's state in :func:`_active_set_scalar`: the iterate and the active rows, in Python floats.

    The active rows are kept in slot order (slot ids ascending) as parallel lists: slot id, row,
    normal, multiplier. ``L`` is the Cholesky factor of their normals' Gram matrix, kept between
    steps (a row added after the others extends it, one dropped last shortens it, else it is
    refactorised), which is the factor a fresh factorisation gives, to the bit, for less work.
    """

    __slots__ = ("x", "slot", "row", "nrm", "lam", "L", "pending", "p", "lam_p")

    def __init__(self, x: list):
        self.x = x
        self.slot: list = []
        self.row: list = []
        self.nrm: list = []
        self.lam: list = []
        self.L: list = []
        self.pending, self.p, self.lam_p = False, 0, 0.0

    def step(self, g: list, gap: float, h_free: np.ndarray, h: np.ndarray) -> bool:
        """One step towards adding row ``p`` (normal g, gap G x − h there); False when no step is possible.

        Marks an added row as not free (``h_free`` -inf) and a dropped one as free again.
        """
        nrm, lam, L = self.nrm, self.lam, self.L
        if len(nrm) == 1:  # the usual second row: the general branch below, written out
            n0, l00 = nrm[0], L[0][0]
            y = [_dot(n0, g) / l00]
            r = [y[0] / l00]
            z = [g[0] - r[0] * n0[0], g[1] - r[0] * n0[1], g[2] - r[0] * n0[2], g[3] - r[0] * n0[3]]
        elif nrm:
            y = _forward(L, [_dot(n, g) for n in nrm])  # also the new row of L if g is added
            r = _backward(L, y)  # g's coordinates on the active normals
            s0, s1, s2, s3 = _combination(r, nrm)
            z = [g[0] - s0, g[1] - s1, g[2] - s2, g[3] - s3]  # g less its active part
        else:
            y, r, z = [], [], g
        gg = _dot(g, g)
        zz = _dot(z, z) if nrm else gg
        z_zero = len(nrm) == _SLOTS or zz < 1e-12 * gg
        t_full = math.inf if z_zero else -gap / zz
        t_part, k = math.inf, -1
        for j, rj in enumerate(r):
            if rj > 0 and lam[j] / rj < t_part:
                t_part, k = lam[j] / rj, j
        t = min(t_full, t_part)
        if t == math.inf:  # infeasible (impossible with the slack): stop, as the JAX loop idles
            self.pending = False
            return False
        if not z_zero:
            self.x = [xd + t * zd for xd, zd in zip(self.x, z)]
        self.lam_p += t
        for j, rj in enumerate(r):
            lam[j] = max(lam[j] - t * rj, 0.0)
        if t_full <= t_part:  # add p in the first free slot
            s = 0
            while s in self.slot:
                s += 1
            j = bisect.bisect(self.slot, s)
            self.slot.insert(j, s)
            self.row.insert(j, self.p)
            nrm.insert(j, g)
            lam.insert(j, self.lam_p)
            h_free[self.p] = -np.inf
            self.pending = False
            if j == len(L):
                L.append(y + [math.sqrt(gg - _sum_sq(y))])
            else:
                self.L = _cholesky(nrm)
        else:  # drop the active row whose multiplier reached zero first
            h_free[self.row[k]] = h[self.row[k]]
            del self.slot[k], self.row[k], nrm[k], lam[k]
            if k == len(L) - 1:
                L.pop()
            else:
                self.L = _cholesky(nrm)
        return True

    def finish(self, h: np.ndarray) -> list:
        """The final Newton step onto the active set (see :func:`_active_set`); the iterate as 4 floats."""
        x, nrm = self.x, self.nrm
        if len(nrm) == 1 and not self.pending:  # the general branch below, written out
            n0, l00 = nrm[0], self.L[0][0]
            y0 = (float(h[self.row[0]]) - _dot(n0, x)) / l00 / l00
            return [x[0] + y0 * n0[0], x[1] + y0 * n0[1], x[2] + y0 * n0[2], x[3] + y0 * n0[3]]
        if nrm and not self.pending:
            y = _backward(self.L, _forward(self.L, [float(h[i]) - _dot(n, x) for i, n in zip(self.row, nrm)]))
            s0, s1, s2, s3 = _combination(y, nrm)
            x = [x[0] + s0, x[1] + s1, x[2] + s2, x[3] + s3]
        return x


def _active_set_scalar(G: np.ndarray, h: np.ndarray, valid: np.ndarray, x0: np.ndarray, gaps0: np.ndarray,
                       max_iter: int, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_active_set` for a few problems, each step of each in Python floats: the same steps, slot by slot.

    G [Q, C, 4]; h, valid [Q, C]; x0 [Q, 4]; gaps0 = G x0 − h (the caller has it). Per step numpy
    only finds the most violated free row of every problem (one batched product and an argmin);
    the step itself is a handful of floats per problem.
    """
    # h on the rows that may still be added, -inf on the others (invalid or active): G x − h_free
    # is then +inf there and the argmin finds the most violated free row.
    h_free = np.where(valid, h, -np.inf)
    cand = np.where(valid, gaps0, np.inf)
    probs = [_Steps(x) for x in x0.tolist()]
    work = range(len(probs))
    for it in range(max_iter):
        if it:
            cand = (G @ np.array([pr.x for pr in probs])[:, :, None])[:, :, 0]
            cand -= h_free
        first = cand.argmin(1).tolist()
        going = []
        for i in work:
            pr = probs[i]
            if not pr.pending:
                if not cand.item(i, first[i]) < -tol:
                    continue  # solved: no violated row left
                pr.p, pr.lam_p, pr.pending = first[i], 0.0, True
            if pr.step(G[i, pr.p].tolist(), cand.item(i, pr.p), h_free[i], h[i]):
                going.append(i)
        work = going
        if not work:
            break
    return np.array([pr.finish(h[i]) for i, pr in enumerate(probs)]), np.array([pr.pending for pr in probs])


def _qp_rows(P: int, m: int, u_max: tuple, rho: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows ``G x ≥ h`` of P problems in x = (u, √ρ s), with the box filled in and m hazard rows to fill.

    G [P, m + 6, 4], h and valid [P, m + 6]: a caller writes the unit normals into ``G[:, :m, :3]``
    (the slack column is set), the offsets into ``h[:, :m]`` and the presence into ``valid[:, :m]``.
    The box is the last 6 rows, u_k ≥ −u_max and −u_k ≥ −u_max (u_max: 3 floats).
    """
    # The filter runs on the same shapes every step: a copy of arrays built once is cheaper than
    # filling them (large batches, which are cheap to fill by comparison, are not kept).
    G, h, valid = _qp_template(P, m, u_max, rho) if P <= 1024 else _qp_template.__wrapped__(P, m, u_max, rho)
    return G.copy(), h.copy(), valid.copy()


@functools.lru_cache(maxsize=16)
def _qp_template(P: int, m: int, u_max: tuple, rho: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What :func:`_qp_rows` copies."""
    G = np.zeros((P, m + 6, 4))
    G[:, :m, 3] = 1.0 / np.sqrt(rho)
    G[:, m:] = _BOX
    h = np.zeros((P, m + 6))
    h[:, m:] = -np.array(u_max + u_max)
    valid = np.zeros((P, m + 6), bool)
    valid[:, m:] = True
    for a in (G, h, valid):
        a.setflags(write=False)
    return G, h, valid


def _solve(u_nom: np.ndarray, G: np.ndarray, h: np.ndarray, valid: np.ndarray, u_max: tuple, rho: float,
           max_iter: int, tol: float, box: tuple | None = None) -> FilterResult:
    """The QP of :func:`_qp_rows`: u_nom [P, 3]; G [P, C, 4]; h, valid [P, C]; u_max 3 floats; box (lo, hi)
    [P, 3] in place of ±u_max (the box rows of ``h`` already hold it)."""
    P = u_nom.shape[0]
    x0 = np.zeros((P, 4))
    x0[:, :3] = u_nom
    # Which commands already satisfy every row and the box (the common case in flight: nothing
    # else to do). As in the JAX filter, on the same rows the solver then works on.
    gaps = (G @ x0[:, :, None])[:, :, 0]
    gaps -= h
    unsafe = (valid & (gaps < -tol)).any(1)
    if not unsafe.any():
        return FilterResult(u=u_nom.copy(), slack=np.zeros(P), intervened=unsafe, correction_norm=np.zeros(P),
                            converged=~unsafe)
    bad = unsafe.nonzero()[0]
    some = bad.size < P  # else every problem is solved: no gathering and scattering
    if some:
        G, h, valid, x0, gaps = G[bad], h[bad], valid[bad], x0[bad], gaps[bad]
    if bad.size <= SCALAR_MAX_PROBLEMS:
        x, pending = _active_set_scalar(G, h, valid, x0, gaps, max_iter, tol)
    else:
        x, pending = _active_set(G, h, valid, x0, max_iter, tol)
    # Out of budget: the dual iterate can leave the box; clipping keeps the command flyable.
    if box is None:
        lim = u_max[0] if u_max[0] == u_max[1] == u_max[2] else np.array(u_max)
        u_bad = np.minimum(np.maximum(x[:, :3], -lim), lim)
    else:
        lo, hi = (b[bad] for b in box) if some else box
        u_bad = np.minimum(np.maximum(x[:, :3], lo), hi)
    slack_bad = np.maximum(x[:, 3] / math.sqrt(rho), 0.0)
    gaps = (G @ x[:, :, None])[:, :, 0]
    gaps -= h
    converged_bad = ~(pending | (valid & (gaps < -10 * tol)).any(1))
    diff = u_bad - x0[:, :3]
    corr_bad = np.sqrt((diff * diff).sum(-1))
    if not some:
        return FilterResult(u=u_bad, slack=slack_bad, intervened=unsafe, correction_norm=corr_bad,
                            converged=converged_bad)
    u = u_nom.copy()
    u[bad] = u_bad
    slack = np.zeros(P)
    slack[bad] = slack_bad
    converged = ~unsafe
    converged[bad] = converged_bad
    corr = np.zeros(P)
    corr[bad] = corr_bad
    return FilterResult(u=u, slack=slack, intervened=unsafe, correction_norm=corr, converged=converged)


_BOX = np.concatenate([np.eye(3), -np.eye(3)])
_BOX = np.concatenate([_BOX, np.zeros((6, 1))], 1)  # the box rows of G (no slack)


def filter_velocity(u_nom: np.ndarray, A: np.ndarray, b: np.ndarray, mask: np.ndarray, u_max, *, rho: float = 1e6,
                    max_iter: int = 16, tol: float = 1e-6, slack_weight: np.ndarray | None = None,
                    box: tuple | None = None) -> FilterResult:
    """Closest velocity to ``u_nom`` [..., 3] with ``A u ≥ b`` (rows where ``mask``) and ``|u_k| ≤ u_max``.

    A [..., m, 3]; b, mask [..., m]; u_max scalar or [3]. Rows are normalised to unit ‖a_j‖ (rows with
    a_j ≈ 0 are ignored). A command that satisfies every row and the box (to ``tol``) is returned
    unchanged; only the other problems go through the active-set steps. ``slack_weight`` [m] or [..., m]: each row's
    share of the shared slack (None: 1), as in the JAX filter. ``box`` = (lo, hi) [..., 3] in place of ±u_max, as there.
    """
    u_nom = np.asarray(u_nom, np.float64)
    lead, m = u_nom.shape[:-1], A.shape[-2]
    P = math.prod(lead)
    nrm, a_hat = barriers.unit(np.asarray(A, np.float64).reshape(P, m, 3))
    valid_rows = np.asarray(mask, bool).reshape(P, m) & (nrm > barriers.EPS)
    if isinstance(u_max, (int, float)):  # the flight runtime's, every step (np.broadcast_to costs microseconds)
        u_max = (float(u_max),) * 3
    else:
        u_max = tuple(np.broadcast_to(np.asarray(u_max, float), (3,)).tolist())
    G, h, valid = _qp_rows(P, m, u_max, float(rho))
    G[:, :m, :3] = a_hat
    if slack_weight is not None:
        G[:, :m, 3] = np.broadcast_to(np.asarray(slack_weight, np.float64), lead + (m,)).reshape(P, m) / np.sqrt(rho)
    h[:, :m] = np.where(valid_rows, np.asarray(b, np.float64).reshape(P, m) / np.where(valid_rows, nrm, 1.0), 0.0)
    valid[:, :m] = valid_rows
    if box is not None:
        box = tuple(np.broadcast_to(np.asarray(x, np.float64), lead + (3,)).reshape(P, 3) for x in box)
        h[:, m:m + 3], h[:, m + 3:] = box[0], -box[1]
    return _reshape(_solve(u_nom.reshape(P, 3), G, h, valid, u_max, rho, max_iter, tol, box), lead)


def _reshape(res: FilterResult, lead: tuple[int, ...]) -> FilterResult:
    return FilterResult(u=res.u.reshape(*lead, 3), slack=res.slack.reshape(lead),
                        intervened=res.intervened.reshape(lead), correction_norm=res.correction_norm.reshape(lead),
                        converged=res.converged.reshape(lead))


# ------------------------------------------------------------------ from observations
def filter_from_obs(layout: ObsLayout, obs: np.ndarray, cmd: np.ndarray, gain: np.ndarray, u_max: float,
                    drone_radius: float, safety: SafetyFilterConfig, gate_half_opening: float = 0.0,
                    gate_bar: float = 0.0, cyl_accel: np.ndarray | None = None, applied: np.ndarray | None = None,
                    command_rate: tuple[float, float] | None = None) -> FilterResult:
    """Filter commands [..., n, 3] using only what each drone observes (raw obs [..., n, D]); gain [..., n].

    As ``cbf_filter.filter_from_obs``: the rows of :func:`aswarm.core.barriers.obs_rows` (one gain per
    drone for all its rows; gate rows present when ``gate_bar > 0`` and the observation has a gate),
    margin, neighbour share, floor height and the QP's settings from ``safety``; ``cyl_accel`` [..., M] (per swarm,
    m/s²) the cylinders' acceleration bounds, used where ``safety.hazard_accel``; ``applied`` [..., n, 3] the commands
    the drones fly now and ``command_rate`` (command acceleration limit, control period), used where
    ``safety.brakes`` (``braking``, ``neighbour_braking``, ``gate_braking`` or ``wall_braking``): the reachable box
    and the braking rows, as there.
    """
    obs = np.asarray(obs, np.float64)
    braking = box = None
    if applied is not None and safety.brakes(command_rate):
        now = np.asarray(applied, np.float64)
        if safety.reachable_box:
            box = command.reachable(now, command_rate[0] * command_rate[1], u_max)
            cmd = np.minimum(np.maximum(cmd, box[0]), box[1])
        braking = (now, float(command_rate[0]), float(command_rate[1]))
    accel = None
    if cyl_accel is not None and safety.hazard_accel:
        accel = np.asarray(cyl_accel, np.float64)[..., None, :]
    rows = barriers.filter_rows(layout, obs, np.asarray(gain, np.float64), safety, drone_radius=drone_radius,
                                gate_half_opening=gate_half_opening, gate_bar=gate_bar, cyl_accel=accel,
                                braking=braking, whole_swarm=barriers.sees_whole_swarm(layout, obs))
    weight = barriers.row_slack_weights(layout, rows, safety)

    def solve(nominal):
        return filter_velocity(nominal, rows.A, rows.b, rows.mask, u_max, rho=safety.rho, max_iter=safety.max_iter,
                               tol=safety.tol, slack_weight=weight, box=box)

    res = solve(cmd)
    if not safety.escape:
        return res
    nominal, stuck = barriers.escape_from(np.asarray(cmd, np.float64), res.u, rows, layout, safety)
    if not stuck.any():
        return dataclasses.replace(res, escaped=stuck)
    out = solve(nominal)  # as the JAX filter: the escape's QP where stuck, the correction from what was asked

    def pick(e, r):
        return np.where(stuck.reshape(stuck.shape + (1,) * (e.ndim - stuck.ndim)), e, r)

    return FilterResult(u=pick(out.u, res.u), slack=pick(out.slack, res.slack), intervened=res.intervened | stuck,
                        correction_norm=np.where(stuck, np.linalg.norm(out.u - cmd, axis=-1), res.correction_norm),
                        converged=pick(out.converged, res.converged), escaped=stuck)

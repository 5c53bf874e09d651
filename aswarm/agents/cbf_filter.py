"""Control-barrier-function (CBF) safety filter for per-drone velocity commands, in JAX.

The barrier rows ``a_j · u ≥ b_j`` (one per hazard, see :mod:`aswarm.core.barriers` for their
derivation) are built by :mod:`aswarm.core.barriers`, shared with the numpy flight filter
(``aswarm.flight.cbf``); :func:`filter_velocity` finds the velocity closest to the policy's that
satisfies all of them:

    min_{u, s}  ||u − u_nom||² + ρ s²
    s.t.        â_j · u + s ≥ b̂_j   (present rows j, normalised to ||â_j|| = 1)
                −u_max ≤ u ≤ u_max   (hard box, never relaxed).

It takes one drone; ``jax.vmap`` it over drones and worlds. :func:`filter_from_obs` does both from
raw observations, with the settings of a :class:`~aswarm.core.safety.SafetyFilterConfig`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from aswarm.core import barriers, command
from aswarm.core.safety import SafetyFilterConfig

_DIM = 4  # decision variables: the velocity (3) and the scaled shared slack
_SLOTS = _DIM  # independent active constraints in R^4: at most 4


@struct.dataclass
class FilterResult:
    """Output of :func:`filter_velocity` for one drone."""

    u: jax.Array  # [3] filtered velocity command
    slack: jax.Array  # [] shared relaxation s ≥ 0 (m/s along each unit constraint normal); ~0 when feasible
    intervened: jax.Array  # [] bool: u_nom violated a constraint or the box, so u != u_nom
    correction_norm: jax.Array  # [] ||u − u_nom||
    active: jax.Array  # [m] bool: constraints binding at the solution
    converged: jax.Array  # [] bool: the active-set loop finished within max_iter
    escaped: jax.Array  # [] bool: the deadlock escape (SafetyFilterConfig.escape) chose the nominal command


# ---------------------------------------------------------------- QP solver
# The QP is solved by the Goldfarb–Idnani dual active-set method on x = (u, √ρ s), in which the
# cost is ½||x − x0||². It is exact (no tolerance on optimality beyond rounding), and in R^4 it
# needs only a handful of add/drop steps, each costing one QR of at most 4 active normals. The
# loop stops when every problem of a vmapped batch is done (finished problems idle meanwhile).
#
# Small vectors are Python lists of scalars (structure of arrays): under vmap every scalar op
# becomes one op over the whole batch, which XLA:CPU vectorises; [B, 4] arrays with a reduction
# over the minor axis of 4 ran 2-3x slower. QR is Gram–Schmidt applied twice (CGS2): orthogonal to
# rounding even at the ~1e3 condition number the slack column (1/√ρ) creates, where normal
# equations (condition squared) lost float32 accuracy.

def _vdot(a: list, b: list) -> jax.Array:
    return sum(x * y for x, y in zip(a, b))


def _qr(rows: list, used: list) -> tuple[list, list]:
    """CGS2 of the used rows: rows[j] = Σ_{i≤j} R[i][j] q[i]; unused slots get q = 0, R[j][j] = 1."""
    q, R = [], [[0.0] * _SLOTS for _ in range(_SLOTS)]
    for j in range(_SLOTS):
        v = list(rows[j])
        coef = [0.0] * j
        for _ in range(2):
            for i in range(j):
                c = _vdot(q[i], v)
                v = [vk - c * qk for vk, qk in zip(v, q[i])]
                coef[i] = coef[i] + c
        sq = _vdot(v, v)
        ok = used[j] & (sq > 0)
        nrm = jnp.sqrt(jnp.where(ok, sq, 1.0))
        inv = jnp.where(ok, 1.0 / nrm, 0.0)
        q.append([vk * inv for vk in v])
        for i in range(j):
            R[i][j] = jnp.where(used[j], coef[i], 0.0)
        R[j][j] = nrm
    return q, R


def _project_out(q: list, g: list) -> tuple[list, list]:
    """(z, w): z = g − Σ w_i q_i is g with its component in span(q) removed (twice, as in CGS2)."""
    z, w = list(g), [0.0] * _SLOTS
    for _ in range(2):
        for i in range(_SLOTS):
            c = _vdot(q[i], z)
            z = [zk - c * qk for zk, qk in zip(z, q[i])]
            w[i] = w[i] + c
    return z, w


def _solve_upper(R: list, w: list) -> list:
    """r with R r = w (back substitution)."""
    r = [None] * _SLOTS
    for i in reversed(range(_SLOTS)):
        r[i] = (w[i] - sum(R[i][k] * r[k] for k in range(i + 1, _SLOTS))) / R[i][i]
    return r


def _solve_lower_t(R: list, d: list) -> list:
    """y with Rᵀ y = d (forward substitution)."""
    y = []
    for j in range(_SLOTS):
        y.append((d[j] - sum(R[i][j] * y[i] for i in range(j))) / R[j][j])
    return y


def _active_set_loop(x0: list, cols: list, h: jax.Array, valid: jax.Array, max_iter: int, tol: float):
    """Goldfarb–Idnani for min ½||x − x0||² s.t. G x ≥ h (rows where valid), G given by its columns.

    Starts from x0 with no active row (dual feasible: x0 is the unconstrained optimum) and takes
    at most ``max_iter`` add/drop steps; finished problems idle. A warm start at clip(u_nom) with the
    clipped bounds active is also dual feasible but measured slower: hazards usually push u back
    inside the box, so the pre-activated bounds cost a drop step each. Returns the iterate, the
    active set as slot indices [4] and usage flags [4], and ``pending`` (a violated row was still
    being added when the budget ran out).
    """
    nc = h.shape[0]
    dt = h.dtype
    rows_id = jnp.arange(nc)
    big = jnp.asarray(jnp.inf, dt)
    zero = jnp.zeros((), dt)

    def body(st):
        it, _, x, normals, idx, used, lam, p, pending, lam_p = st
        in_set = jnp.zeros(nc, bool)
        for j in range(_SLOTS):
            in_set = in_set | ((rows_id == idx[j]) & used[j])
        cand = jnp.where(valid & ~in_set, sum(c * xk for c, xk in zip(cols, x)) - h, big)
        lowest = jnp.min(cand)
        viol = lowest < -tol
        # first index of the minimum: cheaper than argmin's paired reduction on XLA:CPU
        first = jnp.min(jnp.where(cand == lowest, rows_id, nc)).astype(jnp.int32)
        p = jnp.where(pending, p, first)
        lam_p = jnp.where(pending, lam_p, 0.0)
        pending = pending | viol
        pick = rows_id == p
        g = [jnp.sum(jnp.where(pick, c, 0.0)) for c in cols]
        q, R = _qr(normals, used)
        z, w = _project_out(q, g)
        r = [jnp.where(u, rj, 0.0) for u, rj in zip(used, _solve_upper(R, w))]
        zz = _vdot(z, z)
        # z ≈ 0: g lies in the span of the active normals, so one of them must be dropped first.
        z_zero = (used[0] & used[1] & used[2] & used[3]) | (zz < 1e-12 * _vdot(g, g))
        gap = _vdot(g, x) - jnp.sum(jnp.where(pick, h, 0.0))
        t_full = jnp.where(z_zero, big, -gap / jnp.where(z_zero, 1.0, zz))
        t_part, k = big, jnp.int32(0)
        for j in range(_SLOTS):
            blocks = used[j] & (r[j] > 0)
            ratio = jnp.where(blocks, lam[j] / jnp.where(blocks, r[j], 1.0), big)
            better = ratio < t_part
            t_part, k = jnp.where(better, ratio, t_part), jnp.where(better, j, k)
        t = jnp.minimum(t_full, t_part)
        # No finite step would mean an infeasible QP (impossible with the slack): stop, don't spin.
        go = pending & jnp.isfinite(t)
        t = jnp.where(go, t, 0.0)
        x = [xk + jnp.where(z_zero, 0.0, t) * zk for xk, zk in zip(x, z)]
        lam_p = lam_p + t
        add = go & (t_full <= t_part)
        drop = go & (t_full > t_part)
        taken = jnp.bool_(False)
        new = ([], [], [], [])
        for j in range(_SLOTS):
            put = add & ~used[j] & ~taken
            taken = taken | ~used[j]
            out = drop & (k == j)
            new[0].append([jnp.where(put, gk, nk) for gk, nk in zip(g, normals[j])])
            new[1].append(jnp.where(put, p, idx[j]))
            new[2].append((used[j] | put) & ~out)
            new[3].append(jnp.where(put, lam_p, jnp.where(out, 0.0, jnp.maximum(lam[j] - t * r[j], 0.0))))
        # Finished when this step had nothing to do: no violated row pending (or no step possible).
        return it + 1, ~go, x, new[0], new[1], new[2], new[3], p, pending & ~add & go, lam_p

    init = (jnp.int32(0), jnp.bool_(False), x0, [[zero] * _DIM for _ in range(_SLOTS)], [jnp.int32(0)] * _SLOTS,
            [jnp.bool_(False)] * _SLOTS, [zero] * _SLOTS, jnp.int32(0), jnp.bool_(False), zero)
    # A while loop rather than max_iter fixed steps: under vmap it runs until the slowest problem of the
    # batch is done (finished ones idle), usually far fewer steps than the budget.
    out = jax.lax.while_loop(lambda st: (st[0] < max_iter) & ~st[1], body, init)
    _, _, x, _, idx, used, _, _, pending, _ = out
    return x, idx, used, pending


def filter_velocity(u_nom: jax.Array, A: jax.Array, b: jax.Array, mask: jax.Array,
                    u_max: float | jax.Array, *, rho: float = 1e6, max_iter: int = 16,
                    tol: float = 1e-6, slack_weight=None, box: tuple | None = None) -> FilterResult:
    """Closest velocity to ``u_nom`` satisfying ``A u ≥ b`` (rows where ``mask``) and ``|u_k| ≤ u_max``.

    u_nom [3]; A [m, 3]; b [m]; mask [m] bool; u_max scalar or [3]. Rows are normalised to unit
    ‖a_j‖ (rows with a_j ≈ 0 are ignored: u cannot change them), so ``slack`` is in m/s along
    each constraint normal. ``slack_weight`` [m] (None: 1 for every row) scales each row's share of the slack,
    â_j · u + w_j s ≥ b̂_j: a row with w_j < 1 gives way that much less (``barriers.slack_weights``).

    One shared slack s (not one per row): for large ρ the solution first minimises the worst
    violation over all hazards and only then the distance to u_nom, so when the constraints
    cannot all hold no single hazard is sacrificed to spare the others (per-row quadratic slacks
    minimise the sum of squared violations instead, letting one row absorb most of it), and the
    QP keeps 4 variables whatever m is. s ≥ 0 need not be imposed: s < 0 only tightens the rows
    and costs ρ s². With the quadratic penalty s = Σλ_j/ρ is not exactly 0 once a row binds;
    ρ = 1e6 keeps it near 1e-6 m/s per m/s of correction. The box is hard (u = 0 satisfies it),
    so the QP is always feasible.

    If u_nom satisfies every row and the box (to ``tol``), it is returned bit-exactly.
    ``max_iter`` bounds the add/drop steps (fixed cost, linear in it): in dense random scenes
    with m = 48 (~3 binding rows, 40 % infeasible) 12 steps left 4 in 20 000 problems unfinished
    and 16 none. An unfinished problem returns its last iterate clipped to the box, with
    ``converged`` false. Gradients flow through the final active set (exact where it is locally
    constant, i.e. the usual QP sensitivities); the discrete search is not differentiated.

    ``box`` = (lo, hi) [3] replaces the box ±u_max by lo ≤ u ≤ hi (the commands a drone can reach this step, see
    :func:`filter_from_obs`); it must hold a point (lo ≤ hi) for the QP to stay feasible.
    """
    dt = jnp.result_type(u_nom, A, b, jnp.float32)
    u_nom, A, b = u_nom.astype(dt), A.astype(dt), b.astype(dt)
    m = A.shape[0]
    nrm, a_hat = barriers.unit(A)
    valid_rows = mask & (nrm > barriers.EPS)
    b_hat = jnp.where(valid_rows, b / jnp.where(valid_rows, nrm, 1.0), 0.0)
    u_max = jnp.broadcast_to(jnp.asarray(u_max, dt), (3,))
    lo, hi = (-u_max, u_max) if box is None else (jnp.asarray(box[0], dt), jnp.asarray(box[1], dt))
    # Decision x = (u, √ρ s), so the cost is ½||x − x0||²; rows G x ≥ h are the m CBF rows
    # (slack coefficient 1/√ρ), then the box as u_k ≥ −u_max and −u_k ≥ −u_max. G is kept as
    # its 4 columns (structure of arrays, see above).
    e = jnp.eye(3, dtype=dt)
    cols = [jnp.concatenate([a_hat[:, k], e[k], -e[k]]) for k in range(3)]
    if slack_weight is None:  # the program of before the weights, so stored policies keep their bits
        cols.append(jnp.concatenate([jnp.full((m,), 1.0 / jnp.sqrt(rho), dt), jnp.zeros(6, dt)]))
    else:
        cols.append(jnp.concatenate([jnp.asarray(slack_weight, dt) / jnp.sqrt(rho), jnp.zeros(6, dt)]))
    h = jnp.concatenate([b_hat, lo, -hi])
    valid = jnp.concatenate([valid_rows, jnp.ones(6, bool)])
    x0 = [u_nom[0], u_nom[1], u_nom[2], jnp.zeros((), dt)]

    def row_gaps(x: list) -> jax.Array:
        return sum(c * xk for c, xk in zip(cols, x)) - h

    safe = ~jnp.any(valid & (row_gaps(x0) < -tol))

    sg = jax.lax.stop_gradient
    x_loop, idx, used, pending = _active_set_loop(sg(x0), sg(cols), sg(h), valid, max_iter, tol)
    # On the final active set the solution is the projection of x0 onto {N x = h_act}:
    # x = x0 + Q y with Rᵀ y = h_act − N x0 (Q R: QR of the active normals). That closed form
    # carries the gradients. Its value is taken from the loop's iterate plus one Newton correction
    # onto the same set instead: when infeasible √ρ s ~ 1e3, and forming x from x0 would cost u
    # ~1e-4 of float32 cancellation.
    rows_id = jnp.arange(m + 6)
    pick = [rows_id == i for i in idx]
    normals = [[jnp.sum(jnp.where(pk, c, 0.0)) for c in cols] for pk in pick]
    h_act = [jnp.sum(jnp.where(pk, h, 0.0)) for pk in pick]
    q, R = _qr(normals, used)

    def project(start: list) -> list:
        d = [jnp.where(u, ha - _vdot(nj, start), 0.0) for u, ha, nj in zip(used, h_act, normals)]
        y = _solve_lower_t(R, d)
        return [sk + sum(yi * qi[k] for yi, qi in zip(y, q)) for k, sk in enumerate(start)]

    x_grad = project(x0)
    x_val = sg(project(x_loop))
    x = [jnp.where(pending, xl, xg + sg(xv - xg)) for xl, xg, xv in zip(x_loop, x_grad, x_val)]
    # Out of budget: the dual iterate is optimal for a subset of the rows but may leave the box;
    # clipping keeps the command flyable (reported through ``converged``).
    u = jnp.where(safe, u_nom, jnp.clip(jnp.stack(x[:3]), lo, hi))
    slack = jnp.where(safe, 0.0, jnp.maximum(x[3] / jnp.sqrt(rho), 0.0))
    converged = safe | (~pending & ~jnp.any(valid & (row_gaps(sg(x)) < -10 * tol)))
    diff = u - u_nom
    sq = jnp.sum(diff * diff)
    corr = jnp.where(sq > 0, jnp.sqrt(jnp.where(sq > 0, sq, 1.0)), 0.0)
    active = jnp.zeros(m, bool)
    for pk, us in zip(pick, used):
        active = active | (pk[:m] & us)
    return FilterResult(u=u, slack=slack, intervened=~safe, correction_norm=corr, active=active & ~safe,
                        converged=converged, escaped=jnp.zeros((), bool))


# ------------------------------------------------------- from observations
def filter_from_obs(layout, obs: jax.Array, cmd: jax.Array, gain: jax.Array, u_max: float, drone_radius: float,
                    safety: SafetyFilterConfig, gate_half_opening: float = 0.0, gate_bar: float = 0.0,
                    cyl_accel: jax.Array | None = None, applied: jax.Array | None = None,
                    command_rate: tuple[float, float] | None = None) -> FilterResult:
    """Filter commands [..., n, 3] using only what each drone observes (raw obs [..., n, D]).

    The rows are :func:`aswarm.core.barriers.obs_rows` (``[cylinders M | neighbours K | floor 1 | walls 5 |
    current gate 5 | previous gate 5]``), so the flight side runs the very same filter from its own
    observations. ``gain`` [..., n] is one class-K gain per drone, applied to all its rows; margin,
    neighbour share, floor height and the QP's settings come from ``safety``. ``cyl_accel`` [..., M] (per world,
    m/s²): the cylinders' acceleration bounds, used where ``safety.hazard_accel`` (see ``obs_rows``).

    ``applied`` [..., n, 3] the commands the drones fly now and ``command_rate`` = (command acceleration limit m/s²,
    control period s), where ``safety.brakes``: the QP chooses among the commands the limit lets the drone reach this
    step (``cmd`` first moved into that box, as the drone would take it), and the cylinders' rows (``braking``), the
    neighbours' (``neighbour_braking``), the gate frames' (``gate_braking``) or the walls' (``wall_braking``) are the
    braking barriers of ``obs_rows``.
    """
    whole_swarm = barriers.sees_whole_swarm(layout, obs)

    def one(o, g, u, a, now):  # per drone, under vmap: the rows and the QP of one drone, as the filter always traced
        braking, box = None, None
        if now is not None:
            if safety.reachable_box:
                box = command.reachable(now, command_rate[0] * command_rate[1], u_max)
                u = jnp.clip(u, *box)
            braking = (now, command_rate[0], command_rate[1])
        rows = barriers.filter_rows(layout, o, g, safety, drone_radius=drone_radius,
                                    gate_half_opening=gate_half_opening, gate_bar=gate_bar, cyl_accel=a,
                                    braking=braking, whole_swarm=whole_swarm)
        weight = barriers.row_slack_weights(layout, rows, safety)

        def solve(nominal):
            return filter_velocity(nominal, rows.A, rows.b, rows.mask, u_max, rho=safety.rho, max_iter=safety.max_iter,
                                   tol=safety.tol, slack_weight=weight, box=box)

        res = solve(u)
        if not safety.escape:
            return res
        nominal, stuck = barriers.escape_from(u, res.u, rows, layout, safety)
        # The escape's QP only changes where the drone is stuck; u_nom stays the policy's (the correction it is
        # charged for in training is from what it asked).
        out = jax.tree.map(lambda e, r: jnp.where(stuck, e, r), solve(nominal), res)
        sq = jnp.sum((out.u - u) ** 2)
        corr = jnp.where(sq > 0, jnp.sqrt(jnp.where(sq > 0, sq, 1.0)), 0.0)  # finite gradient at 0
        return out.replace(intervened=res.intervened | stuck, escaped=stuck,
                           correction_norm=jnp.where(stuck, corr, res.correction_norm))

    # (static choices: a filter without them traces as it did before they existed)
    if cyl_accel is not None and safety.hazard_accel:
        accel = jnp.broadcast_to(jnp.asarray(cyl_accel)[..., None, :], obs.shape[:-1] + (layout.num_cylinders,))
    else:
        accel = None
    if not safety.brakes(command_rate):
        applied = None
    fn = one
    for _ in range(obs.ndim - 1):
        fn = jax.vmap(fn)
    return fn(obs, gain, cmd, accel, applied)

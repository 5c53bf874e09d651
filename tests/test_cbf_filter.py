"""CBF safety filter: both QP solvers (JAX, numpy) against one reference and OSQP, pass-through, infeasibility,
masks, the shared barrier rows, batching, and the SafetyFilterConfig's way to a bundle and back."""

from __future__ import annotations

import dataclasses
import json
import math

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from qp_reference import osqp_qp, reference_qp

from aswarm.agents.cbf_filter import FilterResult, filter_velocity
from aswarm.core import barriers
from aswarm.core.barriers import Rows, barrier_rows, cylinder_rows, floor_row, neighbour_rows
from aswarm.core.layout import CYL, NBR, ObsLayout
from aswarm.core.safety import LEGACY_FIELDS, SafetyFilterConfig, from_manifest, manifest_fields, nest_legacy
from aswarm.flight import cbf as np_cbf

U_MAX = 2.0
RHO = 1e6
M_ROWS = 12


def random_instance(rng, feasible: bool, m: int = M_ROWS):
    A = rng.normal(size=(m, 3))
    A /= np.linalg.norm(A, axis=1, keepdims=True)
    if feasible:
        b = A @ rng.uniform(-0.9 * U_MAX, 0.9 * U_MAX, 3) - rng.exponential(0.5, m)
    else:
        b = rng.uniform(0.5, 2.0, m)  # every row pushes outwards: no u satisfies them all
    A[m - 2:] = A[:2]  # duplicated rows: degenerate active sets must not break the solver
    b[m - 2:] = b[:2]
    mask = rng.uniform(size=m) < 0.85
    mask[:2] = True
    return rng.uniform(-3.0, 3.0, 3), A, b, mask


def stack(instances):
    u, A, b, mask = (np.stack(x) for x in zip(*instances))
    return jnp.asarray(u, jnp.float32), jnp.asarray(A, jnp.float32), jnp.asarray(b, jnp.float32), jnp.asarray(mask)


batched_filter = jax.jit(jax.vmap(lambda u, A, b, mask: filter_velocity(u, A, b, mask, U_MAX)))
# Eager calls dispatch every op of the unrolled solver one by one: jit even single problems.
single_filter = jax.jit(filter_velocity, static_argnames=("max_iter",))


@pytest.mark.parametrize("feasible", [True, False])
def test_matches_reference_qp(feasible):
    rng = np.random.default_rng(0 if feasible else 1)
    instances = [random_instance(rng, feasible) for _ in range(250 if feasible else 100)]
    res = batched_filter(*stack(instances))
    chex.assert_shape(res.u, (len(instances), 3))
    chex.assert_shape(res.active, (len(instances), M_ROWS))
    u, slack = np.asarray(res.u, float), np.asarray(res.slack, float)
    assert np.all(np.asarray(res.converged))
    assert np.all(np.abs(u) <= U_MAX + 1e-6)
    for k, (u_nom, A, b, mask) in enumerate(instances):
        u_ref, s_ref = reference_qp(u_nom, A, b, mask, U_MAX)
        np.testing.assert_allclose(u[k], u_ref, atol=1e-4)
        np.testing.assert_allclose(slack[k], s_ref, atol=1e-5)
        gaps = (A @ u[k] - b)[mask]
        if feasible:
            assert slack[k] < 1e-4
            assert gaps.min() >= -1e-4  # every present row holds
        else:
            assert slack[k] > 0.1
            assert gaps.min() >= -slack[k] - 1e-4  # rows hold once relaxed by the shared slack
        active = np.asarray(res.active[k])
        assert not np.any(active & ~mask)
        np.testing.assert_allclose(gaps[active[mask]], -slack[k], atol=1e-4)  # binding rows are tight


def test_unchanged_when_already_safe():
    rng = np.random.default_rng(2)
    u_nom = rng.uniform(-1.5, 1.5, (64, 3))
    A = rng.normal(size=(64, M_ROWS, 3))
    b = np.einsum("bmk,bk->bm", A, u_nom) - rng.uniform(0.0, 1.0, (64, M_ROWS))  # u_nom satisfies all rows
    mask = rng.uniform(size=(64, M_ROWS)) < 0.8
    u_nom32 = jnp.asarray(u_nom, jnp.float32)
    res = batched_filter(u_nom32, jnp.asarray(A, jnp.float32), jnp.asarray(b, jnp.float32), jnp.asarray(mask))
    np.testing.assert_array_equal(np.asarray(res.u), np.asarray(u_nom32))
    assert not np.any(np.asarray(res.intervened))
    assert not np.any(np.asarray(res.active))
    np.testing.assert_array_equal(np.asarray(res.slack), 0.0)
    np.testing.assert_array_equal(np.asarray(res.correction_norm), 0.0)


def test_box_only_clips():
    u_nom = jnp.array([3.0, -0.5, -7.0])
    res = single_filter(u_nom, jnp.zeros((1, 3)), jnp.zeros(1), jnp.zeros(1, bool), jnp.array([2.0, 2.0, 1.0]))
    np.testing.assert_allclose(res.u, [2.0, -0.5, -1.0], atol=1e-6)
    assert bool(res.intervened) and float(res.slack) == 0.0
    np.testing.assert_allclose(res.correction_norm, np.hypot(1.0, 6.0), rtol=1e-6)


def test_infeasible_instance_is_finite_and_bounded():
    # Two opposite rows demanding u_x ≥ 1 and u_x ≤ −1, and a third out of the box's reach (padded
    # with absent rows to reuse the compiled batch).
    A = np.zeros((1, M_ROWS, 3), np.float32)
    A[0, :3] = [[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    b = np.zeros((1, M_ROWS), np.float32)
    b[0, :3] = [1.0, 1.0, 5.0]
    res = batched_filter(jnp.array([[0.3, 0.0, 0.5]]), jnp.asarray(A), jnp.asarray(b), jnp.arange(M_ROWS)[None] < 3)
    assert np.all(np.isfinite(np.asarray(res.u))) and bool(res.converged[0])
    assert np.all(np.abs(np.asarray(res.u)) <= 2.0 + 1e-6)
    # The shared slack equalises the worst violation: u_y hits the bound, s = 5 − 2 = 3, u_x anywhere in [−2, 2]
    # → the nearest, 0.3; u_z untouched.
    np.testing.assert_allclose(res.u[0], [0.3, 2.0, 0.5], atol=1e-4)
    np.testing.assert_allclose(res.slack[0], 3.0, atol=1e-4)


def test_masked_and_degenerate_rows_are_ignored():
    rng = np.random.default_rng(3)
    instances = [random_instance(rng, feasible=True) for _ in range(32)]
    u, A, b, mask = stack(instances)
    base = batched_filter(u, A, b, mask)
    # Masked rows get wild contents.
    A2 = jnp.where(mask[..., None], A, 10.0 * jnp.asarray(rng.normal(size=A.shape), jnp.float32))
    b2 = jnp.where(mask, b, 50.0)
    # The last row duplicates row 1, so replacing it changes nothing, unless the replacement counts:
    # a present row with a ≈ 0 cannot be influenced by u and must be dropped, not paid for with slack.
    A2 = A2.at[:, -1].set(0.0)
    b2 = b2.at[:, -1].set(3.0)
    mask2 = mask.at[:, -1].set(True)
    res = batched_filter(u, A2, b2, mask2)
    np.testing.assert_allclose(res.u, base.u, atol=1e-6)
    np.testing.assert_allclose(res.slack, base.slack, atol=1e-6)
    assert not np.any(np.asarray(res.active[:, -1]))


def test_rows_are_scale_invariant():
    rng = np.random.default_rng(4)
    u, A, b, mask = stack([random_instance(rng, feasible=False) for _ in range(16)])
    scale = jnp.asarray(rng.uniform(0.1, 10.0, b.shape), jnp.float32)
    res = batched_filter(u, A * scale[..., None], b * scale, mask)
    base = batched_filter(u, A, b, mask)
    np.testing.assert_allclose(res.u, base.u, atol=1e-4)
    np.testing.assert_allclose(res.slack, base.slack, atol=1e-4)


def test_out_of_budget_is_reported_and_flyable():
    rng = np.random.default_rng(5)
    u, A, b, mask = stack([random_instance(rng, feasible=False) for _ in range(16)])
    res = jax.jit(jax.vmap(lambda *a: filter_velocity(*a, U_MAX, max_iter=1)))(u, A, b, mask)
    assert not np.all(np.asarray(res.converged))
    assert np.all(np.isfinite(np.asarray(res.u))) and np.all(np.abs(np.asarray(res.u)) <= U_MAX)


# ---------------------------------------------------------------- barriers
def test_cylinder_row_hand_derived():
    # Drone 1 m (surface gap minus margin) from a cylinder that moves straight at it at v = 0.5 m/s.
    R, r, margin, gamma, v = 0.2, 0.05, 0.05, 0.2, 0.5
    pos = jnp.array([1.3, 0.0, 1.0])
    con = cylinder_rows(pos, jnp.zeros((1, 2)), jnp.array([R]), jnp.array([[v, 0.0]]), jnp.ones(1, bool),
                               jnp.array([gamma]), drone_radius=r, margin=margin)
    np.testing.assert_allclose(con.h, [1.0], atol=1e-6)  # 1.3 − (0.2 + 0.05 + 0.05)
    np.testing.assert_allclose(con.A, [[1.0, 0.0, 0.0]], atol=1e-6)
    # ḣ = u_x − v ≥ −γ h: the drone must retreat at ≥ v − γ h = 0.3 m/s (closing speed ≤ γ h/|∇h|).
    np.testing.assert_allclose(con.b, [v - gamma * 1.0], atol=1e-6)
    res = single_filter(jnp.array([-1.0, 0.4, 0.0]), con.A, con.b, con.mask, 2.0)
    np.testing.assert_allclose(res.u, [0.3, 0.4, 0.0], atol=1e-5)
    # Static cylinder, γ = 2: approach speed capped at γ h = 2 m/s.
    con = cylinder_rows(pos, jnp.zeros((1, 2)), jnp.array([R]), jnp.zeros((1, 2)), jnp.ones(1, bool),
                               2.0, drone_radius=r, margin=margin)
    res = single_filter(jnp.array([-3.0, 0.0, 0.0]), con.A, con.b, con.mask, 5.0)
    np.testing.assert_allclose(res.u, [-2.0, 0.0, 0.0], atol=1e-5)


def test_moving_cylinder_rows_hold_against_the_acceleration_bound_hand_derived():
    """A cylinder (its look-ahead point) at the origin moving +x at 1 m/s, acceleration bound 2 m/s², look-ahead
    lag 0.3 s: n · u ≥ n · v_c + τ a − γ h, the worst the cylinder can do within the bound before the lagging
    drone's look-ahead point answers."""
    R, r, margin, gamma, lag, a = 0.2, 0.05, 0.05, 1.0, 0.3, 2.0
    vel, accel = jnp.array([[1.0, 0.0]]), jnp.array([a])
    one = dict(drone_radius=r, margin=margin)
    d = np.sqrt(0.5)
    # Ahead of it and aside: d = (0.5, 0.5), so n = (1, 1)/√2, h = √0.5 − 0.3.
    con = cylinder_rows(jnp.array([0.5, 0.5, 1.0]), jnp.zeros((1, 2)), jnp.array([R]), vel, jnp.ones(1, bool),
                        gamma, motion=(accel, lag), **one)
    np.testing.assert_allclose(con.h, [d - 0.3], atol=1e-6)
    np.testing.assert_allclose(con.A, [[d, d, 0.0]], atol=1e-6)
    np.testing.assert_allclose(con.b, [d * 1.0 + lag * a - gamma * (d - 0.3)], atol=1e-6)
    # Hovering there, the filter moves the drone away along n at exactly b (the closest command to 0).
    res = single_filter(jnp.zeros(3), con.A, con.b, con.mask, 2.0)
    np.testing.assert_allclose(res.u, float(con.b[0]) * np.array([d, d, 0.0]), atol=1e-5)
    # A static cylinder (velocity and bound 0) keeps the row it has without motion.
    still = [cylinder_rows(jnp.array([0.5, 0.5, 1.0]), jnp.zeros((1, 2)), jnp.array([R]), jnp.zeros((1, 2)),
                           jnp.ones(1, bool), gamma, motion=m, **one) for m in (None, (jnp.zeros(1), lag))]
    for x, y in zip(*still):
        np.testing.assert_allclose(x, y, atol=1e-7)


def test_moving_gain_cap_is_a_gain_per_hazard_hand_derived():
    """Two cylinders, one moving (bound 2 m/s²) and one static, drone gain 2 /s, moving_gain_max 0.8 /s: the moving
    one's row is b = n · v_c + τ a − 0.8 h, the static one's −2 h; every other row keeps 2; without the cap all take
    2. numpy and JAX build the same rows."""
    R, r, margin, lag, a = 0.2, 0.05, 0.05, 0.3, 2.0
    pos, vel = np.array([0.5, 0.5, 1.0]), np.zeros(3)
    centers, vels = np.array([[0.0, 0.0], [1.1, 0.5]]), np.array([[1.0, 0.0], [0.0, 0.0]])
    accel, present = np.array([a, 0.0]), np.ones(2, bool)
    nbr, none = np.zeros((1, 3)), np.zeros(1, bool)
    kw = dict(drone_radius=r, margin=margin, floor_z=0.0, neighbour_share=0.5, cyl_motion=(accel, lag))
    parts = barriers._barrier_parts(pos, vel, centers, np.full(2, R), vels, present, nbr, nbr, none,
                                    np.array([2.0]), moving_gain_max=0.8, **kw)
    cyl, floor = parts[0], parts[2]
    d = np.sqrt(0.5)
    h = np.array([d - (R + r + margin), 0.6 - (R + r + margin)])
    np.testing.assert_allclose(cyl.h, h, atol=1e-9)
    np.testing.assert_allclose(cyl.b, [d * 1.0 + lag * a - 0.8 * h[0], -2.0 * h[1]], atol=1e-9)
    np.testing.assert_allclose(floor.b, [-2.0 * (1.0 - (r + margin))], atol=1e-9)
    uncapped = barriers._barrier_parts(pos, vel, centers, np.full(2, R), vels, present, nbr, nbr, none,
                                       np.array([2.0]), **kw)[0]
    np.testing.assert_allclose(uncapped.b, [d * 1.0 + lag * a - 2.0 * h[0], -2.0 * h[1]], atol=1e-9)
    # Above the drone's gain the cap changes nothing.
    loose = barriers._barrier_parts(pos, vel, centers, np.full(2, R), vels, present, nbr, nbr, none,
                                    np.array([2.0]), moving_gain_max=3.0, **kw)[0]
    np.testing.assert_allclose(loose.b, uncapped.b, atol=1e-12)
    with jax.enable_x64(True):
        got = barriers._barrier_parts(*(jnp.asarray(x) for x in (pos, vel, centers, np.full(2, R), vels, present, nbr,
                                                                 nbr, none, np.array([2.0]))), moving_gain_max=0.8,
                                      **{**kw, "cyl_motion": (jnp.asarray(accel), lag)})[0]
    np.testing.assert_allclose(np.asarray(got.b), cyl.b, atol=1e-12)


def _moving_and_static_cylinders(vel):
    """The scene of the gain cap's test for the margins' tests: (R, r, margin, lag, a), the ``_barrier_parts``
    arguments for a drone at (0.5, 0.5, 1) flying ``vel``, and its keywords (the cap 0.8 /s, the bounds (a, 0))."""
    R, r, margin, lag, a = 0.2, 0.05, 0.05, 0.3, 2.0
    pos = np.array([0.5, 0.5, 1.0])
    centers, vels = np.array([[0.0, 0.0], [1.1, 0.5]]), np.array([[1.0, 0.0], [0.0, 0.0]])
    nbr, none = np.zeros((1, 3)), np.zeros(1, bool)
    args = (pos, np.asarray(vel, float), centers, np.full(2, R), vels, np.ones(2, bool), nbr, nbr, none,
            np.array([2.0]))
    kw = dict(drone_radius=r, margin=margin, floor_z=0.0, neighbour_share=0.5, cyl_motion=(np.array([a, 0.0]), lag),
              moving_gain_max=0.8)
    return (R, r, margin, lag, a), args, kw


def _jax_agrees_and_config_needs_the_bounds(args, kw, option: str, value: float, numpy_rows, negative: float):
    """The shared tail of the moving rows' option tests: with ``option`` = ``value`` JAX gives ``numpy_rows``' b
    (float64), and the config refuses the option without the bounds that tell a moving cylinder, and below 0."""
    accel, lag = kw["cyl_motion"]
    with jax.enable_x64(True):
        got = barriers._barrier_parts(*(jnp.asarray(x) for x in args), **{option: value},
                                      **{**kw, "cyl_motion": (jnp.asarray(accel), lag)})[0]
    np.testing.assert_allclose(np.asarray(got.b), numpy_rows.b, atol=1e-12)
    with pytest.raises(ValueError, match=rf"{option}={value} with hazard_accel=false: allowed: 0, or hazard_accel"):
        SafetyFilterConfig(**{option: value, "hazard_accel": False})
    with pytest.raises(ValueError, match=rf"invalid safety_filter.{option}={negative}: allowed: >= 0"):
        SafetyFilterConfig(**{option: negative})


def test_moving_margin_widens_the_moving_cylinders_rows_alone_hand_derived():
    """The scene above with moving_margin 0.1 m: the moving cylinder's barrier is h − 0.1 and its row b + γ 0.1 (here
    with the cap's 0.8 /s), the static one's and the floor's unchanged; numpy and JAX agree; in the config it needs
    the bounds that tell a moving cylinder, as the cap does."""
    (R, r, margin, lag, a), args, kw = _moving_and_static_cylinders(np.zeros(3))
    extra = 0.1
    plain = barriers._barrier_parts(*args, **kw)
    wide = barriers._barrier_parts(*args, moving_margin=extra, **kw)
    d = np.sqrt(0.5)
    np.testing.assert_allclose(wide[0].h, [d - (R + r + margin + extra), 0.6 - (R + r + margin)], atol=1e-9)
    np.testing.assert_allclose(wide[0].b, plain[0].b + [0.8 * extra, 0.0], atol=1e-9)
    np.testing.assert_allclose(wide[2].b, plain[2].b, atol=1e-12)  # the floor keeps margin alone
    _jax_agrees_and_config_needs_the_bounds(args, kw, "moving_margin", extra, wide[0], -0.1)
    # Without the bounds (cyl_motion None) no cylinder is known to move: nothing changes.
    still = {**kw, "cyl_motion": None, "moving_gain_max": 0.0}
    np.testing.assert_allclose(barriers._barrier_parts(*args, moving_margin=extra, **still)[0].b,
                               barriers._barrier_parts(*args, **still)[0].b, atol=1e-12)
    assert SafetyFilterConfig(moving_margin=0.1).fitted(0.5, 0.2).moving_margin == 0.1  # a distance: not scaled


def test_moving_margin_time_grows_with_the_closing_speed_hand_derived():
    """moving_margin_time 0.05 s on the scene above, the drone flying (1, −1) m/s: it closes on the moving cylinder
    (at the origin, (1, 0) m/s) at −n · (v − v_c) = 1/√2 m/s, so that row keeps 0.05/√2 m more (b + 0.8 of it); the
    static cylinder, which it closes on at 1 m/s, and the floor keep theirs; flying (1, 1) m/s, which opens the gap
    to the moving cylinder (n · (v − v_c) = 1/√2 > 0), nothing changes; numpy and JAX agree; the config needs the
    bounds."""
    (R, r, margin, lag, a), args, kw = _moving_and_static_cylinders([1.0, -1.0, 0.0])
    T = 0.05
    plain = barriers._barrier_parts(*args, **kw)
    timed = barriers._barrier_parts(*args, moving_margin_time=T, **kw)
    extra = T / np.sqrt(2.0)
    d = np.sqrt(0.5)
    np.testing.assert_allclose(timed[0].h, [d - (R + r + margin + extra), 0.6 - (R + r + margin)], atol=1e-9)
    np.testing.assert_allclose(timed[0].b, plain[0].b + [0.8 * extra, 0.0], atol=1e-9)
    np.testing.assert_allclose(timed[2].b, plain[2].b, atol=1e-12)
    away = (args[0], np.array([1.0, 1.0, 0.0]), *args[2:])
    np.testing.assert_allclose(barriers._barrier_parts(*away, moving_margin_time=T, **kw)[0].b,
                               barriers._barrier_parts(*away, **kw)[0].b, atol=1e-12)
    _jax_agrees_and_config_needs_the_bounds(args, kw, "moving_margin_time", T, timed[0], -1)


def test_rail_speed_takes_the_bound_along_the_cylinders_velocity_hand_derived():
    """rail_speed 0.5 m/s on the scene above (drone at (0.5, 0.5), hovering): the moving cylinder at the origin
    moves along (1, 0) at 1 m/s, so its acceleration (bound 2 m/s²) acts along x alone and enters the row as
    2 |n · (1, 0)| = 2/√2 where the whole bound entered before: b falls by 0.3 (2 − √2); the static cylinder's row
    and the floor's are unchanged, and so are the gain cap's (0.8 /s) and h. Slower than rail_speed (1.5 m/s) the
    whole bound stays; numpy and JAX agree; the config needs the bounds."""
    (R, r, margin, lag, a), args, kw = _moving_and_static_cylinders(np.zeros(3))
    plain = barriers._barrier_parts(*args, **kw)
    rail = barriers._barrier_parts(*args, rail_speed=0.5, **kw)
    np.testing.assert_allclose(rail[0].b, plain[0].b - [lag * (a - a / np.sqrt(2.0)), 0.0], atol=1e-12)
    np.testing.assert_allclose(rail[0].h, plain[0].h, atol=1e-12)
    np.testing.assert_allclose(rail[2].b, plain[2].b, atol=1e-12)
    np.testing.assert_allclose(barriers._barrier_parts(*args, rail_speed=1.5, **kw)[0].b, plain[0].b, atol=1e-12)
    # Beside the sweep (n across the motion) nothing of the bound is left: the drone at (0, 0.5).
    beside = (np.array([0.0, 0.5, 1.0]), *args[1:])
    np.testing.assert_allclose(barriers._barrier_parts(*beside, rail_speed=0.5, **kw)[0].b[0],
                               barriers._barrier_parts(*beside, **kw)[0].b[0] - lag * a, atol=1e-12)
    _jax_agrees_and_config_needs_the_bounds(args, kw, "rail_speed", 0.5, rail[0], -1)


def test_neighbour_rows_split_the_pair_condition():
    rng = np.random.default_rng(6)
    p_i, p_k = jnp.asarray(rng.normal(size=3), jnp.float32), jnp.asarray(rng.normal(size=3), jnp.float32)
    v_i, v_k = jnp.asarray(rng.normal(size=3), jnp.float32), jnp.asarray(rng.normal(size=3), jnp.float32)
    gamma, r, margin = 1.5, 0.06, 0.1
    for w in (0.5, 0.3):
        ci = neighbour_rows(p_i, v_i, p_k[None], v_k[None], jnp.ones(1, bool), gamma, drone_radius=r,
                                   margin=margin, share=w)
        ck = neighbour_rows(p_k, v_k, p_i[None], v_i[None], jnp.ones(1, bool), gamma, drone_radius=r,
                                   margin=margin, share=1.0 - w)
        h = float(jnp.linalg.norm(p_i - p_k)) - (2 * r + margin)
        np.testing.assert_allclose(ci.h, [h], atol=1e-5)
        np.testing.assert_allclose(ci.A, -ck.A, atol=1e-6)
        # n·u_i ≥ b_i and −n·u_k ≥ b_k add up to n·(u_i − u_k) ≥ −γ h, whatever the velocities.
        np.testing.assert_allclose(ci.b + ck.b, [-gamma * h], atol=1e-5)
    # Neither moving, share 1/2: the classic n·u ≥ −γh/2.
    ci = neighbour_rows(p_i, jnp.zeros(3), p_k[None], jnp.zeros((1, 3)), jnp.ones(1, bool), gamma,
                               drone_radius=r, margin=margin)
    np.testing.assert_allclose(ci.b, [-gamma * h / 2], atol=1e-5)


def test_closing_split_leaves_a_braking_leader_a_small_share_and_still_adds_up_to_the_pair_condition():
    """A leader at x = 1 m flying on at 0.2 m/s, its follower at x = 0 closing at 1 m/s, softness s = 0.25 m/s: the
    leader closes at 0, the follower at 1, so the leader's share is (0 + s) / (0 + 1 + 2 s) = 1/6 and the
    follower's 5/6. At a gap h = 0.1 m and γ = 1 /s the leader's row asks n · u ≥ (5/6) 0.2 + (1/6) 1 − h/6 =
    0.3167 m/s of it, where the halves asked 0.6 − h/2 = 0.55 (on, towards what it brakes for)."""
    r, margin, gamma, soft, least = 0.05, 0.0, 1.0, 0.25, 0.1
    p_lead, p_follow = np.array([1.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.0])
    v_lead, v_follow = np.array([0.2, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])
    p_lead = p_lead + np.array([2 * r + 0.1 - 1.0, 0.0, 0.0])  # the gap h = 0.1 m
    w_lead = barriers.closing_share(p_lead, v_lead, p_follow[None], v_follow[None], soft=soft, least=least)
    w_follow = barriers.closing_share(p_follow, v_follow, p_lead[None], v_lead[None], soft=soft, least=least)
    np.testing.assert_allclose(w_lead, [1 / 6])
    np.testing.assert_allclose(w_follow, [5 / 6])
    lead = neighbour_rows(p_lead, v_lead, p_follow[None], v_follow[None], np.ones(1, bool), gamma, drone_radius=r,
                          margin=margin, share=w_lead)
    np.testing.assert_allclose(lead.h, [0.1])
    np.testing.assert_allclose(lead.A, [[1.0, 0.0, 0.0]])
    np.testing.assert_allclose(lead.b, [5 / 6 * 0.2 + 1 / 6 - 0.1 / 6])
    halves = neighbour_rows(p_lead, v_lead, p_follow[None], v_follow[None], np.ones(1, bool), gamma, drone_radius=r,
                            margin=margin)
    np.testing.assert_allclose(halves.b, [0.55])
    # With the reference scaled to 0 (the classic form), the leader may brake to rest: n · u ≥ −h/2 = −0.05 in
    # halves, −h/6 with its closing share.
    np.testing.assert_allclose(neighbour_rows(p_lead, v_lead, p_follow[None], v_follow[None], np.ones(1, bool), gamma,
                                              drone_radius=r, margin=margin, reference=0.0).b, [-0.05])
    np.testing.assert_allclose(neighbour_rows(p_lead, v_lead, p_follow[None], v_follow[None], np.ones(1, bool), gamma,
                                              drone_radius=r, margin=margin, share=w_lead, reference=0.0).b, [-0.1 / 6])
    # Both opening the gap, or sliding past each other: halves. A follower far faster: the clip's floor. Random
    # pairs' rows add up to the pair condition (the neighbour computes 1 - w), in JAX as in numpy.
    for v_i, v_k in ((v_lead, -v_follow), (np.array([0.0, 1.0, 0.0]), np.array([0.0, -2.0, 0.5]))):
        np.testing.assert_allclose(barriers.closing_share(p_lead, v_i, p_follow[None], v_k[None], soft=soft,
                                                          least=least), [0.5])
    np.testing.assert_allclose(barriers.closing_share(p_lead, np.zeros(3), p_follow[None], 50 * v_follow[None],
                                                      soft=soft, least=least), [least])
    rng = np.random.default_rng(3)
    for _ in range(20):
        p_i, p_k, v_i, v_k = rng.normal(size=(4, 3))
        w_i = barriers.closing_share(jnp.asarray(p_i), jnp.asarray(v_i), jnp.asarray(p_k)[None],
                                     jnp.asarray(v_k)[None], soft=soft, least=least)
        w_k = barriers.closing_share(p_k, v_k, p_i[None], v_i[None], soft=soft, least=least)
        np.testing.assert_allclose(np.asarray(w_i) + w_k, [1.0], atol=1e-6)
        ci = neighbour_rows(p_i, v_i, p_k[None], v_k[None], np.ones(1, bool), gamma, drone_radius=r,
                            share=np.asarray(w_i, float))
        ck = neighbour_rows(p_k, v_k, p_i[None], v_i[None], np.ones(1, bool), gamma, drone_radius=r, share=w_k)
        np.testing.assert_allclose(ci.b + ck.b, -gamma * ci.h, atol=1e-5)
        lam = rng.uniform()  # any reference scale both use
        ci, ck = (neighbour_rows(p, v, q[None], u[None], np.ones(1, bool), gamma, drone_radius=r, share=w,
                                 reference=lam) for p, v, q, u, w in ((p_i, v_i, p_k, v_k, np.asarray(w_i, float)),
                                                                      (p_k, v_k, p_i, v_i, w_k)))
        np.testing.assert_allclose(ci.b + ck.b, -gamma * ci.h, atol=1e-5)


def test_the_reference_released_by_closing_speed_lets_a_leader_brake_and_a_column_keep_pace():
    """The leader and follower above (gap h = 0.1 m, γ = 1 /s, halves) close at c = n · (v_f − v_l) = 0.8 m/s. With
    release r = 1.6 m/s the reference scale is 1 − 0.8/1.6 = 1/2: the leader's row asks n · u ≥ ½ (0.2 + 1)/2 − h/2
    = 0.25 m/s (0.55 at scale 1), the follower's −n · u ≥ −0.30 − 0.05, and the two add up to −γh. At r ≤ 0.8 the
    leader may brake to rest (−h/2, the classic form). A column at one speed (c = 0) keeps the full reference: both
    at 1 m/s, the leader's row asks 1 − h/2 (not more than it flies) and the follower's lets it keep pace (u_x ≤
    1 + h/2)."""
    r, gamma, h = 0.05, 1.0, 0.1
    p_lead, p_follow = np.array([2 * r + h, 0.0, 1.0]), np.array([0.0, 0.0, 1.0])
    v_lead, v_follow = np.array([0.2, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])
    one = np.ones(1, bool)

    def rows(release, v_l=v_lead, v_f=v_follow, xp=np):
        lead = neighbour_rows(xp.asarray(p_lead), xp.asarray(v_l), xp.asarray(p_follow)[None], xp.asarray(v_f)[None],
                              one, gamma, drone_radius=r, release=release)
        follow = neighbour_rows(p_follow, v_f, p_lead[None], v_l[None], one, gamma, drone_radius=r, release=release)
        return np.asarray(lead.b), follow.b

    lead, follow = rows(1.6)
    np.testing.assert_allclose(lead, [0.25], atol=1e-6)
    np.testing.assert_allclose(follow, [-0.35], atol=1e-6)
    np.testing.assert_allclose(np.asarray(rows(1.6, xp=jnp)[0]), lead, atol=1e-6)  # JAX as numpy
    for release in (0.8, 0.5):
        np.testing.assert_allclose(rows(release)[0], [-h / 2], atol=1e-6)
    np.testing.assert_allclose(rows(0.0)[0], [0.55], atol=1e-6)  # off: the current velocities
    column, follower = rows(1.6, v_l=v_follow)
    np.testing.assert_allclose(column, [1.0 - h / 2], atol=1e-6)
    np.testing.assert_allclose(follower, [-1.0 - h / 2], atol=1e-6)
    rng = np.random.default_rng(4)  # random pairs, any scale and release both use: the rows add up
    for _ in range(20):
        p_i, p_k, v_i, v_k = rng.normal(size=(4, 3))
        lam, release, w = rng.uniform(), rng.uniform(0.1, 2.0), rng.uniform(0.1, 0.9)
        ci = neighbour_rows(p_i, v_i, p_k[None], v_k[None], one, gamma, drone_radius=r, share=w, reference=lam,
                            release=release)
        ck = neighbour_rows(p_k, v_k, p_i[None], v_i[None], one, gamma, drone_radius=r, share=1 - w, reference=lam,
                            release=release)
        np.testing.assert_allclose(ci.b + ck.b, -gamma * ci.h, atol=1e-5)


def test_floor_row():
    con = floor_row(jnp.array([0.0, 0.0, 0.5]), jnp.array([1.0]), z_min=0.1)
    np.testing.assert_allclose(con.h, [0.4], atol=1e-6)
    res = single_filter(jnp.array([0.0, 0.0, -1.0]), con.A, con.b, con.mask, 2.0)
    np.testing.assert_allclose(res.u, [0.0, 0.0, -0.4], atol=1e-5)  # descend at most γ h


def _scene(key, M=5, K=3):
    ks = jax.random.split(key, 8)
    return dict(
        pos=jnp.array([0.0, 0.0, 1.0]) + 0.3 * jax.random.normal(ks[0], (3,)),
        vel=jax.random.normal(ks[1], (3,)),
        cyl_center=jax.random.uniform(ks[2], (M, 2), minval=-1.0, maxval=1.0),
        cyl_radius=jnp.full((M,), 0.15),
        cyl_vel=0.5 * jax.random.normal(ks[3], (M, 2)),
        cyl_present=jnp.arange(M) < M - 1,
        nbr_pos=jnp.array([0.0, 0.0, 1.0]) + jax.random.uniform(ks[4], (K, 3), minval=-1.0, maxval=1.0),
        nbr_vel=jax.random.normal(ks[5], (K, 3)),
        nbr_present=jnp.ones(K, bool),
        gamma=jax.random.uniform(ks[6], (M + K + 1,), minval=0.5, maxval=3.0),
    )


def _build(s):
    return barrier_rows(**s, drone_radius=0.06, margin=0.1, floor_z=0.0)


def test_barrier_layout_and_masks():
    s = _scene(jax.random.PRNGKey(0))
    con = jax.jit(_build)(s)
    assert isinstance(con, Rows)
    chex.assert_shape([con.A, con.b, con.mask, con.h], [(9, 3), (9,), (9,), (9,)])
    np.testing.assert_array_equal(con.mask, [True] * 4 + [False] + [True] * 3 + [True])
    np.testing.assert_allclose(jnp.linalg.norm(con.A, axis=-1), 1.0, atol=1e-6)
    np.testing.assert_allclose(con.A[:5, 2], 0.0)  # cylinders: horizontal normals
    np.testing.assert_allclose(con.h[-1], s["pos"][2] - 0.16, atol=1e-6)  # floor: z − (r + margin)
    # The same rows from the parts, in the documented order.
    cyl = cylinder_rows(s["pos"], s["cyl_center"], s["cyl_radius"], s["cyl_vel"], s["cyl_present"],
                               s["gamma"][:5], drone_radius=0.06, margin=0.1)
    np.testing.assert_allclose(con.b[:5], cyl.b, atol=1e-6)


def test_jit_vmap_matches_single_calls_and_gradients_are_finite():
    keys = jax.random.split(jax.random.PRNGKey(1), 6).reshape(2, 3, 2)
    scenes = jax.vmap(jax.vmap(_scene))(keys)
    u_nom = 1.5 * jax.random.normal(jax.random.PRNGKey(2), (2, 3, 3))

    def step(s, u):
        con = _build(s)
        return filter_velocity(u, con.A, con.b, con.mask, U_MAX)

    batched = jax.jit(jax.vmap(jax.vmap(step)))(scenes, u_nom)
    assert isinstance(batched, FilterResult)
    chex.assert_shape([batched.u, batched.slack, batched.intervened, batched.correction_norm, batched.active],
                      [(2, 3, 3), (2, 3), (2, 3), (2, 3), (2, 3, 9)])
    chex.assert_tree_all_finite(batched.u)
    single_step = jax.jit(step)
    for i in range(2):
        for j in range(3):
            single = single_step(jax.tree.map(lambda x, i=i, j=j: x[i, j], scenes), u_nom[i, j])
            np.testing.assert_allclose(batched.u[i, j], single.u, atol=1e-6)
            np.testing.assert_allclose(batched.slack[i, j], single.slack, atol=1e-6)
            np.testing.assert_array_equal(batched.active[i, j], single.active)

    # Gradients w.r.t. the gains, the positions and the command stay finite (the coincident
    # neighbour makes a zero-length normal).
    s = jax.tree.map(lambda x: x[0, 0], scenes)
    s["nbr_pos"] = s["nbr_pos"].at[0].set(s["pos"])

    def loss(gamma, pos, u):
        con = _build({**s, "gamma": gamma, "pos": pos})
        res = filter_velocity(u, con.A, con.b, con.mask, U_MAX)
        return jnp.sum(res.u) + res.slack + res.correction_norm

    grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(s["gamma"], s["pos"], u_nom[0, 0])
    chex.assert_tree_all_finite(grads)


def test_gradient_matches_active_set_sensitivity():
    # One binding unit row a: u = u_nom + (b − a·u_nom) a, so ∂u/∂u_nom = I − a aᵀ and ∂u/∂b = a.
    a = jnp.array([0.6, 0.0, 0.8])
    u_nom = jnp.array([-0.5, 0.3, -0.2])

    def f(u, b):
        return filter_velocity(u, a[None], b[None], jnp.ones(1, bool), 2.0).u

    jac_u, jac_b = jax.jit(jax.jacobian(f, argnums=(0, 1)))(u_nom, jnp.asarray(0.5))
    np.testing.assert_allclose(jac_u, np.eye(3) - np.outer(a, a), atol=1e-5)
    np.testing.assert_allclose(jac_b, a, atol=1e-5)


# ---------------------------------------------------------------- the numpy solver, and OSQP
@pytest.mark.parametrize("scalar_below", [0, 10_000], ids=["batched", "one-by-one"])
def test_numpy_qp_matches_the_reference_on_random_problems(scalar_below, monkeypatch):
    """Both ways the numpy active-set steps run (over a batch, or problem by problem in floats) are exact."""
    monkeypatch.setattr(np_cbf, "SCALAR_MAX_PROBLEMS", scalar_below)
    rng = np.random.default_rng(3)
    P, m = 120, 6
    A = rng.normal(size=(P, m, 3))
    b = rng.normal(size=(P, m)) * 2.0
    mask = rng.uniform(size=(P, m)) < 0.8
    u_nom = rng.uniform(-3, 3, size=(P, 3))
    res = np_cbf.filter_velocity(u_nom, A, b, mask, 2.0)
    ref = np.stack([reference_qp(u_nom[i], A[i], b[i], mask[i], 2.0)[0] for i in range(P)])
    assert res.intervened.mean() > 0.5 and np.all(res.converged)
    np.testing.assert_allclose(res.u, ref, atol=1e-8)
    assert np.all(np.abs(res.u) <= 2.0)


def test_both_solvers_and_the_reference_match_osqp_on_random_instances():
    """An independent check by a maintained solver. OSQP's polished solution is exact on the active set it found
    (to the KKT solve's rounding, ~1e-9 here), so: the float64 reference and numpy solver agree with it to 1e-6
    (margin for the conditioning the 1/√ρ slack column brings), the float32 JAX solver to 1e-4 (as against the
    reference: the scaled slack reaches ~1e3 when infeasible, float32 keeps ~1e-4 of it in u)."""
    rng = np.random.default_rng(7)
    instances = [random_instance(rng, feasible=k % 3 != 0) for k in range(48)]
    u_jax = np.asarray(batched_filter(*stack(instances)).u, float)  # the compiled batch of the tests above
    u_np = np_cbf.filter_velocity(*(np.stack(x) for x in zip(*instances)), U_MAX)
    solved = 0
    for k, (u_nom, A, b, mask) in enumerate(instances):
        ref = osqp_qp(u_nom, A, b, mask, U_MAX)
        if ref is None:
            continue
        solved += 1
        u_osqp, s_osqp = ref
        u_ref, s_ref = reference_qp(u_nom, A, b, mask, U_MAX)
        np.testing.assert_allclose(u_ref, u_osqp, atol=1e-6)
        np.testing.assert_allclose(s_ref, s_osqp, atol=1e-6)
        np.testing.assert_allclose(u_np.u[k], u_osqp, atol=1e-6)
        np.testing.assert_allclose(u_jax[k], u_osqp, atol=1e-4)
    assert solved >= 40  # OSQP solved and polished (nearly) every instance: the check did check


def _best_margin(A, b, mask, u_max) -> float:
    """max over the box of the smallest margin min_j (â_j · u − b̂_j) (an LP): < 0 exactly when no command in the
    box satisfies every row, and then its negative is the least worst violation any command can have."""
    from scipy.optimize import linprog

    nrm = np.linalg.norm(A, axis=1)
    keep = mask & (nrm > 1e-9)
    A_hat, b_hat = A[keep] / nrm[keep, None], b[keep] / nrm[keep]
    # variables (u, t): maximise t s.t. t - â_j · u <= -b̂_j
    res = linprog(c=[0, 0, 0, -1], A_ub=np.hstack([-A_hat, np.ones((len(b_hat), 1))]), b_ub=-b_hat,
                  bounds=[(-u_max, u_max)] * 3 + [(None, None)], method="highs")
    assert res.status == 0
    return -res.fun


def test_the_backup_engages_exactly_when_no_command_satisfies_every_row():
    """The filter's defined behaviour when its rows conflict: its shared slack is then the least worst violation any
    command in the box can have (every row gives the same amount, none is sacrificed), and 0 otherwise; the
    evaluation counts a drone-step as a backup step when the slack exceeds INFEASIBLE_SLACK. Checked against an LP
    (scipy's HiGHS) that finds the best margin, for both solvers."""
    from aswarm.analysis.evaluate import INFEASIBLE_SLACK

    rng = np.random.default_rng(11)
    P = 96
    A = rng.normal(size=(P, M_ROWS, 3))
    A /= np.linalg.norm(A, axis=-1, keepdims=True)
    b = np.einsum("pmk,pk->pm", A, rng.uniform(-1.5, 1.5, (P, 3))) + rng.normal(-0.2, 0.3, (P, M_ROWS))
    mask = rng.uniform(size=(P, M_ROWS)) < 0.85
    u_nom = rng.uniform(-3.0, 3.0, (P, 3))
    margin = np.array([_best_margin(A[k], b[k], mask[k], U_MAX) for k in range(P)])
    clear = np.abs(margin) > 1e-3  # leave out the knife edge, where float32 rounding decides
    infeasible = margin < 0
    assert 20 <= np.sum(infeasible & clear) and 20 <= np.sum(~infeasible & clear)  # both sides are tested
    s_jax = np.asarray(batched_filter(*stack(list(zip(u_nom, A, b, mask)))).slack, float)
    s_np = np_cbf.filter_velocity(u_nom, A, b, mask, U_MAX).slack
    # The quadratic penalty leaves s = Σλ/ρ ~ 1e-5 where rows bind but all hold: well under the threshold.
    for s, tol in ((s_np, 5e-5), (s_jax, 2e-4)):
        np.testing.assert_array_equal((s > INFEASIBLE_SLACK)[clear], infeasible[clear])
        np.testing.assert_allclose(s[clear], np.maximum(-margin, 0.0)[clear], atol=tol)


def test_weighted_slack_lets_the_static_rows_give_way_less_hand_derived():
    """u_z ≥ 0 (a floor at the drone, weight 0.1) against −u_z ≥ 1 (a hazard pushing down, weight 1): no command
    satisfies both. Spread evenly, each gives 0.5 m/s; weighted, u_z + 0.1 s ≥ 0 and −u_z + s ≥ 1 give
    s = 1/1.1 and u_z = −s/10: the floor gives 0.09 m/s, the hazard 0.91."""
    A = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    b, mask, w = np.array([0.0, 1.0]), np.ones(2, bool), np.array([0.1, 1.0])
    s = 1 / 1.1
    even = np_cbf.filter_velocity(np.zeros(3), A, b, mask, U_MAX)
    np.testing.assert_allclose(even.u, [0.0, 0.0, -0.5], atol=1e-5)
    weighted = np_cbf.filter_velocity(np.zeros(3), A, b, mask, U_MAX, slack_weight=w)
    np.testing.assert_allclose(weighted.u, [0.0, 0.0, -s / 10], atol=1e-5)
    np.testing.assert_allclose(weighted.slack, s, atol=1e-5)
    res = single_filter(jnp.zeros(3), jnp.asarray(A), jnp.asarray(b), jnp.asarray(mask), U_MAX,
                        slack_weight=jnp.asarray(w))
    np.testing.assert_allclose(res.u, [0.0, 0.0, -s / 10], atol=1e-4)
    # Random problems: both solvers find the same command with the same weights.
    rng = np.random.default_rng(5)
    instances = [random_instance(rng, feasible=k % 2 == 0) for k in range(32)]
    w = rng.uniform(0.05, 1.0, M_ROWS)
    u_np = np_cbf.filter_velocity(*(np.stack(x) for x in zip(*instances)), U_MAX, slack_weight=w).u
    u_jax = jax.jit(jax.vmap(lambda u, A, b, m: filter_velocity(u, A, b, m, U_MAX, slack_weight=w).u))(
        *stack(instances))
    np.testing.assert_allclose(np.asarray(u_jax), u_np, atol=2e-4)


def test_proximity_slack_lets_the_far_row_give_way_first_hand_derived():
    """A cylinder 1.2 m off asks u_x ≥ 1 (it moves at the drone), a neighbour 0.3 m off on the other side −u_x ≥ 0:
    no command satisfies both. Equal weights give 0.5 m/s each, into the neighbour too. With proximity_slack 1 m the
    neighbour's row weighs clip(0.3 / 1, 0.1, 1) = 0.3 and the cylinder's 1: u_x + s ≥ 1 and −u_x + 0.3 s ≥ 0 give
    s = 1/1.3 and u_x = 0.3 s = 0.2308: the near row gives 0.23 m/s, the far one 0.77. Its weight is floored at
    proximity_slack_min, and absent rows (any h) keep weight 1; JAX and numpy agree."""
    layout = ObsLayout(num_cylinders=1, num_neighbours=1)
    m = 2 + barriers.FIXED_ROWS
    A = np.zeros((m, 3))
    A[0], A[1] = [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]
    b, mask, h = np.zeros(m), np.zeros(m, bool), np.full(m, np.nan)
    b[0], mask[:2], h[:2] = 1.0, True, [1.2, 0.3]
    rows = Rows(A, b, mask, h)
    assert barriers.row_slack_weights(layout, rows, SafetyFilterConfig(static_slack=1.0)) is None
    safety = SafetyFilterConfig(static_slack=1.0, proximity_slack=1.0)
    w = barriers.row_slack_weights(layout, rows, safety)
    np.testing.assert_allclose(w, [1.0, 0.3] + [1.0] * barriers.FIXED_ROWS)
    even = np_cbf.filter_velocity(np.zeros(3), A, b, mask, U_MAX)
    np.testing.assert_allclose(even.u, [0.5, 0.0, 0.0], atol=1e-5)
    s = 1 / 1.3
    near = np_cbf.filter_velocity(np.zeros(3), A, b, mask, U_MAX, slack_weight=w)
    np.testing.assert_allclose(near.u, [0.3 * s, 0.0, 0.0], atol=1e-5)
    np.testing.assert_allclose(near.slack, s, atol=1e-5)
    jw = barriers.row_slack_weights(layout, Rows(*(jnp.asarray(x) for x in rows)), safety)
    res = single_filter(jnp.zeros(3), jnp.asarray(A), jnp.asarray(b), jnp.asarray(mask), U_MAX, slack_weight=jw)
    np.testing.assert_allclose(res.u, [0.3 * s, 0.0, 0.0], atol=1e-4)
    # With the static weights: the floor's row (index 2) at 0.5 m weighs 0.1 · 0.5; a row inside its margin the floor.
    rows = Rows(A, b, np.ones(m, bool), np.concatenate([[-0.2, 0.3, 0.5], np.full(m - 3, 2.0)]))
    w = barriers.row_slack_weights(layout, rows, SafetyFilterConfig(proximity_slack=1.0, proximity_slack_min=0.2))
    np.testing.assert_allclose(w[:4], [0.2, 0.3, 0.05, 0.1])
    # A batch of drones (the flight runtime's [n, m] weights) solves as each drone alone.
    batch = np_cbf.filter_velocity(np.zeros((2, 3)), np.stack([A, A]), np.stack([b, b]), np.stack([mask, mask]),
                                   U_MAX, slack_weight=np.stack([np.ones(m), w]))
    np.testing.assert_allclose(batch.u[0], even.u, atol=1e-9)
    alone = np_cbf.filter_velocity(np.zeros(3), A, b, mask, U_MAX, slack_weight=w)
    np.testing.assert_allclose(batch.u[1], alone.u, atol=1e-9)


# ---------------------------------------------------------------- rows from observations
def _random_obs(rng, layout, lead):
    """Raw observations [lead..., D] with valid presence flags, unit (or absent) gate normals and positive
    altitude and wall clearances: what the barrier rows read."""
    obs = rng.normal(size=lead + (layout.size,))
    obs[..., list(layout.presence_columns)] = rng.uniform(size=lead + (len(layout.presence_columns),)) < 0.8
    f = layout.own_slices
    for name in ("target_normal", "prev_gate_normal"):
        yaw = rng.uniform(-np.pi, np.pi, lead)
        n = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], -1)
        obs[..., f[name]] = np.where(rng.uniform(size=lead + (1,)) < 0.8, n, 0.0)
    obs[..., f["altitude"]] = rng.uniform(0.2, 2.5, lead + (1,))
    obs[..., f["wall_clearance"]] = rng.uniform(0.0, 4.0, lead + (5,))
    return obs


def _obs_scene(seed):
    """(layout, rng, random observations [2, 3, D], gains [2, 3], obs_rows' settings) of a small scene."""
    from aswarm.core.layout import ObsLayout

    layout = ObsLayout(num_cylinders=3, num_neighbours=2)
    rng = np.random.default_rng(seed)
    obs = _random_obs(rng, layout, (2, 3))
    return layout, rng, obs, rng.uniform(0.3, 2.0, (2, 3)), dict(drone_radius=0.06, margin=0.1,
                                                                 gate_half_opening=0.3, gate_bar=0.05)


def test_obs_rows_are_one_computation_for_numpy_and_jax_and_both_filters_agree():
    layout, rng, obs, gain, kw = _obs_scene(8)
    rows_np = barriers.obs_rows(layout, obs, gain, **kw)
    rows_jax = jax.jit(lambda o, g: barriers.obs_rows(layout, o, g, **kw))(jnp.asarray(obs, jnp.float32),
                                                                            jnp.asarray(gain, jnp.float32))
    m = 3 + 2 + barriers.FIXED_ROWS
    chex.assert_shape([rows_np.A, rows_np.b, rows_np.mask, rows_np.h], [(2, 3, m, 3), (2, 3, m), (2, 3, m), (2, 3, m)])
    for a, b in zip(rows_np, rows_jax):
        np.testing.assert_allclose(np.asarray(b, float), a, atol=2e-5)
    # Layout: [cylinders | neighbours | floor | walls | gate | previous gate]; presence from the observation.
    assert barriers.row_groups(layout) == (("cylinders", 3), ("neighbours", 2), ("floor", 1), ("walls", 5),
                                           ("gate", 5), ("prev_gate", 5))
    np.testing.assert_array_equal(rows_np.mask[..., :5], obs[..., list(layout.presence_columns)] > 0.5)
    f = layout.own_slices
    np.testing.assert_allclose(rows_np.h[..., 5], obs[..., f["altitude"]][..., 0] - 0.16)
    np.testing.assert_allclose(rows_np.h[..., 6:11], obs[..., f["wall_clearance"]] - 0.16)
    np.testing.assert_allclose(rows_np.A[..., 6:11, :], np.broadcast_to(barriers.WALL_NORMALS, (2, 3, 5, 3)))
    for k, name in ((11, "target_normal"), (16, "prev_gate_normal")):
        has_gate = np.sum(obs[..., f[name]] ** 2, -1) > 0.25
        np.testing.assert_array_equal(rows_np.mask[..., k:k + 5], np.repeat(has_gate[..., None], 5, -1))
    assert not barriers.obs_rows(layout, obs, gain, **{**kw, "gate_bar": 0.0}).mask[..., 11:].any()
    # Both filters from the same observations and settings.
    safety = SafetyFilterConfig(margin=0.1)
    cmd = rng.uniform(-2.0, 2.0, (2, 3, 3))
    u_np = np_cbf.filter_from_obs(layout, obs, cmd, gain, U_MAX, 0.06, safety, 0.3, 0.05).u
    with jax.enable_x64(True):
        from aswarm.agents.cbf_filter import filter_from_obs

        u_jax = jax.jit(lambda o, c, g: filter_from_obs(layout, o, c, g, U_MAX, 0.06, safety, 0.3, 0.05).u)(
            jnp.asarray(obs), jnp.asarray(cmd), jnp.asarray(gain))
    np.testing.assert_allclose(np.asarray(u_jax), u_np, atol=1e-9)
    # With the cylinders' acceleration bounds (per swarm [2, M]), a look-ahead and weighted slack: the same again
    # (and the bounds change the commands: they are used).
    moving = dataclasses.replace(safety, lookahead_xy=0.3, lookahead_z=0.2, hazard_accel=True, static_slack=0.1)
    accel = rng.uniform(0.0, 3.0, (2, layout.num_cylinders))
    res_np = np_cbf.filter_from_obs(layout, obs, cmd, gain, U_MAX, 0.06, moving, 0.3, 0.05, accel)
    plain = np_cbf.filter_from_obs(layout, obs, cmd, gain, U_MAX, 0.06, moving, 0.3, 0.05)
    assert np.abs(res_np.u - plain.u).max() > 1e-3
    with jax.enable_x64(True):
        u_jax = jax.jit(lambda o, c, g, a: filter_from_obs(layout, o, c, g, U_MAX, 0.06, moving, 0.3, 0.05, a).u)(
            jnp.asarray(obs), jnp.asarray(cmd), jnp.asarray(gain), jnp.asarray(accel))
    np.testing.assert_allclose(np.asarray(u_jax), res_np.u, atol=1e-9)
    # With a gain cap on the moving cylinders' rows alone: the same in both, and it changes the commands.
    capped = dataclasses.replace(moving, moving_gain_max=0.3)
    res_cap = np_cbf.filter_from_obs(layout, obs, cmd, gain, U_MAX, 0.06, capped, 0.3, 0.05, accel)
    assert np.abs(res_cap.u - res_np.u).max() > 1e-3
    with jax.enable_x64(True):
        u_jax = jax.jit(lambda o, c, g, a: filter_from_obs(layout, o, c, g, U_MAX, 0.06, capped, 0.3, 0.05, a).u)(
            jnp.asarray(obs), jnp.asarray(cmd), jnp.asarray(gain), jnp.asarray(accel))
    np.testing.assert_allclose(np.asarray(u_jax), res_cap.u, atol=1e-9)
    # With braking: the commands flown now, the reachable box and the braking rows; again the same in both, every
    # command inside the box, and changed by it.
    braking = dataclasses.replace(moving, braking=True)
    applied, rate = rng.uniform(-1.5, 1.5, (2, 3, 3)), (3.0, 0.04)
    res_np = np_cbf.filter_from_obs(layout, obs, cmd, gain, U_MAX, 0.06, braking, 0.3, 0.05, accel, applied, rate)
    assert np.all(np.abs(res_np.u - applied) <= 0.12 + 1e-9)
    assert np.abs(res_np.u - np.clip(cmd, applied - 0.12, applied + 0.12)).max() > 1e-3
    with jax.enable_x64(True):
        u_jax = jax.jit(lambda o, c, g, a, now: filter_from_obs(layout, o, c, g, U_MAX, 0.06, braking, 0.3, 0.05, a,
                                                                now, rate).u)(
            jnp.asarray(obs), jnp.asarray(cmd), jnp.asarray(gain), jnp.asarray(accel), jnp.asarray(applied))
    np.testing.assert_allclose(np.asarray(u_jax), res_np.u, atol=1e-9)
    # The neighbours' braking rows on top, the same in both; they change the commands where no cylinder's row (whose
    # slack the neighbours' share) decides them, so the scene's cylinders are taken away.
    own, cyl, nbr = layout.split(obs)
    cyl = cyl.copy()
    cyl[..., CYL.column("present")] = 0.0
    close = np.concatenate([own, cyl.reshape(2, 3, -1), nbr.reshape(2, 3, -1)], -1)
    both = dataclasses.replace(braking, neighbour_braking=True)
    res_nb = np_cbf.filter_from_obs(layout, close, cmd, gain, U_MAX, 0.06, both, 0.3, 0.05, accel, applied, rate)
    res_cyl = np_cbf.filter_from_obs(layout, close, cmd, gain, U_MAX, 0.06, braking, 0.3, 0.05, accel, applied, rate)
    assert np.abs(res_nb.u - res_cyl.u).max() > 1e-3
    with jax.enable_x64(True):
        u_jax = jax.jit(lambda o, c, g, a, now: filter_from_obs(layout, o, c, g, U_MAX, 0.06, both, 0.3, 0.05, a,
                                                                now, rate).u)(
            jnp.asarray(close), jnp.asarray(cmd), jnp.asarray(gain), jnp.asarray(accel), jnp.asarray(applied))
    np.testing.assert_allclose(np.asarray(u_jax), res_nb.u, atol=1e-9)
    # The neighbours split by closing speed in place of halves, and their reference velocity scaled to rest: each
    # changes the commands, and both together are the same in JAX and numpy.
    split = dataclasses.replace(safety, closing_split=0.3)
    rest = dataclasses.replace(split, neighbour_reference=0.0)
    res_half, res_split, res_rest = (np_cbf.filter_from_obs(layout, close, cmd, gain, U_MAX, 0.06, sf, 0.3, 0.05)
                                     for sf in (safety, split, rest))
    assert np.abs(res_split.u - res_half.u).max() > 1e-3 and np.abs(res_rest.u - res_split.u).max() > 1e-3
    with jax.enable_x64(True):
        u_jax = jax.jit(lambda o, c, g: filter_from_obs(layout, o, c, g, U_MAX, 0.06, rest, 0.3, 0.05).u)(
            jnp.asarray(close), jnp.asarray(cmd), jnp.asarray(gain))
    np.testing.assert_allclose(np.asarray(u_jax), res_rest.u, atol=1e-9)
    # Where the filter sees only some of the swarm (2 neighbours of 5 others: the same drones as two swarms of 6), a
    # pair may be held from one side only, so the split stays in halves.
    assert barriers.sees_whole_swarm(layout, close)
    six = [np.concatenate([x, x], 1) for x in (close, cmd, gain)]
    assert not barriers.sees_whole_swarm(layout, six[0])
    np.testing.assert_array_equal(np_cbf.filter_from_obs(layout, *six, U_MAX, 0.06, split, 0.3, 0.05).u,
                                  np_cbf.filter_from_obs(layout, *six, U_MAX, 0.06, safety, 0.3, 0.05).u)


def test_gate_rows_cap_a_centred_drone_hand_derived():
    """A drone centred 0.5 m before an opening (passage +x): every bar's nearest point is c = half_opening + bar/2
    off its axis, sideways or up or down (the post starts at the bottom edge's middle), so h = √(c² + s²) − k with
    ∇h = (−s, ±c)/√(c² + s²), and the forward speed the rows allow is γ h √(c² + s²)/s: 0.49 m/s at γ = 1 (README,
    "Relaxing the gate rows")."""
    half, bar, r, margin, gamma, s = 0.3, 0.05, 0.06, 0.1, 1.0, 0.5
    c, k = half + bar / 2, bar / 2 + r + margin
    rows = barriers.gate_rows(np.array([-s, 0.0, 1.0]), np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]),
                              np.array(True), gamma, half_opening=half, bar=bar, drone_radius=r, margin=margin)
    d = math.hypot(c, s)
    np.testing.assert_allclose(rows.h, d - k)
    np.testing.assert_allclose(rows.A[:, 0], -s / d)
    np.testing.assert_allclose(np.abs(rows.A[:, 1:]).sum(-1), c / d)  # sideways or vertical, away from the bar
    res = single_filter(jnp.array([3.0, 0.0, 0.0]), jnp.asarray(rows.A, jnp.float32), jnp.asarray(rows.b, jnp.float32),
                        jnp.asarray(rows.mask), 5.0)
    np.testing.assert_allclose(res.u, [0.4906, 0.0, 0.0], atol=2e-4)
    np.testing.assert_allclose(0.4906, gamma * (d - k) * d / s, atol=1e-4)


def test_braking_row_hand_derived():
    """A still cylinder (look-ahead point at the origin), the drone's look-ahead point 0.5 m from its surface
    (h = 0.5) flying straight at it at s m/s, command limit 3 m/s², dt 0.04 s: B = √(2·3·0.5) − s = √3 − s and the
    row is n · u ≥ −s + dt (√(3/(2·0.5)) s − γ B). At s = √3 (B = 0) it asks for exactly 3 m/s² of braking
    (0.12 m/s this step); slower, it lets the drone close in faster than it flies now."""
    R, r, margin, gamma, dt = 0.2, 0.05, 0.05, 1.0, 0.04
    d = 0.5 + R + r + margin
    for s in (np.sqrt(3.0), 1.0):
        con = barriers.cylinder_braking_rows(jnp.array([d, 0.0, 1.0]), jnp.array([-s, 0.0, 0.0]), jnp.zeros((1, 2)),
                                             jnp.array([R]), jnp.zeros((1, 2)), jnp.ones(1, bool), gamma,
                                             accel=jnp.zeros(1), lag=0.3, decel=3.0, dt=dt, drone_radius=r,
                                             margin=margin)
        B = np.sqrt(3.0) - s
        np.testing.assert_allclose(con.h, [0.5], atol=1e-6)
        np.testing.assert_allclose(con.A, [[1.0, 0.0, 0.0]], atol=1e-6)
        np.testing.assert_allclose(con.b, [-s + dt * (np.sqrt(3.0) * s - gamma * B)], rtol=1e-5)
    np.testing.assert_allclose(float(con.b[0]) + 1.0, dt * (np.sqrt(3.0) - gamma * (np.sqrt(3.0) - 1.0)), rtol=1e-5)
    # Flying past it instead (w ⊥ n, |w| = 1): the turning term |w_⊥|²/d = 1/d lets the drone keep going.
    past = barriers.cylinder_braking_rows(jnp.array([d, 0.0, 1.0]), jnp.array([0.0, 1.0, 0.0]), jnp.zeros((1, 2)),
                                          jnp.array([R]), jnp.zeros((1, 2)), jnp.ones(1, bool), gamma,
                                          accel=jnp.zeros(1), lag=0.3, decel=3.0, dt=dt, drone_radius=r, margin=margin)
    np.testing.assert_allclose(past.b, [dt * (-1.0 / d - gamma * np.sqrt(3.0))], rtol=1e-5)


def test_a_braking_drone_stops_short_of_a_cylinder_in_the_command_limits_double_integrator():
    """The model the braking rows assume: the look-ahead point moves at the command, which moves at most 3 m/s²
    (0.12 m/s per 40 ms step, per axis). At 2 m/s, 2 m from a still cylinder's surface, the nominal command keeps
    flying at it, and the gain is 5/s: the velocity rows let the drone close in at up to γ h, which from h = 0.4 m
    on asks for more braking than 3 m/s² (γ · 2 m/s = 10 m/s²), so on the reachable box it hits the cylinder; the
    braking rows start braking in time and the drone stops at the margin (0.05 m, to 3 mm of discretisation)."""
    R, r, dt, step = 0.2, 0.05, 0.04, 0.12
    layout = ObsLayout(num_cylinders=1, num_neighbours=0)
    own, cyl0 = layout.own_slices, layout.own_dim
    safety = SafetyFilterConfig(margin=0.05, hazard_accel=True, braking=True)

    def fly(cfg):
        q, now, lowest = np.array([0.0, 0.0]), np.array([2.0, 0.0, 0.0]), np.inf
        centre = np.array([2.0 + R + r, 0.0])
        for _ in range(100):
            obs = np.zeros((1, layout.size))
            obs[0, own["altitude"]] = 1.0
            obs[0, own["vel"]] = now  # no look-ahead in this config: q is the point itself
            obs[0, own["wall_clearance"]] = 50.0
            rel = centre - q
            obs[0, cyl0 + CYL.slice("rel_xy").start:cyl0 + CYL.slice("rel_xy").stop] = rel
            obs[0, cyl0 + CYL.column("clearance")] = np.linalg.norm(rel) - R - r
            obs[0, cyl0 + CYL.column("present")] = 1.0
            res = np_cbf.filter_from_obs(layout, obs, np.array([[2.0, 0.0, 0.0]]), np.array([5.0]), 2.0, r, cfg,
                                         cyl_accel=np.zeros(1), applied=now[None], command_rate=(3.0, dt))
            now = np.clip(res.u[0], now - step, now + step)
            q = q + dt * now[:2]
            lowest = min(lowest, np.linalg.norm(centre - q) - R - r)
        return lowest, now

    lowest, now = fly(safety)
    assert lowest > 0.045 and abs(now[0]) < 0.01
    lowest, _ = fly(dataclasses.replace(safety, braking=False))
    assert lowest < 0.0


def test_gate_braking_row_hand_derived():
    """A gate at (0, 0, 1.5), passage +x, opening ±0.3 m, bars 0.05 m: its post runs from the bottom bar's middle
    (z = 1.5 − 0.325) to the floor. A drone 0.5 m before the post (at z = 0.8) flying at it at 1.5 m/s: n = −x,
    h = 0.5 − (0.025 + 0.06 + 0.1) = 0.315, B = √(2·3·h) − 1.5 and the row is −u_x ≥ −1.5 − dt (√(3/2h) (−1.5) + γ B).
    Moving along the post changes nothing; sideways the turning term 0.5²/0.5 lowers b by dt · 0.5."""
    gamma, dt, h = 1.0, 0.04, 0.315
    kw = dict(half_opening=0.3, bar=0.05, drone_radius=0.06, margin=0.1)
    centre, normal = np.array([0.0, 0.0, 1.5]), np.array([1.0, 0.0, 0.0])
    pos = np.array([-0.5, 0.0, 0.8])
    B = np.sqrt(2 * 3.0 * h) - 1.5
    want = -1.5 - dt * (np.sqrt(3.0 / (2 * h)) * -1.5 + gamma * B)
    for cmd, shift in (([1.5, 0.0, 0.0], 0.0), ([1.5, 0.0, 0.5], 0.0), ([1.5, 0.5, 0.0], dt * 0.5**2 / 0.5)):
        for xp in (np, jnp):
            rows = barriers.gate_rows(xp.asarray(pos), xp.asarray(centre), xp.asarray(normal), xp.asarray(True), gamma,
                                      braking=(xp.asarray(cmd), 3.0, dt), **kw)
            post = 4  # the 4 edges, then the post
            np.testing.assert_allclose(np.asarray(rows.h)[post], h, atol=1e-6)
            np.testing.assert_allclose(np.asarray(rows.A)[post], [-1.0, 0.0, 0.0], atol=1e-6)
            np.testing.assert_allclose(np.asarray(rows.b)[post], want - shift, rtol=1e-5)
    assert want == pytest.approx(-1.3641, abs=1e-4)  # 3.4 m/s² of braking this step: B < 0 already
    plain = barriers.gate_rows(pos, centre, normal, np.asarray(True), gamma, **kw)
    np.testing.assert_allclose(plain.b[4], -gamma * h)


def test_a_gate_braking_drone_stops_short_of_a_bar_in_the_command_limits_double_integrator():
    """The cylinders' braking test for a gate frame: a drone at 1 m height flying +x at 2 m/s at a gate's vertical
    edge 2 m ahead (the gate's centre 0.325 m to its side: the edge's axis on the drone's line), nominal command
    2 m/s on, gain 5/s, the command limit 3 m/s² on the reachable box. The gate's velocity rows brake too late and
    it hits the bar; with the gate's braking rows it stops at the margin."""
    r, dt, step, c = 0.06, 0.04, 0.12, 0.3 + 0.05 / 2
    layout = ObsLayout(num_cylinders=0, num_neighbours=0)
    own = layout.own_slices
    safety = SafetyFilterConfig(margin=0.05, gate_braking=True)
    centre = np.array([2.0, -c, 1.0])

    def fly(cfg):
        q, now, lowest = np.array([0.0, 0.0, 1.0]), np.array([2.0, 0.0, 0.0]), np.inf
        for _ in range(100):
            obs = np.zeros((1, layout.size))
            obs[0, own["altitude"]] = q[2]
            obs[0, own["vel"]] = now
            obs[0, own["wall_clearance"]] = 50.0
            obs[0, own["target_rel"]] = q - centre
            obs[0, own["target_normal"]] = [1.0, 0.0, 0.0]
            res = np_cbf.filter_from_obs(layout, obs, np.array([[2.0, 0.0, 0.0]]), np.array([5.0]), 2.0, r, cfg,
                                         0.3, 0.05, applied=now[None], command_rate=(3.0, dt))
            now = np.clip(res.u[0], now - step, now + step)
            q = q + dt * now
            lowest = min(lowest, float(geometry.gate_clearance(q[None], centre[None], np.array([[1.0, 0.0, 0.0]]), 0.3,
                                                                0.05, r)[0, 0]))
        return lowest, now

    from aswarm.core import geometry

    lowest, now = fly(safety)
    assert lowest > 0.045 and np.abs(now).max() < 0.01
    lowest, _ = fly(dataclasses.replace(safety, gate_braking=False, braking=True))  # the box, the gate's velocity rows
    assert lowest < 0.0


def test_wall_braking_rows_hand_derived():
    """A drone 2.2 m from the arena's x-high wall (r_d + margin = 0.2: h = 2) flying at it at 2 m/s, gain 2 /s:
    n = −x, B = √(2·3·2) − 2 and the braking row is −u_x ≥ −2 − dt (√(3/4) (−2) + γ B) = −2.048, above the velocity
    row's −γ h = −4, so it binds. 0.8 m off (h = 0.6) at 1.5 m/s the braking row's −1.5 − dt (√(3/1.2) (−1.5) +
    γ (√3.6 − 1.5)) = −1.437 lies below the velocity row's −1.2, which binds there. Moving along the wall changes
    nothing (a plane's normal does not turn); the y-high wall, 4.8 m off, sees the command's y part alone."""
    gamma, dt = 2.0, 0.04
    for x_gap, speed, want in ((2.2, 2.0, -2.0 - dt * (np.sqrt(0.75) * -2.0 + gamma * (np.sqrt(12.0) - 2.0))),
                               (0.8, 1.5, -gamma * 0.6)):
        clearance = np.array([15.0, x_gap, 5.0, 5.0, 2.0])  # x low, x high, y low, y high, ceiling
        for cmd in ([speed, 0.0, 0.0], [speed, 0.7, -0.3]):
            for xp in (np, jnp):
                rows = barriers.wall_rows(xp.asarray(clearance), gamma, drone_radius=0.05, margin=0.15,
                                          braking=(xp.asarray(cmd), 3.0, dt))
                np.testing.assert_allclose(np.asarray(rows.h), clearance - 0.2, atol=1e-6)
                np.testing.assert_allclose(np.asarray(rows.A), barriers.WALL_NORMALS, atol=1e-6)
                np.testing.assert_allclose(np.asarray(rows.b)[1], want, rtol=1e-5)
                y = 4.8  # h of the y-high wall, whose normal (−y) sees the command's y part
                brake_y = -cmd[1] - dt * (np.sqrt(3.0 / (2 * y)) * -cmd[1] + gamma * (np.sqrt(6 * y) - cmd[1]))
                b_y = max(-gamma * y, brake_y)
                np.testing.assert_allclose(np.asarray(rows.b)[3], b_y, rtol=1e-5)
    assert -2.0 - dt * (np.sqrt(0.75) * -2.0 + gamma * (np.sqrt(12.0) - 2.0)) == pytest.approx(-2.0478, abs=1e-4)
    near = -1.5 - dt * (np.sqrt(3.0 / 1.2) * -1.5 + gamma * (np.sqrt(3.6) - 1.5))
    assert near == pytest.approx(-1.4369, abs=1e-4) and near < -gamma * 0.6
    plain = barriers.wall_rows(clearance, gamma, drone_radius=0.05, margin=0.15)
    np.testing.assert_allclose(plain.b, -gamma * (clearance - 0.2))


def test_a_wall_braking_drone_stops_short_of_the_wall_in_the_command_limits_double_integrator():
    """A drone flying +x at 2 m/s, 1.5 m from the arena's x-high wall, nominal command 2 m/s on, gain 5/s, the
    command limit 3 m/s² (0.12 m/s per 40 ms step) after the filter: the wall's velocity row lets it close at 5 h m/s
    and brakes too late, so it leaves the arena; with the walls' braking rows it stops before the margin."""
    r, dt, step, wall = 0.06, 0.04, 0.12, 1.5
    layout = ObsLayout(num_cylinders=0, num_neighbours=0)
    own = layout.own_slices
    safety = SafetyFilterConfig(margin=0.05, wall_braking=True, reachable_box=False)

    def fly(cfg):
        x, now, lowest = 0.0, np.array([2.0, 0.0, 0.0]), np.inf
        for _ in range(100):
            obs = np.zeros((1, layout.size))
            obs[0, own["altitude"]] = 1.0
            obs[0, own["vel"]] = now
            obs[0, own["wall_clearance"]] = [50.0, wall - x, 50.0, 50.0, 2.0]
            res = np_cbf.filter_from_obs(layout, obs, np.array([[2.0, 0.0, 0.0]]), np.array([5.0]), 2.0, r, cfg,
                                         0.3, 0.05, applied=now[None], command_rate=(3.0, dt))
            now = np.clip(res.u[0], now - step, now + step)
            x = x + dt * now[0]
            lowest = min(lowest, wall - x)
        return lowest, now

    lowest, now = fly(safety)
    assert lowest > r + 0.05 - 0.01 and np.abs(now).max() < 0.01
    lowest, _ = fly(dataclasses.replace(safety, wall_braking=False))
    assert lowest < 0.0


def test_neighbour_braking_row_hand_derived():
    """Two drones' look-ahead points on the x axis, this one at the origin and the neighbour 0.5 m beyond the pair's
    distance (h = 0.5) flying at it at s m/s while this one hovers, command limit 3 m/s² each, dt 0.04 s, share 1/2:
    the pair brakes at 6 m/s², B = √(2·6·0.5) − s = √6 − s, and the row is n · u ≥ −dt/2 (√(6/(2·0.5)) (−s) + γ B)
    with n = −x. At s = √6 (B = 0) it asks this drone for exactly 3 m/s² (0.12 m/s this step) away from the
    neighbour; at share 1 (a neighbour that does not brake) it asks for 3 m/s² at B = √(2·3·0.5) − s = 0."""
    r, margin, gamma, dt = 0.06, 0.13, 1.0, 0.04
    d = 0.5 + 2 * r + margin
    for share, decel_pair in ((0.5, 6.0), (1.0, 3.0)):
        s = np.sqrt(decel_pair)  # the closing speed at which the pair's braking distance is h = 0.5
        for speed in (s, 1.0):
            row = barriers.neighbour_braking_rows(np.zeros(3), np.zeros(3), np.array([[d, 0.0, 0.0]]),
                                                  np.array([[-speed, 0.0, 0.0]]), np.ones(1, bool), gamma, decel=3.0,
                                                  dt=dt, drone_radius=r, margin=margin, share=share)
            B = s - speed
            np.testing.assert_allclose(row.h, [0.5])
            np.testing.assert_allclose(row.A, [[-1.0, 0.0, 0.0]])
            np.testing.assert_allclose(row.b, [-dt * share * (-s * speed + gamma * B)], rtol=1e-12)
        if share == 0.5:
            np.testing.assert_allclose(-dt * share * (-s * s), 0.12)  # B = 0: 3 m/s² of braking, away from it
    # Passing side by side (w ⊥ n, |w| = 1): the turning term lets the two keep going.
    past = barriers.neighbour_braking_rows(np.zeros(3), np.array([0.0, 1.0, 0.0]), np.array([[d, 0.0, 0.0]]),
                                           np.zeros((1, 3)), np.ones(1, bool), gamma, decel=3.0, dt=dt,
                                           drone_radius=r, margin=margin)
    np.testing.assert_allclose(past.b, [-dt * 0.5 * (1.0 / d + gamma * np.sqrt(6.0))], rtol=1e-12)


def test_neighbour_braking_rows_split_the_pair_condition():
    """Two drones flying steady commands (each one's velocity is its command) see the same pair: their two rows add
    up to the pair's braking condition n · (u_i − u_k) ≥ n · (c_i − c_k) − dt (|w_⊥|²/d + √(a_pair/2h) n · w + γ B),
    w = c_i − c_k, a_pair = 2 decel, for any positions and commands."""
    rng = np.random.default_rng(3)
    r, margin, gamma, dt, decel = 0.06, 0.13, 1.3, 0.04, 3.0
    for _ in range(20):
        p_i, p_k = rng.uniform(-1.0, 1.0, (2, 3))
        c_i, c_k = rng.uniform(-2.0, 2.0, (2, 3))
        kw = dict(decel=decel, dt=dt, drone_radius=r, margin=margin)
        ri = barriers.neighbour_braking_rows(p_i, c_i, p_k[None], c_k[None], np.ones(1, bool), gamma, **kw)
        rk = barriers.neighbour_braking_rows(p_k, c_k, p_i[None], c_i[None], np.ones(1, bool), gamma, **kw)
        np.testing.assert_allclose(ri.A[0], -rk.A[0], atol=1e-12)
        d = np.linalg.norm(p_i - p_k)
        n, w, h = (p_i - p_k) / d, c_i - c_k, d - 2 * r - margin
        B = np.sqrt(4 * decel * max(h, 0.0)) + n @ w
        rate = (w @ w - (n @ w) ** 2) / d + np.sqrt(2 * decel / (2 * max(h, barriers.BRAKING_MIN_GAP))) * (n @ w)
        np.testing.assert_allclose(ri.b[0] + rk.b[0], n @ w - dt * (rate + gamma * B), rtol=1e-9, atol=1e-12)


def test_neighbour_braking_rows_come_after_every_other_row_with_their_own_gain():
    """obs_rows with the neighbours' braking: the layout of before (velocity rows for the neighbours too), then K
    braking rows, built from the observation with ``braking_gain`` (the drone's gain where it is 0)."""
    from aswarm.core.layout import OWN

    layout, rng, obs, gain, kw = _obs_scene(5)
    applied = rng.uniform(-1.5, 1.5, (2, 3, 3))
    plain = barriers.obs_rows(layout, obs, gain, **kw)
    m, K = plain.b.shape[-1], layout.num_neighbours
    own, _, nbr = layout.split(obs)
    pos = np.concatenate([np.zeros((2, 3, 2)), own[..., OWN.slice("altitude")]], -1)
    for braking_gain, expected_gain in ((7.0, 7.0), (0.0, gain[..., None])):
        rows = barriers.obs_rows(layout, obs, gain, **kw, braking=(applied, 3.0, 0.04), brake=(False, True),
                                 braking_gain=braking_gain)
        assert rows.b.shape[-1] == m + K
        for a, b in zip(rows, plain):
            np.testing.assert_allclose(a[..., :m] if a.ndim == 3 else a[..., :m, :], b)
        extra = barriers.neighbour_braking_rows(pos, applied, NBR.get(nbr, "rel_pos") + pos[..., None, :],
                                                NBR.get(nbr, "rel_vel") + OWN.get(own, "vel")[..., None, :],
                                                NBR.present(nbr), expected_gain, decel=3.0, dt=0.04,
                                                drone_radius=kw["drone_radius"], margin=kw["margin"])
        np.testing.assert_allclose(rows.b[..., m:], extra.b, rtol=1e-12)
        np.testing.assert_array_equal(rows.mask[..., m:], extra.mask)
    weights = barriers.slack_weights(layout, 0.1, m + K)
    np.testing.assert_array_equal(weights[m:], np.ones(K))
    np.testing.assert_array_equal(weights[:m], barriers.slack_weights(layout, 0.1))


@pytest.mark.parametrize("settings", [{}, {"reachable_box": False}, {"neighbour_braking_gain": 10.0},
                                      {"neighbour_braking_gain": 10.0, "reachable_box": False}])
def test_two_braking_drones_head_on_stop_short_of_each_other_in_the_command_limits_double_integrator(settings):
    """The model the neighbours' braking rows assume: each look-ahead point moves at its command, which moves at most
    3 m/s² (0.12 m/s per 40 ms step, per axis), and each sees the other's velocity (its command, in this model).
    Head on at 2 m/s each, 2.5 m apart, both commanded on, gain 5/s: the velocity rows let the pair close in at up to
    γ h, more than the two can take back near the end (γ · 4 m/s = 20 m/s² against 6), and on the reachable box they
    collide; the braking rows start braking in time and stop both at the margin, with the box or without it (the
    limit then applies after the filter) and with the drones' gain or a higher one of their own."""
    r, dt, step, margin = 0.06, 0.04, 0.12, 0.13
    layout = ObsLayout(num_cylinders=0, num_neighbours=1)
    own, nbr0 = layout.own_slices, layout.own_dim
    safety = SafetyFilterConfig(margin=margin, neighbour_braking=True, **settings)

    def fly(cfg):
        p = np.array([[0.0, 0.0, 1.0], [2.5 + 2 * r, 0.0, 1.0]])
        now = np.array([[2.0, 0.0, 0.0], [-2.0, 0.0, 0.0]])
        lowest = np.inf
        for _ in range(100):
            obs = np.zeros((2, layout.size))
            obs[:, own["altitude"]] = 1.0
            obs[:, own["vel"]] = now  # no look-ahead in this config: q is the point itself
            obs[:, own["wall_clearance"]] = 50.0
            obs[:, nbr0 + NBR.slice("rel_pos").start:nbr0 + NBR.slice("rel_pos").stop] = p[::-1] - p
            obs[:, nbr0 + NBR.slice("rel_vel").start:nbr0 + NBR.slice("rel_vel").stop] = now[::-1] - now
            obs[:, nbr0 + NBR.column("present")] = 1.0
            res = np_cbf.filter_from_obs(layout, obs, now.copy(), np.array([5.0, 5.0]), 2.0, r, cfg,
                                         applied=now, command_rate=(3.0, dt))
            now = np.clip(res.u, now - step, now + step)
            p = p + dt * now
            lowest = min(lowest, np.linalg.norm(p[1] - p[0]) - 2 * r)
        return lowest, now

    lowest, now = fly(safety)
    assert lowest > margin - 0.005 and np.abs(now).max() < 0.01
    lowest, _ = fly(dataclasses.replace(safety, neighbour_braking=False, braking=True))  # velocity rows
    assert lowest < 0.0


def test_look_ahead_rows_are_the_plain_rows_at_the_look_ahead_points():
    from aswarm.core.layout import CYL, NBR, OWN

    layout, _, obs, gain, kw = _obs_scene(9)
    tau_xy, tau_z = 0.34, 0.22
    # The same scene with every position moved to its look-ahead point p + τ v, by hand: the drone to
    # (τ vx, τ vy, z + τ vz), each cylinder by τ v_c, each neighbour by τ v_k, the gates staying where they are.
    own, cyl, nbr = (x.copy() for x in layout.split(obs))
    tau = np.array([tau_xy, tau_xy, tau_z])
    v = OWN.get(own, "vel")
    shift = tau * v
    radius = np.linalg.norm(CYL.get(cyl, "rel_xy"), axis=-1) - CYL.get(cyl, "clearance")
    rel = CYL.get(cyl, "rel_xy") + tau_xy * (CYL.get(cyl, "vel_xy") - v[..., None, :2])
    cyl[..., CYL.slice("rel_xy")] = rel
    cyl[..., CYL.column("clearance")] = np.linalg.norm(rel, axis=-1) - radius
    nbr[..., NBR.slice("rel_pos")] += tau * NBR.get(nbr, "rel_vel")
    own[..., OWN.slice("altitude")] += shift[..., 2:]
    own[..., OWN.slice("wall_clearance")] += shift @ np.asarray(barriers.WALL_NORMALS).T
    for name in ("target_rel", "prev_gate_rel"):
        own[..., OWN.slice(name)] += shift
    moved = np.concatenate([own, cyl.reshape(2, 3, -1), nbr.reshape(2, 3, -1)], -1)
    ahead = barriers.obs_rows(layout, obs, gain, lookahead=(tau_xy, tau_z), **kw)
    by_hand = barriers.obs_rows(layout, moved, gain, **kw)
    # The gate rows: the plain rows put the drone at x = y = 0, the look-ahead ones at its look-ahead point;
    # the bars are the same, so the rows are (A, b, mask, h) alike.
    for a, b in zip(ahead, by_hand):
        np.testing.assert_allclose(a, b, atol=1e-12)
    assert not np.allclose(ahead.h, barriers.obs_rows(layout, obs, gain, **kw).h)
    rows_jax = jax.jit(lambda o, g: barriers.obs_rows(layout, o, g, lookahead=(tau_xy, tau_z), **kw))(
        jnp.asarray(obs, jnp.float32), jnp.asarray(gain, jnp.float32))
    for a, b in zip(ahead, rows_jax):
        np.testing.assert_allclose(np.asarray(b, float), a, atol=3e-5)


def _tilted(rng, lead, max_tilt=0.3):
    """Unit quaternions [lead..., 4] of random attitudes tilted up to ``max_tilt`` rad, any yaw."""
    axis = rng.normal(size=lead + (3,))
    axis[..., 2] = 0.0
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    half = rng.uniform(0.0, max_tilt, lead + (1,)) / 2
    tilt = np.concatenate([np.cos(half), np.sin(half) * axis], -1)
    yaw = rng.uniform(-np.pi, np.pi, lead) / 2
    w1, x1, y1, z1 = np.moveaxis(tilt, -1, 0)
    w2, z2 = np.cos(yaw), np.sin(yaw)  # yaw first (about z), then the tilt: q = tilt * yaw
    return np.stack([w1 * w2 - z1 * z2, x1 * w2 + y1 * z2, y1 * w2 - x1 * z2, w1 * z2 + z1 * w2], -1)


def test_second_order_rows_are_the_plain_rows_at_the_second_order_points():
    """``lookahead_accel`` c2: every point moves by τ v + c2 a, a from each drone's attitude (its own quat, each
    neighbour's columns), and the rows are the plain rows there; numpy, JAX and both filters agree on them."""
    from aswarm.core import geometry
    from aswarm.core.layout import CYL, NBR, OWN, ObsLayout

    layout = ObsLayout(num_cylinders=3, num_neighbours=2, neighbour_accel=True)
    rng = np.random.default_rng(21)
    obs = _random_obs(rng, layout, (2, 3))
    obs[..., layout.own_slices["quat"]] = _tilted(rng, (2, 3))
    own, cyl, nbr = (x.copy() for x in layout.split(obs))
    nbr_acc = rng.uniform(-3.0, 3.0, (2, 3, 2, 2))
    obs = np.concatenate([own, cyl.reshape(2, 3, -1), nbr.reshape(2, 3, -1), nbr_acc.reshape(2, 3, -1)], -1)
    gain = rng.uniform(0.3, 2.0, (2, 3))
    kw = dict(drone_radius=0.06, margin=0.1, gate_half_opening=0.3, gate_bar=0.05)
    tau_xy, tau_z, c2 = 0.207, 0.15, 0.039
    a_own = geometry.tilt_accel(OWN.get(own, "quat"))
    assert np.abs(a_own[..., :2]).max() > 0.5 and np.all(a_own[..., 2] == 0)
    a_nbr = np.concatenate([nbr_acc, np.zeros_like(nbr_acc[..., :1])], -1)
    v = OWN.get(own, "vel")
    shift = np.array([tau_xy, tau_xy, tau_z]) * v + c2 * a_own
    radius = np.linalg.norm(CYL.get(cyl, "rel_xy"), axis=-1) - CYL.get(cyl, "clearance")
    rel = CYL.get(cyl, "rel_xy") + tau_xy * CYL.get(cyl, "vel_xy") - shift[..., None, :2]
    cyl[..., CYL.slice("rel_xy")] = rel
    cyl[..., CYL.column("clearance")] = np.linalg.norm(rel, axis=-1) - radius
    nbr[..., NBR.slice("rel_pos")] += (np.array([tau_xy, tau_xy, tau_z]) * NBR.get(nbr, "rel_vel")
                                       + c2 * (a_nbr - a_own[..., None, :]))
    own[..., OWN.slice("altitude")] += shift[..., 2:]
    own[..., OWN.slice("wall_clearance")] += shift @ np.asarray(barriers.WALL_NORMALS).T
    for name in ("target_rel", "prev_gate_rel"):
        own[..., OWN.slice(name)] += shift
    plain = ObsLayout(num_cylinders=3, num_neighbours=2)
    moved = np.concatenate([own, cyl.reshape(2, 3, -1), nbr.reshape(2, 3, -1)], -1)
    ahead = barriers.obs_rows(layout, obs, gain, lookahead=(tau_xy, tau_z), lookahead_accel=c2, **kw)
    by_hand = barriers.obs_rows(plain, moved, gain, **kw)
    for a, b in zip(ahead, by_hand):
        np.testing.assert_allclose(a, b, atol=1e-12)
    first = barriers.obs_rows(layout, obs, gain, lookahead=(tau_xy, tau_z), **kw)
    assert np.abs(ahead.h - first.h).max() > 1e-2  # the accelerations are used
    rows_jax = jax.jit(lambda o, g: barriers.obs_rows(layout, o, g, lookahead=(tau_xy, tau_z), lookahead_accel=c2,
                                                      **kw))(jnp.asarray(obs, jnp.float32),
                                                             jnp.asarray(gain, jnp.float32))
    for a, b in zip(ahead, rows_jax):
        np.testing.assert_allclose(np.asarray(b, float), a, atol=5e-5)
    # Both filters, with the braking rows and the reachable box too.
    from aswarm.agents.cbf_filter import filter_from_obs

    cmd, applied, rate = rng.uniform(-2.0, 2.0, (2, 3, 3)), rng.uniform(-1.5, 1.5, (2, 3, 3)), (3.0, 0.04)
    for safety in (SafetyFilterConfig(margin=0.1, lookahead_xy=tau_xy, lookahead_z=tau_z, lookahead_accel=c2),
                   SafetyFilterConfig(margin=0.1, lookahead_xy=tau_xy, lookahead_z=tau_z, lookahead_accel=c2,
                                      braking=True, neighbour_braking=True, neighbour_braking_gain=10.0,
                                      gate_braking=True)):
        res_np = np_cbf.filter_from_obs(layout, obs, cmd, gain, U_MAX, 0.06, safety, 0.3, 0.05, None, applied, rate)
        with jax.enable_x64(True):
            u_jax = jax.jit(lambda o, c, g, now, sf=safety: filter_from_obs(layout, o, c, g, U_MAX, 0.06, sf, 0.3,
                                                                             0.05, None, now, rate).u)(
                jnp.asarray(obs), jnp.asarray(cmd), jnp.asarray(gain), jnp.asarray(applied))
        np.testing.assert_allclose(np.asarray(u_jax), res_np.u, atol=1e-9)
    # A layout without the neighbours' accelerations cannot take the second-order rows.
    with pytest.raises(ValueError, match="no neighbour accelerations"):
        barriers.obs_rows(plain, moved, gain, lookahead=(tau_xy, tau_z), lookahead_accel=c2, **kw)


def test_second_order_point_of_a_tilted_drone_hand_derived():
    """A drone at rest pitched 10° (thrust towards +x: a = g tan 10° = 1.7298 m/s² along +x), a cylinder of radius
    0.15 m 1 m ahead (+x) and a neighbour 2 m ahead pitched −10°, towards the drone. At c2 = 0.039 s² the drone's
    point moves 0.0675 m towards the cylinder and the neighbour's as far towards the drone: the cylinder's barrier
    falls by 0.0675 m and the pair's by 0.1349 m; at rest the first-order point is the drone itself."""
    from aswarm.core import observation
    from aswarm.core.layout import ObsLayout

    th = np.deg2rad(10.0)
    pitch = np.array([np.cos(th / 2), 0.0, np.sin(th / 2), 0.0])
    pos = np.array([[0.0, 0.0, 1.0], [2.0, 0.0, 1.0]])
    back = pitch * [1.0, 0.0, -1.0, 0.0]
    obs = observation.observe(pos, np.stack([pitch, back]), np.zeros((2, 3)), np.zeros((2, 3)),
                              np.array([[[9.0, 0.0, 1.0]]] * 2), np.zeros((2, 1, 3)), np.zeros(2, int),
                              np.ones(2, bool), np.array([[1.0, 0.0]]), np.zeros((1, 2)), np.array([0.15]),
                              np.array([True]), 0.06, (-8.0, -6.0, 0.0), (8.0, 6.0, 3.0), neighbour_accel=True)
    layout = ObsLayout(num_cylinders=1, num_neighbours=1, neighbour_accel=True)
    kw = dict(drone_radius=0.06, margin=0.1)
    first = barriers.obs_rows(layout, obs, np.ones(2), lookahead=(0.207, 0.15), **kw)
    second = barriers.obs_rows(layout, obs, np.ones(2), lookahead=(0.207, 0.15), lookahead_accel=0.039, **kw)
    d = 0.039 * 9.81 * np.tan(th)
    assert d == pytest.approx(0.06746, abs=1e-5)
    np.testing.assert_allclose(first.h[0, :2], [1.0 - 0.15 - 0.06 - 0.1, 2.0 - 0.12 - 0.1], atol=1e-12)
    np.testing.assert_allclose(second.h[0, 0], first.h[0, 0] - d, atol=1e-12)
    # the pair's barrier, ||Δq|| − 2 r − margin, with both points moved towards each other
    np.testing.assert_allclose(second.h[0, 1], first.h[0, 1] - 2 * d, atol=1e-12)


@pytest.mark.parametrize("lookahead, holds", [(0.0, False), (0.3, True)])
def test_look_ahead_keeps_a_lagging_drone_off_the_floor(lookahead, holds):
    """A point mass whose velocity follows the command with a first-order lag τ = 0.3 s (v̇ = (u − v)/τ), told to
    dive at 2 m/s from 1 m, filtered at 100 Hz with gain 2/s. The single-integrator floor row lets it sink into
    the margin (it brakes only once u changes, and v lags u); at the look-ahead point p + τ v the row is exact
    for this drone (q̇ = u), so its height never falls below the kept 0.16 m (radius 0.06 + margin 0.1, the margin
    of before issue #12 that the figures were taken with)."""
    from aswarm.core.layout import OWN, ObsLayout

    layout = ObsLayout(num_cylinders=0, num_neighbours=0)
    tau, dt, sub = 0.3, 0.01, 10
    z, vz, lowest = 1.0, 0.0, np.inf
    safety = SafetyFilterConfig(lookahead_xy=lookahead, lookahead_z=lookahead, margin=0.1)
    for _ in range(300):
        obs = np.zeros(layout.size)
        obs[OWN.slice("altitude")] = z
        obs[OWN.slice("vel")] = (0.0, 0.0, vz)
        obs[OWN.slice("wall_clearance")] = 10.0
        u = np_cbf.filter_from_obs(layout, obs[None], np.array([[0.0, 0.0, -2.0]]), np.array([2.0]), U_MAX, 0.06,
                                   safety).u[0, 2]
        for _ in range(sub):  # exact for the lag within a step: v relaxes to u with time constant τ
            decay = np.exp(-dt / sub / tau)
            z += u * dt / sub + (vz - u) * tau * (1 - decay)
            vz = u + (vz - u) * decay
            lowest = min(lowest, z)
    if holds:
        assert lowest >= 0.16 - 1e-3, lowest
    else:  # seen: 0.098, 6 cm into the margin
        assert lowest < 0.16 - 0.03, lowest


# ---------------------------------------------------------------- SafetyFilterConfig
def test_safety_filter_config_round_trips_through_a_manifest_and_old_configs_map_into_it():
    cfg = SafetyFilterConfig(margin=0.2, gain_min=0.5, gain_max=3.0, neighbour_share=0.7, max_iter=12,
                             closing_split=0.4)
    assert from_manifest(json.loads(json.dumps(manifest_fields(cfg)))) == cfg
    # A bundle exported before the config (the entries it always had, as the pretrained policy's) reads back
    # as the old defaults, as used (not to be fitted again); one that lacks an entry is a one-line error.
    old = {"method": "attention_cbf", "enabled": True, "gain_source": "attention", "fixed_gain": 1.5,
           "gain_min": 0.3, "gain_max": 2.0, "penalty_max": 2.0, "margin": 0.1, "drone_radius": 0.06,
           "gate_half_opening": 0.3, "gate_bar": 0.05, "floor_z": 0.0, "neighbour_share": 0.5, "rho": 1000000.0,
           "max_iter": 16, "tol": 1e-06}
    assert from_manifest(old) == SafetyFilterConfig(fit_to_drone=False, fit_lookahead=False, lookahead_scale=1.0,
                                                    margin=0.1, hazard_accel=False, static_slack=1.0,
                                                    neighbour_release=0.0)
    with pytest.raises(ValueError, match="missing rho"):
        from_manifest({k: v for k, v in old.items() if k != "rho"})
    # The flat fields of runs written before it (the shipped pretrained config.json has them).
    from aswarm.analysis import evaluate

    train = json.loads((evaluate.PRETRAINED_GEOMETRIC / "config.json").read_text())["train"]
    flat = {k: train[k] for k in LEGACY_FIELDS if k in train} or {"gain_min": 0.3, "gain_max": 2.0,
                                                                  "fixed_gain": 1.5, "filter_margin": 0.1}
    # It was trained with today's defaults but the margin (0.13 since issue #12).
    assert nest_legacy(flat) == {"safety_filter": SafetyFilterConfig(margin=0.1)}
    assert nest_legacy({"filter_margin": 0.3, "seed": 1}) == {"seed": 1,
                                                             "safety_filter": SafetyFilterConfig(margin=0.3)}
    assert nest_legacy({"gain_min": 0.5, "safety_filter": {"tol": 1e-5}})["safety_filter"] == {"tol": 1e-5,
                                                                                           "gain_min": 0.5}
    with pytest.raises(ValueError, match="both flat and nested"):
        nest_legacy({"gain_min": 0.5, "safety_filter": {"gain_min": 0.4}})
    for bad, message in (
            ({"gain_min": 3.0}, "need 0 < min < max"),
            ({"neighbour_share": 0.0}, "invalid safety_filter.neighbour_share"),
            ({"closing_split": 0.3, "closing_share_min": 0.6},
             r"invalid safety_filter.closing_share_min=0.6: allowed: \(0, 0.5\]"),
            ({"closing_split": -0.3}, r"invalid safety_filter.closing_split=-0.3: allowed: >= 0"),
            ({"neighbour_reference": 1.5}, r"invalid safety_filter.neighbour_reference=1.5: allowed: \[0, 1\]"),
            ({"neighbour_release": -1}, r"invalid safety_filter.neighbour_release=-1: allowed: >= 0"),
            ({"proximity_slack": -1}, r"invalid safety_filter.proximity_slack=-1: allowed: >= 0"),
            ({"proximity_slack_min": 0}, r"invalid safety_filter.proximity_slack_min=0: allowed: \(0, 1\]"),
            ({"lookahead_z": -0.1}, r"invalid safety_filter.lookahead_z=-0.1: allowed: >= 0"),
            ({"fit_lookahead": 1}, r"invalid safety_filter.fit_lookahead=1: allowed: true or false"),
            ({"lookahead_scale": -1.0}, r"invalid safety_filter.lookahead_scale=-1.0: allowed: >= 0")):
        with pytest.raises(ValueError, match=message):
            SafetyFilterConfig(**bad)
    # Fitted to a drone: gains scaled to its horizontal lag, look-aheads set to 0.9 of its lags (the lags
    # themselves as runs before the scale; or left alone).
    fitted = SafetyFilterConfig().fitted(0.5, 0.2)
    assert (fitted.gain_max, fitted.fit_to_drone) == (1.0, False)
    assert math.isclose(fitted.lookahead_xy, 0.45) and math.isclose(fitted.lookahead_z, 0.18)
    whole = SafetyFilterConfig(lookahead_scale=1.0).fitted(0.5, 0.2)
    assert (whole.gain_max, whole.lookahead_xy, whole.lookahead_z) == (1.0, 0.5, 0.2)
    assert SafetyFilterConfig(fit_lookahead=False).fitted(0.5, 0.2).lookahead_xy == 0.0
    # The moving cylinders' gain cap is a gain: fitted with the others; off (0) in bundles from before it.
    assert SafetyFilterConfig(moving_gain_max=1.36).fitted(0.5, 0.2).moving_gain_max == 0.68
    assert from_manifest(old).moving_gain_max == 0.0 and from_manifest(old).closing_split == 0.0
    assert from_manifest(old).neighbour_reference == 1.0 and from_manifest(old).neighbour_release == 0.0
    assert from_manifest(old).proximity_slack == 0.0 and from_manifest(old).moving_margin == 0.0
    assert from_manifest(old).moving_margin_time == 0.0 and from_manifest(old).rail_speed == 0.0
    # Runs from before the release read it back as 0 (the shipped policies were measured so), but the race, the
    # dynamic and the race-moving policies, whose stored filters take it since sessions 42, 43 and 44, and the dynamic
    # policy fine-tuned under it on rails (session 49); new runs 0.5.
    from aswarm.analysis import evaluate
    from aswarm.training import run_config

    assert SafetyFilterConfig().neighbour_release == 0.5
    for name in evaluate.shipped():
        rail = name == "pretrained:dynamic-rail"
        want = 0.5 if rail or name in ("pretrained", "pretrained:dynamic", "pretrained:race-moving") else 0.0
        stored = run_config.read(evaluate.run_folder(name)).safety_filter
        assert stored.neighbour_release == want, name
        # Slack weighed by nearness: the dynamic (session 44) and the race (session 45) policies' stored filters.
        assert stored.proximity_slack == (1.0 if rail or name in ("pretrained", "pretrained:dynamic") else 0.0), name
        # A margin for what moves (session 46): an option, stored by no shipped policy (it cost the 1.5x cells).
        assert stored.moving_margin == 0.0 and stored.moving_margin_time == 0.0, name
        # Moving on rails (session 48): only the dynamic policy fine-tuned under it stores it (session 49).
        assert stored.rail_speed == (0.2 if rail else 0.0), name
    with pytest.raises(ValueError, match=r"invalid safety_filter.moving_gain_max=-1.0: allowed: >= 0"):
        SafetyFilterConfig(moving_gain_max=-1.0)
    with pytest.raises(ValueError, match=r"moving_gain_max=1.0 with hazard_accel=false: allowed: 0, or hazard_accel"):
        SafetyFilterConfig(moving_gain_max=1.0, hazard_accel=False)
    # The second-order look-ahead: its c1 is its fit's own (kept when fitted: the vertical one still fitted), it
    # needs one, and bundles from before it read back first order.
    second = SafetyFilterConfig(lookahead_xy=0.207, lookahead_accel=0.039).fitted(0.5, 0.2)
    assert (second.lookahead_xy, second.lookahead_accel) == (0.207, 0.039) and math.isclose(second.lookahead_z, 0.18)
    assert from_manifest(json.loads(json.dumps(manifest_fields(second)))) == second
    assert from_manifest(old).lookahead_accel == 0.0 and from_manifest(old).gate_braking is False
    assert SafetyFilterConfig(gate_braking=True).brakes((3.0, 0.04)) and not SafetyFilterConfig().brakes((3.0, 0.04))
    assert SafetyFilterConfig(wall_braking=True).brakes((3.0, 0.04)) and from_manifest(old).wall_braking is False
    with pytest.raises(ValueError, match=r"lookahead_accel=0.039 with lookahead_xy=0.0: allowed: lookahead_accel 0, "
                                         r"or lookahead_xy > 0"):
        SafetyFilterConfig(lookahead_accel=0.039)
    with pytest.raises(ValueError, match=r"invalid safety_filter.lookahead_accel=-0.1: allowed: >= 0"):
        SafetyFilterConfig(lookahead_accel=-0.1)


def test_train_flags_set_the_safety_filter_old_and_nested_spellings(monkeypatch, tmp_path):
    from aswarm import cli
    from aswarm.training import runner

    seen = []
    monkeypatch.setattr(runner, "train", lambda config, out, **kw: seen.append(config) or tmp_path)
    assert cli.main(["train", "--scenario", "hover", "--method", "fixed_cbf", "--gain-min", "0.4", "--fixed-gain",
                     "0.9", "--filter-margin", "0.2", "--safety-filter.max-iter", "12", "--out", str(tmp_path)]) == 0
    sf = seen[0].safety_filter
    assert (sf.gain_min, sf.fixed_gain, sf.margin, sf.max_iter) == (0.4, 0.9, 0.2, 12)
    assert dataclasses.replace(sf, gain_min=0.3, fixed_gain=1.5, margin=0.13, max_iter=16) == SafetyFilterConfig()


def test_a_second_order_filter_needs_the_neighbours_accelerations_in_its_observation():
    from aswarm.agents.config import TrainConfig
    from aswarm.agents.train import Agent

    sf = SafetyFilterConfig(lookahead_xy=0.207, lookahead_accel=0.039)
    with pytest.raises(ValueError, match=r"lookahead_accel=0.039 with env filter_neighbour_accel=false: allowed: "
                                         r"lookahead_accel 0, or --env filter_neighbour_accel=true"):
        Agent.build(TrainConfig(scenario="hover", method="fixed_cbf", safety_filter=sf))
    agent = Agent.build(TrainConfig(scenario="hover", method="fixed_cbf", safety_filter=sf,
                                    env_overrides=(("filter_neighbour_accel", True),)))
    assert agent.env.filter_layout.neighbour_accel and agent.config.safety_filter.lookahead_accel == 0.039
    # A method without the filter never builds its rows: nothing to refuse.
    assert Agent.build(TrainConfig(scenario="hover", method="mappo", safety_filter=sf)).env.wide_filter is False


def test_the_gain_range_is_still_swept_by_its_flat_names_as_a_value_hyperparameter():
    from aswarm.agents import hparams
    from aswarm.training import sweep

    spec = sweep.parse({"scenario": "hover", "total_steps": 128, "seeds": [0],
                        "grid": {"gain_min": [0.2, 0.4], "gain_max": [3.0]}})
    assert [(c.safety_filter.gain_min, c.safety_filter.gain_max) for c in spec.configs] == [(0.2, 3.0), (0.4, 3.0)]
    (group,) = sweep.groups(spec)  # one compiled program serves both
    assert group.sweep_fields == ("gain_min",)
    np.testing.assert_allclose(hparams.stack(spec.configs, group.sweep_fields)["gain_min"], [0.2, 0.4])
    assert hparams.replaced(spec.configs[0], {"gain_min": 0.4}) == spec.configs[1]


def _wall_trap_obs(drone_y_gap: float = 0.25, cylinder_y: float = 0.15):
    """One drone flying +x beside the arena's y-low wall (``drone_y_gap`` m from it) with a cylinder (radius 0.15)
    ahead at (0.40, ``cylinder_y``) from it, on the side away from the wall: the 16-drone wall trap of the README."""
    layout = ObsLayout(num_cylinders=1, num_neighbours=1)
    obs = np.zeros(layout.size)
    f = layout.own_slices
    obs[f["altitude"]] = 1.0
    obs[f["wall_clearance"]] = [3.0, 3.0, drone_y_gap, 3.0, 1.0]
    cyl0 = layout.own_dim
    rel = np.array([0.40, cylinder_y])
    cyl = np.zeros(CYL.dim)
    cyl[CYL.slice("rel_xy")] = rel
    cyl[CYL.column("clearance")] = np.linalg.norm(rel) - 0.15 - 0.06
    cyl[CYL.column("present")] = 1.0
    obs[cyl0:cyl0 + CYL.dim] = cyl
    return layout, obs


def test_the_deadlock_escape_slides_a_wedged_drone_around_the_cylinder_hand_derived():
    from aswarm.agents.cbf_filter import filter_from_obs

    layout, obs = _wall_trap_obs()
    cmd, gain = np.array([1.5, 0.0, 0.0]), np.array(1.0)
    plain = SafetyFilterConfig(margin=0.1)
    escape = dataclasses.replace(plain, escape=True)
    # Hand-derived: the cylinder's row has the unit normal a = -(0.40, 0.15)/0.427 and b = -(0.427 - 0.31) (gain 1),
    # the wall's u_y >= -(0.25 - 0.16). Projecting (1.5, 0, 0) onto both leaves u_x = (b - a_y u_y) / a_x = 0.158 m/s
    # forward: under a quarter of the 1.5 asked, with the cylinder facing the drone, so stuck.
    d = math.hypot(0.40, 0.15)
    a = -np.array([0.40, 0.15]) / d
    u_y = -0.09
    u_x = (-(d - 0.31) - a[1] * u_y) / a[0]
    res = np_cbf.filter_from_obs(layout, obs, cmd, gain, U_MAX, 0.06, plain)
    np.testing.assert_allclose(res.u, [u_x, u_y, 0.0], atol=1e-5)  # the QP's slack weight 1e6: not exactly 0
    assert res.u[0] < 0.25 * 1.5
    # The escape: 1.5 m/s along the cylinder's tangent, on the side away from the wall (the counterclockwise tangent
    # (-a_y, a_x) points at the wall here, so the other one), which both rows let through unchanged.
    tangent = -np.array([-a[1], a[0]])
    out = np_cbf.filter_from_obs(layout, obs, cmd, gain, U_MAX, 0.06, escape)
    assert out.escaped and out.intervened
    np.testing.assert_allclose(out.u, [*(1.5 * tangent), 0.0], atol=1e-5)
    assert out.u[1] > 1.3  # away from the wall
    np.testing.assert_allclose(out.correction_norm, np.linalg.norm(out.u - cmd))
    # The JAX filter: the same command.
    with jax.enable_x64(True):
        jres = jax.jit(lambda o, c, g: filter_from_obs(layout, o, c, g, U_MAX, 0.06, escape))(
            jnp.asarray(obs), jnp.asarray(cmd), jnp.asarray(gain))
    np.testing.assert_allclose(np.asarray(jres.u), out.u, atol=1e-9)
    assert bool(jres.escaped)


def test_the_deadlock_escape_changes_nothing_where_no_drone_is_stuck():
    from aswarm.agents.cbf_filter import filter_from_obs

    # Away from the wall, a cylinder off the drone's line: its row alone slides the drone past it, keeping more
    # than a quarter of the speed asked (0.69 of 1.5 m/s): not stuck, the plain command.
    layout, obs = _wall_trap_obs(drone_y_gap=2.0, cylinder_y=0.30)
    cmd, gain = np.array([1.5, 0.0, 0.0]), np.array(1.0)
    escape = SafetyFilterConfig(margin=0.1, escape=True)
    res = np_cbf.filter_from_obs(layout, obs, cmd, gain, U_MAX, 0.06, escape)
    plain = np_cbf.filter_from_obs(layout, obs, cmd, gain, U_MAX, 0.06, dataclasses.replace(escape, escape=False))
    assert not res.escaped and res.intervened
    np.testing.assert_array_equal(res.u, plain.u)
    # Random scenes: wherever the escape engages, every row still holds as well as without it (slack no larger than
    # the plain QP's plus round-off), and JAX and numpy agree drone for drone.
    scene_layout, rng, scene_obs, scene_gain, kw = _obs_scene(3)
    cmds = rng.uniform(-2.0, 2.0, (2, 3, 3))
    safety = SafetyFilterConfig(margin=0.1, escape=True, escape_near=1.0, escape_stuck=0.9)
    res = np_cbf.filter_from_obs(scene_layout, scene_obs, cmds, scene_gain, U_MAX, 0.06, safety, 0.3, 0.05)
    assert res.escaped.any()
    with jax.enable_x64(True):
        jres = jax.jit(lambda o, c, g: filter_from_obs(scene_layout, o, c, g, U_MAX, 0.06, safety, 0.3, 0.05))(
            jnp.asarray(scene_obs), jnp.asarray(cmds), jnp.asarray(scene_gain))
    np.testing.assert_array_equal(np.asarray(jres.escaped), res.escaped)
    np.testing.assert_allclose(np.asarray(jres.u), res.u, atol=1e-9)
    rows = barriers.obs_rows(scene_layout, scene_obs, scene_gain, **kw, neighbour_release=safety.neighbour_release)
    nrm = np.linalg.norm(rows.A, axis=-1)
    gap = (np.einsum("...mk,...k->...m", rows.A, res.u) - rows.b) / np.maximum(nrm, 1e-9)
    worst = np.where(rows.mask, -gap, 0.0).max(-1)
    assert np.all(worst <= np.maximum(res.slack, 0.0) * 10 + 1e-6)


def test_the_deadlock_escape_turns_two_drones_meeting_head_on_the_same_way():
    from aswarm.core.layout import NBR

    # Drone 0 at the origin asked +x at 1.5 m/s, drone 1 0.45 m ahead of it asked -x, both hovering, far from walls.
    # Each one's neighbour row faces its command squarely and the reciprocal split leaves it only backing off: stuck.
    # The escape's counterclockwise tangent of the neighbour (nothing else near, no side towards the command) turns
    # drone 0 to -y and drone 1 to +y: each to its right, so they pass instead of mirroring each other.
    layout = ObsLayout(num_cylinders=1, num_neighbours=1)
    obs = np.zeros((2, layout.size))
    f = layout.own_slices
    obs[:, f["altitude"]] = 1.0
    obs[:, f["wall_clearance"]] = 3.0
    nbr0 = layout.own_dim + layout.num_cylinders * CYL.dim
    for i, sign in ((0, 1.0), (1, -1.0)):
        row = np.zeros(NBR.dim)
        row[NBR.slice("rel_pos")] = [sign * 0.45, 0.0, 0.0]
        row[NBR.column("present")] = 1.0
        obs[i, nbr0:nbr0 + NBR.dim] = row
    cmd = np.array([[1.5, 0.0, 0.0], [-1.5, 0.0, 0.0]])
    safety = SafetyFilterConfig(margin=0.1, escape=True)
    res = np_cbf.filter_from_obs(layout, obs, cmd, np.ones(2), U_MAX, 0.06, safety)
    np.testing.assert_array_equal(res.escaped, [True, True])
    np.testing.assert_allclose(res.u, [[0.0, -1.5, 0.0], [0.0, 1.5, 0.0]], atol=1e-6)
    plain = np_cbf.filter_from_obs(layout, obs, cmd, np.ones(2), U_MAX, 0.06, dataclasses.replace(safety, escape=False))
    # Without it each closes its share of the gap, 0.5 x (0.45 - 0.12 - 0.1) m at gain 1/s, straight on: a pair that
    # slows to a stop face to face.
    np.testing.assert_allclose(plain.u, [[0.115, 0.0, 0.0], [-0.115, 0.0, 0.0]], atol=1e-5)

"""The shared core: the observation layout's named fields, the geometry and the observation builder give the
same numbers on numpy float64 and JAX float32/float64 inputs, and the hand-derived values."""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from aswarm.core import geometry as geo
from aswarm.core import observation
from aswarm.core.layout import (
    CYL,
    CYL_FIELDS,
    NBR,
    NBR_ACCEL,
    NBR_FIELDS,
    OWN,
    OWN_FIELDS,
    PRESENT_THRESHOLD,
    ObsLayout,
)

R = 0.06  # drone collision radius
RNG = np.random.default_rng(0)


# ------------------------------------------------------------------ layout
@pytest.mark.parametrize("m,k", [(8, 3), (0, 0), (3, 1)])
def test_named_fields_sit_at_the_described_offsets(m, k):
    lay = ObsLayout(m, k)
    desc = lay.describe()
    assert sum(d["size"] for d in desc) == lay.size
    cyl0, nbr0 = lay.own_dim, lay.own_dim + m * lay.cyl_dim
    for d in desc:
        group, base, dim = {"own": (OWN, 0, 0), "cylinder": (CYL, cyl0, lay.cyl_dim),
                            "neighbour": (NBR, nbr0, lay.nbr_dim)}[d["group"]]
        sl = group.slice(d["name"])
        assert base + d["index"] * dim + sl.start == d["offset"] and sl.stop - sl.start == d["size"]
        col = group.column(d["name"])
        assert col == (sl.start if d["size"] == 1 else sl)
    assert lay.own_slices == {d["name"]: slice(d["offset"], d["offset"] + d["size"]) for d in desc
                              if d["group"] == "own"}
    want = [d["offset"] for d in desc if d["name"] == "present"]
    assert list(lay.presence_columns) == want and len(want) == m + k


def test_named_fields_read_what_the_row_holds():
    lay = ObsLayout(2, 3)
    row = np.arange(lay.size, dtype=float)
    own, cyl, nbr = lay.split(row)
    assert OWN.get(own, "vel").tolist() == row[lay.own_slices["vel"]].tolist()
    assert OWN.get(own, "altitude").shape == ()  # a one-number field drops its axis
    offsets = {(d["group"], d["index"], d["name"]): d["offset"] for d in lay.describe()}
    assert CYL.get(cyl, "clearance").tolist() == [offsets["cylinder", i, "clearance"] for i in range(2)]
    assert CYL.get(cyl, "rel_xy")[1].tolist() == [offsets["cylinder", 1, "rel_xy"] + j for j in range(2)]
    assert NBR.get(nbr, "rel_vel")[2, 0] == offsets["neighbour", 2, "rel_vel"]
    flags = np.zeros(lay.size)
    flags[list(lay.presence_columns)] = [1.0, 0.0, 0.0, 1.0, 1.0]
    _, cyl, nbr = lay.split(flags)
    assert CYL.present(cyl).tolist() == [True, False] and NBR.present(nbr).tolist() == [False, True, True]
    assert CYL.present(jnp.asarray(cyl)).tolist() == [True, False]
    assert 0.0 < PRESENT_THRESHOLD < 1.0
    assert (OWN.dim, CYL.dim, NBR.dim) == tuple(sum(f[1] for f in t) for t in (OWN_FIELDS, CYL_FIELDS, NBR_FIELDS))


def test_the_neighbours_accelerations_follow_every_column_the_policy_reads():
    plain, lay = ObsLayout(2, 3), ObsLayout(2, 3, neighbour_accel=True)
    assert lay.size == plain.size + 3 * NBR_ACCEL.dim and NBR_ACCEL.dim == 2
    desc = lay.describe()
    assert desc[:len(plain.describe())] == plain.describe()  # the policy's layout is a prefix
    tail = desc[len(plain.describe()):]
    assert [(d["group"], d["index"], d["name"], d["offset"]) for d in tail] == [
        ("neighbour_accel", k, "tilt_accel", plain.size + 2 * k) for k in range(3)]
    row = np.arange(lay.size, dtype=float)
    own, cyl, nbr = lay.split(row)
    np.testing.assert_array_equal(np.concatenate([own, cyl.ravel(), nbr.ravel()]), row[:plain.size])
    np.testing.assert_array_equal(lay.neighbour_accels(row), row[plain.size:].reshape(3, 2))
    with pytest.raises(ValueError, match="no neighbour accelerations"):
        plain.neighbour_accels(row[:plain.size])


def test_an_unknown_field_is_refused_in_one_line():
    with pytest.raises(KeyError, match="invalid cylinder field 'radius': allowed: rel_xy, clearance, vel_xy, present"):
        CYL.slice("radius")


# ------------------------------------------------------------------ hand-derived geometry
GATE_POS, HALF = np.array([2.0, 1.0, 1.0]), 0.3


@pytest.mark.parametrize("prev,new,yaw,expected", [
    ((1.9, 1.0, 1.0), (2.1, 1.0, 1.0), 0.0, True),  # through the centre along +x
    ((2.1, 1.0, 1.0), (1.9, 1.0, 1.0), 0.0, False),  # backwards
    ((1.9, 1.35, 1.0), (2.1, 1.35, 1.0), 0.0, False),  # beside the opening
    ((1.9, 1.0, 1.0), (2.0, 1.0, 1.0), 0.0, True),  # ends on the plane: s1 = 0 counts as crossed
    ((1.5, 0.5, 1.0), (2.5, 1.5, 1.0), 0.0, True),  # diagonal, through the centre
    ((1.5, 0.5, 1.0), (2.5, 2.5, 1.0), 0.0, False),  # diagonal, meets the plane at y = 1.5: outside
    ((2.0, 0.9, 1.0), (2.0, 1.1, 1.0), np.pi / 2, True),  # a gate facing +y
    ((1.9, 0.95, 1.0), (2.1, 0.95, 1.0), np.pi / 2, False),  # ... moved parallel to its plane, in front of it
])
def test_gate_crossed_hand_derived(prev, new, yaw, expected):
    normal = geo.horizontal(np.float64(yaw))
    assert bool(geo.gate_crossed(np.array(prev), np.array(new), GATE_POS, normal, HALF)) is expected
    got = geo.gate_crossed(jnp.array(prev), jnp.array(new), jnp.asarray(GATE_POS), geo.horizontal(jnp.float32(yaw)),
                           HALF)
    assert bool(got) is expected


def test_clearances_hand_derived():
    # A cylinder of radius 0.2 at the origin, 1.5 m tall; drones 0.5 m to its side and 0.3 m above its top.
    pos = np.array([[0.5, 0.0, 1.0], [0.0, 0.0, 1.5 + R + 0.3]])
    gap = geo.cylinder_clearance(pos, np.zeros((1, 2)), np.array([0.2]), np.array([1.5]), np.array([True]), R)
    np.testing.assert_allclose(gap[:, 0], [0.5 - 0.2 - R, 0.3])
    absent = geo.cylinder_clearance(pos, np.zeros((1, 2)), np.array([0.2]), np.array([1.5]), np.array([False]), R)
    assert np.all(absent == geo.FAR)
    # Two drones 0.5 m apart, a third inactive.
    d = geo.drone_clearance(np.array([[0.0, 0, 1], [0.3, 0.4, 1], [9, 9, 1]]), np.array([True, True, False]), R)
    np.testing.assert_allclose(d[0, 1], 0.5 - 2 * R)
    assert d[0, 0] == d[0, 2] == d[2, 1] == geo.FAR
    # A gate at x = 2 facing +x: its right bar's axis at y = 1 + 0.3 + 0.025; its post below.
    frames = geo.gate_frames(GATE_POS[None], np.zeros(1), HALF, 0.05)
    assert frames.shape == (1, 5, 2, 3)
    bar = 1.0 + HALF + 0.025
    points = np.array([[2.0, bar - 0.2, 1.0], [2.0, 1.0, 0.3]])
    c = geo.gate_clearance(points, GATE_POS[None], geo.horizontal(np.zeros(1)), HALF, 0.05, R)
    np.testing.assert_allclose(c[:, 0], [0.2 - 0.025 - R, 0.0 - 0.025 - R], atol=1e-12)
    seg = geo.point_segment_distance(np.array([1.0, 2.0, 0.0]), np.zeros(3), np.array([2.0, 0, 0]))
    np.testing.assert_allclose(seg, 2.0)
    low, high = (-1.0, -2.0, 0.0), (1.0, 2.0, 3.0)
    p = np.array([[0.5, -1.5, 1.0], [1.1, 0, 1], [0, 0, -0.5], [0, 0, 3.1]])
    assert geo.out_of_bounds(p, low, high).tolist() == [False, True, False, True]  # the floor is checked apart
    np.testing.assert_allclose(geo.wall_clearance(p[0], np.array(low), np.array(high)), [1.5, 0.5, 0.5, 3.5, 2.0])


def test_cylinder_motion_hand_derived():
    center, axis = np.array([[1.0, 2.0]]), np.array([[0.6, 0.8]])
    amp, omega, phase = np.array([0.5]), np.array([np.pi]), np.array([0.0])
    pos0, vel0 = geo.cylinders_at(center, axis, amp, omega, phase, 0.0)
    np.testing.assert_allclose(pos0, center)
    np.testing.assert_allclose(vel0, axis * 0.5 * np.pi)  # through the centre at full speed
    pos1, vel1 = geo.cylinders_at(center, axis, amp, omega, phase, 0.5)  # a quarter period: at the far end
    np.testing.assert_allclose(pos1, center + 0.5 * axis)
    np.testing.assert_allclose(vel1, 0.0, atol=1e-12)
    still, v = geo.cylinders_at(center, axis, np.zeros(1), omega, phase, np.array([0.3, 7.0]))
    assert still.shape == (2, 1, 2)
    np.testing.assert_allclose(still, np.broadcast_to(center, (2, 1, 2)))
    assert np.all(v == 0)


# ------------------------------------------------------------------ numpy float64 == JAX float32 / float64
def _geometry_cases():
    n, m, g = 4, 3, 2
    pos = RNG.uniform(-1, 1, (n, 3)) + [0, 0, 1]
    prev = pos + RNG.normal(scale=0.3, size=(n, 3))
    gate_pos, gate_yaw = RNG.uniform(-1, 1, (g, 3)) + [0, 0, 1], RNG.uniform(-np.pi, np.pi, g)
    cyl = RNG.uniform(-1, 1, (m, 2))
    tilted = RNG.normal(scale=0.2, size=(n, 4)) + [1.0, 0, 0, 0]  # attitudes up to ~25° off upright
    return {
        "gate_frames": (lambda a, b: geo.gate_frames(a, b, HALF, 0.05), (gate_pos, gate_yaw), (g, 5, 2, 3)),
        "closest_on_segment": (geo.closest_on_segment, (pos, prev, pos[::-1]), (n, 3)),
        "point_segment_distance": (geo.point_segment_distance, (pos, prev, pos[::-1]), (n,)),
        "cylinders_at": (lambda *a: geo.cylinders_at(*a)[0], (cyl, cyl / np.linalg.norm(cyl, axis=-1, keepdims=True),
                                                            RNG.uniform(0, 1, m), RNG.uniform(0, 2, m),
                                                            RNG.uniform(0, 6, m), np.array(1.3)), (m, 2)),
        "gate_crossed": (lambda a, b, c, y: geo.gate_crossed(a, b, c, geo.horizontal(y), 0.3),
                         (prev, pos, np.broadcast_to(gate_pos[0], (n, 3)), np.full(n, gate_yaw[0])), (n,)),
        "cylinder_clearance": (lambda p, c, r, h: geo.cylinder_clearance(p, c, r, h, np.array([True, False, True]), R),
                               (pos, cyl, RNG.uniform(0.1, 0.3, m), RNG.uniform(0.5, 2, m)), (n, m)),
        "drone_clearance": (lambda p: geo.drone_clearance(p, np.array([True, True, False, True]), R), (pos,), (n, n)),
        "gate_clearance": (lambda p, c, y: geo.gate_clearance(p, c, geo.horizontal(y), HALF, 0.05, R),
                           (pos, gate_pos, gate_yaw), (n, g)),
        "out_of_bounds": (lambda p: geo.out_of_bounds(p, (-0.5, -0.5, 0), (0.5, 0.5, 1.5)), (pos,), (n,)),
        "wall_clearance": (lambda p: geo.wall_clearance(p, np.array([-8.0, -6, 0]), np.array([8.0, 6, 3])), (pos,),
                           (n, 5)),
        "horizontal": (geo.horizontal, (gate_yaw,), (g, 3)),
        "tilt_accel": (geo.tilt_accel, (tilted / np.linalg.norm(tilted, axis=-1, keepdims=True),), (n, 3)),
        "norm": (geo.norm, (pos,), (n,)),
    }


@pytest.mark.parametrize("name", sorted(_geometry_cases()))
def test_geometry_is_the_same_on_numpy_and_jax(name):
    fn, args, shape = _geometry_cases()[name]
    want = fn(*args)
    assert isinstance(want, np.ndarray)
    chex.assert_shape(want, shape)
    for dtype, tol in ((jnp.float32, 2e-5), (jnp.float64, 1e-12)):
        with jax.enable_x64(dtype == jnp.float64):
            got = fn(*(jnp.asarray(a, dtype) if np.asarray(a).dtype.kind == "f" else jnp.asarray(a) for a in args))
            chex.assert_shape(got, shape)
            assert isinstance(got, jax.Array)
            np.testing.assert_allclose(np.asarray(got, np.float64), want, rtol=0, atol=tol)


def test_tilt_acceleration_is_g_times_the_tangent_of_the_tilt_towards_where_the_thrust_points():
    th = np.deg2rad(np.array([0.0, 10.0, 25.0]))
    about_x = np.stack([np.cos(th / 2), np.sin(th / 2), 0 * th, 0 * th], -1)  # roll th: thrust axis (0, -sin, cos)
    about_y = np.stack([np.cos(th / 2), 0 * th, np.sin(th / 2), 0 * th], -1)  # pitch th: (sin, 0, cos)
    np.testing.assert_allclose(geo.tilt_accel(about_x), np.stack([0 * th, -9.81 * np.tan(th), 0 * th], -1),
                               atol=1e-12)
    np.testing.assert_allclose(geo.tilt_accel(about_y), np.stack([9.81 * np.tan(th), 0 * th, 0 * th], -1),
                               atol=1e-12)
    # A yaw alone tilts nothing; a yaw of 90° then a pitch turns the pitch's thrust from +x to +y.
    yaw = np.array([np.cos(0.6), 0.0, 0.0, np.sin(0.6)])
    np.testing.assert_allclose(geo.tilt_accel(yaw), np.zeros(3), atol=1e-12)
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    yaw_pitch = np.array([c * np.cos(th[1] / 2), -s * np.sin(th[1] / 2), c * np.sin(th[1] / 2), s * np.cos(th[1] / 2)])
    np.testing.assert_allclose(geo.tilt_accel(yaw_pitch), [0.0, 9.81 * np.tan(th[1]), 0.0], atol=1e-12)


def _scene(lead=(2,), n=5, k=3, m=4):
    """A random observation input: waypoints with gate normals, some drones finished, some cylinders absent."""
    yaw = RNG.uniform(-np.pi, np.pi, k)
    return dict(
        pos=RNG.uniform(-2, 2, lead + (n, 3)) + [0, 0, 1.5], quat=RNG.normal(size=lead + (n, 4)),
        vel=RNG.normal(size=lead + (n, 3)), ang_vel=RNG.normal(size=lead + (n, 3)),
        waypoints=np.broadcast_to(RNG.uniform(-3, 3, (k, 3)), lead + (n, k, 3)),
        normals=np.broadcast_to(geo.horizontal(yaw), lead + (n, k, 3)),
        target=RNG.integers(0, k + 1, lead + (n,)), flying=RNG.random(lead + (n,)) > 0.3,
        cyl_pos=RNG.uniform(-2, 2, lead + (m, 2)), cyl_vel=RNG.normal(size=lead + (m, 2)),
        cyl_radius=RNG.uniform(0.1, 0.3, lead + (m,)), cyl_present=RNG.random(lead + (m,)) > 0.3,
    )


@pytest.mark.parametrize("max_neighbours", [0, 2, 6])
def test_observation_is_the_same_on_numpy_and_jax(max_neighbours):
    s = _scene()
    lay = ObsLayout(4, max_neighbours or 4)
    args = (R, (-8.0, -6.0, 0.0), (8.0, 6.0, 3.0), max_neighbours)
    want = observation.observe(**s, collision_radius=R, arena_low=args[1], arena_high=args[2],
                               max_neighbours=max_neighbours)
    assert isinstance(want, np.ndarray) and want.dtype == np.float64
    chex.assert_shape(want, (2, 5, lay.size))
    own, cyl, nbr = lay.split(want)
    # Hand-checked fields: absent cylinders and neighbours are zero rows; the rest is what was given.
    np.testing.assert_array_equal(OWN.get(own, "vel"), s["vel"])
    np.testing.assert_array_equal(OWN.get(own, "altitude"), s["pos"][..., 2])
    present = np.broadcast_to(s["cyl_present"][:, None], (2, 5, 4))
    assert np.array_equal(CYL.present(cyl), present) and np.all(cyl[~present] == 0)
    np.testing.assert_allclose(CYL.get(cyl, "clearance")[present],
                               (np.linalg.norm(s["cyl_pos"][:, None] - s["pos"][..., None, :2], axis=-1)
                                - s["cyl_radius"][:, None] - R)[present])
    flying_others = NBR.present(nbr).sum(-1)
    n_flying = s["flying"].sum(-1, keepdims=True) - s["flying"]
    assert np.array_equal(flying_others, np.minimum(n_flying, max_neighbours or 4))
    for dtype, tol in ((jnp.float32, 2e-4), (jnp.float64, 1e-12)):
        with jax.enable_x64(dtype == jnp.float64):
            js = {key: jnp.asarray(v, dtype) if v.dtype.kind == "f" else jnp.asarray(v) for key, v in s.items()}
            got = jax.jit(observation.observe, static_argnums=(12, 13, 14, 15))(*js.values(), *args)
            chex.assert_shape(got, want.shape)
            chex.assert_type(got, dtype)
            np.testing.assert_allclose(np.asarray(got, np.float64), want, rtol=0, atol=tol)


def test_observation_without_batch_axes_cylinders_or_neighbours():
    s = _scene(lead=(), n=1, m=0)
    got = observation.observe(**s, collision_radius=R, arena_low=(-8.0, -6.0, 0.0), arena_high=(8.0, 6.0, 3.0))
    chex.assert_shape(got, (1, ObsLayout(0, 0).size))
    np.testing.assert_array_equal(got[0, ObsLayout(0, 0).own_slices["quat"]], s["quat"][0])


def test_nearest_rows_orders_present_neighbours_and_pads():
    # One drone's 3 neighbours at distances 2, 1 (absent), 0.5: the 2 nearest present ones, then a zero row.
    rel = np.array([[[2.0, 0, 0], [1.0, 0, 0], [0.5, 0, 0]]])
    nbr = np.concatenate([rel, np.zeros_like(rel), np.ones((1, 3, 1))], -1)
    present = np.array([[True, False, True]])
    got = observation.nearest_rows(nbr, present, 4)
    chex.assert_shape(got, (1, 4, NBR.dim))
    assert NBR.get(got, "rel_pos")[0, :, 0].tolist() == [0.5, 2.0, 0.0, 0.0]
    assert NBR.present(got)[0].tolist() == [True, True, False, False]
    np.testing.assert_array_equal(np.asarray(observation.nearest_rows(jnp.asarray(nbr), jnp.asarray(present), 4)), got)

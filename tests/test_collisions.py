"""Gate crossings and each kind of collision, at the right distance and not before."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from aswarm.core import geometry as geo
from aswarm.envs import collisions as col
from aswarm.envs import make

R = 0.06  # drone collision radius
EPS = 1e-3


def gate(yaw=0.0):
    return jnp.array([[2.0, 1.0, 1.0]]), jnp.array([yaw])


@pytest.mark.parametrize(
    "prev,new,expected",
    [
        ((1.9, 1.0, 1.0), (2.1, 1.0, 1.0), True),  # through the centre
        ((1.9, 1.25, 1.2), (2.1, 1.25, 1.2), True),  # inside, near a corner
        ((1.9, 1.35, 1.0), (2.1, 1.35, 1.0), False),  # beside the opening (half-opening 0.3)
        ((1.9, 1.0, 1.4), (2.1, 1.0, 1.4), False),  # above it
        ((2.1, 1.0, 1.0), (1.9, 1.0, 1.0), False),  # backwards
        ((1.8, 1.0, 1.0), (1.95, 1.0, 1.0), False),  # not yet at the plane
    ],
)
def test_gate_crossing(prev, new, expected):
    gp, gy = gate()
    hit = geo.gate_crossed(jnp.array([prev]), jnp.array([new]), gp, geo.horizontal(gy), 0.3)
    assert bool(hit[0]) is expected


def test_gate_crossing_respects_gate_yaw():
    gp, gy = gate(np.pi / 2)  # passage towards +y
    fwd = geo.gate_crossed(jnp.array([[2.0, 0.9, 1.0]]), jnp.array([[2.0, 1.1, 1.0]]), gp, geo.horizontal(gy), 0.3)
    side = geo.gate_crossed(jnp.array([[1.9, 1.0, 1.0]]), jnp.array([[2.1, 1.0, 1.0]]), gp, geo.horizontal(gy), 0.3)
    assert bool(fwd[0]) and not bool(side[0])


def test_cylinder_collision_distance():
    c = jnp.array([[0.0, 0.0]])
    rad, h, present = jnp.array([0.15]), jnp.array([2.0]), jnp.array([True])
    touch = 0.15 + R
    gap = geo.cylinder_clearance(jnp.array([[touch + EPS, 0, 1.0], [touch - EPS, 0, 1.0]]), c, rad, h, present, R)
    assert float(gap[0, 0]) == pytest.approx(EPS, abs=1e-5) and float(gap[1, 0]) < 0
    over = geo.cylinder_clearance(jnp.array([[0.0, 0.0, 2.0 + R + EPS]]), c, rad, h, present, R)
    assert float(over[0, 0]) > 0  # passing over the top is not a collision
    absent = geo.cylinder_clearance(jnp.array([[0.0, 0.0, 1.0]]), c, rad, h, jnp.array([False]), R)
    assert float(absent[0, 0]) == geo.FAR


def test_drone_collision_distance():
    pos = jnp.array([[0.0, 0, 1], [2 * R + EPS, 0, 1], [0, 2 * R - EPS, 1]])
    gap = geo.drone_clearance(pos, jnp.array([True, True, True]), R)
    assert float(gap[0, 1]) == pytest.approx(EPS, abs=1e-5)
    assert float(gap[0, 2]) < 0
    assert float(gap[0, 0]) == geo.FAR
    inactive = geo.drone_clearance(pos, jnp.array([True, True, False]), R)
    assert float(inactive[0, 2]) == geo.FAR


def test_gate_frame_collision_distance():
    gp, gy = gate()
    edge = 1.0 + 0.3 + 0.025  # centreline of the right bar (y)
    near = jnp.array([[2.0, edge - 0.025 - R - EPS, 1.0]])
    hit = jnp.array([[2.0, edge - 0.025 - R + EPS, 1.0]])
    assert float(geo.gate_clearance(near, gp, geo.horizontal(gy), 0.3, 0.05, R)[0, 0]) == pytest.approx(EPS, abs=1e-5)
    assert float(geo.gate_clearance(hit, gp, geo.horizontal(gy), 0.3, 0.05, R)[0, 0]) < 0
    post = jnp.array([[2.0, 1.0, 0.3]])  # the post below the gate
    assert float(geo.gate_clearance(post, gp, geo.horizontal(gy), 0.3, 0.05, R)[0, 0]) < 0
    centre = jnp.array([[2.0, 1.0, 1.0]])
    assert float(geo.gate_clearance(centre, gp, geo.horizontal(gy), 0.3, 0.05, R)[0, 0]) > 0.2


@pytest.mark.parametrize("xp", [np, jnp])
def test_gate_clearance_closed_form_matches_the_frame_segments(xp):
    rng = np.random.default_rng(0)
    centre, yaw, half, bar = np.array([[1.0, -2.0, 1.2], [-1.0, 0.5, 0.9]]), np.array([0.7, -2.0]), 0.3, 0.05
    frames = geo.gate_frames(centre, yaw, half, bar)  # [G, 5, 2, 3]: the four bars and the post
    pts = rng.uniform([-2.0, -3.0, -0.1], [2.0, 1.5, 2.2], (3000, 3))
    want = np.min(geo.point_segment_distance(pts[:, None, None], frames[None, :, :, 0], frames[None, :, :, 1]), -1)
    got = geo.gate_clearance(xp.asarray(pts), xp.asarray(centre), geo.horizontal(xp.asarray(yaw)), half, bar, R)
    np.testing.assert_allclose(np.asarray(got), want - bar / 2 - R, atol=1e-5)
    assert np.min(want) < 0.05  # some points lie near a bar or the post, not only far away


def test_bounds():
    lo, hi = (-1.0, -1.0, 0.0), (1.0, 1.0, 2.0)
    pos = jnp.array([[0.99, 0, 1], [1.01, 0, 1], [0, 0, 2.01], [0, 0, -0.5]])
    assert np.asarray(geo.out_of_bounds(pos, lo, hi)).tolist() == [False, True, True, False]  # floor is apart


def _fly(env, state, cmd, steps):
    """Fly until done; returns the last state before the collision step and the final state."""
    step = jax.jit(env.step)
    prev = state
    for _ in range(steps):
        prev, state = state, step(state, cmd)
        if state.done:
            break
    return prev, state


def _hover_env(**kw):
    return make("hover", layout_jitter=0.0, episode_seconds=10.0, **kw)


def test_env_reports_obstacle_collision_when_flying_into_a_cylinder():
    env = make("obstacles", num_agents=1, num_obstacles=1, layout_jitter=0.0)
    s = jax.jit(env.reset)(jax.random.PRNGKey(0))
    p = s.layout.start_pos[0]
    # Put the cylinder 1 m ahead on the drone's path (+x).
    lay = s.layout.replace(cyl_center=jnp.array([[p[0] + 1.0, p[1]]]))
    s = s.replace(layout=lay)
    prev, s = _fly(env, s, jnp.array([[1.0, 0.0, 0.0]]), 200)
    assert bool(s.tracker.collided[0]) and int(s.tracker.collision_kind[0]) == col.OBSTACLE
    assert not bool(prev.tracker.collided[0])
    dist = lambda st: float(jnp.linalg.norm(st.data.qpos[:2] - lay.cyl_center[0]))  # noqa: E731
    assert dist(prev) > 0.15 + R > dist(s)  # not before contact; on the env step that makes it
    assert float(s.reward[0]) == -100.0 and float(s.cost[0]) == 1.0 and float(s.done) == 1.0


def test_env_reports_floor_collision():
    env = _hover_env()
    prev, s = _fly(env, jax.jit(env.reset)(jax.random.PRNGKey(0)), jnp.array([[0.0, 0.0, -1.0]]), 200)
    assert int(s.tracker.collision_kind[0]) == col.FLOOR
    assert float(prev.data.qpos[2]) > R > float(s.data.qpos[2])


def test_env_reports_drone_collision():
    env = make("obstacles", num_agents=2, num_obstacles=0, layout_jitter=0.0)
    s = jax.jit(env.reset)(jax.random.PRNGKey(0))
    sep = float(jnp.linalg.norm(s.layout.start_pos[0] - s.layout.start_pos[1]))
    prev, s = _fly(env, s, jnp.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]]), 200)
    assert np.asarray(s.tracker.collision_kind).tolist() == [col.DRONE, col.DRONE]
    gap = lambda st: float(jnp.linalg.norm(st.data.qpos[:3] - st.data.qpos[7:10]))  # noqa: E731
    assert sep > gap(prev) > 2 * R > gap(s)

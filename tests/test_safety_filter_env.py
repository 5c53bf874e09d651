"""The CBF filter in closed loop with the simulator, built from observations only."""

import jax
import jax.numpy as jnp
import pytest

from aswarm import envs
from aswarm.agents import cbf_filter
from aswarm.agents.config import TrainConfig

MARGIN = 0.05


def _run(env, state, command, use_filter, steps=150, gain=2.0, margin=MARGIN):
    step = jax.jit(env.step)
    filt = jax.jit(lambda o, u: cbf_filter.filter_from_obs(env.obs_layout, o, u, jnp.full(o.shape[:-1], gain),
                                                           env.config.max_speed, env.config.cf.collision_radius,
                                                           margin))
    for _ in range(steps):
        u = filt(state.obs, command).u if use_filter else command
        state = step(state, u)
        if state.done:
            break
    return state


@pytest.mark.parametrize("use_filter", [True, False])
def test_constant_command_at_a_cylinder_stops_short_only_with_the_filter(use_filter):
    env = envs.make("obstacles", num_agents=1, num_obstacles=1, layout_jitter=0.0)
    s = env.reset(jax.random.PRNGKey(0))
    p = s.layout.start_pos[0]
    s = s.replace(layout=s.layout.replace(cyl_center=jnp.array([[p[0] + 1.0, p[1]]])))
    s = _run(env, s, jnp.array([[1.5, 0.0, 0.0]]), use_filter)
    gap = float(env.obs_layout.split(s.obs)[1][0, 0, 2])
    if use_filter:
        assert not bool(s.tracker.collided[0])
        assert 0.0 < gap < MARGIN + 0.02  # stopped just outside the margin
    else:
        assert bool(s.tracker.collided[0])


def test_two_drones_flying_head_on_keep_apart_with_the_filter():
    env = envs.make("obstacles", num_agents=2, num_obstacles=0, layout_jitter=0.0)
    s = env.reset(jax.random.PRNGKey(0))
    s = _run(env, s, jnp.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]]), True, steps=120)
    assert not bool(jnp.any(s.tracker.collided))
    assert float(jnp.linalg.norm(s.data.qpos[:3] - s.data.qpos[7:10])) > 2 * env.config.cf.collision_radius


def test_descending_into_the_floor_is_stopped():
    env = envs.make("hover", layout_jitter=0.0)
    s = _run(env, env.reset(jax.random.PRNGKey(0)), jnp.array([[0.0, 0.0, -1.5]]), True, steps=150)
    assert not bool(s.tracker.collided[0])
    assert not bool(s.tracker.finished[0])  # still flying, not a goal reached on the way down
    assert float(s.data.qpos[2]) > env.config.cf.collision_radius


def test_largest_default_gain_is_safe_at_full_speed():
    """The gain range is bounded by what the controller's lag allows: full speed, off-centre, gain_max."""
    cfg = TrainConfig()
    env = envs.make("obstacles", num_agents=1, num_obstacles=1, layout_jitter=0.0)
    s = env.reset(jax.random.PRNGKey(0))
    p = s.layout.start_pos[0]
    s = s.replace(layout=s.layout.replace(cyl_center=jnp.array([[p[0] + 1.5, p[1] + 0.05]])))
    s = _run(env, s, jnp.array([[env.config.max_speed, 0.0, 0.0]]), True, gain=cfg.gain_max,
             margin=cfg.filter_margin)
    assert not bool(s.tracker.collided[0])

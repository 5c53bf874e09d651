"""MPPI baseline: obstacle avoidance closed loop (and its failure without the obstacle cost), shapes under
jit/vmap, the gate-frame distance, and the evaluation helper."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from aswarm import envs
from aswarm.baselines.mpc import MPCConfig, make_mpc_policy, rollout_mpc
from aswarm.envs import collisions as col
from aswarm.envs.dynamics import drone_state

STEPS = 150  # 3 s: the 2.75 m flight takes ~2 s


def _one_cylinder_in_the_way():
    """One drone at (-4, 0, 1), its goal at (-1.25, 0, 1) and one cylinder halfway, on the straight line."""
    env = envs.make("obstacles", num_agents=1, num_obstacles=1, layout_jitter=0.0, episode_seconds=STEPS / 50)
    s = jax.jit(env.reset)(jax.random.PRNGKey(0))
    start = np.asarray(s.layout.start_pos[0])
    goal = start + np.array([2.75, 0.0, 0.0])
    centre = (start[:2] + goal[:2]) / 2
    layout = s.layout.replace(waypoints=jnp.asarray(goal, jnp.float32)[None, None],
                              cyl_center=jnp.asarray(centre, jnp.float32)[None])
    s = s.replace(layout=layout, obs=jax.jit(env._observe)(drone_state(s.data, 1), layout, s.tracker, s.data.time))
    # The cylinder blocks the straight line: its surface is within the drone's radius of the line.
    assert np.linalg.norm(np.cross(np.append(centre - start[:2], 0), np.append(goal[:2] - start[:2], 0))) < 1e-6
    assert 1.0 < np.linalg.norm(centre - start[:2]) < np.linalg.norm(goal[:2] - start[:2]) - 1.0
    return env, s


def _fly(env, state, config):
    policy = make_mpc_policy(env, config)

    @jax.jit
    def run(state, key):
        def body(c, i):
            s, carry = c
            carry, cmd = policy.act(carry, s.obs, jax.random.fold_in(key, i))
            nxt = env.step(s, cmd)
            nxt = jax.tree.map(lambda a, b: jnp.where(s.done > 0, a, b), s, nxt)  # hold the final state
            return (nxt, carry), None

        return jax.lax.scan(body, (state, policy.init()), jnp.arange(STEPS))[0][0]

    return run(state, jax.random.PRNGKey(1)).tracker


SMALL = dict(samples=32, horizon=12)


def test_mpc_flies_around_a_cylinder_to_its_goal():
    env, s = _one_cylinder_in_the_way()
    tr = _fly(env, s, MPCConfig(**SMALL))
    assert not bool(tr.collided[0]), f"collision of kind {col.KINDS[int(tr.collision_kind[0])]}"
    assert float(tr.min_clearance[0]) > 0.0
    assert bool(tr.finished[0])


def test_without_the_obstacle_cost_the_mpc_hits_the_cylinder():
    env, s = _one_cylinder_in_the_way()
    tr = _fly(env, s, MPCConfig(**SMALL, obstacle_weight=0.0, shadow_weight=0.0))
    assert bool(tr.collided[0]) and int(tr.collision_kind[0]) == col.OBSTACLE


def test_act_shapes_under_jit_and_vmap():
    env = envs.make("race")
    config = MPCConfig(samples=8, horizon=4)
    policy = make_mpc_policy(env, config)
    worlds, n = 3, env.num_agents
    reset = jax.jit(env.reset)
    obs = jnp.stack([reset(jax.random.PRNGKey(i)).obs for i in range(worlds)])
    carry = policy.init((worlds,))
    chex.assert_shape(carry.nominal, (worlds, n, config.horizon, 3))
    act = jax.jit(policy.act)
    carry2, cmd = act(carry, obs, jax.random.PRNGKey(1))
    chex.assert_shape(cmd, (worlds, n, 3))
    chex.assert_trees_all_equal_shapes(carry, carry2)
    assert np.all(np.isfinite(cmd)) and np.all(np.abs(cmd) <= env.config.max_speed + 1e-6)
    np.testing.assert_array_equal(cmd, act(carry, obs, jax.random.PRNGKey(1))[1])  # same key, same plan
    # One world at a time under vmap (traced only: the batched call above already compiled the same maths).
    per_world = jax.eval_shape(jax.vmap(policy.act), carry, obs, jax.random.split(jax.random.PRNGKey(2), worlds))
    chex.assert_shape(per_world[1], (worlds, n, 3))
    chex.assert_shape(per_world[0].nominal, (worlds, n, config.horizon, 3))


def test_the_gate_just_passed_is_remembered():
    env = envs.make("lab")
    policy = make_mpc_policy(env, MPCConfig(samples=8, horizon=4))
    act = jax.jit(policy.act)
    obs = jax.jit(env.reset)(jax.random.PRNGKey(0)).obs  # drones at rest: no dead-reckoning drift
    own = env.obs_layout.own_slices
    carry, _ = act(policy.init(), obs, jax.random.PRNGKey(1))
    assert not np.any(carry.passed_gate[:, 6])
    # The current gate jumps to the next one, as when the drone passes it.
    passed = obs.at[:, own["target_rel"]].set(obs[:, own["next_target_rel"]])
    carry, _ = act(carry, passed, jax.random.PRNGKey(2))
    np.testing.assert_allclose(carry.passed_gate[:, :3], -obs[:, own["target_rel"]], atol=1e-6)
    np.testing.assert_allclose(carry.passed_gate[:, 3:6], obs[:, own["target_normal"]])
    assert np.all(carry.passed_gate[:, 6] == 1)


def test_rollout_mpc_returns_each_episodes_metrics():
    env = envs.make("hover", episode_seconds=0.3)
    rec = rollout_mpc(env, MPCConfig(samples=8, horizon=4), 2, jax.random.PRNGKey(0), chunk=5)
    chex.assert_shape([rec["success"], rec["collision"], rec["episode_length"]], (2,))
    assert np.all(np.asarray(rec["episode_length"]) > 0)


@pytest.mark.parametrize("bad", [dict(samples=2), dict(horizon=0), dict(noise_bank=1000), dict(temperature=0.0)])
def test_bad_config_is_refused(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        MPCConfig(**bad)


def test_rollout_mpc_starts_the_episodes_its_reset_keys_name():
    # One step: each episode's clearance is its layout's, so swapping the keys swaps the episodes.
    env = envs.make("obstacles", num_agents=2, episode_seconds=env_dt(), layout_jitter=1.0)
    keys = jax.random.split(jax.random.PRNGKey(3), 2)
    config = MPCConfig(samples=4, horizon=2)
    a = rollout_mpc(env, config, 2, jax.random.PRNGKey(0), chunk=1, reset_keys=keys)["min_clearance"]
    b = rollout_mpc(env, config, 2, jax.random.PRNGKey(0), chunk=1, reset_keys=keys[::-1])["min_clearance"]
    assert abs(float(a[0] - a[1])) > 0.05  # two different layouts
    np.testing.assert_allclose(np.asarray(b), np.asarray(a)[::-1], atol=0.02)
    with pytest.raises(ValueError, match="3 keys for 2 episodes"):
        rollout_mpc(env, config, 2, jax.random.PRNGKey(0), reset_keys=jax.random.split(keys[0], 3))


def env_dt() -> float:
    return 1.0 / envs.EnvConfig().policy_freq

"""The JaxMARL and PettingZoo interfaces (``aswarm.envs.jaxmarl``, ``aswarm.envs.pettingzoo``) against the native env.

CI installs the ``interfaces`` extra, so these run there: nothing here is skipped when jaxmarl or pettingzoo is
missing.
"""

import warnings

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from pettingzoo.test import parallel_api_test, parallel_seed_test

from aswarm.envs import jaxmarl as marl
from aswarm.envs import pettingzoo as pz
from aswarm.envs.dynamics import drone_state

# 2 drones, 2 cylinders, 5 env steps per episode: a 12-step rollout crosses two auto-resets.
MARL = dict(num_agents=2, num_obstacles=2, episode_seconds=0.2)
# 2 drones, no cylinders, 200 steps per episode: long enough for one drone to reach its goal.
PZ = dict(num_agents=2, num_obstacles=0, episode_seconds=8.0)
WORLDS, STEPS = 2, 12


@pytest.fixture(scope="module")
def menv():
    return marl.make("obstacles", **MARL)


def _random_actions(key, env):
    return jax.random.uniform(key, (STEPS, WORLDS, env.num_agents, 3), minval=-1.0, maxval=1.0) * env.config.max_speed


def test_jaxmarl_rollout_matches_native_env_step_for_step(menv):
    env = menv.env
    reset_keys = jax.random.split(jax.random.PRNGKey(0), WORLDS)
    step_keys = jax.random.split(jax.random.PRNGKey(1), STEPS * WORLDS).reshape(STEPS, WORLDS, -1)
    actions = _random_actions(jax.random.PRNGKey(2), env)

    @jax.jit
    def rollout(reset_keys, step_keys, actions):
        obs, state = jax.vmap(menv.reset)(reset_keys)

        def body(carry, xs):
            obs, state = carry
            keys, act = xs
            act = {a: act[:, i] for i, a in enumerate(menv.agents)}
            obs, state, rew, dones, infos = jax.vmap(menv.step)(keys, state, act)
            return (obs, state), (obs, rew, dones, infos)

        return obs, jax.lax.scan(body, (obs, state), (step_keys, actions))[1]

    obs0, (obs, rew, dones, infos) = rollout(reset_keys, step_keys, actions)
    n, d = env.num_agents, env.observation_size
    assert menv.agents == ["drone_0", "drone_1"]
    chex.assert_shape([obs0["drone_0"], obs["drone_1"]], [(WORLDS, d), (STEPS, WORLDS, d)])
    chex.assert_shape(obs["world_state"], (STEPS, WORLDS, menv.state_size))
    assert menv.state_size == n * d
    chex.assert_shape([rew["drone_0"], dones["__all__"], infos["truncated"], infos["success"]],
                      [(STEPS, WORLDS), (STEPS, WORLDS), (STEPS, WORLDS, n), (STEPS, WORLDS, n)])

    reset, step = jax.jit(env.reset), jax.jit(env.step)
    for b in range(WORLDS):
        s = reset(reset_keys[b])
        np.testing.assert_allclose(np.stack([obs0[a][b] for a in menv.agents]), s.obs, atol=1e-5)
        for t in range(STEPS):
            nxt = step(s, actions[t, b])
            stopped = (nxt.done > 0) | nxt.tracker.finished | nxt.tracker.collided
            for i, a in enumerate(menv.agents):
                np.testing.assert_allclose(rew[a][t, b], nxt.reward[i], atol=1e-5)
                assert bool(dones[a][t, b]) == bool(stopped[i])
            assert bool(dones["__all__"][t, b]) == bool(nxt.done > 0)
            assert bool(infos["truncated"][t, b, 0]) == bool(nxt.truncated > 0)
            # JaxMARL's auto-reset: the new episode is drawn from split(step key)[1].
            s = reset(jax.random.split(step_keys[t, b])[1]) if nxt.done > 0 else nxt
            np.testing.assert_allclose(np.stack([obs[a][t, b] for a in menv.agents]), s.obs, atol=1e-4)
            np.testing.assert_allclose(obs["world_state"][t, b], s.critic_obs, atol=1e-4)
    # The time limit (5 steps) ended both worlds' episodes twice, with truncation, not termination.
    assert np.asarray(dones["__all__"]).sum(0).tolist() == [2, 2]
    assert np.all(np.asarray(infos["truncated"])[np.asarray(dones["__all__"])])


def test_jaxmarl_step_with_a_given_reset_state(menv):
    act = {a: jnp.zeros(3) for a in menv.agents}

    @jax.jit
    def run(key):
        obs, state = menv.reset(key)
        _, given = menv.reset(jax.random.PRNGKey(99))

        def body(state, k):
            obs, state, rew, dones, _ = menv.step(k, state, act, reset_state=given)
            return state, (obs, dones["__all__"], state.tracker.steps)

        return given, jax.lax.scan(body, state, jax.random.split(key, 6))[1]

    given, (obs, done, steps) = run(jax.random.PRNGKey(5))
    assert np.asarray(done).tolist() == [False] * 4 + [True, False]
    assert np.asarray(steps).tolist() == [1, 2, 3, 4, 0, 1]  # the given state started the next episode
    np.testing.assert_array_equal(obs["drone_1"][4], given.obs[1])
    np.testing.assert_array_equal(obs["world_state"][4], given.critic_obs)


def test_jaxmarl_spaces_and_world_state(menv):
    env = menv.env
    assert menv.num_agents == 2 and menv.agent_classes == {"drone": ["drone_0", "drone_1"]}
    space = menv.action_space("drone_1")
    assert space.shape == (3,) and space.low == -env.config.max_speed and space.high == env.config.max_speed
    assert bool(space.contains(space.sample(jax.random.PRNGKey(0))))
    assert menv.observation_space("drone_0").shape == (env.observation_size,)
    key = jax.random.PRNGKey(3)
    obs, state = menv.reset(key)
    np.testing.assert_array_equal(menv.get_world_state(state), obs["world_state"])
    # The world state holds every drone's exact observation (the policy's are noisy: domain randomisation).
    exact = env._observe(drone_state(state.data, 2), state.layout, state.tracker, jnp.zeros(()))
    np.testing.assert_allclose(obs["world_state"], exact.reshape(-1), atol=1e-6)
    assert set(menv.get_avail_actions(state)) == set(menv.agents)


def test_jaxmarl_bad_input_raises_clear_errors(menv):
    _, state = menv.reset(jax.random.PRNGKey(0))
    key, ok = jax.random.PRNGKey(1), jnp.zeros(3)
    with pytest.raises(ValueError, match="unknown agent 'agent_0'.*allowed: drone_0, drone_1"):
        menv.step(key, state, {"drone_0": ok, "drone_1": ok, "agent_0": ok})
    with pytest.raises(ValueError, match="no action for agent 'drone_1'"):
        menv.step(key, state, {"drone_0": ok})
    with pytest.raises(ValueError, match=r"action for 'drone_0' has shape \(2,\): allowed shape is \(3,\)"):
        menv.step(key, state, {"drone_0": jnp.zeros(2), "drone_1": ok})
    with pytest.raises(ValueError, match="must be a dict"):
        menv.step(key, state, jnp.zeros((2, 3)))
    with pytest.raises(ValueError, match="unknown scenario 'racing': allowed: hover"):
        marl.make("racing")


# ------------------------------------------------------------------------------------------------ PettingZoo
@pytest.fixture(scope="module")
def penv():
    return pz.parallel_env("obstacles", render_mode="rgb_array", **PZ)


def test_pettingzoo_passes_the_parallel_api_and_seed_tests(penv):
    with warnings.catch_warnings():
        warnings.filterwarnings("error", module=r"pettingzoo\.")  # its checks only warn
        parallel_api_test(penv, num_cycles=250)  # random commands: episodes end by collision or time limit
        parallel_seed_test(lambda: pz.parallel_env("obstacles", **PZ), num_cycles=50)


def test_pettingzoo_spaces(penv):
    env = penv.env
    assert penv.possible_agents == ["drone_0", "drone_1"]
    assert penv.metadata["name"] == "aswarm_obstacles_v0" and penv.metadata["render_fps"] == 25
    obs, infos = penv.reset(seed=0)
    assert penv.agents == penv.possible_agents and set(infos) == set(penv.agents)
    for a in penv.agents:
        assert penv.observation_space(a) is penv.observation_space(a)
        assert penv.observation_space(a).contains(obs[a]) and obs[a].dtype == np.float32
        box = penv.action_space(a)
        assert box.shape == (3,) and np.all(box.high == env.config.max_speed) and np.all(box.low == -box.high)
    assert penv.state().shape == penv.state_space.shape == (2 * env.observation_size,)


def test_pettingzoo_seeding_is_reproducible():
    one, two = pz.parallel_env("obstacles", **PZ), pz.parallel_env("obstacles", **PZ)
    runs = []
    for env, seeds in ((one, (7, None)), (two, (7, None)), (one, (8,))):
        obs = [env.reset(seed=s)[0]["drone_1"] for s in seeds]  # None: the next episode of seed 7's stream
        act = {a: np.array([0.5, -0.3, 0.2], np.float32) for a in env.agents}
        obs.append(env.step(act)[0]["drone_1"])
        runs.append(np.stack(obs))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.allclose(runs[0][0], runs[0][1])  # reset() without a seed gives a new layout
    assert not np.allclose(runs[0][0], runs[2][0])  # so does another seed


def _fly(env, policy, limit=400):
    """Step until no agent is left; returns every step's (agents before, terminations, truncations, infos)."""
    out = []
    obs = env.reset(seed=1)[0]
    for _ in range(limit):
        if not env.agents:
            return out
        before = list(env.agents)
        obs, _, term, trunc, infos = env.step({a: policy(a, obs[a]) for a in env.agents})
        out.append((before, term, trunc, infos))
    raise AssertionError(f"episode did not end in {limit} steps")


def test_pettingzoo_finished_drone_leaves_and_time_limit_truncates(penv):
    # drone_0 flies to its goal (the observation starts with its position minus the goal); drone_1 hovers.
    steps = _fly(penv, lambda a, o: np.clip(-1.5 * o[:3], -2, 2) if a == "drone_0" else np.zeros(3))
    landed = next(k for k, (_, term, _, _) in enumerate(steps) if term.get("drone_0"))
    _, term, trunc, infos = steps[landed]
    assert infos["drone_0"]["finished"] and not trunc["drone_0"] and not term["drone_1"]
    assert steps[landed + 1][0] == ["drone_1"]  # it left the agents; the other flies on
    before, term, trunc, infos = steps[-1]
    assert len(steps) == penv.env.config.max_steps and before == ["drone_1"]
    assert trunc == {"drone_1": True} and term == {"drone_1": False}
    assert infos["drone_1"]["episode"]["drone_success"] == 0.5
    with pytest.raises(ValueError, match="call reset"):
        penv.step({})


def test_pettingzoo_collision_terminates_every_drone(penv):
    steps = _fly(penv, lambda a, o: np.array([0.0, 0.0, -2.0]))  # into the floor
    before, term, trunc, infos = steps[-1]
    assert before == ["drone_0", "drone_1"] and len(steps) < 100
    assert term == {"drone_0": True, "drone_1": True} and not any(trunc.values())
    assert any(i["collided"] for i in infos.values()) and infos["drone_0"]["episode"]["collision_floor"] == 1.0


def test_pettingzoo_bad_input_raises_clear_errors(penv):
    penv.reset(seed=0)
    ok = np.zeros(3)
    with pytest.raises(ValueError, match="unknown agent 'drone_7': allowed: drone_0, drone_1"):
        penv.step({"drone_0": ok, "drone_1": ok, "drone_7": ok})
    with pytest.raises(ValueError, match="no action for agent 'drone_0'"):
        penv.step({"drone_1": ok})
    with pytest.raises(ValueError, match=r"action for 'drone_1' has shape \(4,\): allowed shape is \(3,\)"):
        penv.step({"drone_0": ok, "drone_1": np.zeros(4)})
    with pytest.raises(ValueError, match="not finite"):
        penv.step({"drone_0": ok, "drone_1": np.array([0.0, np.nan, 0.0])})
    with pytest.raises(ValueError, match="unknown agent 'agent_0'"):
        penv.action_space("agent_0")
    with pytest.raises(ValueError, match="invalid seed -1"):
        penv.reset(seed=-1)
    with pytest.raises(ValueError, match="unknown render_mode 'human': allowed: None, rgb_array"):
        pz.parallel_env("obstacles", render_mode="human", **PZ)


def test_pettingzoo_render_draws_the_arena(penv):
    penv.reset(seed=2)
    first = penv.render()
    assert first.shape == (480, 480, 3) and first.dtype == np.uint8
    assert len(np.unique(first.reshape(-1, 3), axis=0)) > 10  # arena, drones and goals in colour, not a blank
    for _ in range(10):
        penv.step({a: np.array([2.0, 0.0, 0.0]) for a in penv.agents})
    assert not np.array_equal(first, penv.render())  # the drones moved
    quiet = pz.parallel_env("obstacles", **PZ)
    quiet.reset(seed=0)
    with pytest.warns(UserWarning, match="render_mode='rgb_array'"):
        assert quiet.render() is None

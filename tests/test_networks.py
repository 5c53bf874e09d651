"""Networks: shapes, attention normalization, permutation equivariance, masking."""

import chex
import jax
import jax.numpy as jnp
import numpy as np

from aswarm import envs
from aswarm.agents.config import TrainConfig
from aswarm.agents.networks import hazard_mask
from aswarm.agents.train import Agent


def _agent(**kw):
    return Agent.build(TrainConfig(scenario="race", **kw))


def test_shapes_and_attention_weights_sum_to_one():
    agent = _agent()
    env = agent.env
    params = jax.jit(agent.init_params)(jax.random.PRNGKey(0))
    obs = jax.jit(env.reset)(jax.random.PRNGKey(1)).obs
    nobs = obs  # normalization is the identity for these checks
    theta, alpha = agent.cbf.apply(params["cbf"], nobs, hazard_mask(env.obs_layout, obs))
    n, h = env.num_agents, env.config.num_cylinders + env.num_agents - 1
    chex.assert_shape(theta, (n, 2))
    chex.assert_shape(alpha, (n, h))
    np.testing.assert_allclose(alpha.sum(-1), 1.0, rtol=1e-5)
    assert (np.asarray(theta[:, 0]) >= 0).all()
    cfg = agent.config.safety_filter
    assert ((np.asarray(theta[:, 1]) >= cfg.gain_min) & (np.asarray(theta[:, 1]) <= cfg.gain_max)).all()
    chex.assert_shape(agent.actor.apply(params["actor"], obs), (n, 6))
    chex.assert_shape(agent.critic.apply(params["critic"], obs.reshape(-1)), (n,))


def test_attention_is_permutation_equivariant_in_obstacles():
    agent = _agent()
    env = agent.env
    lay = env.obs_layout
    params = jax.jit(agent.init_params)(jax.random.PRNGKey(0))
    obs = jax.jit(env.reset)(jax.random.PRNGKey(2)).obs
    own, cyl, nbr = lay.split(obs)
    perm = np.random.default_rng(0).permutation(lay.num_cylinders)
    obs_p = jnp.concatenate([own, cyl[:, perm].reshape(obs.shape[0], -1), nbr.reshape(obs.shape[0], -1)], -1)
    t1, a1 = agent.cbf.apply(params["cbf"], obs, hazard_mask(lay, obs))
    t2, a2 = agent.cbf.apply(params["cbf"], obs_p, hazard_mask(lay, obs_p))
    np.testing.assert_allclose(t1, t2, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(a1[:, : lay.num_cylinders][:, perm], a2[:, : lay.num_cylinders], rtol=1e-5, atol=1e-7)


def test_absent_obstacles_get_zero_weight():
    env = envs.make("dynamic", min_moving=1)
    agent = Agent.build(TrainConfig(scenario="dynamic"), env)
    params = jax.jit(agent.init_params)(jax.random.PRNGKey(0))
    reset = jax.jit(env.reset)
    for seed in range(5):
        obs = reset(jax.random.PRNGKey(seed)).obs
        mask = hazard_mask(env.obs_layout, obs)
        _, alpha = agent.cbf.apply(params["cbf"], obs, mask)
        assert float(jnp.max(jnp.where(mask, 0.0, alpha))) == 0.0
        np.testing.assert_allclose(alpha.sum(-1), 1.0, rtol=1e-5)


def test_no_hazards_gives_zero_context_not_nan():
    env = envs.make("hover")
    agent = Agent.build(TrainConfig(scenario="hover"), env)
    params = jax.jit(agent.init_params)(jax.random.PRNGKey(0))
    obs = jax.jit(env.reset)(jax.random.PRNGKey(0)).obs
    theta, alpha = agent.cbf.apply(params["cbf"], obs, hazard_mask(env.obs_layout, obs))
    assert alpha.shape == (1, 0) and np.isfinite(np.asarray(theta)).all()


def test_paper_sizes_are_one_flag_away():
    agent = _agent(cbf_hidden=(1024, 256), cbf_embed=3)
    params = jax.eval_shape(agent.init_params, jax.random.PRNGKey(0))
    kernels = [x.shape for x in jax.tree.leaves(params["cbf"]) if x.ndim == 2]
    assert (1024, 256) in kernels and any(k[1] == 3 for k in kernels)


def test_pooled_critic_is_per_drone_equivariant_and_the_same_size_for_any_swarm():
    from aswarm.agents.networks import PooledCritic

    d = 5
    obs = jax.random.normal(jax.random.PRNGKey(0), (3, 4, d))  # [batch, drones, D]
    critic = PooledCritic(num_agents=4, hidden=(16,))
    params = critic.init(jax.random.PRNGKey(1), obs.reshape(3, -1))
    v = critic.apply(params, obs.reshape(3, -1))
    chex.assert_shape(v, (3, 4))
    perm = np.array([2, 0, 3, 1])
    v_p = critic.apply(params, obs[:, perm].reshape(3, -1))
    np.testing.assert_allclose(v_p, v[:, perm], rtol=1e-5, atol=1e-6)
    # The same weights value a swarm of 16: its parameters do not depend on the number of drones.
    big = jax.random.normal(jax.random.PRNGKey(2), (16 * d,))
    chex.assert_shape(PooledCritic(num_agents=16, hidden=(16,)).apply(params, big), (16,))
    assert jax.tree.map(jnp.shape, params) == jax.tree.map(
        jnp.shape, PooledCritic(num_agents=16, hidden=(16,)).init(jax.random.PRNGKey(1), big))


def test_pooled_critic_fits_values_that_depend_on_the_whole_swarm():
    import optax

    from aswarm.agents.networks import PooledCritic

    # Each drone's value: its own first feature plus the swarm's mean second feature (what one drone's return
    # owes to the others), which a per-drone MLP without the pooled context could not fit.
    obs = jax.random.normal(jax.random.PRNGKey(0), (256, 6, 4))
    target = obs[..., 0] + 2.0 * obs[..., 1].mean(-1, keepdims=True)
    critic = PooledCritic(num_agents=6, hidden=(32, 32))
    params = critic.init(jax.random.PRNGKey(1), obs.reshape(256, -1))
    opt = optax.adam(3e-3)

    @jax.jit
    def step(params, opt_state):
        loss, g = jax.value_and_grad(lambda p: jnp.mean((critic.apply(p, obs.reshape(256, -1)) - target) ** 2))(params)
        updates, opt_state = opt.update(g, opt_state)
        return optax.apply_updates(params, updates), opt_state, loss

    opt_state = opt.init(params)
    losses = []
    for _ in range(400):
        params, opt_state, loss = step(params, opt_state)
        losses.append(float(loss))
    assert losses[-1] < 0.05 * losses[0], (losses[0], losses[-1])


def test_pooled_critic_is_a_config_choice():
    from aswarm.agents import config, networks

    assert set(config.CRITICS) == set(networks.CRITICS)  # the names the config allows are the modules there are
    agent = _agent(critic="pooled")
    params = jax.eval_shape(agent.init_params, jax.random.PRNGKey(0))
    obs = jnp.zeros((agent.env.num_agents, agent.env.observation_size))
    chex.assert_shape(jax.eval_shape(agent.critic.apply, params["critic"], obs.reshape(-1)), (agent.env.num_agents,))
    with np.testing.assert_raises_regex(ValueError, "invalid critic='deep': allowed: joint, pooled"):
        TrainConfig(critic="deep")

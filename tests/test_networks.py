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

"""GAE and the PPO / penalty losses against hand-computed cases."""

import jax.numpy as jnp
import numpy as np
import pytest

from aswarm.agents import losses


def test_gae_hand_computed_with_termination():
    g, lam = 0.9, 0.5
    r = jnp.array([1.0, 2.0, 3.0])
    v = jnp.array([0.5, 1.0, 1.5])
    nv = jnp.array([1.0, 1.5, 9.0])  # V(s_{t+1}); the last is the terminal state's (ignored)
    done = jnp.array([0.0, 0.0, 1.0])
    trunc = jnp.zeros(3)
    adv, tgt = losses.gae(r, v, nv, done, trunc, g, lam)
    d2 = 3.0 - 1.5  # terminated: no bootstrap
    d1 = 2.0 + g * 1.5 - 1.0
    d0 = 1.0 + g * 1.0 - 0.5
    a2, a1 = d2, d1 + g * lam * d2
    a0 = d0 + g * lam * a1
    np.testing.assert_allclose(adv, [a0, a1, a2], rtol=1e-6)
    np.testing.assert_allclose(tgt, np.array([a0, a1, a2]) + np.array(v), rtol=1e-6)


def test_gae_bootstraps_on_truncation_but_does_not_leak_across_episodes():
    g, lam = 0.9, 0.5
    r = jnp.array([1.0, 1.0])
    v = jnp.array([0.0, 0.0])
    nv = jnp.array([4.0, 2.0])  # step 0 ends an episode by truncation with true last value 4
    done = jnp.array([1.0, 0.0])
    trunc = jnp.array([1.0, 0.0])
    adv, _ = losses.gae(r, v, nv, done, trunc, g, lam)
    assert float(adv[0]) == pytest.approx(1.0 + g * 4.0)  # bootstrapped, nothing from step 1
    assert float(adv[1]) == pytest.approx(1.0 + g * 2.0)


def test_gae_broadcasts_world_done_over_agents():
    r = jnp.ones((2, 3, 4))  # [T, B, n]
    adv, _ = losses.gae(r, jnp.zeros_like(r), jnp.zeros_like(r), jnp.ones((2, 3)), jnp.zeros((2, 3)), 0.9, 0.9)
    np.testing.assert_allclose(adv, 1.0)


def test_ppo_clip_loss_hand_computed():
    adv = jnp.array([1.0, -1.0])
    old = jnp.zeros(2)
    new = jnp.log(jnp.array([1.5, 0.5]))
    # ratio 1.5 clipped to 1.1 for the positive advantage; 0.5 clipped to 0.9 for the negative one
    expected = -np.mean([min(1.5 * 1, 1.1 * 1), min(0.5 * -1, 0.9 * -1)])
    assert float(losses.ppo_clip_loss(new, old, adv, 0.1)) == pytest.approx(expected)


def test_penalized_advantage_and_penalty_loss_directions():
    a, ac = jnp.array([1.0]), jnp.array([2.0])
    np.testing.assert_allclose(losses.penalized_advantage(a, ac, jnp.array([1.0])), [(1 - 2) / 2])
    # Cost above the limit: descending the loss raises the penalty (negative gradient wrt penalty).
    import jax

    grad = jax.grad(lambda p: losses.penalty_loss(p, jnp.zeros(1), jnp.array(0.5)))(jnp.array([1.0]))
    assert float(grad[0]) < 0
    grad = jax.grad(lambda p: losses.penalty_loss(p, jnp.zeros(1), jnp.array(-0.5)))(jnp.array([1.0]))
    assert float(grad[0]) > 0


def test_gain_target_range():
    t = losses.gain_target(jnp.array([0.0, 0.5, 3.0]), 0.5, 10.0)
    np.testing.assert_allclose(t, [10.0, 5.25, 0.5])


def test_policy_gradient_loss_hand_computed_and_gradient():
    import jax

    logp, adv = jnp.array([-1.0, -2.0]), jnp.array([2.0, -1.0])
    assert float(losses.policy_gradient_loss(logp, adv)) == pytest.approx(-((-1 * 2) + (-2 * -1)) / 2)
    # d/dlogp = -A / N: raises the log-probability of actions with positive advantage only
    np.testing.assert_allclose(jax.grad(losses.policy_gradient_loss)(logp, adv), [-1.0, 0.5])

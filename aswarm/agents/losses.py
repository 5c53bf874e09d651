"""GAE and the MAPPO / MAPPO-Lagrangian / attention-CBF losses.

Array axes: T time, B worlds, n drones. ``done`` and ``truncated`` are per world.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def gae(rewards: jax.Array, values: jax.Array, next_values: jax.Array, done: jax.Array, truncated: jax.Array,
        gamma: float, lam: float) -> tuple[jax.Array, jax.Array]:
    """Generalized advantage estimation with truncation apart from termination.

    Args:
      rewards, values: [T, ...]; ``values[t] = V(s_t)``.
      next_values: [T, ...] value of the state reached by step t *before* any
        auto-reset (so a truncated episode bootstraps from its true last state).
      done, truncated: [T] or broadcastable to rewards; ``done`` ends the
        recursion, only ``done - truncated`` (termination) removes the bootstrap.

    Returns:
      (advantages, value targets), both [T, ...].
    """
    done = jnp.broadcast_to(_expand(done, rewards), rewards.shape)
    terminated = done * (1.0 - jnp.broadcast_to(_expand(truncated, rewards), rewards.shape))
    delta = rewards + gamma * (1.0 - terminated) * next_values - values

    def back(acc, x):
        d, dn = x
        acc = d + gamma * lam * (1.0 - dn) * acc
        return acc, acc

    _, adv = jax.lax.scan(back, jnp.zeros_like(rewards[0]), (delta, done), reverse=True)
    return adv, adv + values


def _expand(x: jax.Array, like: jax.Array) -> jax.Array:
    return x.reshape(x.shape + (1,) * (like.ndim - x.ndim))


def normalize(x: jax.Array, eps: float = 1e-8) -> jax.Array:
    return (x - x.mean()) / (x.std() + eps)


def ppo_clip_loss(log_prob: jax.Array, old_log_prob: jax.Array, advantages: jax.Array, clip: float) -> jax.Array:
    """Negative clipped surrogate ``-E[min(r A, clip(r, 1 - eps, 1 + eps) A)]``."""
    ratio = jnp.exp(log_prob - old_log_prob)
    clipped = jnp.clip(ratio, 1.0 - clip, 1.0 + clip)
    return -jnp.mean(jnp.minimum(ratio * advantages, clipped * advantages))


def policy_gradient_loss(log_prob: jax.Array, advantages: jax.Array) -> jax.Array:
    """A2C's ``-E[log pi(a|s) A]`` (one step per rollout, so no ratio and no clipping)."""
    return -jnp.mean(log_prob * jax.lax.stop_gradient(advantages))


def value_loss(values: jax.Array, targets: jax.Array) -> jax.Array:
    return 0.5 * jnp.mean((values - targets) ** 2)


def penalized_advantage(adv: jax.Array, cost_adv: jax.Array, penalty: jax.Array) -> jax.Array:
    """``(A - theta A_c) / (1 + theta)``: the paper's ``A - theta (A_c + d)`` with ``d`` dropped.

    ``d = J_c - c`` does not depend on the action, so it adds nothing to the
    policy gradient; dividing by ``1 + theta`` keeps the step size independent
    of the penalty's scale (as in Safety-Gym's PPO-Lagrangian).
    """
    penalty = jax.lax.stop_gradient(penalty)
    return (adv - penalty * cost_adv) / (1.0 + penalty)


def penalty_loss(penalty: jax.Array, cost_adv: jax.Array, excess: jax.Array) -> jax.Array:
    """The min over psi of ``-theta_psi (A_c + d)``: descent raises theta where cost exceeds its limit.

    ``excess`` is ``d = J_c - c`` (expected episode cost above the limit).
    """
    return -jnp.mean(penalty * jax.lax.stop_gradient(cost_adv + excess))


def gain_target(cost_return: jax.Array, gain_min: float, gain_max: float) -> jax.Array:
    """Hindsight target of the CBF gain: permissive (``gain_max``) where the drone's discounted
    future cost was zero, falling linearly to ``gain_min`` as that cost reaches one full violation."""
    return gain_max - (gain_max - gain_min) * jnp.clip(cost_return, 0.0, 1.0)

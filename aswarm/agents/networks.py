"""Flax networks: the shared actor, the centralized critics and the attention-CBF network.

Shapes: ``n`` drones, ``D`` observation size, ``M`` cylinders, ``n - 1`` neighbours.
"""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from aswarm.core.layout import CYL, NBR, ObsLayout

ACTIVATIONS = {"gelu": nn.gelu, "tanh": nn.tanh, "relu": nn.relu, "silu": nn.silu}


class MLP(nn.Module):
    hidden: Sequence[int]
    out: int
    activation: str = "tanh"
    out_scale: float = 1.0

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        act = ACTIVATIONS[self.activation]
        for h in self.hidden:
            x = act(nn.Dense(h, kernel_init=nn.initializers.orthogonal(jnp.sqrt(2.0)))(x))
        return nn.Dense(self.out, kernel_init=nn.initializers.orthogonal(self.out_scale))(x)


class Actor(nn.Module):
    """Shared-parameter policy: one drone's normalized obs [..., D] -> Gaussian params [..., 6] (pre-tanh)."""

    hidden: Sequence[int] = (128, 128)
    activation: str = "tanh"
    action_size: int = 3

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        return MLP(self.hidden, 2 * self.action_size, self.activation, out_scale=0.01)(obs)


class CentralCritic(nn.Module):
    """Centralized value: the joint normalized obs [..., n * D] -> one value per drone [..., n]."""

    num_agents: int
    hidden: Sequence[int] = (256, 256)
    activation: str = "tanh"

    @nn.compact
    def __call__(self, joint_obs: jax.Array) -> jax.Array:
        return MLP(self.hidden, self.num_agents, self.activation)(joint_obs)


class PooledCritic(nn.Module):
    """Per-drone value from the drone's own normalized obs and the swarm's pooled embedding:
    [..., n * D] -> [..., n].

    One set of weights for every drone and any n: each drone's value is fitted to its own return (rewards are
    per drone) with the rest of the swarm seen through a mean and a max over embedded observations, where the
    joint critic's input, and its noise in each drone's advantage, grow with the swarm.
    """

    num_agents: int
    hidden: Sequence[int] = (256, 256)
    activation: str = "tanh"
    embed: int = 64

    @nn.compact
    def __call__(self, joint_obs: jax.Array) -> jax.Array:
        obs = joint_obs.reshape(*joint_obs.shape[:-1], self.num_agents, -1)
        e = ACTIVATIONS[self.activation](nn.Dense(self.embed)(obs))  # [..., n, E]
        pooled = jnp.concatenate([e.mean(-2, keepdims=True), e.max(-2, keepdims=True)], -1)
        x = jnp.concatenate([obs, jnp.broadcast_to(pooled, (*e.shape[:-1], 2 * self.embed))], -1)
        return MLP(self.hidden, 1, self.activation)(x)[..., 0]


CRITICS = {"joint": CentralCritic, "pooled": PooledCritic}


class AttentionCBF(nn.Module):
    """Attention over hazards (cylinders and neighbours) -> CBF parameters per drone.

    For hazard features x_i: K_i = W_K x_i, V_i = W_V x_i; from the drone's hidden
    state h: Q = W_Q h; alpha = softmax(Q.K / sqrt(d)) over present hazards;
    c = sum_i alpha_i V_i; theta = f_CBF(h, c). theta is ``[penalty, gain]``:
    the safety penalty weighting the cost advantage (>= 0) and the class-K gain
    gamma of the CBF safety filter (in ``[gain_min, gain_max]``, 1/s).
    """

    layout: ObsLayout
    embed: int = 8  # d, key/query dimension (paper: 3)
    hidden: Sequence[int] = (64, 64)  # f_CBF (paper: 1024, 256)
    state_hidden: int = 64
    activation: str = "gelu"
    penalty_max: float = 2.0
    gain_min: float = 0.3
    gain_max: float = 2.0

    @nn.compact
    def __call__(self, obs: jax.Array, hazard_mask: jax.Array) -> tuple[jax.Array, jax.Array]:
        """obs [..., D] normalized, hazard_mask [..., M + n - 1] -> (theta [..., 2], alpha [..., M + n - 1])."""
        act = ACTIVATIONS[self.activation]
        own, cyl, nbr = self.layout.split(obs)
        h = act(nn.Dense(self.state_hidden)(own))
        q = nn.Dense(self.embed, use_bias=False, name="W_Q")(h)
        keys = [nn.Dense(self.embed, use_bias=False, name="W_K_cyl")(cyl),
                nn.Dense(self.embed, use_bias=False, name="W_K_nbr")(nbr)]
        vals = [nn.Dense(self.embed, use_bias=False, name="W_V_cyl")(cyl),
                nn.Dense(self.embed, use_bias=False, name="W_V_nbr")(nbr)]
        k, v = jnp.concatenate(keys, -2), jnp.concatenate(vals, -2)  # [..., H, d]
        logits = jnp.einsum("...d,...hd->...h", q, k) / jnp.sqrt(self.embed)
        # Absent hazards get exactly zero weight; with none present the context is zero.
        alpha = jax.nn.softmax(jnp.where(hazard_mask, logits, -1e9), axis=-1) * hazard_mask
        context = jnp.einsum("...h,...hd->...d", alpha, v)
        out = MLP(self.hidden, 2, self.activation, out_scale=0.1)(jnp.concatenate([h, context], -1))
        penalty = jnp.minimum(jax.nn.softplus(out[..., 0]), self.penalty_max)
        gain = self.gain_min + (self.gain_max - self.gain_min) * jax.nn.sigmoid(out[..., 1])
        return jnp.stack([penalty, gain], -1), alpha


def hazard_mask(layout: ObsLayout, raw_obs: jax.Array) -> jax.Array:
    """[..., M + n - 1] presence flags read from *raw* (unnormalized) observations."""
    _, cyl, nbr = layout.split(raw_obs)
    return jnp.concatenate([CYL.present(cyl), NBR.present(nbr)], -1)

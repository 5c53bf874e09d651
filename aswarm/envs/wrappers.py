"""Brax-style wrappers: batching over worlds and auto-reset."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from aswarm.envs.swarm_env import State


class Wrapper:
    def __init__(self, env):
        self.env = env

    def __getattr__(self, name):
        return getattr(self.env, name)

    def reset(self, key: jax.Array, params=None) -> State:
        return self.env.reset(key, params)

    def step(self, state: State, action: jax.Array) -> State:
        return self.env.step(state, action)


class AutoResetWrapper(Wrapper):
    """Starts a new episode, with a fresh layout, where ``done``.

    The returned state keeps the finished step's reward, cost, done, truncated
    and metrics; its obs belong to the new episode. ``info["final_obs"]`` and
    ``info["final_critic_obs"]`` hold the last observation of the finished
    episode, so a learner can bootstrap on truncation. A new episode keeps the state's ``params`` (and draws
    its own domain randomisation around them).
    """

    def reset(self, key: jax.Array, params=None) -> State:
        state = self.env.reset(key, params)
        info = dict(state.info, reset_key=key, final_obs=state.obs, final_critic_obs=state.critic_obs)
        return state.replace(info=info)

    def step(self, state: State, action: jax.Array) -> State:
        key, new_key = jax.random.split(state.info["reset_key"])
        inner = state.replace(info={k: v for k, v in state.info.items()
                                    if k not in ("reset_key", "final_obs", "final_critic_obs")})
        nxt = self.env.step(inner, action)
        fresh = self.env.reset(new_key, state.params)
        done = nxt.done > 0
        pick = lambda a, b: jax.tree.map(lambda x, y: jnp.where(done, x, y), a, b)  # noqa: E731
        out = nxt.replace(
            data=pick(fresh.data, nxt.data), obs=pick(fresh.obs, nxt.obs),
            critic_obs=pick(fresh.critic_obs, nxt.critic_obs), layout=pick(fresh.layout, nxt.layout),
            tracker=pick(fresh.tracker, nxt.tracker), onboard=pick(fresh.onboard, nxt.onboard),
            filter_obs=pick(fresh.filter_obs, nxt.filter_obs),
        )
        info = dict(nxt.info, reset_key=key, final_obs=nxt.obs, final_critic_obs=nxt.critic_obs)
        return out.replace(info=info)


class VmapWrapper(Wrapper):
    """Batches ``reset``/``step`` over a leading world axis; ``reset`` takes [B] keys or one key and ``batch_size``,
    and ``params`` for every world (``EnvParams``) or one per world (a leading [B] axis, ``params.stack``)."""

    def __init__(self, env, batch_size: int | None = None):
        super().__init__(env)
        self.batch_size = batch_size

    def reset(self, key: jax.Array, params=None) -> State:
        if self.batch_size is not None and key.ndim == 1:
            key = jax.random.split(key, self.batch_size)
        if params is None:
            return jax.vmap(self.env.reset)(key)
        # One value per world when the (scalar) mass has a leading axis; else the same params for every world.
        per_world = jnp.ndim(getattr(getattr(params, "cf", None), "mass", 0.0)) > 0  # else reset says what is wrong
        return jax.vmap(self.env.reset, in_axes=(0, 0 if per_world else None))(key, params)

    def step(self, state: State, action: jax.Array) -> State:
        return jax.vmap(self.env.step)(state, action)


def wrap_for_training(env, batch_size: int) -> Wrapper:
    return VmapWrapper(AutoResetWrapper(env), batch_size)

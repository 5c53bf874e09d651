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


# What a new episode replaces; the finished step's reward, cost, done, truncated and metrics stay.
_EPISODE = ("data", "obs", "critic_obs", "layout", "tracker", "onboard", "filter_obs")
_AUTO_INFO = ("reset_key", "final_obs", "final_critic_obs")


def _episode(state: State) -> dict:
    return {f: getattr(state, f) for f in _EPISODE}


def _bare(state: State) -> State:
    return state.replace(info={k: v for k, v in state.info.items() if k not in _AUTO_INFO})


def _restart(nxt: State, fresh: dict, key: jax.Array) -> State:
    """``nxt`` with ``fresh``'s episode where it is done (``done`` [] for one world, [B] for a batch)."""
    done = nxt.done > 0
    pick = lambda x, y: jnp.where(done.reshape(done.shape + (1,) * (x.ndim - done.ndim)), x, y)  # noqa: E731
    out = nxt.replace(**jax.tree.map(pick, fresh, _episode(nxt)))
    return out.replace(info=dict(nxt.info, reset_key=key, final_obs=nxt.obs, final_critic_obs=nxt.critic_obs))


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
        nxt = self.env.step(_bare(state), action)
        return _restart(nxt, _episode(self.env.reset(new_key, state.params)), key)


class BatchAutoResetWrapper(Wrapper):
    """:class:`AutoResetWrapper` around a :class:`VmapWrapper` that draws the new episodes only on steps where some
    world is done: the draws (layout, domain randomisation, the first observation) cost about a tenth of an env step
    on one device, and most steps of a batch end no episode. The same episodes up to float rounding, not bit for bit:
    XLA compiles the reset inside the ``cond`` on its own, and a new episode's first observation differed by up to
    1e-5 (BENCHMARKS.md, session 25)."""

    def reset(self, key: jax.Array, params=None) -> State:
        keys = self.env.world_keys(key)
        state = self.env.reset(keys, params)
        info = dict(state.info, reset_key=keys, final_obs=state.obs, final_critic_obs=state.critic_obs)
        return state.replace(info=info)

    def step(self, state: State, action: jax.Array) -> State:
        keys = jax.vmap(jax.random.split)(state.info["reset_key"])
        nxt = self.env.step(_bare(state), action)
        fresh = jax.lax.cond(jnp.any(nxt.done > 0), lambda: _episode(self.env.reset(keys[:, 1], state.params)),
                             lambda: _episode(nxt))
        return _restart(nxt, fresh, keys[:, 0])


class VmapWrapper(Wrapper):
    """Batches ``reset``/``step`` over a leading world axis; ``reset`` takes [B] keys or one key and ``batch_size``,
    and ``params`` for every world (``EnvParams``) or one per world (a leading [B] axis, ``params.stack``)."""

    def __init__(self, env, batch_size: int | None = None):
        super().__init__(env)
        self.batch_size = batch_size

    def world_keys(self, key: jax.Array) -> jax.Array:
        """[B] keys, one per world: ``key`` itself where it is [B] already, else ``batch_size`` split from it."""
        if self.batch_size is not None and key.ndim == 1:
            return jax.random.split(key, self.batch_size)
        return key

    def reset(self, key: jax.Array, params=None) -> State:
        key = self.world_keys(key)
        if params is None:
            return jax.vmap(self.env.reset)(key)
        # One value per world when the (scalar) mass has a leading axis; else the same params for every world.
        per_world = jnp.ndim(getattr(getattr(params, "cf", None), "mass", 0.0)) > 0  # else reset says what is wrong
        return jax.vmap(self.env.reset, in_axes=(0, 0 if per_world else None))(key, params)

    def step(self, state: State, action: jax.Array) -> State:
        return jax.vmap(self.env.step)(state, action)


def wrap_for_training(env, batch_size: int) -> Wrapper:
    return BatchAutoResetWrapper(VmapWrapper(env, batch_size))

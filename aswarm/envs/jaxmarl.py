"""Every scenario as a JaxMARL ``MultiAgentEnv``: agents keyed by name, for JaxMARL's baselines and wrappers.

The native environment keeps the agent as a leading array axis (``SwarmEnv``); this wrapper only packs those
arrays into dicts keyed ``"drone_0"``, ``"drone_1"``, ... at the boundary. It needs the optional ``interfaces``
extra (``pip install aswarm[interfaces]``): nothing else in aswarm imports this module.

- ``reset(key) -> (obs, state)``; ``step(key, state, actions) -> (obs, state, rewards, dones, infos)``, where
  ``state`` is the native :class:`aswarm.envs.State` (the auto-reset wrapper's, so ``state.info["final_obs"]``
  holds the last observation of a finished episode).
- Actions: per agent a world-frame velocity command ``[vx, vy, vz]`` in m/s, a ``Box(-max_speed, max_speed,
  (3,))``. Observations: per agent a ``Box(-inf, inf, (obs_dim,))`` (``env.obs_layout`` describes the fields).
- The centralized critic's input follows JaxMARL's SMAX: ``obs["world_state"]`` (``[state_size]``, the exact,
  noise-free observations of every drone, the native ``critic_obs``) and ``get_world_state(state)``.
- ``dones[agent]`` is True once the drone finished its mission or collided, and for every drone when the episode
  ends; ``dones["__all__"]`` ends the episode (any collision, all finished, or the time limit).
  ``infos["truncated"]`` (per agent, [n]) tells the time limit from a terminal state, so a learner can bootstrap;
  ``infos["cost"]`` is the safety cost and the rest are the episode metrics (read them where ``dones["__all__"]``),
  every leaf shaped [n] as JaxMARL's baselines reshape infos per agent.
- Auto-reset as JaxMARL's ``MultiAgentEnv.step``: where ``dones["__all__"]``, the returned obs and state belong
  to a new episode drawn with ``jax.random.split(key)[1]``, while rewards, dones and infos are the finished step's.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jaxmarl.environments import spaces
from jaxmarl.environments.multi_agent_env import MultiAgentEnv

from aswarm.envs.registry import make as make_native
from aswarm.envs.swarm_env import State, SwarmEnv
from aswarm.envs.wrappers import AutoResetWrapper

WORLD_STATE = "world_state"


def agent_names(num_agents: int) -> list[str]:
    return [f"drone_{i}" for i in range(num_agents)]


class SwarmMultiAgentEnv(MultiAgentEnv):
    """A native :class:`SwarmEnv` as a JaxMARL ``MultiAgentEnv`` (jittable and vmappable; build it with
    :func:`make`). The native env stays reachable as ``.env``."""

    def __init__(self, env: SwarmEnv):
        super().__init__(num_agents=env.num_agents)
        self.env = env
        self._auto = AutoResetWrapper(env)
        self.agents = agent_names(env.num_agents)
        self.obs_dim = env.observation_size
        self.state_size = env.critic_observation_size  # SMAX's name for the world state's size
        speed = float(env.config.max_speed)
        self.observation_spaces = {a: spaces.Box(-jnp.inf, jnp.inf, (self.obs_dim,)) for a in self.agents}
        self.action_spaces = {a: spaces.Box(-speed, speed, (env.action_size,)) for a in self.agents}

    @property
    def name(self) -> str:
        return f"aswarm_{self.env.config.scenario}"

    @property
    def agent_classes(self) -> dict:
        return {"drone": list(self.agents)}

    # ----------------------------------------------------------------- API
    @partial(jax.jit, static_argnums=(0,))
    def reset(self, key: jax.Array) -> tuple[dict, State]:
        state = self._auto.reset(key)
        return self.get_obs(state), state

    @partial(jax.jit, static_argnums=(0,))
    def step(self, key: jax.Array, state: State, actions: dict,
             reset_state: State | None = None) -> tuple[dict, State, dict, dict, dict]:
        if reset_state is not None:  # a caller-chosen next episode: JaxMARL's own select over the whole state
            return MultiAgentEnv.step(self, key, state, actions, reset_state)
        # One auto-reset, the native wrapper's, seeded as MultiAgentEnv.step seeds its reset: it draws the next
        # episode from split(info["reset_key"])[1], which is split(key)[1] here.
        state = self._auto.step(state.replace(info={**state.info, "reset_key": key}), self.stack_actions(actions))
        return (self.get_obs(state), state) + self._transition(state)

    def step_env(self, key: jax.Array, state: State, actions: dict) -> tuple[dict, State, dict, dict, dict]:
        """One step without auto-reset (``key`` is unused: the step itself draws nothing outside the state)."""
        nxt = self.env.step(state, self.stack_actions(actions))
        nxt = nxt.replace(info={**nxt.info, "final_obs": nxt.obs, "final_critic_obs": nxt.critic_obs})
        return (self.get_obs(nxt), nxt) + self._transition(nxt)

    def get_obs(self, state: State) -> dict:
        obs = {a: state.obs[i] for i, a in enumerate(self.agents)}
        obs[WORLD_STATE] = state.critic_obs
        return obs

    def get_world_state(self, state: State) -> jax.Array:
        """[state_size]: every drone's exact observation, in agent order (the native ``critic_obs``)."""
        return state.critic_obs

    def get_avail_actions(self, state: State) -> dict:
        # Continuous commands: every axis is always available.
        return {a: jnp.ones(self.env.action_size, bool) for a in self.agents}

    # ------------------------------------------------------------- helpers
    def stack_actions(self, actions: dict) -> jax.Array:
        """[n_agents, 3] from ``{agent: [3]}``; raises ``ValueError`` for unknown or missing agents or bad shapes
        (at trace time: shapes and keys are static)."""
        if not isinstance(actions, dict):
            raise ValueError(f"actions must be a dict keyed by agent, got {type(actions).__name__}: "
                             f"allowed keys: {', '.join(self.agents)}")
        unknown = sorted(set(actions) - set(self.agents))
        if unknown:
            raise ValueError(f"unknown agent {unknown[0]!r} in actions: allowed: {', '.join(self.agents)}")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"no action for agent {missing[0]!r}: give one for every agent in "
                             f"{', '.join(self.agents)}")
        want = (self.env.action_size,)
        for a in self.agents:
            if jnp.shape(actions[a]) != want:
                raise ValueError(f"action for {a!r} has shape {tuple(jnp.shape(actions[a]))}: allowed shape is {want} "
                                 "(a world-frame velocity command [vx, vy, vz] in m/s)")
        return jnp.stack([jnp.asarray(actions[a], jnp.float32) for a in self.agents])

    def _transition(self, state: State) -> tuple[dict, dict, dict]:
        """Rewards, dones and infos of the step that produced ``state``.

        After an auto-reset the tracker is the new episode's, but then every drone is done anyway; otherwise it
        is the stepped one, so a finished or collided drone is done from the step it stopped on.
        """
        n = self.num_agents
        done = state.done > 0
        stopped = done | state.tracker.finished | state.tracker.collided
        rewards = {a: state.reward[i] for i, a in enumerate(self.agents)}
        dones = {a: stopped[i] for i, a in enumerate(self.agents)}
        dones["__all__"] = done
        per_agent = lambda x: jnp.broadcast_to(x, (n,))  # noqa: E731
        infos = {"truncated": per_agent(state.truncated > 0), "cost": state.cost,
                 **{k: per_agent(v) for k, v in state.metrics.items()}}
        return rewards, dones, infos


def make(name: str, **overrides) -> SwarmMultiAgentEnv:
    """Scenario ``name`` (as :func:`aswarm.envs.make`, which validates it and the overrides) for JaxMARL."""
    return SwarmMultiAgentEnv(make_native(name, **overrides))

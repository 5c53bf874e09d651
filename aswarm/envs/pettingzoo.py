"""Every scenario as a PettingZoo ``ParallelEnv`` on the host: numpy in, numpy out, the jitted native env beneath.

It needs the optional ``interfaces`` extra (``pip install aswarm[interfaces]``); nothing else in aswarm imports
this module. One world per object and a host round trip per step: for training at scale use the native batched
env (``aswarm.envs.wrap_for_training``) or the JaxMARL wrapper (``aswarm.envs.jaxmarl``).

- Agents ``"drone_0"``, ``"drone_1"``, ...; actions are world-frame velocity commands ``[vx, vy, vz]`` in m/s
  (``Box(-max_speed, max_speed, (3,))``), observations ``Box(-inf, inf, (obs_dim,))`` (``env.obs_layout``).
- A drone that finished its mission is terminated and leaves ``agents`` (it lands, as in a real flight); any
  collision terminates every drone still flying (the episode ends); the time limit truncates them.
- ``reset(seed=...)`` is reproducible: the same seed gives the same layout, domain randomisation and noise.
  ``reset()`` without a seed draws the next episode from the last seed's stream. ``options`` are not used.
- ``render()`` (``render_mode="rgb_array"``) draws a top-down frame with matplotlib: it needs no OpenGL.
- ``state()`` is the centralized critic's input: every drone's exact observation, in agent order.
"""

from __future__ import annotations

import numbers

import gymnasium
import jax
import numpy as np
from pettingzoo import ParallelEnv

from aswarm.envs.dynamics import drone_state
from aswarm.envs.registry import make as make_native
from aswarm.envs.scenarios import cylinders_at
from aswarm.envs.swarm_env import State, SwarmEnv

RENDER_MODES = ("rgb_array",)


class SwarmParallelEnv(ParallelEnv):
    """A native :class:`SwarmEnv` as a PettingZoo ``ParallelEnv`` (build it with :func:`parallel_env`)."""

    def __init__(self, env: SwarmEnv, render_mode: str | None = None, render_size: tuple[int, int] = (480, 480)):
        if render_mode is not None and render_mode not in RENDER_MODES:
            raise ValueError(f"unknown render_mode {render_mode!r}: allowed: None, {', '.join(RENDER_MODES)}")
        if len(render_size) != 2 or min(render_size) < 16:
            raise ValueError(f"invalid render_size {render_size!r}: allowed: (width, height), each at least 16 pixels")
        self.env = env
        self.render_mode = render_mode
        self.render_size = tuple(int(v) for v in render_size)
        cfg = env.config
        self.metadata = {"render_modes": list(RENDER_MODES), "name": f"aswarm_{cfg.scenario}_v0",
                         "is_parallelizable": True, "render_fps": cfg.policy_freq}
        n, d = env.num_agents, env.observation_size
        self.possible_agents = [f"drone_{i}" for i in range(n)]
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        self.agents: list[str] = []
        speed = float(cfg.max_speed)
        self.observation_spaces = {a: gymnasium.spaces.Box(-np.inf, np.inf, (d,), np.float32)
                                   for a in self.possible_agents}
        self.action_spaces = {a: gymnasium.spaces.Box(-speed, speed, (env.action_size,), np.float32)
                              for a in self.possible_agents}
        self.state_space = gymnasium.spaces.Box(-np.inf, np.inf, (env.critic_observation_size,), np.float32)
        self._reset = jax.jit(lambda key: _with_view(env.reset(key)))
        self._step = jax.jit(lambda state, action: _with_view(env.step(state, action)))
        self._key: jax.Array | None = None
        self._state: State | None = None
        self._view: dict | None = None

    # ----------------------------------------------------------------- API
    def observation_space(self, agent: str) -> gymnasium.spaces.Box:
        return self.observation_spaces[self._check_agent(agent)]

    def action_space(self, agent: str) -> gymnasium.spaces.Box:
        return self.action_spaces[self._check_agent(agent)]

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        if seed is not None:
            if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
                raise ValueError(f"invalid seed {seed!r}: allowed: None or an integer >= 0")
            self._key = jax.random.PRNGKey(int(seed))
        elif self._key is None:  # unseeded, as gymnasium: a fresh stream from the OS
            self._key = jax.random.PRNGKey(int(np.random.SeedSequence().generate_state(1)[0]))
        self._key, key = jax.random.split(self._key)
        self._state, view = self._reset(key)
        self._view = jax.device_get(view)
        self.agents = list(self.possible_agents)
        obs = self._view["obs"]
        return {a: obs[i] for i, a in enumerate(self.agents)}, {a: {} for a in self.agents}

    def step(self, actions: dict) -> tuple[dict, dict, dict, dict, dict]:
        if self._state is None or not self.agents:
            raise ValueError("no agent is flying: the episode is over or has not started; call reset() first")
        live = list(self.agents)
        self._state, view = self._step(self._state, self._stack_actions(actions, live))
        v = self._view = jax.device_get(view)
        done, truncated = bool(v["done"]), bool(v["truncated"])
        obs, rewards, terminations, truncations, infos = {}, {}, {}, {}, {}
        for a in live:
            i = self._index[a]
            obs[a] = v["obs"][i]
            rewards[a] = float(v["reward"][i])
            # A finished drone has landed; a collision ends the episode for every drone still flying.
            terminations[a] = bool(v["finished"][i] or v["collided"][i] or (done and not truncated))
            truncations[a] = truncated and not terminations[a]
            infos[a] = {"cost": float(v["cost"][i]), "finished": bool(v["finished"][i]),
                        "collided": bool(v["collided"][i])}
            if done:
                infos[a]["episode"] = {k: float(x) for k, x in v["metrics"].items()}
        self.agents = [a for a in live if not (terminations[a] or truncations[a])]
        return obs, rewards, terminations, truncations, infos

    def state(self) -> np.ndarray:
        if self._view is None:
            raise ValueError("no state yet: call reset() first")
        return np.asarray(self._view["critic_obs"])

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            gymnasium.logger.warn("render() without a render_mode does nothing: make the env with "
                                  "render_mode='rgb_array'")
            return None
        if self._state is None:
            raise ValueError("nothing to render yet: call reset() first")
        return top_down_frame(self.env, self._state, *self.render_size)

    def close(self) -> None:
        self._state = self._view = None  # nothing else is held (no window, no file)
        self.agents = []

    # ------------------------------------------------------------- helpers
    def _check_agent(self, agent: str) -> str:
        if agent not in self._index:
            raise ValueError(f"unknown agent {agent!r}: allowed: {', '.join(self.possible_agents)}")
        return agent

    def _stack_actions(self, actions: dict, live: list[str]) -> np.ndarray:
        """[n, 3] float32; agents no longer flying hover (the native env zeroes their commands anyway)."""
        if not isinstance(actions, dict):
            raise ValueError(f"actions must be a dict keyed by agent, got {type(actions).__name__}: "
                             f"allowed keys: {', '.join(live)}")
        for a in actions:
            self._check_agent(a)
        missing = [a for a in live if a not in actions]
        if missing:
            raise ValueError(f"no action for agent {missing[0]!r}: give one for every agent in env.agents "
                             f"({', '.join(live)})")
        out = np.zeros((len(self.possible_agents), self.env.action_size), np.float32)
        for a in live:
            act = np.asarray(actions[a], np.float32)
            if act.shape != out.shape[1:]:
                raise ValueError(f"action for {a!r} has shape {act.shape}: allowed shape is {out.shape[1:]} "
                                 "(a world-frame velocity command [vx, vy, vz] in m/s)")
            if not np.all(np.isfinite(act)):
                raise ValueError(f"action for {a!r} is not finite: {act.tolist()}; allowed: finite m/s")
            out[self._index[a]] = act
        return out


def _with_view(state: State) -> tuple[State, dict]:
    """The state and what the host reads of it each step, fetched in one transfer."""
    tr = state.tracker
    return state, {"obs": state.obs, "critic_obs": state.critic_obs, "reward": state.reward, "cost": state.cost,
                   "done": state.done > 0, "truncated": state.truncated > 0, "finished": tr.finished,
                   "collided": tr.collided, "metrics": state.metrics}


def top_down_frame(env: SwarmEnv, state: State, width: int = 480, height: int = 480) -> np.ndarray:
    """[height, width, 3] uint8: the arena from above, with cylinders, gates, goals and drones (a collided drone
    is a red cross, a finished one a hollow circle). Matplotlib's Agg canvas: no display, no OpenGL."""
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle, Rectangle

    cfg = env.config
    n = env.num_agents
    lay, data, tr = jax.device_get((state.layout, state.data, state.tracker))
    pos = np.asarray(drone_state(data, n).pos)
    t = float(data.time)
    cyl_xy, _ = cylinders_at(lay, np.float32(t))
    cyl_xy = np.asarray(cyl_xy)

    dpi = 100
    fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0.02, 0.02, 0.96, 0.9))
    lo, hi = cfg.arena_low, cfg.arena_high
    ax.add_patch(Rectangle(lo[:2], hi[0] - lo[0], hi[1] - lo[1], fill=False, color="0.3", lw=1.5))
    for j in range(len(lay.cyl_radius)):
        if lay.cyl_present[j]:
            moving = lay.cyl_amplitude[j] > 0
            ax.add_patch(Circle(cyl_xy[j], float(lay.cyl_radius[j]), color="tab:orange" if moving else "0.5"))
    for k in range(len(lay.gate_yaw)):
        c, yaw = lay.gate_pos[k, :2], float(lay.gate_yaw[k])
        side = np.array([-np.sin(yaw), np.cos(yaw)]) * (cfg.gate_half_opening + cfg.gate_bar)
        ends = np.stack([c - side, c + side])
        ax.plot(ends[:, 0], ends[:, 1], color="tab:blue", lw=3, solid_capstyle="butt")
    colours = colormaps["tab10"] if n <= 10 else colormaps["turbo"]
    for i in range(n):
        col = colours(i if n <= 10 else i / max(n - 1, 1))
        if env.kind != "track":
            goal = lay.waypoints[i, 0]
            ax.plot(goal[0], goal[1], marker="x", ms=7, color=col)
        if tr.collided[i]:
            ax.plot(pos[i, 0], pos[i, 1], marker="X", ms=10, color="red")
        else:
            ax.plot(pos[i, 0], pos[i, 1], marker="o", ms=8, color=col, mfc="none" if tr.finished[i] else col)
    ax.set_xlim(lo[0] - 0.3, hi[0] + 0.3)
    ax.set_ylim(lo[1] - 0.3, hi[1] + 0.3)
    ax.set_aspect("equal")
    ax.set_axis_off()  # the arena's rectangle is the frame
    fig.suptitle(f"{cfg.scenario}  t = {t:.2f} s", fontsize=10)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def parallel_env(name: str, render_mode: str | None = None, **overrides) -> SwarmParallelEnv:
    """Scenario ``name`` (as :func:`aswarm.envs.make`, which validates it and the overrides) for PettingZoo."""
    return SwarmParallelEnv(make_native(name, **overrides), render_mode=render_mode)

"""Typed training configuration; defaults from the paper's Table II unless a measurement says otherwise."""

from __future__ import annotations

import dataclasses
import math

from aswarm.core.safety import SafetyFilterConfig
from aswarm.envs.config import EnvConfig

CRITICS = ("joint", "pooled")  # networks.CRITICS: the modules

METHODS = {
    "attention_cbf": "the full method: attention-CBF penalties and CBF safety filter with learned gains",
    "attention_penalty": "attention-CBF penalties, no safety filter",
    "fixed_cbf": "CBF safety filter with a fixed gain (no attention), plain MAPPO objective",
    "mappo_lagrangian": "MAPPO-Lagrangian: one learned scalar multiplier, no filter",
    "mappo": "plain MAPPO: no cost, no filter",
    "a2c": "synchronous advantage actor-critic (centralized critic, one gradient step per rollout): no cost, no filter",
}


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    scenario: str = "race"
    method: str = "attention_cbf"
    seed: int = 0
    # Env steps (each moves every drone once). 3M since session 26 (issue #15): on the drone that flies (identified
    # rotor spin-down), training seeds 0 / 1 / 2 reached 99.0 / 99.5 / 99.1 % success with 0.1 / 0.1 / 0 %
    # collision episodes on 1000 unseen episodes, as 4M (seed 0: 99.1 %, 0 %) and 3.5M (99.0 %, 0 %) did, in
    # three quarters of 4M's time (README, "Speed"). The shipped policies store their own budgets.
    total_steps: int = 3_000_000
    # 256 worlds: 4x the updates of 1024 for the same env steps at about the same env-steps/s; the race
    # learnt in ~1M steps where 1024 worlds had not after 11M (README, "Results so far").
    num_envs: int = 256
    rollout_steps: int = 32
    epochs: int = 2  # 4 x 4 ran at 0.52x the throughput (BENCHMARKS.md)
    minibatches: int = 2
    # Table II, but for the actor's rate: at 5e-4 the KL per update stayed ~1e-3 (2e-3 learnt faster).
    actor_lr: float = 2e-3
    critic_lr: float = 5e-3
    anneal_lr: bool = True  # every rate falls linearly to 0 over total_steps (optax.linear_schedule)
    cbf_lr: float = 1e-3
    clip: float = 0.1
    gae_lambda: float = 0.95
    gamma: float = 0.95
    cbf_coef: float = 0.1  # alpha, weight of the CBF loss
    value_coef: float = 0.5
    entropy_coef: float = 1e-3
    max_grad_norm: float = 0.5
    # Target critics with soft updates: 0 bootstraps GAE from the critics being trained (PPO's usual way);
    # tau > 0 from copies that follow them as target <- tau * critic + (1 - tau) * target after each update.
    # Off by default: measured on the race, it did not help (README).
    target_tau: float = 0.0
    cost_limit: float = 0.02  # allowed expected discounted cost-to-go per drone
    lagrange_init: float = 0.0  # mappo_lagrangian: initial multiplier
    # Networks.
    actor_hidden: tuple[int, ...] = (64, 64)
    critic_hidden: tuple[int, ...] = (128, 128)
    # "joint": an MLP over the swarm's joint observation with one output per drone (MAPPO's centralized critic);
    # "pooled": one per-drone MLP over the drone's observation and a mean and max over the swarm's
    # (networks.PooledCritic: its size does not grow with the swarm).
    critic: str = "joint"
    cbf_hidden: tuple[int, ...] = (64, 64)  # paper: (1024, 256)
    cbf_embed: int = 8  # paper: 3
    cbf_state_hidden: int = 64
    # Multiplies the actor's Gaussian std (brax's var_scale): 1 starts at std 0.69 before the tanh.
    action_std_scale: float = 1.0
    penalty_max: float = 2.0  # at 10 the penalty saturated within 20 updates and froze progress
    # The CBF safety filter's margin, gain range (also the attention-CBF network's output range), fixed
    # gain (fixed_cbf) and QP settings: used by training, evaluation and, through the export manifest,
    # the flight runtime. Runs written before it had flat gain_min, gain_max, fixed_gain, filter_margin
    # (core.safety.nest_legacy maps them).
    safety_filter: SafetyFilterConfig = SafetyFilterConfig()
    # Training reward per second per m/s of the filter's correction ||u_safe - u_nom|| (methods with the
    # filter), so the policy learns to command what the filter lets through. Measured (README): filter
    # intervention 58 -> 27 % of drone-steps on `obstacles` and 71 -> 66 % on the race, success 99.6 -> 99.9 %
    # and 99.9 % on both.
    correction_penalty: float = 2.0
    # Devices the worlds are split over (data-parallel, gradients averaged): 0 takes as many of the visible
    # devices as divide num_envs, and the run folder records the number used, so a resume lays itself out
    # the same way. On a CPU each core is a device (sharding.use_cpu_cores): 2 cores trained the race at
    # 1.33x the env-steps/s of one device holding both (BENCHMARKS.md).
    devices: int = 0
    # A checkpoint (run folder, 'pretrained' or 'pretrained:NAME') whose networks start this run: every network
    # whose shapes fit is copied (the actor and the attention-CBF network of a policy with the same observation
    # layout), the others start fresh (a joint critic of another swarm size), and the observation normaliser comes
    # along. "" starts from random weights. How a 16-drone policy starts from the 4-drone one (README, "Swarms").
    init_from: str = ""
    # Host loop.
    checkpoint_minutes: float = 5.0
    updates_per_chunk: int = 10
    # The env a new run starts from: the scenario's preset with these (FIELD or nested cf.FIELD, value) pairs.
    # A record once resolved: ``env`` holds the run's full environment, and a stored run loads it as stored
    # (editing a preset must not change the env an old checkpoint is evaluated or exported on).
    env_overrides: tuple[tuple[str, object], ...] = ()
    env: EnvConfig | None = None  # None: resolved from scenario and env_overrides in __post_init__

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"invalid method={self.method!r}: allowed: {', '.join(METHODS)}")
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float) and not math.isfinite(v):
                raise ValueError(f"invalid {f.name}={v!r}: must be a finite number")
        if self.critic not in CRITICS:
            raise ValueError(f"invalid critic={self.critic!r}: allowed: {', '.join(CRITICS)}")
        if not 0 <= self.target_tau <= 1:
            raise ValueError(f"invalid target_tau={self.target_tau}: must be in [0, 1] (0: no target critics)")
        if self.correction_penalty < 0:
            raise ValueError(f"invalid correction_penalty={self.correction_penalty}: must be >= 0")
        if self.devices < 0:
            raise ValueError(f"invalid devices={self.devices}: must be >= 0 (0: as many as divide num_envs)")
        for name in ("total_steps", "num_envs", "rollout_steps", "epochs", "minibatches", "updates_per_chunk",
                     "cbf_embed", "cbf_state_hidden"):
            if getattr(self, name) <= 0:
                raise ValueError(f"invalid {name}={getattr(self, name)!r}: must be > 0")
        for name in ("actor_hidden", "critic_hidden", "cbf_hidden"):  # a zero-width layer trains nothing
            if any(not isinstance(w, int) or w <= 0 for w in getattr(self, name)):
                raise ValueError(f"invalid {name}={getattr(self, name)!r}: allowed: layer widths > 0, e.g. 64,64")
        for name in ("actor_lr", "critic_lr", "cbf_lr", "clip", "max_grad_norm", "checkpoint_minutes",
                     "action_std_scale"):
            if getattr(self, name) <= 0:
                raise ValueError(f"invalid {name}={getattr(self, name)!r}: must be > 0")
        for name in ("gamma", "gae_lambda"):
            if not 0 < getattr(self, name) <= 1:
                raise ValueError(f"invalid {name}={getattr(self, name)!r}: must be in (0, 1]")
        if (self.num_envs * self.rollout_steps) % self.minibatches:
            raise ValueError(f"invalid minibatches={self.minibatches}: must divide num_envs * rollout_steps = "
                             f"{self.num_envs * self.rollout_steps}")
        if not isinstance(self.safety_filter, SafetyFilterConfig):
            raise ValueError(f"invalid safety_filter={self.safety_filter!r}: allowed: a SafetyFilterConfig")
        self._resolve_env()

    def _resolve_env(self) -> None:
        """Fill ``env`` from the preset for a new run; check a given one against scenario and env_overrides."""
        from aswarm import config_args
        from aswarm.envs import registry

        if self.env is None:
            env = config_args.replace_fields(registry.preset(self.scenario), dict(self.env_overrides))
            object.__setattr__(self, "env", env)
            return
        if not isinstance(self.env, EnvConfig):
            raise ValueError(f"invalid env={self.env!r}: allowed: an EnvConfig")
        if self.env.scenario != self.scenario:
            raise ValueError(f"invalid env.scenario={self.env.scenario!r}: must equal scenario={self.scenario!r}")
        # The record must agree with the env it produced (catches dataclasses.replace(config, env_overrides=...),
        # which would otherwise keep the old env).
        if config_args.replace_fields(self.env, dict(self.env_overrides)) != self.env:
            raise ValueError(f"invalid env_overrides={self.env_overrides!r}: they disagree with env; allowed: "
                             "env=None (resolved from the preset) or overrides the env holds")

    @property
    def num_epochs(self) -> int:
        return 1 if self.method == "a2c" else self.epochs

    @property
    def num_minibatches(self) -> int:
        return 1 if self.method == "a2c" else self.minibatches

    @property
    def steps_per_update(self) -> int:
        return self.num_envs * self.rollout_steps

    @property
    def num_updates(self) -> int:
        return max(1, self.total_steps // self.steps_per_update)

    @property
    def uses_filter(self) -> bool:
        return self.method in ("attention_cbf", "fixed_cbf")

    @property
    def uses_attention(self) -> bool:
        return self.method in ("attention_cbf", "attention_penalty")

    @property
    def uses_cost(self) -> bool:
        return self.method in ("attention_cbf", "attention_penalty", "mappo_lagrangian")

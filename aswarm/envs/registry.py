"""``make(name, **overrides)``: a scenario's environment, as ``mujoco_playground.registry.load``."""

from __future__ import annotations

import dataclasses

from aswarm.envs.config import EnvConfig
from aswarm.envs.presets import SCENARIOS
from aswarm.envs.swarm_env import SwarmEnv


def preset(name: str, **overrides) -> EnvConfig:
    """The scenario's :class:`EnvConfig` with ``overrides`` applied and validated."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}: allowed: {', '.join(SCENARIOS)}")
    fields = {f.name for f in dataclasses.fields(EnvConfig)}
    bad = sorted(set(overrides) - fields)
    if bad:
        raise ValueError(f"unknown env config field {bad[0]!r}: allowed: {', '.join(sorted(fields))}")
    return EnvConfig(**{**SCENARIOS[name].preset, **overrides, "scenario": name})


def make(name: str, **overrides) -> SwarmEnv:
    """Build scenario ``name`` (see :data:`SCENARIOS`) with config fields overridden.

    Raises ``ValueError`` naming the bad value and what is allowed, before any compile.
    """
    return SwarmEnv(preset(name, **overrides))


def names() -> tuple[str, ...]:
    return tuple(SCENARIOS)

"""``make(name, **overrides)``: a scenario's environment, as ``mujoco_playground.registry.load``."""

from __future__ import annotations

from aswarm.envs.scenarios import SCENARIOS, preset
from aswarm.envs.swarm_env import SwarmEnv


def make(name: str, **overrides) -> SwarmEnv:
    """Build scenario ``name`` (see :data:`SCENARIOS`) with config fields overridden.

    Raises ``ValueError`` naming the bad value and what is allowed, before any compile.
    """
    return SwarmEnv(preset(name, **overrides))


def names() -> tuple[str, ...]:
    return tuple(SCENARIOS)

"""MJX Crazyflie swarm environments."""

from aswarm.core.layout import ObsLayout
from aswarm.envs.config import EnvConfig
from aswarm.envs.registry import make, names, preset
from aswarm.envs.swarm_env import State, SwarmEnv
from aswarm.envs.wrappers import AutoResetWrapper, VmapWrapper, wrap_for_training

__all__ = ["EnvConfig", "make", "names", "preset", "ObsLayout", "State", "SwarmEnv", "AutoResetWrapper",
           "VmapWrapper", "wrap_for_training"]

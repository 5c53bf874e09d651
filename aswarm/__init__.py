"""aswarm: safe multi-drone reinforcement learning in JAX (AttentionSwarm reproduction)."""

__version__ = "0.1.0"

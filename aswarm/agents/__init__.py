"""Learners: MAPPO with the attention-CBF network, its safety filter, training and evaluation."""

# brax and mujoco-mjx print warp import failures on stdout when first imported; import mjx quietly
# before any of them so that `aswarm eval --json` prints JSON only.
from aswarm.envs import mjx_import  # noqa: F401

"""The host side of training: the loop, checkpoints, sharding over devices, sweeps."""

"""The velocity command a drone receives, written once for numpy and JAX (the array API)."""

from __future__ import annotations

from aswarm.core.geometry import namespace


def limit_change(cmd, previous, step):
    """``cmd`` moved at most ``step`` (m/s, per axis) from ``previous``: the command's acceleration limit.

    The firmware's velocity PID tilts 25° per m/s of velocity error and saturates at 20° (0.8 m/s), so a
    command that jumps further in one step swings the tilt setpoint end to end; this bounds the swing.
    """
    xp = namespace(cmd, previous)
    return previous + xp.clip(cmd - previous, -step, step)

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


def reachable(previous, step, limit):
    """(lo, hi): the commands :func:`limit_change` lets through from ``previous`` [..., 3] (``step`` m/s per axis),
    within the command bound ±``limit``: the box a safety filter that knows the limit chooses in."""
    xp = namespace(previous)
    return xp.maximum(previous - step, -limit), xp.minimum(previous + step, limit)


# A drone on the firmware's Mellinger controller tracks full-state setpoints, not velocities: its velocity
# command reaches it as a setpoint that moves with the command (the same on the simulated drone and in flight).
def setpoint_position(reference, cmd, dt):
    """The position of the full-state setpoint sent while ``cmd`` (m/s) is held for ``dt`` s from
    ``reference``: the middle of the stretch the command flies, so a drone flying the command is on average
    at its setpoint (the firmware holds a setpoint as sent; it does not move it with its velocity)."""
    return reference + (0.5 * dt) * cmd


def advance_reference(reference, cmd, dt, position, leash):
    """The setpoint's reference after ``cmd`` was held for ``dt``: moved by ``cmd * dt``, then kept within
    ``leash`` (m) of the drone's ``position`` so that a drone that fell behind is not pulled the whole way."""
    xp = namespace(reference, cmd, position)
    ahead = reference + dt * cmd - position
    dist = xp.sqrt(xp.sum(ahead * ahead, axis=-1, keepdims=True))
    return position + ahead * xp.minimum(1.0, leash / xp.maximum(dist, 1e-9))

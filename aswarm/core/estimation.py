"""Velocity from positions: the least-squares line through a window of timed samples.

The flight runtime estimates each drone's velocity this way from motion-capture poses
(:mod:`aswarm.flight.estimator`), and the simulator can show the policy the same estimate from its noisy
positions (``randomize.velocity_window``), so a policy trains on the velocity it will fly with: lagging about
half the window and carrying the position noise. Plain arithmetic on arrays: numpy and ``jax.numpy`` both.
"""

from __future__ import annotations


def slope_weights(t):
    """Weights ``c`` [..., W] of samples at times ``t`` [..., W] (at least two distinct): the least-squares slope of
    samples ``y`` [..., W, k] is ``sum_i c_i y_i``. Times may be relative to any origin."""
    dt = t - t.mean(axis=-1, keepdims=True)
    return dt / (dt * dt).sum(axis=-1, keepdims=True)

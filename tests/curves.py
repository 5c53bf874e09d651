"""Comparing learning curves computed in another summation order (other devices, vmapped, another CPU).

Round-off from a different order of the same sums grows over the updates: a handful of updates in, values
agree to a fraction of the curve's own scale, not of each entry, since some metrics are differences of
near-equal terms (cost excess J_c - d) or ratios of small variances (explained variance). A bug (an
unaveraged gradient, a wrong trial's values) moves them by percents of the scale.
"""

import numpy as np


def assert_same_curve(actual, desired, scale_rtol: float, err_msg: str = "", atol: float = 1e-5) -> None:
    """``|actual - desired| <= scale_rtol * max|desired| + atol`` at every update."""
    actual, desired = np.asarray(actual, dtype=np.float64), np.asarray(desired, dtype=np.float64)
    assert actual.shape == desired.shape, (actual.shape, desired.shape, err_msg)
    tol = scale_rtol * float(np.max(np.abs(desired), initial=0.0)) + atol
    np.testing.assert_array_less(np.abs(actual - desired), tol, err_msg=f"{err_msg} (tolerance {tol:.3g})")


def assert_same_params(actual, desired, atol: float = 1e-4, err_msg: str = "") -> None:
    """Every leaf to ``rtol 1e-4, atol``: Adam divides by the root of the second moment, so entries whose
    gradient is near zero amplify the round-off of another summation order (seen: 3e-5 on one Xeon, 1.2e-5 on
    an EPYC, on 4 of 4352 entries)."""
    import jax

    for x, y in zip(jax.tree.leaves(actual), jax.tree.leaves(desired), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-4, atol=atol, err_msg=err_msg)

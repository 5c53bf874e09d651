"""Observations on the flight side: the simulator's own builder, :func:`aswarm.core.observation.observe`.

Shapes: leading batch axes ``...`` (worlds), ``n`` drones, ``K`` waypoints, ``M`` cylinders. The field
tables live in :mod:`aswarm.core.layout` (free of JAX, shared with the simulator), and
:func:`aswarm.flight.bundle.load_bundle` checks a bundle's layout against them. Called on numpy arrays,
the builder runs in numpy alone (the flight side imports no JAX).
"""

from __future__ import annotations

from aswarm.core.layout import (
    CYL,
    CYL_FIELDS,
    MIN_TARGET_DIST,
    NBR,
    NBR_FIELDS,
    OWN,
    OWN_FIELDS,
    PRESENT_THRESHOLD,
    ObsLayout,
)
from aswarm.core.observation import nearest_rows, observe, others

__all__ = ["CYL", "CYL_FIELDS", "MIN_TARGET_DIST", "NBR", "NBR_FIELDS", "OWN", "OWN_FIELDS", "PRESENT_THRESHOLD",
           "ObsLayout", "nearest_rows", "observe", "others"]

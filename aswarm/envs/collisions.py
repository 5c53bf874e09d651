"""Collision kinds of the simulator (MJX contacts stay off: collisions are analytic).

Every drone is a sphere of radius ``r`` (``CrazyflieParams.collision_radius``). A *clearance* is the gap
between surfaces: negative means collision. The clearances themselves (and ``FAR``, reported for what is
absent) are :mod:`aswarm.core.geometry`'s, shared with the safety filter, the MPC and the flight runtime;
this module holds only what the environment adds: which kind of collision ended a drone's flight.
"""

from __future__ import annotations

# What a drone collided with first (``Tracker.collision_kind``), in the order the environment checks them;
# ``KINDS[k]`` names kind ``k`` in the metrics (``collision_<name>``).
NONE, OBSTACLE, DRONE, GATE, FLOOR, BOUNDS = range(6)
KINDS = ("none", "obstacle", "drone", "gate", "floor", "bounds")

"""The flight-side runtime: numpy only, no JAX, flax, MuJoCo or brax.

A policy leaves training as a bundle (``aswarm export``): ``policy.npz`` of plain float32 arrays and
``manifest.json``. This package loads it and turns mocap poses into velocity setpoints exactly as the
simulator and the trainer would:

| module | holds |
|---|---|
| ``bundle.py`` | load a bundle, check its format, hash and arrays |
| ``estimator.py`` | velocity and body angular rate from timestamped poses |
| (``aswarm.core``) | the observation layout and builder, the geometry and the barrier rows, shared with the simulator |
| ``policy.py`` | observation normalizer, actor and attention-CBF network (forward passes) |
| ``cbf.py`` | the CBF safety filter's QP in numpy (rows from ``aswarm.core.barriers``, as the JAX filter) |
| ``runtime.py`` | ``FlightController``: poses in, bounded world-frame velocity setpoints out, with safety checks |
| ``fly.py`` | ``aswarm fly``: the flight sequence (pre-flight checks, take-off, staggered starts, loop, landing) |
| ``mocap.py`` | pose sources: live motion capture (``motioncapture``, imported lazily), its mock, CSV replays |
| ``links.py`` | the radio side: the ``Link`` protocol, a recording stand-in, the cflib swarm (imported lazily) |
| ``swarm_config.py`` | the swarm file (TOML): each drone's URI, rigid body and start; obstacles |
| ``record.py`` | the flight record (npz + JSON, written atomically) and its figure |
| ``clock.py`` | the wall clock and a fake one for tests |
| ``bench.py`` | per-step cost of the runtime |
| ``export.py``, ``sitl.py`` | write a bundle, fly it in the simulator (JAX; the package imports neither) |

Every array function takes leading batch axes (worlds, drones), so software-in-the-loop runs many
episodes at once through the same code that flies.
"""

from aswarm.flight.bundle import Bundle, BundleError, load_bundle
from aswarm.flight.runtime import Event, FlightController, Obstacles, SafetyConfig, StepResult

__all__ = ["Bundle", "BundleError", "load_bundle", "Event", "FlightController", "Obstacles", "SafetyConfig",
           "StepResult"]

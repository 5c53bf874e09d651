"""The swarm file of ``aswarm fly --config``: which radio and which mocap rigid body is which drone (TOML).

Crazyswarm2's ``crazyflies.yaml`` in TOML (``tomllib`` is in the standard library; YAML is not a dependency)::

    [drones.cf1]                         # drone names; their order in the file is the policy's drone order
    uri = "radio://0/80/2M/E7E7E7E701"   # one radio address per drone
    rigid_body = "cf1"                   # the name the mocap system streams for it
    initial_position = [4.24, -2.83, 0.0] # m, world; where it stands (served by --mocap mock, checked otherwise)
    # enabled = false                    # leave it on the ground (or choose with --drones cf1,cf2)

    [obstacles.pole1]                    # vertical cylinders the policy avoids, tracked by the mocap system
    rigid_body = "pole1"
    radius = 0.15                        # m
    moving = false                       # true: its velocity is estimated from its poses
    # accel = 1.0                        # m/s^2 bound for a moving one (default: the bundle's moving_accel_bound)
    # initial_position = [0.0, 0.0, 0.0] # served by --mocap mock

    [mocap]
    frequency = 100                      # Hz of the mock backend (live systems run at their own rate)

Every mistake is one ``ValueError`` line naming the bad value and what is allowed.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path

DRONE_KEYS = ("uri", "rigid_body", "initial_position", "enabled")
OBSTACLE_KEYS = ("rigid_body", "radius", "moving", "accel", "initial_position")
MOCAP_KEYS = ("frequency",)
SECTIONS = ("drones", "obstacles", "mocap")


@dataclasses.dataclass(frozen=True)
class DroneEntry:
    name: str
    uri: str
    rigid_body: str
    initial_position: tuple[float, float, float] | None = None


@dataclasses.dataclass(frozen=True)
class ObstacleEntry:
    name: str
    rigid_body: str
    radius: float  # m
    moving: bool = False
    accel: float | None = None  # m/s^2; None: the bundle's bound for moving cylinders (0 for a static one)
    initial_position: tuple[float, float, float] | None = None


@dataclasses.dataclass(frozen=True)
class SwarmConfig:
    drones: tuple[DroneEntry, ...]  # in the policy's drone order
    obstacles: tuple[ObstacleEntry, ...] = ()
    mock_frequency: float = 100.0  # Hz

    @property
    def uris(self) -> list[str]:
        return [d.uri for d in self.drones]

    @property
    def names(self) -> list[str]:
        return [d.name for d in self.drones]


def load_swarm_config(path: str | Path, select: Sequence[str] | None = None,
                      num_drones: int | None = None, max_obstacles: int | None = None) -> SwarmConfig:
    """Read and check a swarm file; ``select``: the drone names to fly (default: every enabled one);
    ``num_drones``/``max_obstacles``: what the bundle flies and observes."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"swarm config {path} does not exist: allowed: a TOML file with [drones.NAME] tables")
    try:
        data = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"swarm config {path} is not valid TOML: {e}".replace("\n", " ")) from None
    return parse_swarm_config(data, str(path), select, num_drones, max_obstacles)


def parse_swarm_config(data: Mapping, where: str = "swarm config", select: Sequence[str] | None = None,
                       num_drones: int | None = None, max_obstacles: int | None = None) -> SwarmConfig:
    """:func:`load_swarm_config` on an already parsed table."""
    for key in data:
        if key not in SECTIONS:
            raise ValueError(f"{where}: unknown section {key!r}: allowed: {', '.join(SECTIONS)}")
    drones_t = data.get("drones")
    if not isinstance(drones_t, Mapping) or not drones_t:
        raise ValueError(f"{where}: no [drones.NAME] tables: allowed: one table per drone with "
                         f"{', '.join(DRONE_KEYS)}")
    drones, uris, bodies = [], {}, {}
    for name, d in drones_t.items():
        if not isinstance(d, Mapping):
            raise ValueError(f"{where}: drones.{name} is not a table: allowed: [drones.{name}] with "
                             f"{', '.join(DRONE_KEYS)}")
        _known(d, DRONE_KEYS, f"{where}: drone {name!r}")
        uri = _text(d, "uri", f"{where}: drone {name!r}", "a radio URI such as radio://0/80/2M/E7E7E7E701")
        body = _text(d, "rigid_body", f"{where}: drone {name!r}", "the name the mocap system streams for it")
        if uri in uris:
            raise ValueError(f"{where}: drones {uris[uri]!r} and {name!r} have the same uri {uri!r}: allowed: one "
                             "radio address per drone")
        if body in bodies:
            raise ValueError(f"{where}: drones {bodies[body]!r} and {name!r} have the same rigid_body {body!r}: "
                             "allowed: one rigid body per drone")
        uris[uri], bodies[body] = name, name
        enabled = d.get("enabled", True)
        if not isinstance(enabled, bool):
            raise ValueError(f"{where}: drone {name!r} enabled={enabled!r}: allowed: true or false")
        entry = DroneEntry(name=str(name), uri=uri, rigid_body=body,
                           initial_position=_position(d, f"{where}: drone {name!r}"))
        drones.append((entry, enabled))
    if select:
        known = [e.name for e, _ in drones]
        for s in select:
            if s not in known:
                raise ValueError(f"{where}: unknown drone {s!r}: allowed: {', '.join(known)}")
        chosen = [e for e, _ in drones if e.name in select]
    else:
        chosen = [e for e, on in drones if on]
    if num_drones is not None and len(chosen) != num_drones:
        raise ValueError(f"{where}: {len(chosen)} drones to fly ({', '.join(e.name for e in chosen) or 'none'}) but "
                         f"the bundle was trained for {num_drones}: allowed: exactly {num_drones} (enabled = false "
                         "or --drones NAME,... chooses them)")

    obstacles = []
    for name, o in (data.get("obstacles") or {}).items():
        if not isinstance(o, Mapping):
            raise ValueError(f"{where}: obstacles.{name} is not a table: allowed: [obstacles.{name}] with "
                             f"{', '.join(OBSTACLE_KEYS)}")
        what = f"{where}: obstacle {name!r}"
        _known(o, OBSTACLE_KEYS, what)
        body = _text(o, "rigid_body", what, "the name the mocap system streams for it")
        if body in bodies:
            raise ValueError(f"{what}: rigid_body {body!r} is already {bodies[body]!r}: allowed: one rigid body each")
        bodies[body] = name
        radius = o.get("radius")
        if isinstance(radius, bool) or not isinstance(radius, int | float) or not (math.isfinite(radius)
                                                                                   and radius > 0):
            raise ValueError(f"{what} radius={radius!r}: allowed: a number > 0 (m)")
        moving = o.get("moving", False)
        if not isinstance(moving, bool):
            raise ValueError(f"{what} moving={moving!r}: allowed: true or false")
        accel = o.get("accel")
        if accel is not None and (isinstance(accel, bool) or not isinstance(accel, int | float)
                                  or not (math.isfinite(accel) and accel >= 0)):
            raise ValueError(f"{what} accel={accel!r}: allowed: a number >= 0 (m/s^2)")
        obstacles.append(ObstacleEntry(name=str(name), rigid_body=body, radius=float(radius), moving=moving,
                                       accel=None if accel is None else float(accel),
                                       initial_position=_position(o, what)))
    if max_obstacles is not None and len(obstacles) > max_obstacles:
        raise ValueError(f"{where}: {len(obstacles)} obstacles but the policy observes at most {max_obstacles}: "
                         f"allowed: at most {max_obstacles} [obstacles.NAME] tables")

    mocap = data.get("mocap") or {}
    if not isinstance(mocap, Mapping):
        raise ValueError(f"{where}: mocap is not a table: allowed: [mocap] with {', '.join(MOCAP_KEYS)}")
    _known(mocap, MOCAP_KEYS, f"{where}: [mocap]")
    freq = mocap.get("frequency", 100)
    if isinstance(freq, bool) or not isinstance(freq, int | float) or not (math.isfinite(freq) and 1 <= freq <= 1000):
        raise ValueError(f"{where}: [mocap] frequency={freq!r}: allowed: a number of Hz from 1 to 1000")
    return SwarmConfig(drones=tuple(chosen), obstacles=tuple(obstacles), mock_frequency=float(freq))


def _known(table: Mapping, allowed: tuple[str, ...], what: str) -> None:
    for key in table:
        if key not in allowed:
            raise ValueError(f"{what} has unknown key {key!r}: allowed: {', '.join(allowed)}")


def _text(table: Mapping, key: str, what: str, meaning: str) -> str:
    v = table.get(key)
    if not isinstance(v, str) or not v.strip():
        missing = "has no" if v is None else f"has an invalid {key}={v!r}, not a"
        raise ValueError(f"{what} {missing} {key}: allowed: {meaning}")
    return v.strip()


def _position(table: Mapping, what: str) -> tuple[float, float, float] | None:
    p = table.get("initial_position")
    if p is None:
        return None
    if (not isinstance(p, list) or len(p) != 3
            or not all(isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x) for x in p)):
        raise ValueError(f"{what} initial_position={p!r}: allowed: [x, y, z], three finite numbers (m)")
    return (float(p[0]), float(p[1]), float(p[2]))

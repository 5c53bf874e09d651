"""Where ``aswarm fly`` gets poses: live motion capture (the ``motioncapture`` package), its mock, or a CSV replay.

A :class:`MocapSource` is started with the flight's clock and a callback; it calls the callback with a
:class:`PoseFrame` on every new frame, at its own rate (the flight loop forwards each frame to the drones' estimators
from there, so poses reach them at the mocap rate, not the control rate), and ``latest(now)`` gives the control loop
the newest frame whenever it asks.

- :class:`MotionCaptureSource`: ``motioncapture.connect(backend, {"hostname": HOST})`` for any backend that library
  has (vicon, optitrack, qualisys, vrpn, nokov, ...), read on its own thread, blocking in ``waitForNextFrame``.
  Rigid bodies map to drones and obstacles by the swarm file (:mod:`aswarm.flight.swarm_config`). Timestamps are the
  flight clock's when the frame arrived: the Python bindings do not expose the capture time.
- ``--mocap mock``: the library's own ``mock`` backend, which serves fixed rigid bodies (given to it as
  ``rigid_bodies="name(x,y,z,qw,qx,qy,qz);..."``, here the swarm file's initial positions) at its ``frequency``.
  Fixed bodies would make a rehearsal fly nothing, so :class:`KinematicSwarm` moves the served drone bodies by the
  commands the stand-in link was sent (take-off, velocity setpoints through the drone's measured velocity lag,
  landing): the real library paces the frames, the adapter moves the bodies.
- :class:`ReplaySource`: a CSV of recorded poses (``t,drone,x,y,z,qw,qx,qy,qz``), ``t`` counted from the start of the
  control loop; before it, every drone holds its first pose (dry runs only).
"""

from __future__ import annotations

import collections
import csv
import dataclasses
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Protocol

import numpy as np

from aswarm.core.estimation import slope_weights
from aswarm.flight.clock import Clock

CSV_COLUMNS = ("t", "drone", "x", "y", "z", "qw", "qx", "qy", "qz")
IDENTITY = (1.0, 0.0, 0.0, 0.0)  # wxyz


@dataclasses.dataclass(frozen=True)
class PoseFrame:
    positions: np.ndarray  # [n, 3] m; NaN for a drone not seen yet
    quats: np.ndarray  # [n, 4] wxyz; NaN for a drone not seen yet
    timestamps: np.ndarray  # [n] s (flight clock) of each drone's newest pose; NaN for none
    bad: np.ndarray | None = None  # [n] bool: the newest value served for the drone was not finite
    obstacle_xy: np.ndarray | None = None  # [m, 2] m; NaN for an obstacle not seen yet
    obstacle_vel: np.ndarray | None = None  # [m, 2] m/s, estimated from its poses (0 for a static one)
    obstacle_times: np.ndarray | None = None  # [m] s
    frame_time: float = float("nan")  # s: when the newest frame arrived
    frames: int = 0  # frames received so far


class MocapSource(Protocol):
    """Serves poses; see the module docstring."""

    def start(self, clock: Clock, on_frame: Callable[[PoseFrame], None]) -> None: ...

    def latest(self, now: float) -> PoseFrame: ...

    def anchor(self, now: float) -> None:
        """The control loop starts at ``now`` (a replay starts replaying here; a live source ignores it)."""
        ...

    def finished(self, now: float) -> bool: ...

    def stop(self) -> None: ...


# ------------------------------------------------------------------ live: the motioncapture package
def connect_motioncapture(backend: str, options: dict[str, str]):
    """``motioncapture.connect`` (imported here: the flight side runs without the package unless it is used)."""
    try:
        import motioncapture
    except ImportError as e:
        raise RuntimeError("live motion capture needs the motioncapture package: pip install 'aswarm[flight]'") from e
    try:
        return motioncapture.connect(backend, options)
    except RuntimeError as e:  # e.g. "Unknown motion capture type!" or a refused connection, from the C++ side
        raise ValueError(f"invalid --mocap {backend}:{options.get('hostname', '')}: motioncapture says: {e}") from None


class MotionCaptureSource:
    """Rigid bodies of a ``motioncapture`` connection as drone and obstacle poses.

    ``drones``/``obstacles``: rigid-body names in drone/obstacle order; ``moving``: which obstacles move (their
    velocity is a least-squares slope over their last ``velocity_window`` s of poses). ``connect``: a function
    returning an object with ``waitForNextFrame()`` and ``rigidBodies`` (default: the real package). ``paced_hz``:
    instead of a thread blocking in ``waitForNextFrame``, read frames on the clock's ``every`` at this rate (for a fake
    clock in tests). ``positions``: replaces the served drone positions (``fn(now, served [n, 3]) -> [n, 3]``; the
    rehearsal's kinematics).
    """

    def __init__(self, connect: Callable[[], object], drones: Sequence[str], obstacles: Sequence[str] = (),
                 moving: Sequence[bool] | None = None, *, paced_hz: float | None = None,
                 positions: Callable[[float, np.ndarray], np.ndarray] | None = None, velocity_window: float = 0.1):
        self._connect = connect
        self.drones, self.obstacles = list(drones), list(obstacles)
        self.moving = np.array(moving if moving is not None else [False] * len(self.obstacles), bool)
        self.paced_hz = paced_hz
        self._positions = positions
        self._window = velocity_window
        n, m = len(self.drones), len(self.obstacles)
        self._pos, self._quat, self._t = np.full((n, 3), np.nan), np.full((n, 4), np.nan), np.full(n, np.nan)
        self._bad = np.zeros(n, bool)
        self._oxy, self._ot = np.full((m, 2), np.nan), np.full(m, np.nan)
        self._history = [collections.deque(maxlen=64) for _ in range(m)]
        self._frame_time, self._frames = float("nan"), 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._stop_timer: Callable[[], None] | None = None
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None  # what ended the reading thread, if anything did
        self.seen: set[str] = set()  # every rigid-body name the system has streamed

    def start(self, clock: Clock, on_frame: Callable[[PoseFrame], None]) -> None:
        mc = self._connect()  # on the caller's thread: a refused connection fails here, before anything flies

        def read() -> None:
            self._read(mc, clock.now())
            on_frame(self.latest(clock.now()))

        if self.paced_hz:
            self._stop_timer = clock.every(1.0 / self.paced_hz, lambda now: read())
            return

        def loop() -> None:
            try:
                while not self._stop.is_set():
                    mc.waitForNextFrame()
                    if not self._stop.is_set():
                        read()
            except BaseException as e:  # reported to the flight loop, which stops the drones
                self.error = e

        self._thread = threading.Thread(target=loop, daemon=True, name="aswarm-mocap")
        self._thread.start()

    def _read(self, mc, now: float) -> None:
        bodies = mc.rigidBodies
        with self._lock:
            self.seen.update(bodies)
            served = np.full((len(self.drones), 3), np.nan)
            quats = np.full((len(self.drones), 4), np.nan)
            for i, name in enumerate(self.drones):
                rb = bodies.get(name)
                if rb is not None:
                    served[i] = np.asarray(rb.position, np.float64)
                    q = rb.rotation
                    quats[i] = (q.w, q.x, q.y, q.z)
            have = np.array([name in bodies for name in self.drones], bool)
            if self._positions is not None:
                served = np.where(have[:, None], self._positions(now, served), np.nan)
            finite = np.isfinite(served).all(-1) & np.isfinite(quats).all(-1)
            self._bad = np.where(have, ~finite, self._bad)
            good = have & finite
            self._pos[good], self._quat[good], self._t[good] = served[good], quats[good], now
            for j, name in enumerate(self.obstacles):
                rb = bodies.get(name)
                if rb is None:
                    continue
                xy = np.asarray(rb.position, np.float64)[:2]
                if np.isfinite(xy).all():
                    self._oxy[j], self._ot[j] = xy, now
                    self._history[j].append((now, xy[0], xy[1]))
            self._frame_time, self._frames = now, self._frames + 1

    def latest(self, now: float) -> PoseFrame:
        if self.error is not None:
            raise RuntimeError(f"the motion capture thread stopped: {self.error!r}") from self.error
        with self._lock:
            vel = np.zeros_like(self._oxy)
            for j, hist in enumerate(self._history):
                if self.moving[j]:
                    vel[j] = _slope(hist, self._window)
            return PoseFrame(self._pos.copy(), self._quat.copy(), self._t.copy(), self._bad.copy(), self._oxy.copy(),
                             vel, self._ot.copy(), self._frame_time, self._frames)

    def anchor(self, now: float) -> None:
        pass

    def finished(self, now: float) -> bool:
        return False

    def stop(self) -> None:
        self._stop.set()
        if self._stop_timer is not None:
            self._stop_timer()
        if self._thread is not None:
            # A live system that stopped streaming leaves the thread blocked in waitForNextFrame: it is a daemon.
            self._thread.join(timeout=1.0)


def _slope(hist, window: float) -> np.ndarray:
    """m/s: least-squares slope of the (t, x, y) samples within ``window`` s of the newest."""
    if len(hist) < 2:
        return np.zeros(2)
    a = np.array(hist)
    a = a[a[:, 0] >= a[-1, 0] - window]
    if len(a) < 2:
        return np.zeros(2)
    if np.ptp(a[:, 0]) <= 0:
        return np.zeros(2)
    return slope_weights(a[:, 0]) @ a[:, 1:]  # the runtime's own line fit (core.estimation)


def mock_rigid_bodies(bodies: Sequence[tuple[str, Sequence[float]]]) -> str:
    """The mock backend's ``rigid_bodies`` option: ``name(x,y,z,qw,qx,qy,qz);...`` (level attitude)."""
    for name, _ in bodies:
        if not name or any(c in name for c in "();, "):
            raise ValueError(f"rigid body name {name!r} cannot be served by the mock backend: allowed: names without "
                             "spaces, commas, semicolons or parentheses")
    return ";".join(f"{name}({p[0]:.6f},{p[1]:.6f},{p[2]:.6f},1,0,0,0)" for name, p in bodies)


# ------------------------------------------------------------------ rehearsal kinematics
class KinematicSwarm:
    """Where the drones of a rehearsal are: a kinematic stand-in for the drones, driven by what the link is sent.

    On the ground until take-off; take-off and landing move z at a constant rate over their duration, as the
    high-level commander's trajectories do to first order; velocity setpoints move a drone through a first-order lag
    (``lag`` (xy, z) s: the bundle's measured velocity lag); an emergency stop drops it to the floor. No physics, no
    collisions: it shows that the loop, its timing and the course work together, not how the real drones will fly.
    """

    def __init__(self, initial: np.ndarray, lag: tuple[float, float] = (0.34, 0.22)):
        self.pos = np.array(initial, np.float64).reshape(-1, 3)
        self.home = self.pos.copy()
        n = len(self.pos)
        self.vel = np.zeros((n, 3))
        self.cmd = np.zeros((n, 3))
        self.tau = np.array([lag[0], lag[0], lag[1]], np.float64)
        self.mode = ["ground"] * n
        self.ramp = [(0.0, 0.0, 0.0, 0.0)] * n  # (t0, z0, z1, duration) of a take-off or landing
        self.t: float | None = None
        self._lock = threading.Lock()

    def _advance(self, now: float) -> None:
        if self.t is None:
            self.t = now
        dt = max(0.0, now - self.t)
        self.t = max(self.t, now)
        if dt == 0.0:
            return
        decay = np.exp(-dt / self.tau)
        for i, mode in enumerate(self.mode):
            if mode == "velocity":
                v0 = self.vel[i]
                v1 = self.cmd[i] + (v0 - self.cmd[i]) * decay
                # The exact integral of the lagged velocity over dt.
                self.pos[i] += self.cmd[i] * dt + (v0 - self.cmd[i]) * self.tau * (1.0 - decay)
                self.vel[i] = v1
            elif mode in ("takeoff", "land"):
                t0, z0, z1, dur = self.ramp[i]
                s = 1.0 if dur <= 0 else min(1.0, (now - t0) / dur)
                self.pos[i, 2] = z0 + (z1 - z0) * s
                self.vel[i] = 0.0
                if s >= 1.0:
                    self.mode[i] = "hover" if mode == "takeoff" else "ground"
            self.pos[i, 2] = max(self.pos[i, 2], 0.0)

    def positions(self, now: float) -> np.ndarray:
        with self._lock:
            self._advance(now)
            return self.pos.copy()

    def served(self, now: float, served: np.ndarray) -> np.ndarray:
        """The mock's fixed bodies moved by the kinematics: served - home + where the drone is now."""
        return served - self.home + self.positions(now)

    def takeoff(self, now: float, height: float, duration: float) -> None:
        with self._lock:
            self._advance(now)
            for i in range(len(self.pos)):
                self.mode[i] = "takeoff"
                self.ramp[i] = (now, self.pos[i, 2], height, duration)

    def velocity(self, now: float, drones: np.ndarray, velocities: np.ndarray) -> None:
        with self._lock:
            self._advance(now)
            for i in np.flatnonzero(drones):
                if self.mode[i] in ("hover", "velocity"):
                    self.mode[i] = "velocity"
                    self.cmd[i] = velocities[i]

    def land(self, now: float, drones: Sequence[int], duration: float) -> None:
        with self._lock:
            self._advance(now)
            for i in drones:
                if self.mode[i] != "ground":
                    self.mode[i] = "land"
                    self.ramp[i] = (now, self.pos[i, 2], 0.0, duration)

    def stop(self, now: float) -> None:
        with self._lock:
            self._advance(now)
            for i in range(len(self.pos)):
                self.mode[i] = "ground"
                self.pos[i, 2] = 0.0
                self.vel[i] = 0.0


# ------------------------------------------------------------------ replay
class ReplaySource:
    """Poses replayed from a CSV (columns :data:`CSV_COLUMNS`, ``nan`` for a missing pose); ``t`` counts from the
    control loop's start, before which every drone holds its first pose (stamped as fresh)."""

    def __init__(self, path: str | Path, num_drones: int):
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"mocap replay file {path} does not exist: allowed: a CSV with columns "
                             f"{','.join(CSV_COLUMNS)}")
        with path.open(newline="") as f:
            reader = csv.DictReader(f)
            missing = [c for c in CSV_COLUMNS if c not in (reader.fieldnames or [])]
            if missing:
                raise ValueError(f"mocap replay {path} lacks column {missing[0]!r}: allowed header "
                                 f"{','.join(CSV_COLUMNS)}")
            rows = []
            for i, row in enumerate(reader, start=2):
                try:
                    rows.append([float(row[c]) for c in CSV_COLUMNS])
                except (TypeError, ValueError):
                    raise ValueError(f"mocap replay {path} line {i}: {row}: allowed: numbers (nan for a missing "
                                     "pose)") from None
        if not rows:
            raise ValueError(f"mocap replay {path} has no poses")
        data = np.array(rows)
        drone = data[:, 1]
        wrong = (drone != np.round(drone)) | (drone < 0) | (drone >= num_drones)
        if np.any(wrong):
            raise ValueError(f"mocap replay {path}: drone {drone[wrong][0]:g}: allowed: integers 0..{num_drones - 1} "
                             "(the drone order: --uris, or the swarm file's)")
        if not np.all(np.isfinite(data[:, 0])):
            raise ValueError(f"mocap replay {path}: every row needs a finite time t")
        order = np.argsort(data[:, 0], kind="stable")
        self.data = data[order]
        self.n = num_drones
        self.start_t = float(self.data[0, 0])
        self.end = float(self.data[-1, 0])
        gaps = np.diff(np.unique(self.data[:, 0]))
        self.rate_hz = float(1.0 / np.median(gaps)) if len(gaps) else 100.0
        self._first = np.full((num_drones, 7), np.nan)
        for row in self.data[::-1]:
            self._first[int(row[1])] = row[2:]
        self._i = 0
        self._anchor: float | None = None
        self._frame = PoseFrame(np.full((num_drones, 3), np.nan), np.full((num_drones, 4), np.nan),
                                np.full(num_drones, np.nan))
        self._stop_timer: Callable[[], None] | None = None
        self._frames = 0
        self._lock = threading.Lock()  # a real-time replay is read by its ticker thread and the control loop

    def start(self, clock: Clock, on_frame: Callable[[PoseFrame], None]) -> None:
        def tick(now: float) -> None:
            self._frames += 1
            on_frame(self.latest(now))

        self._stop_timer = clock.every(1.0 / self.rate_hz, tick)

    def anchor(self, now: float) -> None:
        self._anchor = now

    def latest(self, now: float) -> PoseFrame:
        with self._lock:
            return self._latest(now)

    def _latest(self, now: float) -> PoseFrame:
        if self._anchor is None:
            ts = np.where(np.isfinite(self._first[:, 0]), now, np.nan)
            return PoseFrame(self._first[:, :3].copy(), self._first[:, 3:].copy(), ts, np.zeros(self.n, bool),
                             frame_time=now, frames=self._frames)
        replay_t = now - self._anchor + self.start_t
        if replay_t > self.end + 1e-9:  # after the end every drone holds its last pose, as before the start
            last = self._final()
            ts = np.where(np.isfinite(last.positions).all(-1), now, np.nan)
            return dataclasses.replace(last, timestamps=ts, frame_time=now, frames=self._frames)
        pos, quat, ts = self._frame.positions.copy(), self._frame.quats.copy(), self._frame.timestamps.copy()
        while self._i < len(self.data) and self.data[self._i, 0] <= replay_t + 1e-9:
            t, d, x, y, z, qw, qx, qy, qz = self.data[self._i]
            k = int(d)
            pos[k], quat[k] = (x, y, z), (qw, qx, qy, qz)
            # A nan row is a missing pose: the drone has none at that time.
            ts[k] = t - self.start_t + self._anchor if np.isfinite([x, y, z]).all() else np.nan
            self._i += 1
        self._frame = PoseFrame(pos, quat, ts, np.zeros(self.n, bool), frame_time=now, frames=self._frames)
        return self._frame

    def _final(self) -> PoseFrame:
        """The replay's last pose of every drone."""
        while self._i < len(self.data):
            self._latest(self._anchor + self.end - self.start_t)
        return self._frame

    def finished(self, now: float) -> bool:
        return self._anchor is not None and now - self._anchor + self.start_t > self.end + 1e-9

    def stop(self) -> None:
        if self._stop_timer is not None:
            self._stop_timer()

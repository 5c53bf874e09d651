"""The radio side of ``aswarm fly``: the :class:`Link` protocol, a recording stand-in and the cflib swarm.

The flight sequence (:func:`aswarm.flight.fly.fly`) talks to the drones only through a :class:`Link`, one method per
thing it does, so the sequence can be checked without radios: :class:`RecordingLink` records every call with the
flight clock's time and can be told to fail (a lost link at setpoint round k, a low battery, an estimator that never
settles, Ctrl-C); :class:`DryRunLink` is the same and prints what it is sent; :class:`CflibLink` sends it to
Crazyflies with cflib (imported when it connects, never before).

cflib units: ``send_velocity_world_setpoint(vx, vy, vz, yawrate)`` m/s in the world frame and **degrees/s** (sent as
0: the policy was trained with the onboard controller holding yaw); ``send_extpose(x, y, z, qx, qy, qz, qw)``;
high-level ``takeoff(height_m, duration_s)``, ``land(0.0, duration_s)``, ``stop()`` (motors off).
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable, Sequence
from typing import Protocol

import numpy as np

from aswarm.flight.clock import Clock

YAW_RATE_DEG_S = 0.0  # cflib's yaw rate unit is degrees per second
# supervisor.info bits (firmware supervisor.c; cflib's Supervisor.STATES)
CAN_BE_ARMED, IS_ARMED, CAN_FLY, IS_FLYING = 1 << 0, 1 << 1, 1 << 3, 1 << 4


@dataclasses.dataclass(frozen=True)
class Telemetry:
    """The newest values logged from each drone (NaN / -1 where none arrived yet)."""

    estimate: np.ndarray  # [n, 3] m, stateEstimate.x/y/z
    vbat: np.ndarray  # [n] V, pm.vbat
    supervisor: np.ndarray  # [n] int, supervisor.info bitfield; -1 unknown (firmware without it)
    variance: np.ndarray  # [n, 3] m^2, kalman.varPX/varPY/varPZ
    variance_seq: np.ndarray  # [n] int: variance samples received so far (a sample is counted once, however polled)


class Link(Protocol):
    """One method per thing the flight sequence does to the swarm (drone i is ``uris[i]``)."""

    uris: list[str]

    def connect(self) -> None: ...

    def set_params(self, params: dict) -> None: ...

    def send_poses(self, positions: np.ndarray, quats: np.ndarray, valid: np.ndarray) -> None:
        """extpose for every valid drone; called on the mocap thread at the mocap rate."""
        ...

    def reset_estimators(self) -> None: ...

    def telemetry(self) -> Telemetry: ...

    def lost(self) -> dict[str, str]:
        """uri -> cflib's message for every link lost since connect."""
        ...

    def arm(self) -> None: ...

    def takeoff(self, height: float, duration: float) -> None:
        """Start every drone's take-off; returns at once (the sequence waits on its clock, streaming poses)."""
        ...

    def send_velocities(self, t: float, velocities: np.ndarray, active: np.ndarray) -> None: ...

    def send_full_states(self, t: float, positions: np.ndarray, velocities: np.ndarray,
                         active: np.ndarray) -> None: ...

    def land(self, drones: Sequence[int], duration: float) -> None: ...

    def stop(self) -> None:
        """After landing: motors off (the high-level commander's stop) and disarm."""
        ...

    def emergency_stop(self) -> None: ...

    def close(self) -> None: ...


# ------------------------------------------------------------------ stand-in
@dataclasses.dataclass(frozen=True)
class Failures:
    """What a :class:`RecordingLink` gets wrong, to check that the sequence stops the drones."""

    lost_link_at: int | None = None  # the link to drone ``drone`` is lost at this setpoint round (0-based)
    interrupt_at: int | None = None  # this setpoint round raises KeyboardInterrupt (Ctrl-C)
    drone: int = 0
    battery: float = 4.10  # V every drone reports
    low_battery: float | None = None  # V drone ``drone`` reports instead
    settle_after: float | None = 0.3  # s after a reset until the estimator's variances hold still; None: never


@dataclasses.dataclass(frozen=True)
class Call:
    t: float  # s, the flight clock
    name: str
    args: tuple = ()


class RecordingLink:
    """Records every call with its time; reports a battery, a settling estimator and the poses it was sent.

    ``kinematics`` (a :class:`aswarm.flight.mocap.KinematicSwarm`) is moved by the commands, for a rehearsal.
    """

    def __init__(self, uris: Sequence[str], clock: Clock | None = None, failures: Failures = Failures(),
                 kinematics=None):
        self.uris = list(uris)
        self.clock = clock  # None: the flight's clock, set by fly()
        self.failures = failures
        self.kinematics = kinematics
        self.calls: list[Call] = []
        n = len(self.uris)
        self._estimate = np.full((n, 3), np.nan)
        self._reset_at: float | None = None
        self._samples = 0
        self._rounds = 0
        self._lost: dict[str, str] = {}
        self._bits = np.full(n, CAN_BE_ARMED)
        self._lock = threading.Lock()  # poses arrive on the mocap thread

    def _now(self) -> float:
        return self.clock.now() if self.clock is not None else time.monotonic()

    def _record(self, name: str, *args) -> float:
        t = self._now()
        with self._lock:
            self.calls.append(Call(t, name, args))
        return t

    def connect(self) -> None:
        self._record("connect")

    def set_params(self, params: dict) -> None:
        self._record("set_params", dict(params))

    def send_poses(self, positions, quats, valid) -> None:
        self._record("send_poses", np.array(positions), np.array(valid))
        with self._lock:
            self._estimate = np.where(np.asarray(valid)[:, None], positions, self._estimate)

    def reset_estimators(self) -> None:
        self._reset_at = self._record("reset_estimators")

    def telemetry(self) -> Telemetry:
        n = len(self.uris)
        f = self.failures
        vbat = np.full(n, f.battery)
        if f.low_battery is not None:
            vbat[f.drone] = f.low_battery
        now = self._now()
        self._samples += 1
        settled = (self._reset_at is not None and f.settle_after is not None and now - self._reset_at >= f.settle_after)
        # Unsettled: variances that keep moving (what the convergence check watches), settled: constant.
        var = np.full((n, 3), 1e-4 if settled else 1e-2 * (1 + self._samples % 2))
        with self._lock:
            return Telemetry(self._estimate.copy(), vbat, self._bits.copy(), var, np.full(n, self._samples))

    def lost(self) -> dict[str, str]:
        return dict(self._lost)

    def arm(self) -> None:
        self._record("arm")
        self._bits |= IS_ARMED | CAN_FLY

    def takeoff(self, height: float, duration: float) -> None:
        t = self._record("takeoff", height, duration)
        self._bits |= IS_FLYING
        if self.kinematics is not None:
            self.kinematics.takeoff(t, height, duration)

    def _round(self) -> None:
        f = self.failures
        k = self._rounds
        self._rounds += 1
        if f.interrupt_at is not None and k == f.interrupt_at:
            raise KeyboardInterrupt
        if f.lost_link_at is not None and k >= f.lost_link_at:
            self._lost[self.uris[f.drone]] = "Too many packets lost"

    def send_velocities(self, t: float, velocities: np.ndarray, active: np.ndarray) -> None:
        self._round()
        now = self._record("send_velocities", np.array(velocities), np.array(active))
        if self.kinematics is not None:
            self.kinematics.velocity(now, active, velocities)

    def send_full_states(self, t: float, positions: np.ndarray, velocities: np.ndarray, active: np.ndarray) -> None:
        self._round()
        now = self._record("send_full_states", np.array(positions), np.array(velocities), np.array(active))
        if self.kinematics is not None:
            self.kinematics.velocity(now, active, velocities)

    def land(self, drones: Sequence[int], duration: float) -> None:
        t = self._record("land", tuple(int(i) for i in drones), duration)
        if self.kinematics is not None:
            self.kinematics.land(t, drones, duration)

    def stop(self) -> None:
        t = self._record("stop")
        self._bits &= ~(IS_ARMED | IS_FLYING)
        if self.kinematics is not None:
            self.kinematics.stop(t)

    def emergency_stop(self) -> None:
        t = self._record("emergency_stop")
        self._bits &= ~(IS_ARMED | IS_FLYING)
        if self.kinematics is not None:
            self.kinematics.stop(t)

    def close(self) -> None:
        self._record("close")

    # For tests and reports.
    def names(self) -> list[str]:
        return [c.name for c in self.calls]

    def times(self, name: str) -> np.ndarray:
        return np.array([c.t for c in self.calls if c.name == name])


class DryRunLink(RecordingLink):
    """A :class:`RecordingLink` that prints what would be sent, one line per command (``setpoints=False``: the
    sequence only, for long rehearsals); needs no radio and no cflib."""

    def __init__(self, uris: Sequence[str], out: Callable[[str], None] = print, clock: Clock | None = None,
                 failures: Failures = Failures(), kinematics=None, setpoints: bool = True,
                 names: Sequence[str] | None = None):
        super().__init__(uris, clock, failures, kinematics)
        self.out = out
        self.setpoints = setpoints
        self.names = list(names) if names else [f"cf{i}" for i in range(len(self.uris))]

    def connect(self) -> None:
        super().connect()
        self.out(f"connect {len(self.uris)} drones (dry run: no radio)")

    def set_params(self, params: dict) -> None:
        super().set_params(params)
        for name, value in params.items():
            self.out(f"param all {name}={value}")

    def reset_estimators(self) -> None:
        super().reset_estimators()
        self.out("reset estimators all (kalman.resetEstimation 1, 0)")

    def arm(self) -> None:
        super().arm()
        self.out("arm all")

    def takeoff(self, height: float, duration: float) -> None:
        super().takeoff(height, duration)
        self.out(f"takeoff all height={height:.2f} m duration={duration:.1f} s")

    def send_velocities(self, t: float, velocities: np.ndarray, active: np.ndarray) -> None:
        super().send_velocities(t, velocities, active)
        if not self.setpoints:
            return
        for i, (uri, v) in enumerate(zip(self.uris, velocities)):
            if active[i]:
                self.out(f"t={t:.3f} {self.names[i]} {uri} send_velocity_world_setpoint vx={v[0]:+.3f} vy={v[1]:+.3f} "
                         f"vz={v[2]:+.3f} m/s yawrate={YAW_RATE_DEG_S:g} deg/s")

    def send_full_states(self, t: float, positions: np.ndarray, velocities: np.ndarray, active: np.ndarray) -> None:
        super().send_full_states(t, positions, velocities, active)
        if not self.setpoints:
            return
        for i, (uri, p, v) in enumerate(zip(self.uris, positions, velocities)):
            if active[i]:
                self.out(f"t={t:.3f} {self.names[i]} {uri} send_full_state_setpoint pos=({p[0]:+.3f}, {p[1]:+.3f}, "
                         f"{p[2]:+.3f}) m vel=({v[0]:+.3f}, {v[1]:+.3f}, {v[2]:+.3f}) m/s acc=0 level rates=0")

    def land(self, drones: Sequence[int], duration: float) -> None:
        super().land(drones, duration)
        for i in drones:
            self.out(f"land {self.names[i]} {self.uris[i]} duration={duration:.1f} s")

    def stop(self) -> None:
        super().stop()
        self.out("stop all (motors off) and disarm")

    def emergency_stop(self) -> None:
        super().emergency_stop()
        self.out("EMERGENCY STOP all")


# ------------------------------------------------------------------ cflib
@dataclasses.dataclass(frozen=True)
class CflibConfig:
    cache: str = "./cache"  # cflib's TOC cache folder (connecting without it downloads every TOC)
    telemetry_ms: int = 100  # log period of stateEstimate.x/y/z, pm.vbat, supervisor.info
    variance_ms: int = 100  # log period of kalman.varPX/varPY/varPZ


class CflibLink:
    """A cflib ``Swarm`` (``pip install 'aswarm[flight]'``); cflib is imported in :meth:`connect`."""

    def __init__(self, uris: Sequence[str], config: CflibConfig = CflibConfig()):
        self.uris = list(uris)
        self.config = config
        n = len(self.uris)
        self.cfs: dict = {}
        self.swarm = None
        self._estimate = np.full((n, 3), np.nan)
        self._vbat = np.full(n, np.nan)
        self._supervisor = np.full(n, -1)
        self._variance = np.full((n, 3), np.nan)
        self._variance_seq = np.zeros(n, np.int64)
        self._lost: dict[str, str] = {}
        self._lock = threading.Lock()

    def connect(self) -> None:
        try:
            import cflib.crtp
            from cflib.crazyflie.log import LogConfig
            from cflib.crazyflie.swarm import CachedCfFactory, Swarm
        except ImportError as e:
            raise RuntimeError("flying needs cflib: pip install 'aswarm[flight]' (or use --dry-run)") from e
        cflib.crtp.init_drivers()
        self.swarm = Swarm(self.uris, factory=CachedCfFactory(rw_cache=self.config.cache))
        self.swarm.open_links()  # in parallel, one thread per drone
        self.swarm.parallel_safe(lambda scf: self.cfs.__setitem__(scf.cf.link_uri, scf.cf))
        for i, uri in enumerate(self.uris):
            cf = self.cfs[uri]
            cf.connection_lost.add_callback(lambda link_uri, msg: self._lost.__setitem__(link_uri, str(msg)))
            tele = LogConfig(name="aswarm", period_in_ms=self.config.telemetry_ms)
            for name in ("stateEstimate.x", "stateEstimate.y", "stateEstimate.z", "pm.vbat"):
                tele.add_variable(name, "float")
            if cf.log.toc.get_element_by_complete_name("supervisor.info") is not None:  # firmware from 2024 on
                tele.add_variable("supervisor.info", "uint16_t")
            tele.data_received_cb.add_callback(lambda ts, data, lc, i=i: self._telemetry(i, data))
            var = LogConfig(name="aswarm_var", period_in_ms=self.config.variance_ms)
            for name in ("kalman.varPX", "kalman.varPY", "kalman.varPZ"):
                var.add_variable(name, "float")
            var.data_received_cb.add_callback(lambda ts, data, lc, i=i: self._variances(i, data))
            for lc in (tele, var):
                cf.log.add_config(lc)
                lc.start()

    def _telemetry(self, i: int, data: dict) -> None:
        with self._lock:
            self._estimate[i] = (data["stateEstimate.x"], data["stateEstimate.y"], data["stateEstimate.z"])
            self._vbat[i] = data["pm.vbat"]
            self._supervisor[i] = data.get("supervisor.info", -1)

    def _variances(self, i: int, data: dict) -> None:
        with self._lock:
            self._variance[i] = (data["kalman.varPX"], data["kalman.varPY"], data["kalman.varPZ"])
            self._variance_seq[i] += 1

    def set_params(self, params: dict) -> None:
        for uri in self.uris:
            for name, value in params.items():
                self.cfs[uri].param.set_value(name, str(value))

    def send_poses(self, positions, quats, valid) -> None:
        for i, uri in enumerate(self.uris):
            if valid[i]:
                (x, y, z), (qw, qx, qy, qz) = positions[i], quats[i]
                # cflib's order: x y z qx qy qz qw
                self.cfs[uri].extpos.send_extpose(float(x), float(y), float(z), float(qx), float(qy), float(qz),
                                                  float(qw))

    def reset_estimators(self) -> None:
        for uri in self.uris:
            self.cfs[uri].param.set_value("kalman.resetEstimation", "1")
        time.sleep(0.1)  # the firmware resets on the rising edge; the poses keep streaming on the mocap thread
        for uri in self.uris:
            self.cfs[uri].param.set_value("kalman.resetEstimation", "0")

    def telemetry(self) -> Telemetry:
        with self._lock:
            return Telemetry(self._estimate.copy(), self._vbat.copy(), self._supervisor.copy(), self._variance.copy(),
                             self._variance_seq.copy())

    def lost(self) -> dict[str, str]:
        return dict(self._lost)

    def _each(self, fn: Callable) -> None:
        for uri in self.uris:
            fn(self.cfs[uri])

    def arm(self) -> None:
        # cflib >= 0.1.29 has the supervisor (with its own fallback for old firmware); older cflib the platform call.
        self._each(lambda cf: cf.supervisor.send_arming_request(True) if hasattr(cf, "supervisor")
                   else cf.platform.send_arming_request(True))

    def takeoff(self, height: float, duration: float) -> None:
        self._each(lambda cf: cf.high_level_commander.takeoff(height, duration))

    def send_velocities(self, t: float, velocities: np.ndarray, active: np.ndarray) -> None:
        for i, uri in enumerate(self.uris):
            if active[i]:
                vx, vy, vz = (float(v) for v in velocities[i])
                self.cfs[uri].commander.send_velocity_world_setpoint(vx, vy, vz, YAW_RATE_DEG_S)

    def send_full_states(self, t: float, positions: np.ndarray, velocities: np.ndarray, active: np.ndarray) -> None:
        for i, uri in enumerate(self.uris):
            if active[i]:
                pos, vel = [float(x) for x in positions[i]], [float(x) for x in velocities[i]]
                # cflib: orientation [qx, qy, qz, qw], rates in deg/s
                self.cfs[uri].commander.send_full_state_setpoint(pos, vel, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0],
                                                                 0.0, 0.0, YAW_RATE_DEG_S)

    def land(self, drones: Sequence[int], duration: float) -> None:
        for i in drones:
            cf = self.cfs[self.uris[i]]
            cf.commander.send_notify_setpoint_stop()  # back to the high-level commander
            cf.high_level_commander.land(0.0, duration)

    def stop(self) -> None:
        def stop_one(cf) -> None:
            cf.high_level_commander.stop()
            if hasattr(cf, "supervisor"):
                cf.supervisor.send_arming_request(False)

        self._each(stop_one)

    def emergency_stop(self) -> None:
        for uri in self.uris:
            cf = self.cfs.get(uri)
            if cf is None:
                continue
            try:
                if hasattr(cf, "supervisor"):
                    cf.supervisor.send_emergency_stop()
                else:
                    cf.loc.send_emergency_stop()
            except Exception:  # keep stopping the others
                pass

    def close(self) -> None:
        if self.swarm is not None:
            self.swarm.close_links()

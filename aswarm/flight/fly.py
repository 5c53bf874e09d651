"""``aswarm fly``: fly a bundle's policy on a Crazyflie swarm with live motion capture (numpy; cflib only when flying).

The sequence (Bitcraze's mocap swarm example, done for a swarm and a streamed policy):

1. connect to every drone in parallel (:class:`~aswarm.flight.links.CflibLink`; cflib imported only here);
2. set the onboard controller the bundle was trained on (manifest ``drone.firmware_params``: ``stabilizer.controller``
   1 is the firmware PID, 2 Mellinger) and the Kalman estimator (``stabilizer.estimator = 2``, and
   ``locSrv.extQuatStdDev = 0.06``, the example's attitude noise for mocap quaternions);
3. start the pose stream: every mocap frame is forwarded (``extpose``) on the mocap thread, at the mocap rate, from
   here until the motors are off;
4. wait until every drone's rigid body is streamed; reset the estimators and wait until they settle (the example's
   check: over the last ``variance_window`` samples, ``kalman.varPX/varPY/varPZ`` each vary by less than
   ``variance_threshold``);
5. refuse to fly, in one line, unless every battery is at least ``min_battery`` at rest and every drone has a valid
   pose fresher than ``stale_after`` (nothing is armed or sent then);
6. arm, take off with the high-level commander, and wait for the take-off while watching the swarm;
7. the control loop at the manifest's rate (``FlightController.step`` on the newest poses; velocity setpoints, or
   full states for Mellinger), each drone released as the simulator released it (drone i after i *
   ``start_interval`` s on a track; held at a zero command before, as in training); a drone the runtime asks to land
   is handed to the high-level commander's ``land``;
8. land everyone else, keep the poses streaming until the landing is over, stop the motors and disarm, stop the
   pose stream, close the links.

Watched throughout (from connecting to the motors stopping): a lost radio link (cflib's ``connection_lost``), a
rigid body with no pose for longer than ``pose_lost_after``, a NaN/Inf pose from the mocap, a failed mocap thread,
Ctrl-C and any exception stop every drone at once (``emergency_stop``). Before arming, a failed check refuses the
flight without an emergency stop (that would lock unarmed drones until they are restarted). The flight record
(:mod:`aswarm.flight.record`) is written in every case.

Units and conventions (cflib): ``send_velocity_world_setpoint`` takes vx, vy, vz in **m/s** in the world frame and the
yaw rate in **degrees/s**, sent as 0 (the policy was trained with the onboard controller holding yaw). The firmware's
commander watchdog levels a drone that gets no setpoint for 500 ms and cuts its motors after 2 s: the loop streams
one setpoint per drone per control period (40 ms at 25 Hz).

Mocap: ``--mocap vicon:HOST`` (any backend of the ``motioncapture`` package: optitrack, qualisys, vrpn, nokov, ...)
with a swarm file (``--config``, :mod:`aswarm.flight.swarm_config`) naming each drone's rigid body; ``--mocap mock``
rehearses with the package's mock backend and a kinematic stand-in for the drones (dry run only); ``--mocap
replay:POSES.csv`` replays a CSV (``t,drone,x,y,z,qw,qx,qy,qz``, t from the control loop's start; dry run only), with
the drones in ``--uris`` or the swarm file's order.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from aswarm.core import command
from aswarm.flight import estimator
from aswarm.flight.bundle import Bundle, load_bundle
from aswarm.flight.clock import Clock, FakeClock, RealClock
from aswarm.flight.links import CflibLink, DryRunLink, Link, RecordingLink
from aswarm.flight.mocap import (
    CSV_COLUMNS,
    KinematicSwarm,
    MocapSource,
    MotionCaptureSource,
    PoseFrame,
    ReplaySource,
    connect_motioncapture,
    mock_rigid_bodies,
)
from aswarm.flight.record import PHASES, FlightRecorder, format_timing
from aswarm.flight.runtime import FlightController, Obstacles, SafetyConfig
from aswarm.flight.swarm_config import SwarmConfig, load_swarm_config

__all__ = ["CSV_COLUMNS", "CflibLink", "DryRunLink", "FlightAbort", "FlightChecks", "FlightPlan", "FlightRefused",
           "Link", "MocapSource", "PoseFrame", "RecordingLink", "ReplaySource", "course_from", "fly", "main",
           "release_times", "run", "variances_settled"]


class FlightRefused(RuntimeError):
    """A check before arming failed: nothing was armed or sent."""


class FlightAbort(RuntimeError):
    """Something went wrong with drones armed: every drone got an emergency stop."""


@dataclasses.dataclass(frozen=True)
class FlightPlan:
    takeoff_height: float = 1.0  # m: where the simulator's drones start (the race's start_center z)
    takeoff_seconds: float = 2.0
    settle_seconds: float = 0.5  # hover after the take-off before the policy starts
    land_seconds: float = 2.0
    landed_margin: float = 0.5  # s the poses keep streaming after a landing's duration before the motors stop
    max_seconds: float = 60.0  # the control loop ends (and lands everyone) after this long
    realtime: bool = True  # on the wall clock; False: a fake clock (replays in tests and non-realtime dry runs)


@dataclasses.dataclass(frozen=True)
class FlightChecks:
    # Kalman estimator (stabilizer.estimator 2) and Bitcraze's attitude noise for mocap quaternions.
    estimator_params: tuple[tuple[str, float], ...] = (("stabilizer.estimator", 2), ("locSrv.extQuatStdDev", 0.06))
    # V at rest, before arming. The firmware's discharge table for the stock 250 mAh cell (pm_stm32f4.c,
    # bat671723HS25C) puts 3.78 V at 10 % charge and 3.00 V at 0 %: below 3.7 V at rest the cell is nearly empty and
    # sags under the ~0.5 V hover load to the firmware's 3.2 V low-battery level within the flight.
    min_battery: float = 3.7
    pose_timeout: float = 5.0  # s for every rigid body to appear in the stream
    telemetry_timeout: float = 3.0  # s for every drone's first battery reading
    converge_timeout: float = 10.0  # s for the estimators to settle after the reset
    variance_window: int = 10  # samples (Bitcraze's check: 10)
    variance_threshold: float = 1e-3  # m^2, largest change of each variance over the window (Bitcraze's: 0.001)
    poll_seconds: float = 0.1  # how often the sequence looks at the variances and the swarm before take-off
    # s without a pose before every drone is stopped. The runtime hovers a drone from stale_after (0.1 s); without
    # extpose the Kalman estimator runs on the IMU alone and drifts by decimetres within a second, so past 0.3 s a
    # drone is stopped rather than flown on a drifting estimate.
    pose_lost_after: float = 0.3

    def __post_init__(self) -> None:
        for name in ("min_battery", "pose_timeout", "telemetry_timeout", "converge_timeout", "variance_threshold",
                     "poll_seconds", "pose_lost_after"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"invalid {name}={v!r}: must be a number > 0")
        if self.variance_window < 2:
            raise ValueError(f"invalid variance_window={self.variance_window!r}: must be >= 2 samples")


def variances_settled(history: np.ndarray, window: int, threshold: float) -> np.ndarray:
    """[n] bool: each drone's last ``window`` samples of ``history`` [T, n, 3] (kalman.varPX/Y/Z) are finite and each
    varies by less than ``threshold`` (Bitcraze's convergence check)."""
    history = np.asarray(history, np.float64)
    if history.ndim != 3 or len(history) < window:
        return np.zeros(history.shape[1] if history.ndim == 3 else 0, bool)
    h = history[-window:]
    return np.all(np.isfinite(h).all(0) & (h.max(0) - h.min(0) < threshold), -1)


def release_times(bundle: Bundle) -> np.ndarray:
    """[n] s after the control loop starts when each drone may go: i * ``start_interval`` on a track, as the
    simulator released them (``SwarmEnv._release_time``); 0 elsewhere, or where the bundle does not record it."""
    n = bundle.num_agents
    if bundle.kind != "track":
        return np.zeros(n)
    src = bundle.manifest.get("source", {}).get("env_config") or {}
    interval = src.get("start_interval", bundle.manifest["scenario"].get("env_overrides", {}).get("start_interval", 0))
    return np.arange(n) * float(interval or 0.0)


def course_from(bundle: Bundle, course_file: str | Path | None) -> dict:
    """reset() arguments: the course file's gates/goals/obstacles, else the manifest's nominal course."""
    spec = json.loads(Path(course_file).read_text()) if course_file else {}
    out = {}
    if bundle.kind == "track":
        out["gates"] = np.asarray(spec.get("gates", bundle.manifest["course"]["gates"]), float)
    else:
        if "goals" not in spec:
            raise ValueError(f"scenario kind {bundle.kind!r} needs goals: allowed: --course FILE with "
                             '{"goals": [[x, y, z], ...]} (one per drone)')
        out["goals"] = np.asarray(spec["goals"], float)
    obstacles = spec.get("obstacles")
    if obstacles:
        ob = np.asarray(obstacles, float)
        if ob.ndim != 2 or ob.shape[1] != 3:
            raise ValueError(f"course obstacles have shape {ob.shape}: allowed: [[x, y, radius], ...] (m)")
        out["obstacles"] = Obstacles(pos=ob[:, :2], radius=ob[:, 2])
    return out


def fly(bundle: Bundle, link: Link, mocap: MocapSource, *, plan: FlightPlan = FlightPlan(),
        safety: SafetyConfig = SafetyConfig(), course: dict | None = None, clock: Clock | None = None,
        log: Callable[[str], None] = print, estimation: estimator.EstimatorConfig = estimator.EstimatorConfig(),
        checks: FlightChecks = FlightChecks(), swarm: SwarmConfig | None = None, record: str | Path | None = None,
        meta: Mapping | None = None) -> dict:
    """Run the whole sequence (module docstring) on ``link`` with poses from ``mocap``; returns a summary.

    ``swarm``: the swarm file (names, rigid bodies, obstacles' radii); ``record``: where to write the flight record
    (``.npz`` and ``.json``), written whatever happens. Raises :class:`FlightRefused` (nothing armed),
    :class:`FlightAbort` (emergency stop sent), or what interrupted the flight (after the emergency stop).
    """
    n = len(link.uris)
    ctl = FlightController(bundle, n, safety=safety, estimation=estimation)
    course = dict(course or course_from(bundle, None))
    fixed_obstacles = course.pop("obstacles", None)
    ctl.reset(**course)
    period = 1.0 / bundle.rate_hz
    drone = bundle.manifest.get("drone", {})
    full_state = drone.get("setpoint") == "full_state"
    if full_state and (not isinstance(drone.get("reference_leash"), int | float) or not drone["reference_leash"] > 0):
        raise ValueError(f"invalid manifest drone.reference_leash={drone.get('reference_leash')!r}: allowed: a "
                         "number > 0 (m) for full-state setpoints; export the bundle again")
    names = swarm.names if swarm else [f"cf{i}" for i in range(n)]
    bodies = [d.rigid_body for d in swarm.drones] if swarm else names
    obstacle_entries = swarm.obstacles if swarm else ()
    m = len(obstacle_entries)
    moving_bound = float(bundle.env.get("moving_accel_bound", 0.0))
    obstacle_accel = (np.array([o.accel if o.accel is not None else (moving_bound if o.moving else 0.0)
                                for o in obstacle_entries]) if any(o.moving for o in obstacle_entries) else None)
    release = release_times(bundle)
    clock = clock or (RealClock() if plan.realtime else FakeClock())
    if isinstance(link, RecordingLink) and link.clock is None:
        link.clock = clock
    if full_state:
        log(f"the policy was trained on {drone.get('controller')}: streaming full-state setpoints along the "
            f"integrated command (reference leash {float(drone['reference_leash']):g} m)")
    if drone.get("controller") == "geometric":
        log("warning: the policy was trained on the geometric controller, which the firmware does not have; "
            "the drones fly controller_pid (retrain on the default drone)")
    if release.any():
        log(f"staggered starts as trained: drone i released after {release[1]:g} s x i")

    t_begin = clock.now()
    rec = FlightRecorder(n, m, t_begin, {
        "format": "aswarm-flight-record", "version": 1,
        "started": datetime.datetime.now().isoformat(timespec="seconds"),
        "bundle": str(bundle.path), "scenario": bundle.scenario, "kind": bundle.kind, "rate_hz": bundle.rate_hz,
        "names": names, "uris": list(link.uris), "rigid_bodies": bodies,
        "obstacles": [o.name for o in obstacle_entries], "obstacle_radius": [o.radius for o in obstacle_entries],
        "course": {k: np.asarray(v).tolist() for k, v in course.items()},
        "gate_half_opening": float(bundle.env["gate_half_opening"]), "release_times": release.tolist(),
        "plan": dataclasses.asdict(plan), "checks": dataclasses.asdict(checks), **(meta or {})})
    t0 = [None]  # when the control loop started (loop time 0)
    last_good = np.full(n, np.nan)  # flight-clock time of each drone's newest finite pose
    forwarded = np.full(n, -np.inf)  # timestamp of the newest pose forwarded to each drone
    thread_errors: list[BaseException] = []
    summary = {"steps": 0, "events": [], "landed_early": [], "status": "running", "reason": ""}

    def note(what: str) -> None:
        rec.sequence.append({"clock": clock.now(), "what": what})

    def forward(frame: PoseFrame) -> None:
        # On the mocap thread: each new pose goes to its drone once.
        try:
            valid = (np.isfinite(frame.positions).all(-1) & np.isfinite(frame.quats).all(-1)
                     & np.isfinite(frame.timestamps) & (frame.timestamps > forwarded))
            if valid.any():
                link.send_poses(frame.positions, frame.quats, valid)
                forwarded[valid] = frame.timestamps[valid]
                rec.pose_sent(clock.now())
        except BaseException as e:  # the flight loop stops the drones
            thread_errors.append(e)

    def who(i: int) -> str:
        return f"{names[i]} ({link.uris[i]}, rigid body {bodies[i]!r})"

    def check(now: float, frame: PoseFrame) -> np.ndarray:
        """Raise FlightAbort on a lost link, a NaN pose or a lost rigid body; returns each drone's pose age."""
        if thread_errors:
            raise FlightAbort(f"forwarding poses failed: {thread_errors[0]!r}")
        lost = link.lost()
        if lost:
            uri, msg = next(iter(lost.items()))
            i = link.uris.index(uri) if uri in link.uris else 0
            raise FlightAbort(f"lost the radio link to {who(i)}: {msg}")
        if frame.bad is not None and frame.bad.any():
            raise FlightAbort(f"the mocap served a NaN/Inf pose for {who(int(np.flatnonzero(frame.bad)[0]))}")
        good = np.isfinite(frame.positions).all(-1) & np.isfinite(frame.timestamps)
        np.copyto(last_good, np.where(good, np.fmax(last_good, frame.timestamps), last_good))
        age = now - last_good
        gone = ~(age <= checks.pose_lost_after)  # NaN: never seen
        if gone.any():
            i = int(np.flatnonzero(gone)[0])
            seen = "never seen" if np.isnan(age[i]) else f"no pose for {age[i]:.2f} s"
            raise FlightAbort(f"lost {who(i)}: {seen} (limit {checks.pose_lost_after:g} s)")
        return age

    def obstacles_of(frame: PoseFrame):
        if not m:
            return fixed_obstacles
        return Obstacles(pos=frame.obstacle_xy, radius=np.array([o.radius for o in obstacle_entries]),
                         vel=frame.obstacle_vel, accel=obstacle_accel)

    def row(now: float, phase: str, frame: PoseFrame, age: np.ndarray, out=None, lateness: float = np.nan,
            latency: float = np.nan, released: np.ndarray | None = None) -> None:
        tele = link.telemetry()
        nan3 = np.full((n, 3), np.nan)
        off = np.zeros(n, bool)
        rec.row(time=now, phase=PHASES.index(phase), pos=frame.positions, quat=frame.quats, pose_age=age,
                estimate=tele.estimate, vbat=tele.vbat, supervisor=tele.supervisor,
                raw=out.nominal if out is not None else nan3, filtered=out.velocity if out is not None else nan3,
                intervened=out.intervened if out is not None else off, hover=out.hover if out is not None else off,
                land=out.land if out is not None else off, released=released if released is not None else off,
                target=out.target if out is not None else np.zeros(n, int), latency=latency, lateness=lateness,
                obstacle_xy=frame.obstacle_xy if m else np.zeros((0, 2)))

    def watch(seconds: float, phase: str) -> None:
        """Stream poses (the mocap thread does) and watch the swarm for ``seconds``, a row per control period."""
        end = clock.now() + seconds
        while True:
            now = clock.now()
            frame = mocap.latest(now)
            row(now, phase, frame, check(now, frame))
            if now >= end - 1e-9:
                return
            clock.sleep(min(period, end - now))

    def wait_for(what: str, timeout: float, ready: Callable[[float], bool]) -> bool:
        end = clock.now() + timeout
        while not ready(clock.now()):
            lost = link.lost()
            if lost:
                uri, msg = next(iter(lost.items()))
                raise FlightRefused(f"{what}: lost the radio link to {uri}: {msg}")
            if thread_errors:
                raise FlightRefused(f"{what}: forwarding poses failed: {thread_errors[0]!r}")
            if clock.now() >= end:
                return False
            clock.sleep(checks.poll_seconds)
        return True

    armed = False
    try:
        link.connect()
        note("connected")
        params = {**dict(drone.get("firmware_params", {})), **dict(checks.estimator_params)}
        link.set_params(params)
        note("params set: " + ", ".join(f"{k}={v}" for k, v in params.items()))
        mocap.start(clock, forward)
        note("pose stream started")

        def have_poses(now: float) -> bool:
            f = mocap.latest(now)
            return bool((np.isfinite(f.positions).all(-1) & np.isfinite(f.timestamps)).all())

        if not wait_for("poses", checks.pose_timeout, have_poses):
            f = mocap.latest(clock.now())
            missing = [bodies[i] for i in np.flatnonzero(~np.isfinite(f.positions).all(-1))]
            streamed = sorted(getattr(mocap, "seen", ()))
            raise FlightRefused(f"no pose for rigid bod{'y' if len(missing) == 1 else 'ies'} {', '.join(missing)} "
                                f"after {checks.pose_timeout:g} s"
                                + (f": the mocap streams {', '.join(streamed) or 'nothing'}" if streamed or
                                   hasattr(mocap, "seen") else ""))
        note("every rigid body streamed")
        link.reset_estimators()
        note("estimators reset")
        history: list[np.ndarray] = []
        last_seq = [None]

        def settled(now: float) -> bool:
            tele = link.telemetry()
            # A sample polled twice would look like a variance holding still: only new ones count.
            if last_seq[0] is None or (tele.variance_seq > last_seq[0]).all():
                history.append(tele.variance)
                last_seq[0] = tele.variance_seq
            return bool(variances_settled(np.array(history), checks.variance_window, checks.variance_threshold).all())

        if not wait_for("estimators", checks.converge_timeout, settled):
            ok = variances_settled(np.array(history), checks.variance_window, checks.variance_threshold)
            bad = [names[i] for i in np.flatnonzero(~ok)]
            raise FlightRefused(f"the position estimate of {', '.join(bad)} did not settle within "
                                f"{checks.converge_timeout:g} s of the reset (kalman.varPX/Y/Z kept changing by "
                                f">= {checks.variance_threshold:g}): check its rigid body and the pose stream")
        note("estimators converged")
        if not wait_for("battery", checks.telemetry_timeout,
                        lambda now: bool(np.isfinite(link.telemetry().vbat).all())):
            bad = [names[i] for i in np.flatnonzero(~np.isfinite(link.telemetry().vbat))]
            raise FlightRefused(f"no battery reading (pm.vbat) from {', '.join(bad)} within "
                                f"{checks.telemetry_timeout:g} s")
        vbat = link.telemetry().vbat
        if (vbat < checks.min_battery).any():
            i = int(np.argmin(vbat))
            raise FlightRefused(f"battery of {who(i)} is {vbat[i]:.2f} V at rest: allowed: >= "
                                f"{checks.min_battery:g} V (charge it)")
        note("batteries ok: " + ", ".join(f"{v:.2f} V" for v in vbat))
        now = clock.now()
        frame = mocap.latest(now)
        age = now - frame.timestamps
        fresh = np.isfinite(frame.positions).all(-1) & np.isfinite(frame.quats).all(-1) & (age <= safety.stale_after)
        if frame.bad is not None:
            fresh &= ~frame.bad
        if not fresh.all():
            i = int(np.flatnonzero(~fresh)[0])
            raise FlightRefused(f"no valid pose of {who(i)} fresher than {safety.stale_after:g} s before take-off "
                                f"(age {age[i]:.3f} s)")
        note("every pose valid and fresh")
        try:
            check(now, frame)
        except FlightAbort as e:  # nothing armed yet
            raise FlightRefused(str(e)) from None

        armed = True  # from here on any failure stops the motors
        link.arm()
        note("armed")
        link.takeoff(plan.takeoff_height, plan.takeoff_seconds)
        note("take-off")
        watch(plan.takeoff_seconds + plan.settle_seconds, "takeoff")

        t0[0] = rec.t0 = clock.now()
        mocap.anchor(t0[0])
        note("control loop started")
        reference = None  # full-state setpoints: where the integrated command stands, per drone
        landed: set[int] = set()
        k = 0
        while True:
            due = t0[0] + k * period
            clock.sleep(due - clock.now())
            now = clock.now()
            lt = now - t0[0]
            if lt > plan.max_seconds + 1e-9 or mocap.finished(now):
                break
            frame = mocap.latest(now)
            age = check(now, frame)
            released = lt >= release - 1e-9
            out = ctl.step(frame.positions, frame.quats, frame.timestamps, now=now, obstacles=obstacles_of(frame),
                           hold=~released)
            for e in out.events:
                ev = {"t": e.time - t0[0], "drone": e.drone, "name": names[e.drone], "kind": e.kind,
                      "detail": e.detail}
                rec.events.append(ev)
                summary["events"].append(e)
                log(f"event t={ev['t']:.3f} {names[e.drone]} {e.kind} {e.detail}".rstrip())
            new = [int(i) for i in np.flatnonzero(out.land) if i not in landed]
            if new:
                link.land(new, plan.land_seconds)
                landed.update(new)
                note("land requested by the runtime: " + ", ".join(names[i] for i in new))
            active = ~out.land
            if full_state:
                seen = np.isfinite(out.position).all(-1, keepdims=True)
                if reference is None:
                    reference = np.full_like(out.position, np.nan)
                reference = np.where(np.isnan(reference) & seen, out.position, reference)
                link.send_full_states(lt, command.setpoint_position(reference, out.velocity, period), out.velocity,
                                      active & np.isfinite(reference).all(-1))
                ahead = command.advance_reference(reference, out.velocity, period, np.where(seen, out.position, 0.0),
                                                  float(drone["reference_leash"]))
                reference = np.where(seen, ahead, reference)
            else:
                link.send_velocities(lt, out.velocity, active)
            sent = clock.now()
            row(now, "control", frame, age, out, lateness=now - due, latency=sent - frame.frame_time,
                released=released)
            k += 1
            summary["steps"] = k
            if len(landed) == n:
                break
        summary["landed_early"] = sorted(landed)
        rest = [i for i in range(n) if i not in landed]
        if rest:
            link.land(rest, plan.land_seconds)
        note("landing")
        watch(plan.land_seconds + plan.landed_margin, "landing")
        link.stop()
        note("motors stopped, disarmed")
        summary["status"] = "landed"
    except FlightRefused as e:
        summary.update(status="refused", reason=str(e))
        note(f"refused: {e}")
        log(f"refusing to fly: {e}")
        raise
    except BaseException as e:
        reason = str(e) if isinstance(e, FlightAbort) else ("Ctrl-C" if isinstance(e, KeyboardInterrupt)
                                                              else f"{type(e).__name__}: {e}")
        summary.update(status="emergency stop", reason=reason)
        note(f"emergency stop: {reason}")
        log(f"emergency stop of every drone: {reason}" + ("" if armed else " (before arming)"))
        link.emergency_stop()
        raise
    finally:
        for end in (mocap.stop, link.close):
            try:
                end()
            except Exception as e:  # the record is still written
                log(f"warning: {end.__qualname__} failed: {e!r}")
        note("pose stream stopped, links closed")
        rec.meta.update(status=summary["status"], reason=summary["reason"], steps=summary["steps"])
        summary["timing"] = rec_timing = _timing(rec)
        if summary["status"] == "landed":  # (after an emergency stop, its line stays the last: timing is recorded)
            log(format_timing(rec_timing))
        if record is not None:
            try:
                npz, _ = rec.write(record)
                summary["record"] = str(npz)
                log(f"flight record: {npz} (+ .json)")
            except OSError as e:  # never hide why the flight ended
                log(f"warning: the flight record could not be written to {record}: {e}")
    return summary


def _timing(rec: FlightRecorder) -> dict:
    from aswarm.flight.record import timing

    return timing(rec.arrays(), rec.meta.get("rate_hz"))


# ------------------------------------------------------------------ command line
def parse_mocap(spec: str) -> tuple[str, str]:
    """(kind, argument) of ``--mocap``: ("replay", CSV), ("mock", ""), or (a motioncapture backend, HOST)."""
    kind, _, arg = spec.partition(":")
    if kind == "replay" and arg:
        return kind, arg
    if kind == "mock" and not arg:
        return kind, ""
    if kind and arg and kind not in ("replay", "mock"):
        return kind, arg
    raise ValueError(f"invalid --mocap {spec!r}: allowed: vicon:HOST, optitrack:HOST, qualisys:HOST, vrpn:HOST (any "
                     f"motioncapture backend), mock, or replay:POSES.csv (columns {','.join(CSV_COLUMNS)})")


def make_mocap(kind: str, arg: str, bundle: Bundle, swarm: SwarmConfig | None,
               num_drones: int) -> tuple[MocapSource, KinematicSwarm | None]:
    """The pose source of ``--mocap KIND:ARG`` (:func:`parse_mocap`), and for ``mock`` the kinematic stand-in that
    the dry-run link moves."""
    if kind == "replay":
        return ReplaySource(arg, num_drones), None
    if swarm is None:
        raise ValueError(f"--mocap {kind} needs --config FILE: the swarm file maps rigid bodies to drones")
    bodies = [d.rigid_body for d in swarm.drones]
    obstacles = [o.rigid_body for o in swarm.obstacles]
    moving = [o.moving for o in swarm.obstacles]
    if kind != "mock":
        return MotionCaptureSource(lambda: connect_motioncapture(kind, {"hostname": arg}), bodies, obstacles,
                                   moving), None
    unplaced = [d.name for d in swarm.drones if d.initial_position is None] + \
               [o.name for o in swarm.obstacles if o.initial_position is None]
    if unplaced:
        raise ValueError(f"--mocap mock serves each rigid body at its initial_position, which {', '.join(unplaced)} "
                         "lack(s): allowed: initial_position = [x, y, z] (m) in the swarm file")
    kin = KinematicSwarm(np.array([d.initial_position for d in swarm.drones]), bundle.velocity_lag or (0.34, 0.22))
    served = [(d.rigid_body, d.initial_position) for d in swarm.drones] + \
             [(o.rigid_body, o.initial_position) for o in swarm.obstacles]
    # The library's mock backend paces the frames (its own thread, its own rate) and serves the bodies where the
    # swarm file puts them; the kinematics move the drone bodies by what the dry-run link is sent.
    options = {"rigid_bodies": mock_rigid_bodies(served), "frequency": str(int(round(swarm.mock_frequency)))}
    return MotionCaptureSource(lambda: connect_motioncapture("mock", options), bodies, obstacles, moving,
                               positions=kin.served), kin


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--bundle", required=True, type=Path, help="bundle folder from `aswarm export`")
    p.add_argument("--config", type=Path, default=None,
                   help="swarm file (TOML): each drone's uri, rigid body and initial position, obstacles' rigid "
                        "bodies and radii (aswarm/flight/crazyflies.example.toml); needed for live mocap and mock")
    p.add_argument("--drones", default=None, help="comma-separated drone names of the swarm file to fly (default: "
                                                  "every enabled one)")
    p.add_argument("--uris", default=None,
                   help="replays without a swarm file: comma-separated radio URIs, one per drone (drone i = i-th URI)")
    p.add_argument("--mocap", required=True,
                   help="vicon:HOST, optitrack:HOST, qualisys:HOST, vrpn:HOST (any motioncapture backend), mock "
                        "(rehearsal, with --dry-run), or replay:POSES.csv (columns t,drone,x,y,z,qw,qx,qy,qz)")
    p.add_argument("--course", type=Path, default=None,
                   help='JSON {"gates": [[x,y,z,yaw],...], "goals": [[x,y,z],...], "obstacles": [[x,y,r],...]}; '
                        "default: the manifest's nominal gates")
    p.add_argument("--dry-run", action="store_true",
                   help="no radio: a stand-in link records (and prints) what would be sent; with --mocap mock the "
                        "served drones move by the commands")
    p.add_argument("--quiet", action="store_true", help="dry run: print the sequence and events, not every setpoint")
    p.add_argument("--record", type=Path, default=None,
                   help="flight record NAME(.npz/.json) (default runs/flights/flight-DATE-TIME)")
    p.add_argument("--takeoff-height", type=float, default=1.0, help="m")
    p.add_argument("--max-seconds", type=float, default=60.0)
    p.add_argument("--min-battery", type=float, default=FlightChecks.min_battery, help="V at rest before arming")
    p.add_argument("--realtime", action="store_true", help="pace a replayed dry run on the wall clock")
    estimator.add_arguments(p)


def _positive(args: argparse.Namespace, *names: str) -> None:
    for name in names:
        v = getattr(args, name)
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"invalid --{name.replace('_', '-')} {v!r}: must be a number > 0")


def run(args: argparse.Namespace, out: Callable[[str], None] = print) -> int:
    """The ``aswarm fly`` command (also ``python -m aswarm.flight.fly``, which imports no JAX)."""
    _positive(args, "takeoff_height", "max_seconds", "min_battery")
    kind, arg = parse_mocap(args.mocap)
    bundle = load_bundle(args.bundle)
    n = bundle.num_agents
    swarm = None
    if args.config is not None:
        if args.uris:
            raise ValueError("--uris and --config both name the drones: allowed: one of them (the swarm file holds "
                             "the URIs)")
        select = [s for s in args.drones.split(",") if s] if args.drones else None
        swarm = load_swarm_config(args.config, select, num_drones=n, max_obstacles=int(bundle.env["num_cylinders"]))
        uris = swarm.uris
    elif kind != "replay":
        raise ValueError(f"--mocap {args.mocap} needs --config FILE: the swarm file maps rigid bodies to drones")
    else:
        uris = [u for u in (args.uris or "").split(",") if u]
        if not uris:
            raise ValueError(f"invalid --uris {args.uris!r}: allowed: comma-separated radio URIs (or --config FILE)")
        if len(uris) != n:
            raise ValueError(f"{len(uris)} URIs but the bundle was trained for {n} drones: allowed: exactly {n} URIs")
    if kind in ("replay", "mock") and not args.dry_run:
        raise ValueError(f"--mocap {kind} cannot fly real drones (their poses would not be measured): use --dry-run, "
                         "or a live system such as --mocap vicon:HOST")

    clock: Clock = RealClock() if (kind != "replay" or args.realtime) else FakeClock()
    mocap, kin = make_mocap(kind, arg, bundle, swarm, len(uris))
    if args.dry_run:
        link: Link = DryRunLink(uris, out, clock, kinematics=kin, setpoints=not args.quiet,
                                names=swarm.names if swarm else None)
    else:
        link = CflibLink(uris)
    plan = FlightPlan(takeoff_height=args.takeoff_height, max_seconds=args.max_seconds,
                      realtime=not isinstance(clock, FakeClock))
    checks = FlightChecks(min_battery=args.min_battery)
    record = args.record or Path("runs/flights") / f"flight-{time.strftime('%Y%m%d-%H%M%S')}"
    summary = fly(bundle, link, mocap, plan=plan, course=course_from(bundle, args.course), clock=clock, log=out,
                  estimation=estimator.from_args(args), checks=checks, swarm=swarm, record=record,
                  meta={"mocap": args.mocap, "dry_run": bool(args.dry_run), "config": str(args.config or ""),
                        "kinematic_rehearsal": kin is not None})
    out(f"flight loop ended after {summary['steps']} steps; {len(summary['events'])} events; landed early: "
        f"{', '.join(swarm.names[i] if swarm else f'cf{i}' for i in summary['landed_early']) or 'none'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="aswarm fly", description=__doc__.split("\n\n")[0])
    add_arguments(p)
    args = p.parse_args(argv)
    try:
        return run(args)
    except FlightAbort as e:
        print(f"aswarm fly: emergency stop: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("aswarm fly: interrupted: every drone was sent an emergency stop", file=sys.stderr)
        return 130
    except (ValueError, RuntimeError) as e:  # includes FlightRefused: nothing was armed
        print(f"aswarm fly: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

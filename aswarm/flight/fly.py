"""``aswarm fly``: stream the bundle's velocity setpoints to a Crazyflie swarm (numpy; cflib only when flying).

The loop, at the manifest's control rate (25 Hz for the shipped scenarios):

1. read the latest pose of every drone from a :class:`MocapSource`;
2. forward the poses to the drones (``extpose``: their onboard estimators fuse the mocap pose);
3. :meth:`FlightController.step` gives world-frame velocity setpoints (finite, within ±max_speed);
4. send each drone ``send_velocity_world_setpoint(vx, vy, vz, yawrate)``; a drone the controller
   asks to land is handed to the high-level commander's ``land``. A policy trained on the firmware's
   Mellinger controller (manifest ``drone.setpoint`` "full_state") is sent
   ``send_full_state_setpoint(pos, vel, acc, orientation, rollrate, pitchrate, yawrate)`` instead: the
   velocity setpoint, a position that moves with it (the command integrated from where the drone was at
   the first step, kept within ``drone.reference_leash`` of the drone: ``aswarm.core.command``, as the
   simulated drone it trained on got it), zero acceleration, a level orientation and zero rates.

Units and conventions (cflib): ``send_velocity_world_setpoint`` takes vx, vy, vz in **m/s** in the
world frame and the yaw rate in **degrees/s** (not rad/s); this loop sends yaw rate 0, as the
policy was trained with the onboard controller holding yaw. Take-off and landing use the
high-level commander (``takeoff(height_m, duration_s)``, ``land(0.0, duration_s)``);
``send_notify_setpoint_stop()`` hands control back to it from the streamed setpoints.

Firmware setpoint timeout: the Crazyflie's commander watchdog levels the drone (zero roll/pitch
rate) when no setpoint arrives for 500 ms and cuts the motors after 2 s, so setpoints must be
streamed steadily; this loop sends one per drone per control period (40 ms at 25 Hz). On Ctrl-C or
any exception every drone gets an emergency stop (motors off at once), then the links close.

Mocap: :class:`ReplaySource` reads a CSV of poses with the header ``t,drone,x,y,z,qw,qx,qy,qz``:
``t`` seconds, ``drone`` the index 0..n-1 in the order of ``--uris``, position in metres (world,
z up), orientation a wxyz quaternion body->world. A replay only drives ``--dry-run``; a live
system (Vicon, OptiTrack) plugs in by implementing :class:`MocapSource`.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Protocol

import numpy as np

from aswarm.core import command
from aswarm.flight import estimator
from aswarm.flight.bundle import Bundle, load_bundle
from aswarm.flight.runtime import FlightController, Obstacles, SafetyConfig

CSV_COLUMNS = ("t", "drone", "x", "y", "z", "qw", "qx", "qy", "qz")
YAW_RATE_DEG_S = 0.0  # cflib's yaw rate unit is degrees per second


@dataclasses.dataclass(frozen=True)
class PoseFrame:
    positions: np.ndarray  # [n, 3] m; NaN for a drone not seen
    quats: np.ndarray  # [n, 4] wxyz; NaN for a drone not seen
    timestamps: np.ndarray  # [n] s; NaN for a drone not seen


class MocapSource(Protocol):
    """Where poses come from. ``latest(now)``: every drone's newest pose at or before ``now`` (s)."""

    def latest(self, now: float) -> PoseFrame: ...

    def finished(self, now: float) -> bool: ...


class ReplaySource:
    """Poses replayed from a CSV (columns :data:`CSV_COLUMNS`), on the clock the loop gives."""

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
        if np.any((drone != np.round(drone)) | (drone < 0) | (drone >= num_drones)):
            bad = drone[(drone != np.round(drone)) | (drone < 0) | (drone >= num_drones)][0]
            raise ValueError(f"mocap replay {path}: drone {bad:g}: allowed: integers 0..{num_drones - 1} "
                             "(the order of --uris)")
        if not np.all(np.isfinite(data[:, 0])):
            raise ValueError(f"mocap replay {path}: every row needs a finite time t")
        order = np.argsort(data[:, 0], kind="stable")
        self.data = data[order]
        self.n = num_drones
        self.start = float(self.data[0, 0])
        self.end = float(self.data[-1, 0])
        self._i = 0
        self._frame = PoseFrame(np.full((num_drones, 3), np.nan), np.full((num_drones, 4), np.nan),
                                np.full(num_drones, np.nan))

    def latest(self, now: float) -> PoseFrame:
        pos, quat, ts = self._frame.positions.copy(), self._frame.quats.copy(), self._frame.timestamps.copy()
        while self._i < len(self.data) and self.data[self._i, 0] <= now:
            t, d, x, y, z, qw, qx, qy, qz = self.data[self._i]
            k = int(d)
            pos[k], quat[k], ts[k] = (x, y, z), (qw, qx, qy, qz), t
            self._i += 1
        self._frame = PoseFrame(pos, quat, ts)
        return self._frame

    def finished(self, now: float) -> bool:
        return now > self.end


class Link(Protocol):
    """The radio side: one method per thing the loop does to the swarm (drone i is ``uris[i]``)."""

    uris: list[str]

    def takeoff(self, height: float, duration: float) -> None: ...

    def set_params(self, params: dict) -> None: ...

    def send_poses(self, positions: np.ndarray, quats: np.ndarray, valid: np.ndarray) -> None: ...

    def send_velocities(self, t: float, velocities: np.ndarray, active: np.ndarray) -> None: ...

    def send_full_states(self, t: float, positions: np.ndarray, velocities: np.ndarray,
                         active: np.ndarray) -> None: ...

    def land(self, drones: Sequence[int], duration: float) -> None: ...

    def emergency_stop(self) -> None: ...

    def close(self) -> None: ...


class DryRunLink:
    """Prints what would be sent, one line per command; needs no radio and no cflib."""

    def __init__(self, uris: Sequence[str], out: Callable[[str], None] = print):
        self.uris = list(uris)
        self.out = out

    def takeoff(self, height: float, duration: float) -> None:
        self.out(f"takeoff all height={height:.2f} m duration={duration:.1f} s")

    def set_params(self, params: dict) -> None:
        for name, value in params.items():
            self.out(f"param all {name}={value}")

    def send_poses(self, positions, quats, valid) -> None:
        pass  # the drones' own estimators are not simulated in a dry run

    def send_velocities(self, t: float, velocities: np.ndarray, active: np.ndarray) -> None:
        for i, (uri, v) in enumerate(zip(self.uris, velocities)):
            if active[i]:
                self.out(f"t={t:.3f} cf{i} {uri} send_velocity_world_setpoint vx={v[0]:+.3f} vy={v[1]:+.3f} "
                         f"vz={v[2]:+.3f} m/s yawrate={YAW_RATE_DEG_S:g} deg/s")

    def send_full_states(self, t: float, positions: np.ndarray, velocities: np.ndarray, active: np.ndarray) -> None:
        for i, (uri, p, v) in enumerate(zip(self.uris, positions, velocities)):
            if active[i]:
                self.out(f"t={t:.3f} cf{i} {uri} send_full_state_setpoint pos=({p[0]:+.3f}, {p[1]:+.3f}, "
                         f"{p[2]:+.3f}) m vel=({v[0]:+.3f}, {v[1]:+.3f}, {v[2]:+.3f}) m/s acc=0 level rates=0")

    def land(self, drones: Sequence[int], duration: float) -> None:
        for i in drones:
            self.out(f"land cf{i} {self.uris[i]} duration={duration:.1f} s")

    def emergency_stop(self) -> None:
        self.out("EMERGENCY STOP all")

    def close(self) -> None:
        pass


class CflibLink:
    """A cflib ``Swarm`` (``pip install 'aswarm[flight]'``); cflib is imported here, not before."""

    def __init__(self, uris: Sequence[str], cache: str = "./cache"):
        try:
            import cflib.crtp
            from cflib.crazyflie.swarm import CachedCfFactory, Swarm
        except ImportError as e:
            raise RuntimeError("flying needs cflib: pip install 'aswarm[flight]' (or use --dry-run)") from e
        cflib.crtp.init_drivers()
        self.uris = list(uris)
        self.swarm = Swarm(self.uris, factory=CachedCfFactory(rw_cache=cache))
        self.swarm.open_links()
        self.cfs = {}
        self.swarm.parallel_safe(lambda scf, uri: self.cfs.__setitem__(uri, scf.cf),
                                 args_dict={u: [u] for u in self.uris})
        self.swarm.reset_estimators()

    def set_params(self, params: dict) -> None:
        for uri in self.uris:
            for name, value in params.items():
                self.cfs[uri].param.set_value(name, value)

    def takeoff(self, height: float, duration: float) -> None:
        for uri in self.uris:
            self.cfs[uri].high_level_commander.takeoff(height, duration)
        time.sleep(duration + 0.5)

    def send_poses(self, positions, quats, valid) -> None:
        for i, uri in enumerate(self.uris):
            if valid[i]:
                (x, y, z), (qw, qx, qy, qz) = positions[i], quats[i]
                self.cfs[uri].extpos.send_extpose(x, y, z, qx, qy, qz, qw)  # cflib's order: x y z qx qy qz qw

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
        self.swarm.close_links()


@dataclasses.dataclass(frozen=True)
class FlightPlan:
    takeoff_height: float = 1.0  # m
    takeoff_seconds: float = 2.0
    land_seconds: float = 2.0
    max_seconds: float = 60.0  # the loop ends (and lands everyone) after this long
    realtime: bool = True  # pace the loop on the wall clock (a dry run may go as fast as it can)


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
        safety: SafetyConfig = SafetyConfig(), course: dict | None = None, clock: Callable[[], float] | None = None,
        log: Callable[[str], None] = print,
        estimation: estimator.EstimatorConfig = estimator.EstimatorConfig()) -> dict:
    """Take off, stream setpoints until every drone landed or finished (or the time is up), land.

    ``clock`` gives the loop's time in the mocap's clock (default: replay time advancing one control
    period per step when not ``plan.realtime``, else ``time.monotonic``). Returns a summary.
    """
    n = len(link.uris)
    ctl = FlightController(bundle, n, safety=safety, estimation=estimation)
    course = dict(course or course_from(bundle, None))
    obstacles = course.pop("obstacles", None)
    ctl.reset(**course)
    period = 1.0 / bundle.rate_hz
    steps, landed, events = 0, set(), []
    drone = bundle.manifest.get("drone", {})
    full_state = drone.get("setpoint") == "full_state"
    reference = None  # full-state setpoints: where the integrated command stands, per drone
    if full_state:
        if not isinstance(drone.get("reference_leash"), (int, float)) or not drone["reference_leash"] > 0:
            raise ValueError(f"invalid manifest drone.reference_leash={drone.get('reference_leash')!r}: allowed: a "
                             "number > 0 (m) for full-state setpoints; export the bundle again")
        log(f"the policy was trained on {drone.get('controller')}: streaming full-state setpoints along the "
            f"integrated command (reference leash {float(drone['reference_leash']):g} m)")
    if drone.get("controller") == "geometric":
        log("warning: the policy was trained on the geometric controller, which the firmware does not have; "
            "the drones fly controller_pid (retrain on the default drone)")
    try:
        # The onboard controller the policy was trained with (manifest "drone": controller_pid is
        # stabilizer.controller 1).
        link.set_params(dict(drone.get("firmware_params", {})))
        link.takeoff(plan.takeoff_height, plan.takeoff_seconds)
        t0 = clock() if clock else getattr(mocap, "start", 0.0)
        wall0 = time.monotonic()
        while True:
            now = clock() if clock else t0 + steps * period
            if now - t0 > plan.max_seconds or mocap.finished(now):
                break
            frame = mocap.latest(now)
            valid = np.isfinite(frame.positions).all(-1) & np.isfinite(frame.quats).all(-1)
            link.send_poses(frame.positions, frame.quats, valid)
            out = ctl.step(frame.positions, frame.quats, frame.timestamps, now=now, obstacles=obstacles)
            for e in out.events:
                events.append(e)
                log(f"event t={e.time:.3f} cf{e.drone} {e.kind} {e.detail}".rstrip())
            new = [i for i in np.flatnonzero(out.land) if i not in landed]
            if new:
                link.land(new, plan.land_seconds)
                landed.update(int(i) for i in new)
            active = ~out.land
            if full_state:
                seen = np.isfinite(out.position).all(-1, keepdims=True)
                if reference is None:
                    reference = np.full_like(out.position, np.nan)
                reference = np.where(np.isnan(reference) & seen, out.position, reference)
                link.send_full_states(now, command.setpoint_position(reference, out.velocity, period), out.velocity,
                                      active & np.isfinite(reference).all(-1))
                ahead = command.advance_reference(reference, out.velocity, period, np.where(seen, out.position, 0.0),
                                                  float(drone["reference_leash"]))
                reference = np.where(seen, ahead, reference)
            else:
                link.send_velocities(now, out.velocity, active)
            steps += 1
            if len(landed) == n:
                break
            if plan.realtime:
                time.sleep(max(0.0, wall0 + steps * period - time.monotonic()))
        rest = [i for i in range(n) if i not in landed]
        if rest:
            link.land(rest, plan.land_seconds)
    except BaseException:
        link.emergency_stop()
        raise
    finally:
        link.close()
    return {"steps": steps, "events": events, "landed_early": sorted(landed)}


def parse_mocap(spec: str, num_drones: int) -> MocapSource:
    kind, _, arg = spec.partition(":")
    if kind == "replay" and arg:
        return ReplaySource(arg, num_drones)
    raise ValueError(f"invalid --mocap {spec!r}: allowed: replay:POSES.csv (columns {','.join(CSV_COLUMNS)})")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--bundle", required=True, type=Path, help="bundle folder from `aswarm export`")
    p.add_argument("--uris", required=True, help="comma-separated radio URIs, one per drone (drone i = i-th URI)")
    p.add_argument("--mocap", required=True, help="replay:POSES.csv (columns t,drone,x,y,z,qw,qx,qy,qz)")
    p.add_argument("--course", type=Path, default=None,
                   help='JSON {"gates": [[x,y,z,yaw],...], "goals": [[x,y,z],...], "obstacles": [[x,y,r],...]}; '
                        "default: the manifest's nominal gates")
    p.add_argument("--dry-run", action="store_true", help="print the setpoints instead of sending them (no cflib)")
    p.add_argument("--takeoff-height", type=float, default=1.0, help="m")
    p.add_argument("--max-seconds", type=float, default=60.0)
    p.add_argument("--realtime", action="store_true", help="pace a dry run on the wall clock")
    estimator.add_arguments(p)


def run(args: argparse.Namespace, out: Callable[[str], None] = print) -> int:
    """The ``aswarm fly`` command (also ``python -m aswarm.flight.fly``, which imports no JAX)."""
    uris = [u for u in args.uris.split(",") if u]
    if not uris:
        raise ValueError(f"invalid --uris {args.uris!r}: allowed: comma-separated radio URIs")
    for name in ("takeoff_height", "max_seconds"):
        v = getattr(args, name)
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"invalid --{name.replace('_', '-')} {v!r}: must be a number > 0")
    bundle = load_bundle(args.bundle)
    if len(uris) != bundle.num_agents:
        raise ValueError(f"{len(uris)} URIs but the bundle was trained for {bundle.num_agents} drones: allowed: "
                         f"exactly {bundle.num_agents} URIs")
    mocap = parse_mocap(args.mocap, len(uris))
    if not args.dry_run and isinstance(mocap, ReplaySource):
        raise ValueError("a replayed pose log cannot fly real drones (their poses would not be measured): "
                         "use --dry-run, or a live MocapSource from Python")
    link = DryRunLink(uris, out) if args.dry_run else CflibLink(uris)
    plan = FlightPlan(takeoff_height=args.takeoff_height, max_seconds=args.max_seconds,
                      realtime=args.realtime or not args.dry_run)
    summary = fly(bundle, link, mocap, plan=plan, course=course_from(bundle, args.course), log=out,
                  estimation=estimator.from_args(args))
    out(f"flight loop ended after {summary['steps']} steps; {len(summary['events'])} events; landed early: "
        f"{summary['landed_early'] or 'none'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="aswarm fly", description=__doc__.split("\n\n")[0])
    add_arguments(p)
    args = p.parse_args(argv)
    try:
        return run(args)
    except (ValueError, RuntimeError) as e:
        print(f"aswarm fly: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

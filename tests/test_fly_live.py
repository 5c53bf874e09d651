"""``aswarm fly`` with live motion capture: the flight sequence against the recording stand-in link on a fake clock,
its emergency stops, the flight record and its figure, the swarm file, and a rehearsal on the motioncapture
package's own mock backend. No JAX: the bundle is the synthetic one of ``aswarm.flight.bench``."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from types import SimpleNamespace

import numpy as np
import pytest

from aswarm.flight import bench, record
from aswarm.flight import bundle as fb
from aswarm.flight import fly as ffly
from aswarm.flight import swarm_config as sc
from aswarm.flight.clock import FakeClock
from aswarm.flight.links import Failures, RecordingLink
from aswarm.flight.mocap import KinematicSwarm, MotionCaptureSource

RATE = 25  # the synthetic bundle's control rate
MOCAP_HZ = 100
START = np.array([[3.0, -3.5, 0.0], [2.2, -3.5, 0.0], [1.4, -3.5, 0.0], [0.6, -3.5, 0.0]])
OBSTACLE = (-2.0, 2.0, 0.0)
SWARM_TOML = "\n".join(
    [f'[drones.cf{i + 1}]\nuri = "radio://0/80/2M/E7E7E7E70{i + 1}"\nrigid_body = "cf{i + 1}"\n'
     f"initial_position = [{p[0]}, {p[1]}, {p[2]}]\n" for i, p in enumerate(START)]
    + [f'[obstacles.pole]\nrigid_body = "pole"\nradius = 0.15\ninitial_position = [{OBSTACLE[0]}, {OBSTACLE[1]}, '
       f"{OBSTACLE[2]}]\n[mocap]\nfrequency = {MOCAP_HZ}\n"])
PLAN = ffly.FlightPlan(takeoff_seconds=1.0, settle_seconds=0.2, land_seconds=1.0, landed_margin=0.3, max_seconds=4.0,
                       realtime=False)


def _bundle(start_interval: float = 1.0) -> fb.Bundle:
    """The synthetic race bundle, commanding a few cm/s (so nothing leaves the arena), staggered as trained."""
    b = bench.synthetic_bundle(actor_scale=0.02)
    m = dict(b.manifest)
    m["source"] = {**m["source"], "env_config": {"start_interval": start_interval}}
    m["drone"] = {**m["drone"], "firmware_params": {"stabilizer.controller": 1}}  # as export writes for the PID
    return fb.bundle_from(m, dict(b.arrays))


@pytest.fixture(scope="module")
def swarm(tmp_path_factory):
    path = tmp_path_factory.mktemp("swarm") / "crazyflies.toml"
    path.write_text(SWARM_TOML)
    return sc.load_swarm_config(path, num_drones=4, max_obstacles=8)


class FakeMotionCapture:
    """What ``motioncapture.connect`` returns, serving the kinematic drones and a pole; ``vanish``/``nan``: a body
    that stops being streamed / is served as NaN once ``when()`` is true."""

    def __init__(self, clock, kin: KinematicSwarm, swarm: sc.SwarmConfig, vanish=None, nan=None):
        self.clock, self.kin, self.swarm, self.vanish, self.nan = clock, kin, swarm, vanish, nan

    @property
    def rigidBodies(self):  # noqa: N802 (the package's name)
        q = SimpleNamespace(w=1.0, x=0.0, y=0.0, z=0.0)
        bodies = {d.rigid_body: np.asarray(d.initial_position, np.float32) for d in self.swarm.drones}
        bodies["pole"] = np.asarray(OBSTACLE, np.float32)
        if self.vanish and self.vanish[1]():
            bodies.pop(self.vanish[0])
        if self.nan and self.nan[1]():
            bodies[self.nan[0]] = np.full(3, np.nan, np.float32)
        return {k: SimpleNamespace(name=k, position=v, rotation=q) for k, v in bodies.items()}

    def waitForNextFrame(self):  # noqa: N802
        pass


def _flight(swarm, tmp_path, failures=Failures(), vanish=None, nan=None, link_cls=RecordingLink, bundle=None,
            plan=PLAN):
    """Fly the sequence on a fake clock; returns (summary or the exception raised, link, record)."""
    clock = FakeClock()
    kin = KinematicSwarm(np.array([d.initial_position for d in swarm.drones]), (0.34, 0.22))
    link = link_cls(swarm.uris, clock, failures, kinematics=kin)
    fake = FakeMotionCapture(clock, kin, swarm, vanish, nan)
    mocap = MotionCaptureSource(lambda: fake, [d.rigid_body for d in swarm.drones], ["pole"], paced_hz=MOCAP_HZ,
                                positions=kin.served)
    lines = []
    try:
        result = ffly.fly(bundle or _bundle(), link, mocap, plan=plan, clock=clock, swarm=swarm, log=lines.append,
                          record=tmp_path / "flight")
    except BaseException as e:  # KeyboardInterrupt included
        result = e
    return result, link, record.load_record(tmp_path / "flight"), lines


def _rounds(link):
    return lambda: len(link.times("send_velocities"))


# ------------------------------------------------------------------ the sequence
def test_the_sequence_runs_in_order_with_poses_at_the_mocap_rate_and_staggered_starts(swarm, tmp_path):
    summary, link, rec, lines = _flight(swarm, tmp_path)
    assert summary["status"] == "landed", lines
    names = link.names()
    first = {name: names.index(name) for name in dict.fromkeys(names)}
    order = ["connect", "set_params", "send_poses", "reset_estimators", "arm", "takeoff", "send_velocities", "land",
             "stop", "close"]
    assert [first[n] for n in order] == sorted(first[n] for n in order), [n for n in dict.fromkeys(names)]
    assert "emergency_stop" not in names
    params = link.calls[first["set_params"]].args[0]
    assert params == {"stabilizer.controller": 1, "stabilizer.estimator": 2, "locSrv.extQuatStdDev": 0.06}
    t = {n: link.times(n) for n in ("send_poses", "reset_estimators", "arm", "takeoff", "send_velocities", "land",
                                    "stop")}
    # Poses stream before the reset; the estimator settles (0.3 s here) and its 10-sample window fills before arming.
    assert t["send_poses"][0] < t["reset_estimators"][0]
    assert t["arm"][0] - t["reset_estimators"][0] >= 0.3 + 0.9
    # Setpoints at the manifest's rate, poses at the mocap's (4x more often) through the control loop.
    sp = t["send_velocities"]
    np.testing.assert_allclose(np.diff(sp), 1.0 / RATE, atol=1e-9)
    inside = t["send_poses"][(t["send_poses"] >= sp[0]) & (t["send_poses"] <= sp[-1])]
    assert abs(len(inside) / (sp[-1] - sp[0]) - MOCAP_HZ) < 2
    assert len(sp) == round(PLAN.max_seconds * RATE) + 1
    # The poses keep streaming through the landing until the motors stop.
    land_end = t["land"][-1] + PLAN.land_seconds
    assert t["send_poses"][-1] >= land_end and t["send_poses"][-1] <= t["stop"][0]
    assert np.all(t["send_poses"][t["send_poses"] > sp[-1]].size >= (PLAN.land_seconds + 0.3) * MOCAP_HZ - 2)
    # Staggered starts: drone i gets a zero command until i s into the loop, then the policy's.
    sent = np.array([c.args[0] for c in link.calls if c.name == "send_velocities"])
    loop_t = sp - sp[0]
    for i in range(4):
        held = loop_t < i - 1e-9
        assert np.all(sent[held, i] == 0.0)
        assert np.abs(sent[~held, i]).max() > 1e-3
    released = rec["released"][rec["phase"] == 1]
    assert [int(np.argmax(released[:, i])) for i in range(4)] == [0, RATE, 2 * RATE, 3 * RATE]
    # The kinematic drones took off to the take-off height and came down again.
    z = rec["pos"][:, :, 2]
    assert np.allclose(z[rec["phase"] == 1][0], PLAN.takeoff_height, atol=1e-3) and np.all(z[-1] < 0.05)


def test_a_low_battery_refuses_the_flight_before_anything_is_armed(swarm, tmp_path):
    result, link, rec, lines = _flight(swarm, tmp_path, Failures(low_battery=3.52, drone=2))
    assert isinstance(result, ffly.FlightRefused)
    assert "battery of cf3 (radio://0/80/2M/E7E7E7E703, rigid body 'cf3') is 3.52 V at rest: allowed: >= 3.7 V" \
        in str(result)
    for name in ("arm", "takeoff", "send_velocities", "emergency_stop"):
        assert name not in link.names()
    assert link.names()[-1] == "close" and "send_poses" in link.names()
    assert rec.meta["status"] == "refused" and "3.52 V" in rec.meta["reason"] and len(rec["time"]) == 0


def test_an_estimator_that_never_settles_refuses_the_flight(swarm, tmp_path):
    result, link, rec, _ = _flight(swarm, tmp_path, Failures(settle_after=None))
    assert isinstance(result, ffly.FlightRefused) and "did not settle within 10 s" in str(result)
    assert "arm" not in link.names() and rec.meta["status"] == "refused"


def test_a_rigid_body_the_mocap_does_not_stream_refuses_the_flight(swarm, tmp_path):
    result, link, rec, _ = _flight(swarm, tmp_path, vanish=("cf2", lambda: True))
    assert isinstance(result, ffly.FlightRefused)
    assert "no pose for rigid body cf2 after 5 s: the mocap streams cf1, cf3, cf4, pole" in str(result)
    assert "reset_estimators" not in link.names() and "arm" not in link.names()


@pytest.mark.parametrize("failure", ["lost_link", "ctrl_c", "lost_body", "nan_pose", "exception"])
def test_every_failure_in_flight_stops_every_drone_and_writes_the_record(swarm, tmp_path, failure):
    class Raising(RecordingLink):
        def send_velocities(self, t, velocities, active):
            if len(self.times("send_velocities")) == 10:
                raise ZeroDivisionError("a bug")
            super().send_velocities(t, velocities, active)

    kwargs, link_cls = {}, RecordingLink
    box = {}

    def after(k):
        return lambda: len(box["link"].times("send_velocities")) >= k if "link" in box else False

    if failure == "lost_link":
        kwargs["failures"] = Failures(lost_link_at=10, drone=1)
    elif failure == "ctrl_c":
        kwargs["failures"] = Failures(interrupt_at=10)
    elif failure == "lost_body":
        kwargs["vanish"] = ("cf3", after(10))
    elif failure == "nan_pose":
        kwargs["nan"] = ("cf4", after(10))
    else:
        link_cls = Raising

    class Boxed(link_cls):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            box["link"] = self

    result, link, rec, lines = _flight(swarm, tmp_path, link_cls=Boxed, **kwargs)
    expected = {"lost_link": (ffly.FlightAbort, "lost the radio link to cf2 (radio://0/80/2M/E7E7E7E702"),
                "ctrl_c": (KeyboardInterrupt, "Ctrl-C"),
                "lost_body": (ffly.FlightAbort, "lost cf3 (radio://0/80/2M/E7E7E7E703, rigid body 'cf3'): no pose for"),
                "nan_pose": (ffly.FlightAbort, "the mocap served a NaN/Inf pose for cf4"),
                "exception": (ZeroDivisionError, "ZeroDivisionError: a bug")}[failure]
    assert isinstance(result, expected[0]), result
    names = link.names()
    assert "emergency_stop" in names and names[-1] == "close" and "stop" not in names
    stop_t = link.times("emergency_stop")[0]
    assert not np.any(link.times("send_velocities") > stop_t)  # nothing flies after the stop
    assert lines[-2].startswith("emergency stop of every drone")  # then the record's line
    assert rec.meta["status"] == "emergency stop" and expected[1] in rec.meta["reason"]
    # Stopped at the next control step after the failure (setpoint round 10: the link is lost while it is sent; the
    # others fail after round 9), a lost body once the limit has passed since its last pose.
    sp = link.times("send_velocities")
    failed = sp[10] if failure == "lost_link" else sp[9]
    limit = ffly.FlightChecks().pose_lost_after + 1.0 / MOCAP_HZ if failure == "lost_body" else 0.0
    assert limit - 1.0 / MOCAP_HZ < stop_t - failed <= limit + 1.0 / RATE + 1e-9
    assert len(rec["time"]) > 0 and rec["phase"][-1] == 1


def test_variance_check_is_bitcrazes_range_test():
    h = np.full((12, 2, 3), 0.5)
    h[:, 1, 2] = np.linspace(0.5, 0.49, 12)  # drone 1's z variance still drops by 0.01 over the window
    assert ffly.variances_settled(h, 10, 1e-3).tolist() == [True, False]
    assert ffly.variances_settled(h[:5], 10, 1e-3).tolist() == [False, False]  # the window is not full yet
    h[-1, 0, 0] = np.nan
    assert ffly.variances_settled(h, 10, 1e-3).tolist() == [False, False]


def test_release_times_follow_the_trained_start_interval():
    assert ffly.release_times(_bundle(1.0)).tolist() == [0.0, 1.0, 2.0, 3.0]
    assert ffly.release_times(bench.synthetic_bundle()).tolist() == [0.0] * 4  # not recorded: all at once


# ------------------------------------------------------------------ the record
def test_the_record_round_trips_and_plots(swarm, tmp_path):
    summary, link, rec, _ = _flight(swarm, tmp_path)
    a = rec.arrays
    T = len(a["time"])
    assert a["pos"].shape == (T, 4, 3) and a["raw"].shape == (T, 4, 3) and a["obstacle_xy"].shape == (T, 1, 2)
    control = a["phase"] == 1
    assert control.sum() == summary["steps"] == len(link.times("send_velocities"))
    # What was sent is the record's filtered command; the raw one is the actor's, NaN outside the loop.
    sent = np.array([c.args[0] for c in link.calls if c.name == "send_velocities"])
    np.testing.assert_array_equal(a["filtered"][control], sent)
    assert np.isfinite(a["raw"][control]).all() and np.isnan(a["raw"][~control]).all()
    np.testing.assert_allclose(a["obstacle_xy"][control][:, 0], np.tile(OBSTACLE[:2], (control.sum(), 1)), atol=1e-6)
    assert np.all(a["vbat"] == 4.10) and set(np.unique(a["supervisor"][control])) == {1 | 2 | 8 | 16}
    # The onboard estimate is what the stand-in was last sent: the mocap pose.
    np.testing.assert_allclose(a["estimate"][control], a["pos"][control], atol=1e-6)
    assert rec.meta["names"] == ["cf1", "cf2", "cf3", "cf4"] and rec.meta["release_times"] == [0, 1, 2, 3]
    tm = rec.meta["timing"]
    assert tm["control_steps"] == summary["steps"] and abs(tm["period_ms_mean"] - 40.0) < 1e-6
    assert abs(tm["pose_rate_hz"] - MOCAP_HZ) < 2
    assert [s["what"] for s in rec.meta["sequence"]][:3] == ["connected", "params set: stabilizer.controller=1, "
                                                             "stabilizer.estimator=2, locSrv.extQuatStdDev=0.06",
                                                             "pose stream started"]
    png = record.plot_flight(tmp_path / "flight.npz", tmp_path / "side.png", compare=rec)
    assert png.stat().st_size > 20_000
    from aswarm import cli

    assert cli.main(["plot", "--flight", str(tmp_path / "flight.npz")]) == 0  # beside the record by default
    assert (tmp_path / "flight.png").stat().st_size > 20_000
    with pytest.raises(ValueError, match="flight record .*missing not found"):
        record.load_record(tmp_path / "missing.npz")


# ------------------------------------------------------------------ the swarm file
@pytest.mark.parametrize("text, select, message", [
    (SWARM_TOML, ["cf1", "cf9"], "unknown drone 'cf9': allowed: cf1, cf2, cf3, cf4"),
    (SWARM_TOML.replace("E7E7E7E702", "E7E7E7E701"), None,
     "drones 'cf1' and 'cf2' have the same uri 'radio://0/80/2M/E7E7E7E701': allowed: one radio address per drone"),
    (SWARM_TOML.replace('rigid_body = "cf3"\n', ""), None,
     "drone 'cf3' has no rigid_body: allowed: the name the mocap system streams for it"),
    (SWARM_TOML, ["cf1", "cf2"], "2 drones to fly (cf1, cf2) but the bundle was trained for 4: allowed: exactly 4"),
    (SWARM_TOML.replace("radius = 0.15", "radius = -1"), None, "obstacle 'pole' radius=-1: allowed: a number > 0"),
    (SWARM_TOML.replace("uri =", "url =", 1), None, "drone 'cf1' has unknown key 'url': allowed: uri, rigid_body"),
    ("[drones.cf1\n", None, "is not valid TOML"),
])
def test_bad_swarm_files_are_one_line_errors(tmp_path, text, select, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ValueError) as e:
        sc.load_swarm_config(path, select, num_drones=4, max_obstacles=8)
    assert message in str(e.value) and "\n" not in str(e.value)


def test_aswarm_fly_reports_a_bad_swarm_file_in_one_line(tmp_path, capsys):
    b = bench.synthetic_bundle()
    fb.write_bundle(tmp_path / "bundle", dict(b.arrays), {k: v for k, v in b.manifest.items()
                                                           if k not in ("arrays", "npz_sha256")})
    (tmp_path / "bad.toml").write_text(SWARM_TOML.replace("E7E7E7E702", "E7E7E7E701"))
    assert ffly.main(["--bundle", str(tmp_path / "bundle"), "--config", str(tmp_path / "bad.toml"), "--mocap",
                      "vicon:192.168.1.5"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("aswarm fly: error: ") and "same uri" in err
    (tmp_path / "ok.toml").write_text(SWARM_TOML)
    assert ffly.main(["--bundle", str(tmp_path / "bundle"), "--config", str(tmp_path / "ok.toml"), "--mocap",
                      "mock"]) == 2
    assert "--mocap mock cannot fly real drones" in capsys.readouterr().err


# ------------------------------------------------------------------ the real library's mock backend
def test_a_rehearsal_on_the_motioncapture_mock_backend_flies_the_kinematic_drones(swarm, tmp_path):
    pytest.importorskip("motioncapture", reason="the motioncapture package is not installed (pip install "
                                                "'aswarm[flight]')")
    bundle = _bundle()
    mocap, kin = ffly.make_mocap("mock", "", bundle, swarm, 4)
    lines = []
    link = ffly.DryRunLink(swarm.uris, lines.append, kinematics=kin, setpoints=False, names=swarm.names)
    plan = ffly.FlightPlan(takeoff_seconds=0.5, settle_seconds=0.1, land_seconds=0.5, landed_margin=0.2,
                           max_seconds=1.2)
    checks = ffly.FlightChecks(poll_seconds=0.05, variance_window=4)
    summary = ffly.fly(bundle, link, mocap, plan=plan, swarm=swarm, log=lines.append, record=tmp_path / "mock",
                       checks=checks)
    assert summary["status"] == "landed" and summary["steps"] >= 0.8 * plan.max_seconds * RATE, lines
    rec = record.load_record(tmp_path / "mock")
    control = rec["phase"] == 1
    # The served bodies moved: up to the take-off height, then down; the pole stayed where the file put it.
    assert np.abs(rec["pos"][control][0, :, 2] - plan.takeoff_height).max() < 0.05
    assert rec["pos"][-1, :, 2].max() < 0.05
    np.testing.assert_allclose(rec["obstacle_xy"][control][-1, 0], OBSTACLE[:2], atol=1e-5)
    tm = rec.meta["timing"]
    assert tm["pose_rate_hz"] > 0.5 * MOCAP_HZ and 0 < tm["latency_ms_mean"] < 40
    assert any(line.startswith("timing over") for line in lines)


def test_the_flight_side_imports_without_motioncapture_and_cflib():
    code = textwrap.dedent("""
        import importlib.abc, sys
        class Block(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in ("motioncapture", "cflib", "jax", "flax", "mujoco", "brax"):
                    raise ImportError("blocked: " + name)
        sys.meta_path.insert(0, Block())
        from aswarm.flight import fly, links, mocap, record, swarm_config, clock
        try:
            mocap.connect_motioncapture("vicon", {"hostname": "h"})
        except RuntimeError as e:
            print(e)
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    assert "live motion capture needs the motioncapture package" in run.stdout


def test_the_record_json_is_plain_json(swarm, tmp_path):
    _, _, rec, _ = _flight(swarm, tmp_path, Failures(low_battery=3.0))
    meta = json.loads((tmp_path / "flight.json").read_text())
    assert meta["status"] == "refused" and meta["uris"] == swarm.uris and meta["timing"] == {"control_steps": 0}


# ------------------------------------------------------------------ the cflib link, against a stand-in cflib
def _fake_cflib(monkeypatch, calls: list):
    """Modules cflib.crtp, cflib.crazyflie.log and .swarm with the calls CflibLink makes, recorded in ``calls``."""
    import types

    class Caller:
        def __init__(self):
            self.callbacks = []

        def add_callback(self, cb):
            self.callbacks.append(cb)

        def call(self, *args):
            for cb in self.callbacks:
                cb(*args)

    def recorder(prefix):
        class Part:
            def __getattr__(self, name):
                return lambda *args: calls.append((prefix, name, args))

        return Part()

    class LogConfig:
        def __init__(self, name, period_in_ms):
            self.name, self.period_in_ms, self.variables = name, period_in_ms, []
            self.data_received_cb = Caller()

        def add_variable(self, name, fetch_as=None):
            self.variables.append((name, fetch_as))

        def start(self):
            calls.append(("log", "start", (self.name,)))

    class Cf:
        def __init__(self, uri):
            self.link_uri = uri
            self.connection_lost = Caller()
            self.configs = []
            toc = SimpleNamespace(get_element_by_complete_name=lambda name: object())
            self.log = SimpleNamespace(toc=toc, add_config=self.configs.append)
            for part in ("param", "extpos", "supervisor", "high_level_commander", "commander"):
                setattr(self, part, recorder(f"{uri[-2:]}.{part}"))

    class Swarm:
        def __init__(self, uris, factory=None):
            self.scfs = [SimpleNamespace(cf=Cf(u)) for u in uris]

        def open_links(self):
            calls.append(("swarm", "open_links", ()))

        def parallel_safe(self, fn):
            for scf in self.scfs:
                fn(scf)

        def close_links(self):
            calls.append(("swarm", "close_links", ()))

    crtp = types.ModuleType("cflib.crtp")
    crtp.init_drivers = lambda: calls.append(("crtp", "init_drivers", ()))
    log = types.ModuleType("cflib.crazyflie.log")
    log.LogConfig = LogConfig
    swarm = types.ModuleType("cflib.crazyflie.swarm")
    swarm.Swarm, swarm.CachedCfFactory = Swarm, lambda rw_cache=None: None
    top, cf = types.ModuleType("cflib"), types.ModuleType("cflib.crazyflie")
    top.crtp, top.crazyflie = crtp, cf
    for name, mod in (("cflib", top), ("cflib.crtp", crtp), ("cflib.crazyflie", cf), ("cflib.crazyflie.log", log),
                      ("cflib.crazyflie.swarm", swarm)):
        monkeypatch.setitem(sys.modules, name, mod)


def test_the_cflib_link_makes_the_calls_of_bitcrazes_example(monkeypatch):
    calls = []
    _fake_cflib(monkeypatch, calls)
    uris = ["radio://0/80/2M/E7E7E7E701", "radio://0/80/2M/E7E7E7E702"]
    link = ffly.CflibLink(uris)
    link.connect()
    assert calls[:2] == [("crtp", "init_drivers", ()), ("swarm", "open_links", ())]
    tele, var = link.cfs[uris[1]].configs
    assert [v for v, _ in tele.variables] == ["stateEstimate.x", "stateEstimate.y", "stateEstimate.z", "pm.vbat",
                                              "supervisor.info"]
    assert [v for v, _ in var.variables] == ["kalman.varPX", "kalman.varPY", "kalman.varPZ"]
    tele.data_received_cb.call(0, {"stateEstimate.x": 1.0, "stateEstimate.y": 2.0, "stateEstimate.z": 0.5,
                                   "pm.vbat": 3.95, "supervisor.info": 11}, tele)
    var.data_received_cb.call(0, {"kalman.varPX": 1e-3, "kalman.varPY": 2e-3, "kalman.varPZ": 3e-3}, var)
    t = link.telemetry()
    assert t.variance_seq.tolist() == [0, 1]
    assert t.vbat[1] == 3.95 and np.isnan(t.vbat[0]) and t.supervisor.tolist() == [-1, 11]
    np.testing.assert_allclose(t.estimate[1], [1.0, 2.0, 0.5])
    np.testing.assert_allclose(t.variance[1], [1e-3, 2e-3, 3e-3])
    calls.clear()
    link.set_params({"stabilizer.estimator": 2})
    link.send_poses(np.array([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]]), np.array([[0.9, 0.1, 0.2, 0.3], [1, 0, 0, 0]]),
                    np.array([True, False]))
    link.arm()
    link.send_velocities(0.0, np.array([[0.1, -0.2, 0.3], [0.0, 0.0, 0.0]]), np.array([True, False]))
    link.land([1], 2.0)
    link.stop()
    link.emergency_stop()
    assert calls == [
        ("01.param", "set_value", ("stabilizer.estimator", "2")), ("02.param", "set_value", ("stabilizer.estimator",
                                                                                           "2")),
        ("01.extpos", "send_extpose", (1.0, 2.0, 3.0, 0.1, 0.2, 0.3, 0.9)),  # cflib's quaternion order: x y z w
        ("01.supervisor", "send_arming_request", (True,)), ("02.supervisor", "send_arming_request", (True,)),
        ("01.commander", "send_velocity_world_setpoint", (0.1, -0.2, 0.3, 0.0)),  # yaw rate 0 deg/s
        ("02.commander", "send_notify_setpoint_stop", ()), ("02.high_level_commander", "land", (0.0, 2.0)),
        ("01.high_level_commander", "stop", ()), ("01.supervisor", "send_arming_request", (False,)),
        ("02.high_level_commander", "stop", ()), ("02.supervisor", "send_arming_request", (False,)),
        ("01.supervisor", "send_emergency_stop", ()), ("02.supervisor", "send_emergency_stop", ())]
    assert link.lost() == {}
    link.cfs[uris[0]].connection_lost.call(uris[0], "Too many packets lost")
    assert link.lost() == {uris[0]: "Too many packets lost"}


def test_a_moving_obstacles_velocity_is_the_line_fit_over_its_recent_poses():
    from aswarm.flight.mocap import _slope

    # 0.6 m/s in x, -0.2 m/s in y, sampled at 100 Hz; an old sample far off the line lies outside the window.
    hist = [(-1.0, 9.0, 9.0)] + [(t, 1.0 + 0.6 * t, 2.0 - 0.2 * t) for t in np.arange(0.0, 0.1, 0.01)]
    np.testing.assert_allclose(_slope(hist, window=0.2), [0.6, -0.2], atol=1e-9)
    np.testing.assert_allclose(_slope(hist[:1], window=0.2), [0.0, 0.0])  # one pose: no velocity yet

"""The flight record: what ``aswarm fly`` saw, computed and sent, per drone and step, written even when it stopped.

Two files side by side, each written under a temporary name and renamed into place (a reader never sees half of
one): ``NAME.npz`` (arrays, plain numbers, read without pickle) and ``NAME.json`` (metadata: the bundle, the drones,
URIs and rigid bodies, the course, the release times, the status and its reason, the sequence with its times, the
runtime's events and the loop's timing). One row per control period from take-off to the end of the landing:

| array | shape | meaning |
|---|---|---|
| ``time`` | [T] | s since the control loop started (negative during take-off) |
| ``phase`` | [T] | index into ``PHASES`` (take-off, control, landing) |
| ``pos``, ``quat`` | [T, n, 3], [T, n, 4] | newest mocap pose (m, wxyz); NaN before the first |
| ``pose_age`` | [T, n] | s since that pose arrived |
| ``estimate`` | [T, n, 3] | the drone's onboard estimate (``stateEstimate.x/y/z``), m |
| ``vbat`` | [T, n] | battery, V (``pm.vbat``) |
| ``supervisor`` | [T, n] | ``supervisor.info`` bitfield, -1 unknown |
| ``raw``, ``filtered`` | [T, n, 3] | policy command before the filter, and what was sent (m/s); NaN off control |
| ``intervened``, ``hover`` | [T, n] | the filter changed the command; the command was forced to zero |
| ``land``, ``released`` | [T, n] | asked to land; past its release time (staggered starts) |
| ``target`` | [T, n] | current gate (or goal) index |
| ``latency`` | [T] | s from the newest mocap frame's arrival to the setpoints having been sent |
| ``lateness`` | [T] | s the control step started after its scheduled time |
| ``obstacle_xy`` | [T, m, 2] | obstacles' newest positions, m |
| ``pose_times`` | [P] | s (loop time) of every pose batch forwarded to the drones |
"""

from __future__ import annotations

import dataclasses
import json
import os
import threading
from collections.abc import Mapping
from pathlib import Path

import numpy as np

PHASES = ("takeoff", "control", "landing")
ROW_FIELDS = ("time", "phase", "pos", "quat", "pose_age", "estimate", "vbat", "supervisor", "raw", "filtered",
              "intervened", "hover", "land", "released", "target", "latency", "lateness", "obstacle_xy")


class FlightRecorder:
    """Collects rows during a flight; :meth:`write` saves them (call it from a ``finally``)."""

    def __init__(self, num_drones: int, num_obstacles: int = 0, t0: float = 0.0, meta: Mapping | None = None):
        self.n, self.m = num_drones, num_obstacles
        self.t0 = t0  # flight-clock time of loop time 0: the control loop's start, once it started
        self.rows: list[dict] = []
        self.meta: dict = dict(meta or {})
        self.events: list[dict] = []
        self.sequence: list[dict] = []
        self._pose_times: list[float] = []
        self._lock = threading.Lock()  # poses are forwarded on the mocap thread

    def row(self, **values) -> None:
        """One row of ``ROW_FIELDS``; ``time`` on the flight clock."""
        self.rows.append(values)

    def pose_sent(self, t: float) -> None:
        with self._lock:
            self._pose_times.append(t)

    def arrays(self) -> dict[str, np.ndarray]:
        n, m = self.n, self.m
        empty = {"time": (), "phase": (), "pos": (n, 3), "quat": (n, 4), "pose_age": (n,), "estimate": (n, 3),
                 "vbat": (n,), "supervisor": (n,), "raw": (n, 3), "filtered": (n, 3), "intervened": (n,),
                 "hover": (n,), "land": (n,), "released": (n,), "target": (n,), "latency": (), "lateness": (),
                 "obstacle_xy": (m, 2)}
        types = {"phase": np.int8, "supervisor": np.int32, "target": np.int32, "intervened": bool, "hover": bool,
                 "land": bool, "released": bool}
        out = {}
        for name in ROW_FIELDS:
            dtype = types.get(name, np.float64)
            if self.rows:
                out[name] = np.stack([np.asarray(r[name], dtype) for r in self.rows])
            else:
                out[name] = np.zeros((0,) + empty[name], dtype)
        out["time"] = out["time"] - self.t0
        with self._lock:
            out["pose_times"] = np.array(self._pose_times, np.float64) - self.t0
        return out

    def write(self, path: str | Path) -> tuple[Path, Path]:
        """``path`` with suffix .npz and .json, each atomically; returns both paths."""
        arrays = self.arrays()
        # Sequence times, as the arrays', in s since the control loop started (negative before it).
        sequence = [{"t": s["clock"] - self.t0, "what": s["what"]} for s in self.sequence]
        meta = {**self.meta, "loop_start_clock": self.t0, "events": self.events, "sequence": sequence,
                "timing": timing(arrays, self.meta.get("rate_hz"))}
        return write_record(path, arrays, meta)


def write_record(path: str | Path, arrays: Mapping[str, np.ndarray], meta: Mapping) -> tuple[Path, Path]:
    base = Path(path)
    base = base.with_suffix("") if base.suffix in (".npz", ".json") else base
    base.parent.mkdir(parents=True, exist_ok=True)
    npz, js = base.with_name(base.name + ".npz"), base.with_name(base.name + ".json")
    tmp = npz.with_name(f".{npz.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, npz)
    tmp = js.with_name(f".{js.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(meta, indent=2, default=_json_default) + "\n")
    os.replace(tmp, js)
    return npz, js


def _json_default(x):
    if isinstance(x, np.ndarray | np.generic):
        return x.tolist()
    if dataclasses.is_dataclass(x):
        return dataclasses.asdict(x)
    return str(x)


@dataclasses.dataclass(frozen=True)
class FlightRecord:
    arrays: Mapping[str, np.ndarray]
    meta: Mapping

    def __getitem__(self, name: str) -> np.ndarray:
        return self.arrays[name]


def load_record(path: str | Path) -> FlightRecord:
    """Read ``NAME.npz`` and ``NAME.json`` (either name, or NAME alone)."""
    base = Path(path)
    base = base.with_suffix("") if base.suffix in (".npz", ".json") else base
    npz, js = base.with_name(base.name + ".npz"), base.with_name(base.name + ".json")
    if not npz.is_file() or not js.is_file():
        raise ValueError(f"flight record {base} not found: allowed: NAME.npz with NAME.json beside it, as `aswarm "
                         "fly` writes them")
    with np.load(npz, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    return FlightRecord(arrays, json.loads(js.read_text()))


def timing(arrays: Mapping[str, np.ndarray], rate_hz: float | None = None) -> dict:
    """The control loop's timing (ms) and the pose stream's rate (Hz), from a record's arrays."""
    control = arrays["phase"] == PHASES.index("control")
    t, lat, late = arrays["time"][control], arrays["latency"][control], arrays["lateness"][control]
    out: dict = {"control_steps": int(control.sum())}
    if len(t) >= 2:
        dt = np.diff(t)
        out.update(period_ms_mean=1e3 * float(dt.mean()), period_ms_std=1e3 * float(dt.std()),
                   period_ms_max=1e3 * float(dt.max()))
        if rate_hz:
            out["late_steps"] = int(np.sum(dt > 1.5 / rate_hz))  # a period half again as long as it should be
    lat = lat[np.isfinite(lat)]
    if len(lat):
        out.update(latency_ms_mean=1e3 * float(lat.mean()), latency_ms_p50=1e3 * float(np.percentile(lat, 50)),
                   latency_ms_p95=1e3 * float(np.percentile(lat, 95)), latency_ms_max=1e3 * float(lat.max()))
    if len(late):
        out.update(lateness_ms_p95=1e3 * float(np.percentile(late, 95)), lateness_ms_max=1e3 * float(late.max()))
    pt = arrays["pose_times"]
    if len(t) >= 2 and len(pt):
        inside = pt[(pt >= t[0]) & (pt <= t[-1])]
        span = float(t[-1] - t[0])
        if span > 0:
            out["pose_rate_hz"] = len(inside) / span
    return out


def format_timing(tm: Mapping) -> str:
    if "latency_ms_mean" not in tm:
        return f"timing: {tm.get('control_steps', 0)} control steps (too few to measure)"
    parts = [f"mocap -> setpoint latency {tm['latency_ms_mean']:.2f} ms mean, {tm['latency_ms_p95']:.2f} ms p95, "
             f"{tm['latency_ms_max']:.2f} ms max"]
    if "period_ms_mean" in tm:
        parts.append(f"control period {tm['period_ms_mean']:.2f} ms mean, jitter {tm['period_ms_std']:.2f} ms std, "
                     f"{tm['period_ms_max']:.2f} ms max ({tm.get('late_steps', 0)} late steps)")
    if "pose_rate_hz" in tm:
        parts.append(f"poses forwarded at {tm['pose_rate_hz']:.1f} Hz")
    return f"timing over {tm['control_steps']} control steps: " + "; ".join(parts)


# ------------------------------------------------------------------ figure
def plot_flight(record: FlightRecord | str | Path, out: str | Path, compare: FlightRecord | str | Path | None = None,
                dpi: int = 100) -> Path:
    """Top view and altitude (mocap solid, onboard estimate dashed), commands (raw dotted, sent solid, filter
    interventions marked) and battery over time; ``compare``: another record (e.g. ``aswarm sitl --replay``) drawn
    thin and grey beside it."""
    from matplotlib import colormaps
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle

    out = Path(out)
    if out.suffix.lower() not in (".png", ".pdf", ".svg"):
        raise ValueError(f"invalid --out {str(out)!r}: allowed file types: .png, .pdf, .svg")
    rec = record if isinstance(record, FlightRecord) else load_record(record)
    other = None if compare is None else compare if isinstance(compare, FlightRecord) else load_record(compare)
    a, meta = rec.arrays, rec.meta
    n = a["pos"].shape[1]
    names = meta.get("names") or [f"cf{i}" for i in range(n)]
    colours = [colormaps["tab10"](i % 10) for i in range(n)]
    # Figure without pyplot: drawing a record changes no global matplotlib state.
    fig = Figure(figsize=(13, 9), dpi=dpi, layout="constrained")
    axes = fig.subplots(2, 2)
    top, alt, cmd, bat = axes[0, 0], axes[0, 1], axes[1, 0], axes[1, 1]
    t = a["time"]
    for g in (meta.get("course") or {}).get("gates", []):
        x, y, _, yaw = g
        h = float(meta.get("gate_half_opening", 0.3))
        dx, dy = -np.sin(yaw) * h, np.cos(yaw) * h
        top.plot([x - dx, x + dx], [y - dy, y + dy], color="k", lw=3)
    for goal in (meta.get("course") or {}).get("goals", []):
        top.plot(goal[0], goal[1], "k*", ms=10)
    radii = meta.get("obstacle_radius", [])
    if a["obstacle_xy"].shape[0]:
        for j, r in enumerate(radii):
            xy = a["obstacle_xy"][:, j]
            xy = xy[np.isfinite(xy).all(-1)]
            if len(xy):
                top.plot(xy[:, 0], xy[:, 1], color="0.5", lw=0.8)
                top.add_patch(Circle(tuple(xy[-1]), r, color="0.6", alpha=0.5))
    if other is not None:
        for i in range(min(n, other.arrays["pos"].shape[1])):
            p = other.arrays["pos"][:, i]
            top.plot(p[:, 0], p[:, 1], color="0.4", lw=0.8, ls="-.", label="simulated (SITL)" if i == 0 else None)
            alt.plot(other.arrays["time"], p[:, 2], color="0.4", lw=0.8, ls="-.")
    for i in range(n):
        c = colours[i]
        p, e = a["pos"][:, i], a["estimate"][:, i]
        top.plot(p[:, 0], p[:, 1], color=c, lw=1.5, label=f"{names[i]} mocap")
        top.plot(e[:, 0], e[:, 1], color=c, lw=1.0, ls="--", label=f"{names[i]} estimate")
        alt.plot(t, p[:, 2], color=c, lw=1.5)
        alt.plot(t, e[:, 2], color=c, lw=1.0, ls="--")
        raw, sent = np.linalg.norm(a["raw"][:, i], axis=-1), np.linalg.norm(a["filtered"][:, i], axis=-1)
        cmd.plot(t, raw, color=c, lw=0.8, ls=":")
        cmd.plot(t, sent, color=c, lw=1.3, label=names[i])
        hit = a["intervened"][:, i]
        cmd.plot(t[hit], sent[hit], "o", color=c, ms=3)
        bat.plot(t, a["vbat"][:, i], color=c, lw=1.3, label=names[i])
    for ax in (alt, cmd, bat):
        for k, phase in enumerate(PHASES):
            inside = a["phase"] == k
            if inside.any() and phase != "control":
                ax.axvspan(t[inside].min(), t[inside].max(), color="0.9", zorder=0)
        ax.set_xlabel("time since the control loop started (s)")
    top.set_aspect("equal", adjustable="datalim")
    top.set(xlabel="x (m)", ylabel="y (m)", title="top view: mocap (solid), onboard estimate (dashed)")
    top.legend(fontsize=7, ncol=2)
    alt.set(ylabel="z (m)", title="altitude (take-off and landing shaded)")
    cmd.set(ylabel="|command| (m/s)",
            title="policy command (dotted) and sent after the filter (solid; o: filter acted)")
    cmd.legend(fontsize=7)
    bat.set(ylabel="pm.vbat (V)", title="battery")
    status = meta.get("status", "?") + (f": {meta['reason']}" if meta.get("reason") else "")
    fig.suptitle(f"flight record: {meta.get('scenario', '?')}, {n} drones, {meta.get('mocap', '?')}"
                 f"{' (dry run)' if meta.get('dry_run') else ''}; {status}", fontsize=10)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.stem}.{os.getpid()}.tmp{out.suffix}")  # renamed into place: never half a figure
    fig.savefig(tmp, dpi=dpi)
    os.replace(tmp, out)
    return out

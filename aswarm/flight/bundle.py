"""Policy bundles: ``policy.npz`` (plain float32 arrays) and ``manifest.json``, written and checked here.

``aswarm export`` (``aswarm/flight/export.py``) fills a manifest from a checkpoint with :func:`make_manifest`
and writes it with :func:`write_bundle`; the flight side reads it with :func:`load_bundle`, which
refuses anything it cannot run exactly: another format or version, a hash that does not match the
arrays, missing, misshapen or non-finite arrays, or an observation layout other than the one
:mod:`aswarm.core.observation` builds. Array names are the flax parameter paths without the
``params`` level (``actor/MLP_0/Dense_0/kernel``, ``cbf/W_Q/kernel``) plus ``obs_norm/mean`` and
``obs_norm/std``. Nothing is pickled: the npz is read with ``allow_pickle=False``.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import shutil
import tempfile
import types
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from aswarm.core.layout import OBS_NORM_CLIP, ObsLayout, neighbour_slots
from aswarm.core.safety import SafetyFilterConfig, from_manifest
from aswarm.flight.policy import PolicyWeights, weights_from_arrays

FORMAT = "aswarm-policy-bundle"
FORMAT_VERSION = 1
NPZ = "policy.npz"
MANIFEST = "manifest.json"
KINDS = ("track", "crossing", "hover")


class BundleError(ValueError):
    """A bundle that cannot be read, or that this runtime cannot fly exactly."""


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def make_manifest(*, scenario: str, kind: str, env: Mapping, env_overrides: Mapping, course: Mapping,
                  layout: ObsLayout, networks: Mapping, safety_filter: Mapping, train_config: Mapping,
                  train_config_sha256: str, source: str, trained_updates: int, drone: Mapping | None = None) -> dict:
    """The manifest of a bundle (without ``arrays`` and ``npz_sha256``, which :func:`write_bundle` adds).

    ``env`` must hold num_agents, num_cylinders, num_gates, max_speed (m/s), policy_freq (Hz),
    collision_radius (m), arena_low/arena_high (m), gate_half_opening, gate_bar, goal_radius (m) and
    episode_seconds; ``course`` the nominal gates ``[[x, y, z, yaw_rad], ...]`` and start positions.
    """
    if kind not in KINDS:
        raise ValueError(f"invalid kind={kind!r}: allowed: {', '.join(KINDS)}")
    speed = float(env["max_speed"])
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "scenario": {"name": scenario, "kind": kind, "env_overrides": dict(env_overrides)},
        "env": dict(env),
        "course": dict(course),
        "observation": {"size": layout.size, "num_cylinders": layout.num_cylinders,
                        "num_neighbours": layout.num_neighbours, "fields": layout.describe()},
        "action": {"size": 3, "meaning": "velocity setpoint [vx, vy, vz] per drone", "unit": "m/s", "frame": "world",
                   "low": -speed, "high": speed, "clip": "per axis",
                   "deterministic": "tanh(actor_out[:3]) * max_speed, then the safety filter"},
        "control": {"rate_hz": int(env["policy_freq"]), "period_s": 1.0 / int(env["policy_freq"])},
        "normalizer": {"formula": "clip((obs - mean) / std, -max_abs_value, max_abs_value)",
                       "max_abs_value": OBS_NORM_CLIP},
        "networks": dict(networks),
        "safety_filter": dict(safety_filter),
        "drone": dict(drone or {}),
        "source": {"checkpoint": source, "trained_updates": int(trained_updates),
                   "train_config_sha256": train_config_sha256, "train_config": dict(train_config)},
    }


def write_bundle(out_dir: str | Path, arrays: Mapping[str, np.ndarray], manifest: Mapping,
                 force: bool = False) -> Path:
    """Write ``policy.npz`` and ``manifest.json`` into ``out_dir``, atomically.

    Everything goes into a temporary folder next to ``out_dir`` that is renamed into place only when
    complete, so a crash never leaves a half-written bundle. An existing ``out_dir`` is replaced only
    with ``force`` and only if it is a bundle or empty (never an unrelated folder).
    """
    out = Path(out_dir)
    _check_target(out, force)
    arrays = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in arrays.items()}
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        with open(tmp / NPZ, "wb") as f:
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        full = dict(manifest)
        full["arrays"] = {k: {"shape": list(v.shape), "dtype": "float32"} for k, v in arrays.items()}
        full["npz_sha256"] = sha256_file(tmp / NPZ)
        (tmp / MANIFEST).write_text(json.dumps(full, indent=2, default=_json_default) + "\n")
        if out.exists():
            _check_target(out, force)
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
            os.replace(out, old / "bundle")
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return out


def _json_default(x):
    if isinstance(x, np.ndarray | np.generic):
        return x.tolist()
    return str(x)


def _check_target(out: Path, force: bool) -> None:
    if not out.exists():
        return
    if not force:
        raise BundleError(f"bundle {out} already exists: allowed: a new --out folder, or --force to overwrite it")
    if not out.is_dir() or (any(out.iterdir()) and not (out / MANIFEST).exists()):
        raise BundleError(f"{out} exists and is not a bundle: --force replaces only a bundle or an empty folder")


@dataclasses.dataclass(frozen=True)
class Bundle:
    """A checked bundle: its manifest, its arrays (read-only) and the networks' weights."""

    path: Path | None
    manifest: Mapping
    arrays: Mapping[str, np.ndarray]
    layout: ObsLayout
    weights: PolicyWeights
    safety: SafetyFilterConfig  # the filter's settings, from the manifest's safety_filter entries

    @property
    def env(self) -> Mapping:
        return self.manifest["env"]

    @property
    def kind(self) -> str:
        return self.manifest["scenario"]["kind"]

    @property
    def scenario(self) -> str:
        return self.manifest["scenario"]["name"]

    @property
    def num_agents(self) -> int:
        return int(self.env["num_agents"])

    @property
    def max_neighbours(self) -> int:
        """0: every other drone is observed, in index order; K: the K nearest (``EnvConfig.max_neighbours``)."""
        return int(self.env.get("max_neighbours", 0))

    @property
    def filter_neighbours(self) -> int:
        """``EnvConfig.filter_neighbours`` (bundles from before it: 0, the filter on the policy's rows)."""
        return int(self.env.get("filter_neighbours", 0))

    @property
    def filter_neighbour_accel(self) -> bool:
        """``EnvConfig.filter_neighbour_accel`` (bundles from before it: false)."""
        return bool(self.env.get("filter_neighbour_accel", False))

    @functools.cached_property
    def filter_layout(self) -> ObsLayout:
        """The layout of the observations the runtime builds and the safety filter's rows come from: the policy's
        (``layout``), or with more nearest neighbours (``EnvConfig.filter_neighbours``) and with their accelerations
        (``EnvConfig.filter_neighbour_accel``; bundles from before them: the policy's), of which the policy reads the
        prefix ``layout.size``."""
        _, k = neighbour_slots(self.num_agents, self.max_neighbours, self.filter_neighbours)
        return dataclasses.replace(self.layout, num_neighbours=k, neighbour_accel=self.filter_neighbour_accel)

    @property
    def max_speed(self) -> float:
        return float(self.env["max_speed"])

    @property
    def command_accel_limit(self) -> float:
        """m/s², the fastest the sent command may change per axis; 0 (and bundles from before it): no limit."""
        return float(self.env.get("command_accel_limit", 0.0))

    @property
    def rate_hz(self) -> int:
        return int(self.manifest["control"]["rate_hz"])

    @property
    def velocity_lag(self) -> tuple[float, float] | None:
        """s, 63 % of a 1 m/s velocity step in x and in z, measured on the drone the policy trained on; bundles from
        before it was recorded: what their fitted look-ahead implies, else None."""
        lag = self.manifest.get("drone", {}).get("velocity_lag")
        if lag is not None:
            return float(lag[0]), float(lag[1])
        sf = self.safety_filter
        if sf.get("fit_lookahead") and sf.get("lookahead_scale", 0) > 0 and sf.get("lookahead_xy", 0) > 0:
            k = float(sf["lookahead_scale"])
            return float(sf["lookahead_xy"]) / k, float(sf["lookahead_z"]) / k
        return None

    @property
    def safety_filter(self) -> Mapping:
        return self.manifest["safety_filter"]


def load_bundle(path: str | Path) -> Bundle:
    """Read and check a bundle folder; raises :class:`BundleError` with the reason."""
    path = Path(path)
    if not (path / MANIFEST).is_file() or not (path / NPZ).is_file():
        raise BundleError(f"{path} is not a bundle: allowed: a folder with {MANIFEST} and {NPZ} from `aswarm export`")
    try:
        manifest = json.loads((path / MANIFEST).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise BundleError(f"{path / MANIFEST} is not valid JSON: {e}") from e
    fmt = manifest.get("format") if isinstance(manifest, dict) else None
    if fmt != FORMAT:
        raise BundleError(f"{path / MANIFEST} has format {fmt!r}: allowed: {FORMAT!r}")
    if manifest.get("format_version") != FORMAT_VERSION:
        raise BundleError(f"bundle format_version {manifest.get('format_version')!r} is not supported: allowed: "
                          f"{FORMAT_VERSION} (export again with this version of aswarm)")
    digest = sha256_file(path / NPZ)
    if digest != manifest.get("npz_sha256"):
        raise BundleError(f"{path / NPZ} has sha256 {digest}, the manifest says {manifest.get('npz_sha256')}: "
                          "the weights were changed or corrupted after export")
    try:
        with np.load(path / NPZ, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError) as e:
        raise BundleError(f"{path / NPZ} cannot be read without pickle: {e}") from e
    return bundle_from(manifest, arrays, path)


def bundle_from(manifest: Mapping, arrays: Mapping[str, np.ndarray], path: Path | None = None) -> Bundle:
    """Check a manifest against its arrays and this runtime, and arrange the weights."""
    try:
        listed = manifest["arrays"]
        env, obs = manifest["env"], manifest["observation"]
        kind = manifest["scenario"]["kind"]
        nets = manifest["networks"]
        _ = (manifest["safety_filter"]["enabled"], manifest["control"]["rate_hz"])
    except (KeyError, TypeError) as e:
        raise BundleError(f"manifest is missing {e}: allowed: a manifest written by `aswarm export`") from e
    if kind not in KINDS:
        raise BundleError(f"manifest scenario kind {kind!r} is not supported: allowed: {', '.join(KINDS)}")
    if set(listed) != set(arrays):
        raise BundleError(f"arrays {sorted(set(listed) ^ set(arrays))} differ between the manifest and the npz")
    for name, a in arrays.items():
        want = (tuple(listed[name]["shape"]), listed[name]["dtype"])
        if (a.shape, str(a.dtype)) != want:
            raise BundleError(f"array {name} has shape {a.shape} and dtype {a.dtype}: the manifest says {want}")
        if not np.all(np.isfinite(a)):
            raise BundleError(f"array {name} holds NaN or Inf: the policy cannot be flown")
    n, m = int(env["num_agents"]), int(env["num_cylinders"])
    # Bundles from before max_neighbours observed every other drone.
    layout = ObsLayout(num_cylinders=m, num_neighbours=int(env.get("max_neighbours", 0)) or n - 1)
    if obs.get("fields") != layout.describe() or obs.get("size") != layout.size:
        raise BundleError(f"the bundle's observation layout (size {obs.get('size')}) is not the one this runtime "
                          f"builds for {n} drones and {m} cylinders (size {layout.size}): export it with this version")
    try:
        weights = weights_from_arrays(arrays, nets["actor"]["activation"], nets["cbf"]["activation"])
    except (KeyError, TypeError) as e:
        raise BundleError(f"manifest networks entry is missing {e}") from e
    except ValueError as e:
        raise BundleError(str(e)) from e
    if weights.mean.shape != (layout.size,) or weights.actor[0][0].shape[0] != layout.size:
        raise BundleError(f"normalizer or actor input has size {weights.mean.shape[0]}/{weights.actor[0][0].shape[0]}:"
                          f" the observation has size {layout.size}")
    if np.any(weights.std <= 0):
        raise BundleError("obs_norm/std has entries <= 0: allowed: positive standard deviations")
    try:
        safety = from_manifest(manifest["safety_filter"])
    except (TypeError, ValueError) as e:
        raise BundleError(str(e)) from e
    frozen = {}
    for k, v in arrays.items():
        v = np.array(v)
        v.setflags(write=False)
        frozen[k] = v
    return Bundle(path=path, manifest=types.MappingProxyType(dict(manifest)), arrays=types.MappingProxyType(frozen),
                  layout=layout, weights=weights, safety=safety)

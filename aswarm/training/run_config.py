"""A run folder's ``config.json``: the training config and the run's full resolved environment.

``{"train": TrainConfig fields but env, "env": EnvConfig fields}``. A run loads its environment from the
``env`` section as stored; scenario presets are only the defaults of new runs, so editing a preset never
changes the env an old checkpoint is evaluated or exported on. ``train.env_overrides`` stays as a record
of what the run asked for. A config.json whose ``env`` section is missing or does not match today's
``EnvConfig`` gets a one-line error naming :func:`convert` (``aswarm convert-run RUN_DIR``).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from aswarm import config_args
from aswarm.agents.config import TrainConfig
from aswarm.core import safety
from aswarm.envs.config import EnvConfig, legacy_drone_stored, with_legacy_drone

CONVERTER = "aswarm convert-run"


def payload(config: TrainConfig) -> dict:
    train = dataclasses.asdict(config)
    env = train.pop("env")
    return {"train": train, "env": env}


def dumps(config: TrainConfig) -> str:
    """The text of ``config.json`` (its sha256 goes into an export's manifest)."""
    return json.dumps(payload(config), indent=2, default=str)


def write(run_dir: Path, config: TrainConfig) -> None:
    """Write ``run_dir/config.json`` atomically (a crash leaves the old file or the new one)."""
    tmp = Path(run_dir) / "config.json.tmp"
    tmp.write_text(dumps(config))
    tmp.replace(Path(run_dir) / "config.json")


def _read_json(run_dir: Path) -> tuple[Path, dict]:
    from aswarm.training.checkpoint import CheckpointError

    path = Path(run_dir) / "config.json"
    if not path.exists():
        raise CheckpointError(f"{run_dir} is not a run folder: {path.name} is missing")
    try:
        raw = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise CheckpointError(f"{path} is not a valid aswarm run config: {e}") from e
    if not isinstance(raw, dict) or not isinstance(raw.get("train"), dict):
        raise CheckpointError(f"{path} is not a valid aswarm run config: no 'train' section")
    return path, raw


def _train_fields(path: Path, train: dict) -> dict:
    """The ``train`` section as TrainConfig arguments (lists -> tuples), without building it."""
    from aswarm.training.checkpoint import CheckpointError

    train = dict(train)
    train.pop("env", None)
    try:
        train = safety.nest_legacy(train)  # runs from before TrainConfig.safety_filter: flat gain_min, ...
    except ValueError as e:
        raise CheckpointError(f"{path} is not a valid aswarm run config: {e}") from e
    # Runs from before SafetyFilterConfig.fit_to_drone were trained with the gains they store, unfitted; runs from
    # before fit_lookahead had their gains fitted, not the look-aheads; runs from before lookahead_scale set the
    # look-aheads to the lags themselves; runs from before hazard_accel held moving cylinders to their velocity only,
    # and spread the filter's slack evenly (static_slack 1).
    sf = train.get("safety_filter")
    if sf is None:
        train["safety_filter"] = {"fit_to_drone": False, "fit_lookahead": False, "hazard_accel": False,
                                  "static_slack": 1.0}
    elif isinstance(sf, dict):
        train["safety_filter"] = {"fit_to_drone": False, "fit_lookahead": False, "lookahead_scale": 1.0,
                                  "hazard_accel": False, "static_slack": 1.0, **sf}
    elif isinstance(sf, safety.SafetyFilterConfig):  # nest_legacy's, from flat fields: an old run
        train["safety_filter"] = dataclasses.replace(sf, fit_to_drone=False, fit_lookahead=False, hazard_accel=False,
                                                     static_slack=1.0)
    types = config_args.field_types(TrainConfig)
    unknown = sorted(set(train) - set(types))
    if unknown:
        raise CheckpointError(f"{path} is not a valid aswarm run config: unknown train field {unknown[0]!r}")
    return {k: config_args.as_tuples(v) if not dataclasses.is_dataclass(types[k]) else v for k, v in train.items()}


def read(run_dir: Path) -> TrainConfig:
    """The run's TrainConfig with its environment exactly as stored in ``config.json``."""
    from aswarm.training.checkpoint import CheckpointError

    path, raw = _read_json(run_dir)
    try:
        env = config_args.from_dict(EnvConfig, with_legacy_drone(raw["env"]), "env", require_all=True)
    except (KeyError, TypeError, ValueError) as e:
        why = "no 'env' section" if isinstance(e, KeyError) else str(e)
        raise CheckpointError(f"{path} holds no usable env ({why}): convert it with `{CONVERTER} {run_dir}`") from e
    try:
        fields = _train_fields(path, raw["train"])
        nested = {k: config_args.from_dict(t, fields[k], f"train.{k}")
                  for k, t in config_args.field_types(TrainConfig).items()
                  if dataclasses.is_dataclass(t) and isinstance(fields.get(k), dict)}
        return TrainConfig(**{**fields, **nested, "env": env})
    except (TypeError, ValueError) as e:
        if isinstance(e, CheckpointError):
            raise
        raise CheckpointError(f"{path} is not a valid aswarm run config: {e}") from e


def convert(run_dir: Path) -> tuple[Path, list[str]]:
    """Give an old run folder a complete ``env`` section; returns (config.json, what was filled in).

    Fields the stored section has are kept as stored; fields it lacks (a run older than the field, or no
    section at all) take what the old loader gave them: the scenario's preset today with the run's
    ``env_overrides``. The original is kept as ``config.json.orig``.
    """
    from aswarm.envs import registry
    from aswarm.training.checkpoint import CheckpointError

    path, raw = _read_json(run_dir)
    fields = _train_fields(path, raw["train"])
    scenario = fields.get("scenario", TrainConfig.scenario)
    overrides = dict(fields.get("env_overrides", ()))
    try:
        base = dataclasses.asdict(config_args.replace_fields(registry.preset(scenario), overrides))
    except ValueError as e:
        raise CheckpointError(f"{path}: cannot rebuild its env from scenario {scenario!r}: {e}") from e
    stored = raw.get("env")
    stored = with_legacy_drone(stored) if isinstance(stored, dict) else legacy_drone_stored()
    filled = []

    def merge(base: dict, stored: dict, prefix: str) -> dict:
        out = {}
        for k, v in base.items():
            if k not in stored:
                filled.append(prefix + k)
                out[k] = v
            elif isinstance(v, dict) and isinstance(stored[k], dict):
                out[k] = merge(v, stored[k], f"{prefix}{k}.")
            else:
                out[k] = stored[k]
        unknown = sorted(set(stored) - set(base))
        if unknown:
            raise CheckpointError(f"{path}: env field {prefix + unknown[0]!r} no longer exists; it cannot be "
                                  "converted without changing the run's environment")
        return out

    raw = {**raw, "env": merge(base, stored, "")}
    orig = path.with_name("config.json.orig")
    if not orig.exists():
        orig.write_text(path.read_text())
    tmp = path.with_name("config.json.tmp")
    tmp.write_text(json.dumps(raw, indent=2, default=str))
    tmp.replace(path)
    read(run_dir)  # what it must be now: loadable
    return path, filled

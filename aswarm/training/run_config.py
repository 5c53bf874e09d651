"""A run folder's ``config.json``: the training config and the run's full resolved environment.

``{"train": TrainConfig fields but env, "env": EnvConfig fields}``. A run loads its environment from the
``env`` section as stored; scenario presets are only the defaults of new runs, so editing a preset never
changes the env an old checkpoint is evaluated or exported on. ``train.env_overrides`` stays as a record
of what the run asked for. A config.json whose ``env`` section is missing or does not match today's
``EnvConfig`` gets a one-line error naming :func:`convert` (``aswarm convert-run RUN_DIR``).

The same file, or a TOML file of the same fields, starts a new run: ``aswarm train --config FILE``
(:func:`load_file`).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import tomllib
import typing
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


def _upgrade_train(train: dict) -> dict:
    """A stored ``train`` section with what older runs wrote read as today's fields; a ValueError if it cannot be."""
    train = dict(train)
    train.pop("env", None)
    train = safety.nest_legacy(train)  # runs from before TrainConfig.safety_filter: flat gain_min, ...
    # Runs from before SafetyFilterConfig.fit_to_drone were trained with the gains they store, unfitted; runs from
    # before fit_lookahead had their gains fitted, not the look-aheads; runs from before lookahead_scale set the
    # look-aheads to the lags themselves; runs from before hazard_accel held moving cylinders to their velocity only,
    # and spread the filter's slack evenly (static_slack 1); runs from before braking had velocity rows only; runs from
    # before neighbour_release kept the neighbours' reference whatever the closing speed.
    sf = train.get("safety_filter")
    if sf is None:
        train["safety_filter"] = {"fit_to_drone": False, "fit_lookahead": False, "hazard_accel": False,
                                  "static_slack": 1.0, "braking": False, "neighbour_release": 0.0}
    elif isinstance(sf, dict):
        train["safety_filter"] = {"fit_to_drone": False, "fit_lookahead": False, "lookahead_scale": 1.0,
                                  "hazard_accel": False, "static_slack": 1.0, "braking": False,
                                  "neighbour_release": 0.0, **sf}
    elif isinstance(sf, safety.SafetyFilterConfig):  # nest_legacy's, from flat fields: an old run
        train["safety_filter"] = dataclasses.replace(sf, fit_to_drone=False, fit_lookahead=False, hazard_accel=False,
                                                     static_slack=1.0, braking=False, neighbour_release=0.0)
    return train


def _train_fields(path: Path, train: dict) -> dict:
    """The ``train`` section as TrainConfig arguments (lists -> tuples), without building it."""
    from aswarm.training.checkpoint import CheckpointError

    try:
        train = _upgrade_train(train)
    except ValueError as e:
        raise CheckpointError(f"{path} is not a valid aswarm run config: {e}") from e
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


# --- config files: `aswarm train --config FILE` ----------------------------------------------------------------


def load_file(path: str | Path, train: typing.Mapping | None = None,
              env: typing.Mapping | None = None) -> TrainConfig:
    """The TrainConfig of a config file with command-line values on top; a one-line ValueError for a bad file.

    The file is TOML (``.json``: JSON) and holds TrainConfig fields at the top, the safety filter's in a
    ``[safety_filter]`` table and env fields in an ``[env]`` table (nested ones as ``[env.cf]`` or
    ``env.cf.mass = ...``, as a sweep file's ``env.FIELD``), or it is a run folder's ``config.json`` (a ``train``
    and an ``env`` section; what older runs wrote is read as :func:`read` reads it). Env fields override the
    scenario's preset. ``train`` ({dotted name: value}, ``safety_filter.margin``) and ``env`` ({dotted name:
    value}) are the command line's, and override the file's.

    The file is checked on its own first, so an error in it names the file; then the flags apply. The run's
    ``env_overrides`` record what the file's ``env_overrides`` and env fields ask that the preset does not hold,
    and the command line's ``--env``: the file's env fields replace the preset's even where the preset changed
    since (a run's config.json reproduces that run's environment). A ``--scenario`` other than the file's is
    refused when the file sets env fields: they were written for its own scenario.
    """
    where = str(path)
    doc = _read_file(Path(path))
    if "train" in doc:  # a run folder's config.json
        unknown = sorted(set(doc) - {"train", "env"})
        if unknown:
            raise ValueError(f"{where}: unknown section {unknown[0]!r} of a run's config; allowed: train, env")
        for key in ("train", "env"):
            if not isinstance(doc.get(key, {}), dict):
                raise ValueError(f"{where}: invalid {key} = {doc[key]!r}; allowed: a table of {key} fields")
        try:
            train_doc = _upgrade_train(doc["train"])
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from None
        env_doc = with_legacy_drone(doc.get("env", {}))
    else:
        train_doc = dict(doc)
        env_doc = train_doc.pop("env", {})
        if not isinstance(env_doc, dict):
            raise ValueError(f"{where}: invalid env = {env_doc!r}; allowed: a table of env fields ([env])")
        try:  # the safety filter's old flat names, as flags and sweep files take them (gain_min, ...)
            train_doc = safety.nest_legacy(train_doc)
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from None
    if isinstance(train_doc.get("safety_filter"), safety.SafetyFilterConfig):  # nest_legacy's: back to a table
        train_doc["safety_filter"] = dataclasses.asdict(train_doc["safety_filter"])
    recorded = _env_overrides(where, train_doc.pop("env_overrides", []))
    file_train = config_args.table_fields(train_doc, TrainConfig, where, "train config")
    file_env = config_args.table_fields(env_doc, EnvConfig, f"{where}: env", "env config")
    try:
        _compose(file_train, file_env, recorded, {})
    except ValueError as e:
        raise ValueError(f"{where}: {e}") from None
    file_env.pop("scenario", None)
    scenario = file_train.get("scenario", TrainConfig.scenario)
    flag = (train or {}).get("scenario", scenario)
    if flag != scenario and (file_env or recorded):  # its env fields were written for its own scenario's preset
        raise ValueError(f"invalid --scenario {flag!r} with --config {where}: the file sets env fields of scenario "
                         f"{scenario!r}; allowed: its scenario, or a file without env fields")
    return _compose({**file_train, **(train or {})}, file_env, recorded, dict(env or {}))


def _read_file(path: Path) -> dict:
    if not path.is_file():
        raise ValueError(f"invalid --config {str(path)!r}: not a file; allowed: a TOML file (configs/race.toml) "
                         "or a run folder's config.json")
    text = path.read_text()
    try:
        doc = json.loads(text) if path.suffix.lower() == ".json" else tomllib.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as e:
        kind = "JSON" if path.suffix.lower() == ".json" else "TOML"
        raise ValueError(f"invalid --config {str(path)!r}: not valid {kind}: {e}") from None
    if not isinstance(doc, dict):
        raise ValueError(f"invalid --config {str(path)!r}: allowed: a table of config fields")
    return doc


def _env_overrides(where: str, pairs) -> dict:
    """A file's ``env_overrides`` ([[FIELD, value], ...], as config.json writes them) -> {dotted name: typed value}."""
    if not isinstance(pairs, (list, tuple)) or not all(isinstance(p, (list, tuple)) and len(p) == 2
                                                       and isinstance(p[0], str) for p in pairs):
        raise ValueError(f"{where}: invalid env_overrides = {pairs!r}; allowed: a list of [FIELD, value] pairs")
    return config_args.table_fields({k: v for k, v in pairs}, EnvConfig, f"{where}: env_overrides", "env config")


def _compose(train: dict, env: dict, recorded: dict, flags: dict) -> TrainConfig:
    """TrainConfig from dotted train fields, env fields over the scenario's preset, the recorded env overrides of
    the file and the command line's ``--env`` ``flags`` (recorded always, as without a file)."""
    from aswarm.envs import registry

    top = {k: v for k, v in train.items() if "." not in k}
    nested = {k.partition(".")[2]: v for k, v in train.items() if k.startswith("safety_filter.")}
    scenario = top.get("scenario", TrainConfig.scenario)
    preset = registry.preset(scenario)
    record = dict(recorded)
    for key, value in env.items():
        if key != "scenario" and (key in record or functools.reduce(getattr, key.split("."), preset) != value):
            record[key] = value
    record.update(flags)
    resolved = config_args.replace_fields(preset, {**recorded, **env, **flags})
    return TrainConfig(**top, safety_filter=config_args.replace_fields(safety.SafetyFilterConfig(), nested),
                       env=resolved, env_overrides=tuple(record.items()))

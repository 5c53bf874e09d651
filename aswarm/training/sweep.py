"""Hyperparameter sweeps: every configuration x seed of a sweep file trained inside one ``jit``.

A sweep file (TOML) names the scenario, the budget, the seeds and a ``[grid]`` or ``[random]``
search, or an ``[optuna]`` search (``optuna_search.py``: rounds of configurations drawn by Optuna, each round
trained as one vmapped program). Configurations that differ only in value-only hyperparameters
(``hparams.VALUE_FIELDS``: learning rates, clip, GAE lambda, gamma, loss coefficients, cost limit, CBF gain and
penalty bounds) share one compiled program, vmapped over configurations and seeds. Any other field (network sizes,
number of worlds, method, ``env.*`` fields such as reward weights, which the environment bakes into
its code) starts a new group with its own compile.

``OUT/`` holds ``sweep.json`` (the plan), ``groups/gN/checkpoints`` (the stacked state, for resuming),
one run folder per trial in ``trials/`` (``config.json``, ``metrics.jsonl``, ``checkpoints/``,
``curves.png``: ``aswarm eval --checkpoint OUT/trials/c00-s0`` reads it), and the reports
``results.csv``, ``results.json``, ``report.md`` and ``curves.png``.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import itertools
import json
import math
import time
import tomllib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import jax
import numpy as np

from aswarm import config_args
from aswarm.agents import hparams
from aswarm.agents.config import TrainConfig
from aswarm.core import safety

if TYPE_CHECKING:
    from aswarm.training.optuna_search import OptunaSearch

TOP_KEYS = ("name", "scenario", "method", "total_steps", "seeds", "last_updates", "sample_seed", "max_trials",
            "fixed", "grid", "random", "optuna")
# More trials than this is more likely a typo in a grid than a plan: the file must say max_trials = N (or --yes).
MAX_TRIALS = 256
# Set once for the whole sweep, at the top level of the file.
NOT_SWEPT = ("scenario", "seed", "total_steps", "env_overrides")
RANK_METRICS = ("success", "collision", "episode_return")


@dataclasses.dataclass(frozen=True)
class Trial:
    name: str  # run folder name, c{config}-s{seed}
    config_index: int
    config: TrainConfig  # with its seed


@dataclasses.dataclass(frozen=True)
class Group:
    """Trials that share one compiled program: they differ only in ``sweep_fields`` and seeds."""

    index: int
    trials: tuple[Trial, ...]
    sweep_fields: tuple[str, ...]


@dataclasses.dataclass(frozen=True)
class SweepSpec:
    name: str
    configs: tuple[TrainConfig, ...]  # one per point of the search, seed 0
    labels: tuple[str, ...]  # what each configuration sets, e.g. "actor_lr=0.001 gamma=0.9"
    points: tuple[dict, ...]  # the searched values of each configuration
    seeds: tuple[int, ...]
    last_updates: int  # final metrics: episode-weighted mean over this many last updates
    source: str  # the file's text, to recognise the sweep on resume
    # An [optuna] search: its configurations are drawn while it trains, so ``configs`` is empty at parse time.
    optuna: OptunaSearch | None = None

    @property
    def trials(self) -> tuple[Trial, ...]:
        return tuple(Trial(f"c{i:02d}-s{s}", i, dataclasses.replace(c, seed=s))
                     for i, c in enumerate(self.configs) for s in self.seeds)


# --- the sweep file -------------------------------------------------------------------------------------


def _types() -> tuple[dict, dict]:
    """Field types of TrainConfig and of every EnvConfig field, nested ones by dotted name (``cf.mass``)."""
    from aswarm import envs

    env = {k: t for k, t in config_args.leaf_types(envs.EnvConfig).items() if config_args.is_flag(t)}
    # The safety filter's sweepable settings under their flat names (gain_min, ...: also the hyperparameters').
    legacy = {k: config_args.field_types(safety.SafetyFilterConfig)[v] for k, v in safety.LEGACY_FIELDS.items()}
    return {**config_args.field_types(TrainConfig), **legacy}, env


# A TOML value as a field of its type: one home, shared with `aswarm train --config` (config_args.coerce).
_coerce = config_args.coerce


def _field(where: str, key: str, train_types: dict, env_types: dict):
    """(is_env, name, type) of a sweep key: a TrainConfig field or ``env.FIELD``."""
    if key.startswith("env."):
        name = key[4:]
        if name not in env_types or name == "scenario":
            raise ValueError(f"{where}: unknown env field {name!r}; allowed: "
                             f"{', '.join(sorted(k for k in env_types if k != 'scenario'))}")
        return True, name, env_types[name]
    if key not in train_types or key in NOT_SWEPT:
        allowed = sorted(k for k in train_types if k not in NOT_SWEPT)
        hint = {"seed": " (give seeds = [...] at the top level)", "scenario": " (set it at the top level)",
                "total_steps": " (set it at the top level)"}.get(key, "")
        raise ValueError(f"{where}: unknown field {key!r}{hint}; allowed: {', '.join(allowed)} or env.FIELD")
    return False, key, train_types[key]


def _flatten_env(table: dict) -> dict:
    """TOML ``env.x = ...`` (a nested table) and ``"env.x" = ...`` both become the key ``"env.x"``; nested env
    fields too (``env.cf.mass = ...`` -> ``"env.cf.mass"``), down to a field (a ``{low, high}`` range stays)."""
    out = {k: v for k, v in table.items() if k != "env"}
    env = table.get("env", {})
    if not isinstance(env, dict):
        raise ValueError(f"invalid env = {env!r}: allowed: a table of env fields (env.FIELD = ...)")
    out.update({f"env.{k}": v for k, v in config_args.flatten(env, _types()[1]).items()})
    return out


def _table(data: dict, key: str, name: str) -> dict:
    value = data.get(key, {})
    if not isinstance(value, dict):
        raise ValueError(f"sweep {name}: invalid {key} = {value!r}; allowed: a table [{key}]")
    return _flatten_env(value)


def _random_points(name: str, table: dict, seed: int, types: tuple[dict, dict]) -> list[dict]:
    samples = table.pop("samples", None)
    if not isinstance(samples, int) or isinstance(samples, bool) or samples < 1:
        raise ValueError(f"sweep {name}: [random] invalid samples = {samples!r}; allowed: an integer >= 1")
    if not table:
        raise ValueError(f"sweep {name}: [random] is empty; allowed: FIELD = [choices] or FIELD = {{low, high, log}}")
    rng = np.random.default_rng(seed)
    draws = {}
    for key, spec in table.items():
        where = f"sweep {name}: [random] {key}"
        _, _, kind = _field(where, key, *types)
        if isinstance(spec, list):
            if not spec:
                raise ValueError(f"{where}: empty list of choices; allowed: one value or more")
            choices = [_coerce(where, kind, v) for v in spec]
            draws[key] = [choices[i] for i in rng.integers(len(choices), size=samples)]
        elif isinstance(spec, dict):
            if kind is not float:
                raise ValueError(f"{where}: a range needs a float field; allowed here: a list of choices")
            extra = set(spec) - {"low", "high", "log"}
            if extra or "low" not in spec or "high" not in spec:
                raise ValueError(f"{where}: invalid range {spec!r}; allowed keys: low, high, log")
            lo, hi = _coerce(where, float, spec["low"]), _coerce(where, float, spec["high"])
            log = _coerce(where, bool, spec.get("log", False))
            if not lo < hi or (log and lo <= 0):
                raise ValueError(f"{where}: invalid range low={lo}, high={hi}; need low < high"
                                 + (" and low > 0 for log = true" if log else ""))
            u = rng.uniform(size=samples)
            vals = np.exp(np.log(lo) + u * (np.log(hi) - np.log(lo))) if log else lo + u * (hi - lo)
            draws[key] = [float(v) for v in vals]
        else:
            raise ValueError(f"{where}: invalid {spec!r}; allowed: a list of choices or {{low, high, log}}")
    return [{k: draws[k][i] for k in draws} for i in range(samples)]


def _grid_points(name: str, table: dict, types: tuple[dict, dict]) -> list[dict]:
    if not table:
        raise ValueError(f"sweep {name}: [grid] is empty; allowed: FIELD = [value, ...] for one field or more")
    lists = {}
    for key, values in table.items():
        where = f"sweep {name}: [grid] {key}"
        _, _, kind = _field(where, key, *types)
        if not isinstance(values, list) or not values:
            raise ValueError(f"{where}: invalid {values!r}; allowed: a non-empty list of values")
        lists[key] = [_coerce(where, kind, v) for v in values]
        repeated = next((v for i, v in enumerate(lists[key]) if v in lists[key][:i]), None)
        if repeated is not None:  # the same trials twice, under two names
            raise ValueError(f"{where}: value {repeated!r} is listed twice; allowed: distinct values")
    return [dict(zip(lists, combo)) for combo in itertools.product(*lists.values())]


def _label(point: dict) -> str:
    def fmt(v):
        return f"{v:.3g}" if isinstance(v, float) else ",".join(map(str, v)) if isinstance(v, tuple) else str(v)

    return " ".join(f"{k}={fmt(v)}" for k, v in point.items()) or "base"


def parse(data: dict, name: str = "sweep", source: str = "", yes: bool = False) -> SweepSpec:
    """A parsed TOML document -> SweepSpec; every error is a one-line ValueError, raised before any compile.

    More than ``max_trials`` trials (default :data:`MAX_TRIALS`) are refused unless ``yes``.
    """
    from aswarm import envs

    types = _types()
    unknown = sorted(set(data) - set(TOP_KEYS))
    if unknown:
        raise ValueError(f"sweep {name}: unknown key {unknown[0]!r}; allowed: {', '.join(TOP_KEYS)}")
    name = data.get("name", name)
    if not isinstance(name, str) or not name:
        raise ValueError(f"sweep: invalid name = {name!r}; allowed: a non-empty string")
    top = {}
    for key, kind, required in (("scenario", str, True), ("total_steps", int, True), ("method", str, False),
                                ("last_updates", int, False), ("sample_seed", int, False),
                                ("max_trials", int, False)):
        if key not in data:
            if required:
                raise ValueError(f"sweep {name}: missing {key} = ...; a sweep needs scenario, total_steps and seeds")
            continue
        top[key] = _coerce(f"sweep {name}: {key}", kind, data[key])
    seeds = data.get("seeds")
    if not isinstance(seeds, list) or not seeds or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0
                                                            for s in seeds):
        raise ValueError(f"sweep {name}: invalid seeds = {seeds!r}; allowed: a non-empty list of integers >= 0")
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"sweep {name}: invalid seeds = {seeds!r}; allowed: distinct integers")
    last_updates = top.pop("last_updates", 5)
    if last_updates < 1:
        raise ValueError(f"sweep {name}: invalid last_updates = {last_updates}; allowed: an integer >= 1")
    sample_seed = top.pop("sample_seed", 0)
    max_trials = top.pop("max_trials", MAX_TRIALS)
    if max_trials < 1:
        raise ValueError(f"sweep {name}: invalid max_trials = {max_trials}; allowed: an integer >= 1")

    fixed = {}
    for key, value in _table(data, "fixed", name).items():
        where = f"sweep {name}: [fixed] {key}"
        fixed[key] = _coerce(where, _field(where, key, *types)[2], value)
    searches = [k for k in ("grid", "random", "optuna") if k in data]
    if len(searches) != 1:
        raise ValueError(f"sweep {name}: needs exactly one of [grid], [random] or [optuna]; found "
                         f"{' and '.join(f'[{k}]' for k in searches) or 'none'}")
    if searches == ["optuna"]:
        return _parse_optuna(data, name, source, yes, top, fixed, tuple(seeds), last_updates, max_trials, types)
    if searches == ["grid"]:
        points = _grid_points(name, _table(data, "grid", name), types)
    else:
        points = _random_points(name, _table(data, "random", name), sample_seed, types)
    if len(points) * len(seeds) > max_trials and not yes:  # before building thousands of configurations
        raise ValueError(f"sweep {name}: {len(points) * len(seeds)} trials ({len(points)} configurations x "
                         f"{len(seeds)} seeds) is more than max_trials = {max_trials}; allowed: set max_trials "
                         f"in the file, or pass --yes")
    for key in points[0]:
        if key in fixed:
            raise ValueError(f"sweep {name}: {key!r} is both fixed and searched; allowed: one of the two")

    configs, labels, checked_envs = [], [], {}
    for point in points:
        values = {**top, **fixed, **point}
        train = {k: v for k, v in values.items() if not k.startswith("env.")}
        env_over = tuple(sorted((k[4:], v) for k, v in values.items() if k.startswith("env.")))
        label = _label(point)
        try:
            cfg = TrainConfig(**safety.nest_legacy(train), env_overrides=env_over)  # resolves and checks the env
            if cfg.env not in checked_envs:  # builds the model only: no compile
                checked_envs[cfg.env] = envs.SwarmEnv(cfg.env)
        except ValueError as e:
            raise ValueError(f"sweep {name}: configuration {label}: {e}") from None
        configs.append(cfg)
        labels.append(label)
    return SweepSpec(name=name, configs=tuple(configs), labels=tuple(labels), points=tuple(points),
                     seeds=tuple(seeds), last_updates=last_updates, source=source)


def _parse_optuna(data: dict, name: str, source: str, yes: bool, top: dict, fixed: dict, seeds: tuple[int, ...],
                  last_updates: int, max_trials: int, types: tuple[dict, dict]) -> SweepSpec:
    """The [optuna] search of a sweep file: its base configuration (top level and [fixed]) and its table."""
    from aswarm import envs
    from aswarm.training import optuna_search  # imports optuna itself only now: a file with [optuna] needs it

    if "sample_seed" in data:
        raise ValueError(f"sweep {name}: sample_seed is for [random]; allowed with [optuna]: seed = N in [optuna]")
    train = {k: v for k, v in {**top, **fixed}.items() if not k.startswith("env.")}
    env_over = tuple(sorted((k[4:], v) for k, v in fixed.items() if k.startswith("env.")))
    try:
        base = TrainConfig(**safety.nest_legacy(train), env_overrides=env_over)
        envs.SwarmEnv(base.env)  # builds the model only: no compile
    except ValueError as e:
        raise ValueError(f"sweep {name}: configuration [fixed]: {e}") from None
    table = data["optuna"]
    if not isinstance(table, dict):
        raise ValueError(f"sweep {name}: invalid optuna = {table!r}; allowed: a table [optuna]")
    search = optuna_search.parse_table(name, table, base, fixed, types)
    trials = search.rounds * search.batch * len(seeds)
    if trials > max_trials and not yes:
        raise ValueError(f"sweep {name}: {trials} trials ({search.rounds} rounds x {search.batch} configurations x "
                         f"{len(seeds)} seeds) is more than max_trials = {max_trials}; allowed: set max_trials "
                         f"in the file, or pass --yes")
    return SweepSpec(name=name, configs=(), labels=(), points=(), seeds=seeds, last_updates=last_updates,
                     source=source, optuna=search)


def load(path: str | Path, yes: bool = False) -> SweepSpec:
    """Read and check a sweep file; a ValueError (before anything compiles) when it is bad."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"invalid sweep file {str(path)!r}: not a file; allowed: a TOML sweep file")
    text = path.read_text()
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"invalid sweep file {str(path)!r}: not valid TOML: {e}") from None
    return parse(data, path.stem, text, yes=yes)


def groups(spec: SweepSpec) -> tuple[Group, ...]:
    """Trials grouped by everything but the value-only hyperparameters: one compile per group."""
    defaults = TrainConfig()
    blank = {f: hparams.value(defaults, f) for f in hparams.VALUE_FIELDS}
    by_key: dict = {}
    for t in spec.trials:
        by_key.setdefault(hparams.replaced(dataclasses.replace(t.config, seed=0), blank), []).append(t)
    return tuple(Group(i, tuple(ts), hparams.varying([t.config for t in ts])) for i, ts in enumerate(by_key.values()))


# --- training -------------------------------------------------------------------------------------------


def _programs(group: Group, mesh=None):
    """(agent, jitted init, jitted chunk, keys, values, mesh) of a group, laid out over ``mesh`` (default: all
    devices)."""
    agent, init_fn, chunk_fn, mesh = build_program(group, mesh)
    return (agent, init_fn, chunk_fn, *group_args(group, mesh), mesh)


def group_args(group: Group, mesh) -> tuple:
    """(keys, values): the init arguments of ``group``'s trials, laid out over ``mesh``. Any group with the same
    shapes and ``sweep_fields`` runs in the program :func:`build_program` made for one of them."""
    from jax.sharding import NamedSharding
    from jax.sharding import PartitionSpec as P

    from aswarm.training import sharding

    keys = np.stack([np.asarray(jax.random.PRNGKey(t.config.seed)) for t in group.trials])
    values = hparams.stack([t.config for t in group.trials], group.sweep_fields)
    lead = NamedSharding(mesh, P("trial"))
    return sharding.put(keys, lead), sharding.put(values, lead)


def build_program(group: Group, mesh=None) -> tuple:
    """(agent, jitted init, jitted chunk, mesh) of a group, laid out over ``mesh`` (default: all devices)."""
    from aswarm.agents.train import make_train
    from aswarm.training import sharding

    base = group.trials[0].config
    mesh = mesh or sharding.make_mesh(len(group.trials), base.num_envs)
    return (*_group_program(make_train, base, group.sweep_fields, len(group.trials), mesh), mesh)


@functools.lru_cache(maxsize=4)
def _group_program(make_train: Callable, base, sweep_fields: tuple[str, ...], k: int, mesh) -> tuple:
    """(agent, jitted init, jitted chunk) of ``k`` trials of ``base`` that differ in ``sweep_fields`` and seeds.
    Kept for the process's next build of the same group (a resumed sweep, the next round of a search), as
    ``runner.train_program`` keeps a run's."""
    from aswarm.training import sharding

    agent, init, chunk, _ = make_train(base, sweep_fields, shard_rows=sharding.rows_constraint(mesh))

    def vinit(keys, values):
        # A loop, not vmap: batching the orthogonal initializers' QR over trials made XLA's batched LAPACK
        # call deadlock on the 2-thread CPU pool (as batched Cholesky did, shared/crazyflie.md).
        return jax.lax.map(lambda a: init(*a), (keys, values))

    def vchunk(ts, n: int):
        return jax.vmap(lambda s: chunk(s, n), spmd_axis_name="trial")(ts)

    keys = jax.ShapeDtypeStruct((k, *jax.random.PRNGKey(0).shape), jax.random.PRNGKey(0).dtype)
    like = jax.eval_shape(vinit, keys, hparams.stack([base] * k, sweep_fields))
    return (agent, *sharding.sharded_fns(vinit, vchunk, like, mesh, stacked=True))


def _run_group(group: Group, out: Path, progress: bool, max_updates: int | None, mesh,
               log: Callable[[str], None]) -> dict:
    """Train one group to its budget (or ``max_updates`` more) with the runner's host loop (a run is a group
    of one trial); returns its timing and whether it finished."""
    from aswarm.training import runner, sharding

    gdir = out / "groups" / f"g{group.index}"
    done_file = gdir / "done.json"
    if done_file.exists():
        log(f"group {group.index}: finished earlier, skipped")
        return json.loads(done_file.read_text())
    primary = jax.process_index() == 0
    base = group.trials[0].config
    t0 = time.monotonic()
    agent, init_fn, chunk_fn, keys, values, mesh = _programs(group, mesh)
    log(f"group {group.index}: {len(group.trials)} trials in one program, swept {list(group.sweep_fields) or 'seeds'}"
        f"; {sharding.describe(mesh)}")
    tdirs = [out / "trials" / t.name for t in group.trials]
    if primary:
        for t, d in zip(group.trials, tdirs):
            d.mkdir(parents=True, exist_ok=True)
            runner.write_config(d, t.config)
    program = runner.Program(agent.env, init_fn, chunk_fn, (keys, values), mesh, stacked=True)
    total = base.num_updates
    try:
        res = runner.run_loop(program, base, gdir, tdirs, progress=progress, max_updates=max_updates,
                              desc=f"group {group.index}", log=log, label=f"group {group.index}")
    except runner.TrainingDiverged as e:
        # Every trial diverged: nothing left to train; each trial folder holds its DIVERGED file.
        log(f"group {group.index}: every trial diverged ({e})")
        result = {"group": group.index, "trials": [t.name for t in group.trials],
                  "sweep_fields": group.sweep_fields, "updates": None, "finished": True, "diverged": True,
                  "wall_s": time.monotonic() - t0, "devices": int(mesh.devices.size)}
        if primary:
            done_file.write_text(json.dumps(result))
        return result
    update = res.update
    result = {"group": group.index, "trials": [t.name for t in group.trials], "sweep_fields": group.sweep_fields,
              "updates": update, "finished": update >= total, "wall_s": time.monotonic() - t0,
              "devices": int(mesh.devices.size)}
    if update < total:
        return result
    save_trials(group, update, res.state, agent.env, tdirs)
    if primary:
        done_file.write_text(json.dumps(result))
    return result


def save_trials(group: Group, update: int, state, env, tdirs: list[Path]) -> None:
    """Each trial's slice of the stacked ``state`` as a plain run's checkpoint in its folder, and its curves."""
    from aswarm.training import checkpoint, runner, sharding

    final = sharding.fetch(state)
    for i, (t, d) in enumerate(zip(group.trials, tdirs)):
        # The trial's own config holds its values: saved without hparams, the checkpoint is a plain run's,
        # so `aswarm eval`, `aswarm export` and `aswarm train --resume` read it.
        trial_state = sharding.for_checkpoint(hparams.index(final, i).replace(hparams={}))
        trial_mngr = checkpoint.manager(d, fingerprint=checkpoint.fingerprint(t.config, env))
        if trial_mngr.latest_step() != update:  # not saved already by a run killed before its results were kept
            checkpoint.save(trial_mngr, update, trial_state)
        if jax.process_index() == 0:
            runner.plot_curves(d)


def _check_plan(spec: SweepSpec, out: Path) -> None:
    plan = out / "sweep.json"
    payload = {"name": spec.name, "source": spec.source, "trials": [t.name for t in spec.trials],
               "labels": list(spec.labels)}
    if plan.exists():
        if json.loads(plan.read_text()).get("source") != spec.source:
            raise ValueError(f"invalid --out {str(out)!r}: it holds a different sweep; allowed: the same sweep file "
                             "(to resume) or a new folder")
        return
    if jax.process_index() == 0:
        out.mkdir(parents=True, exist_ok=True)
        plan.write_text(json.dumps(payload, indent=2))


def run(spec: SweepSpec, out: str | Path, progress: bool = True, max_updates: int | None = None, mesh=None,
        log: Callable[[str], None] = print) -> dict | None:
    """Train every trial of ``spec`` into ``out`` (resuming what is there); returns the results, or None when
    ``max_updates`` (updates per group in this call, for tests) stopped it early."""
    from aswarm.training import sharding

    if spec.optuna is not None:
        from aswarm.training import optuna_search

        return optuna_search.run(spec, out, progress=progress, max_updates=max_updates, mesh=mesh, log=log)
    out = Path(out)
    if jax.process_index() != 0:  # several hosts: one of them reports
        log = lambda _: None  # noqa: E731
    gs = groups(spec)
    for g in gs:  # fail before compiling anything
        num_envs = g.trials[0].config.num_envs
        if mesh is None:
            sharding.make_mesh(len(g.trials), num_envs)
        elif num_envs % dict(mesh.shape)["env"] or len(g.trials) % dict(mesh.shape)["trial"]:
            raise ValueError(f"invalid mesh {dict(mesh.shape)} for {len(g.trials)} trials of {num_envs} worlds: "
                             "allowed: axes that divide them")
    _check_plan(spec, out)
    timings = [_run_group(g, out, progress, max_updates, mesh, log) for g in gs]
    if not all(t["finished"] for t in timings):
        return None
    results = summarize(spec, out)
    results["groups"] = timings
    if jax.process_index() == 0:
        write_reports(results, out)
    return results


# --- results --------------------------------------------------------------------------------------------


def final_metrics(rows: list[dict], last: int) -> dict:
    """Success, collision and return over the last ``last`` updates, weighted by the episodes that ended."""
    tail = rows[-last:]
    eps = np.array([r["episodes"] for r in tail], float)
    out = {}
    for m in RANK_METRICS:
        v = np.array([r[f"episode/{m}"] for r in tail], float)
        out[m] = float(np.sum(v * eps) / np.sum(eps)) if eps.sum() > 0 else math.nan
    return out


def _stats(xs: Sequence[float]) -> dict:
    a = np.asarray(xs, float)
    ok = a[np.isfinite(a)]
    if not ok.size:
        return {"mean": math.nan, "std": math.nan, "min": math.nan, "max": math.nan}
    return {"mean": float(ok.mean()), "std": float(ok.std(ddof=1)) if ok.size > 1 else 0.0,
            "min": float(ok.min()), "max": float(ok.max())}


def summarize(spec: SweepSpec, out: Path) -> dict:
    """Per configuration: the final metrics' mean and spread over seeds; configurations ranked best first."""
    from aswarm.training.runner import read_metrics  # JAX: parsing a sweep file stays light

    trials = spec.trials
    per_config = []
    for ci, (label, point) in enumerate(zip(spec.labels, spec.points)):
        mine = [t for t in trials if t.config_index == ci]
        finals = {t.name: final_metrics(read_metrics(out / "trials" / t.name), spec.last_updates) for t in mine}
        diverged = [t.name for t in mine if (out / "trials" / t.name / "DIVERGED").exists()]
        entry = {"config": ci, "label": label, "point": point, "trials": finals, "diverged": diverged}
        entry.update({m: _stats([f[m] for f in finals.values()]) for m in RANK_METRICS})
        per_config.append(entry)

    def rank_key(e):
        nan_last = lambda x, sign: (math.inf if math.isnan(x) else sign * x)  # noqa: E731
        return (len(e["diverged"]) > 0, nan_last(e["success"]["mean"], -1), nan_last(e["collision"]["mean"], 1),
                nan_last(e["episode_return"]["mean"], -1))

    ranked = sorted(per_config, key=rank_key)
    for r, e in enumerate(ranked, 1):
        e["rank"] = r
    return {"name": spec.name, "seeds": list(spec.seeds), "last_updates": spec.last_updates, "configs": ranked}


def format_table(results: dict) -> str:
    """The ranked markdown table: mean ± std over seeds."""
    head = "| rank | config | success | collision | return | trials |\n|---:|---|---:|---:|---:|---|\n"
    def cell(s: dict) -> str:
        return "n/a" if math.isnan(s["mean"]) else f"{s['mean']:.3f} ± {s['std']:.3f}"

    lines = []
    for e in results["configs"]:
        note = f" ({len(e['diverged'])} diverged)" if e["diverged"] else ""
        if e.get("pruned_at") is not None:  # an [optuna] search's
            note += f" (pruned at update {e['pruned_at']})"
        elif e.get("state") == "FAIL":
            note += " (failed)"
        lines.append(f"| {e['rank']} | {e['label']} | {cell(e['success'])} | {cell(e['collision'])} | "
                     f"{cell(e['episode_return'])} | c{e['config']:02d}-s*{note} |")
    return head + "\n".join(lines)


def write_reports(results: dict, out: Path) -> list[Path]:
    """results.json, results.csv, report.md and curves.png in ``out``."""
    out = Path(out)
    (out / "results.json").write_text(json.dumps(results, indent=2, default=str))
    with (out / "results.csv").open("w", newline="") as f:
        fields = sorted({k for e in results["configs"] for k in e["point"]})
        w = csv.writer(f)
        w.writerow(["rank", "config", "label", *fields,
                    *[f"{m}_{s}" for m in RANK_METRICS for s in ("mean", "std", "min", "max")], "diverged"])
        for e in results["configs"]:
            w.writerow([e["rank"], e["config"], e["label"], *[e["point"].get(k, "") for k in fields],
                        *[e[m][s] for m in RANK_METRICS for s in ("mean", "std", "min", "max")], len(e["diverged"])])
    (out / "report.md").write_text(f"# sweep {results['name']}\n\nFinal metrics: episode-weighted mean over the "
                                   f"last {results['last_updates']} updates; mean ± std over seeds "
                                   f"{results['seeds']}.\n\n{format_table(results)}\n")
    return [out / "results.json", out / "results.csv", out / "report.md", plot_curves(results, out)]


def plot_curves(results: dict, out: Path) -> Path:
    """Learning curves per configuration: mean over seeds, with the seeds' range shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("episode/episode_return", "episode return"), ("episode/success", "success rate"),
              ("episode/collision", "collision rate")]
    from aswarm.training.runner import read_metrics

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    for ci, e in enumerate(sorted(results["configs"], key=lambda e: e["config"])):
        runs = [read_metrics(out / "trials" / name) for name in e["trials"]]
        n = min(len(r) for r in runs)
        if n == 0:
            continue
        x = np.array([r["env_steps"] for r in runs[0][:n]])
        for ax, (name, _) in zip(axes, panels):
            y = np.array([[row[name] for row in r[:n]] for r in runs])
            ax.plot(x, y.mean(0), color=f"C{ci % 10}", label=e["label"] if ax is axes[0] else None)
            ax.fill_between(x, y.min(0), y.max(0), color=f"C{ci % 10}", alpha=0.15)
    for ax, (_, title) in zip(axes, panels):
        ax.set_title(title)
        ax.set_xlabel("env steps")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"sweep {results['name']}")
    fig.tight_layout()
    from aswarm.analysis.plots import save_figure

    path = save_figure(fig, out / "curves.png", dpi=100)
    plt.close(fig)
    return path


# --- benchmark ------------------------------------------------------------------------------------------


def _time_program(init_fn, chunk_fn, args: tuple, updates: int) -> tuple[float, float]:
    """(seconds to first result, compile included; seconds of the compiled training run, best of 2)."""
    t0 = time.perf_counter()
    compiled = chunk_fn.lower(jax.block_until_ready(init_fn(*args)), updates).compile()
    jax.block_until_ready(compiled(init_fn(*args)))
    first = time.perf_counter() - t0
    runs = []
    for _ in range(2):
        ts = jax.block_until_ready(init_fn(*args))  # the chunk donates its input: a fresh state each time
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(ts))
        runs.append(time.perf_counter() - t0)
    return first, min(runs)


def bench_sweep(spec: SweepSpec, seed: int | None = None, log: Callable[[str], None] = print) -> dict:
    """Wall time of the spec's configurations (one seed) trained in one vmapped program vs one after another.

    "With compile" is the time to the first result: sequential runs compile once per configuration,
    because the plain trainer bakes its hyperparameters into the program as constants. "Compiled" is
    the training run alone (``num_updates`` updates, best of 2). Only the first group is timed (the
    configurations that share a program), on one device.
    """
    from aswarm.agents.train import make_train
    from aswarm.training import sharding

    if spec.optuna is not None:
        raise ValueError(f"invalid --bench for sweep {spec.name}: its [optuna] configurations are drawn as it "
                         "trains; allowed: a [grid] or [random] sweep")
    seed = spec.seeds[0] if seed is None else seed
    group = groups(dataclasses.replace(spec, seeds=(seed,)))[0]
    base = group.trials[0].config
    n = base.num_updates
    _, init_fn, chunk_fn, keys, values, _ = _programs(group, sharding.make_mesh(1, base.num_envs, jax.devices()[:1]))
    v_total, v_run = _time_program(init_fn, chunk_fn, (keys, values), n)
    log(f"one vmapped program, {len(group.trials)} configurations: {v_total:.1f} s with compile, {v_run:.2f} s run")
    s_total = s_run = 0.0
    for t in group.trials:
        _, init, chunk, _ = make_train(t.config)
        first, run = _time_program(jax.jit(init), jax.jit(chunk, static_argnums=1),
                                   (jax.random.PRNGKey(t.config.seed),), n)
        s_total, s_run = s_total + first, s_run + run
        log(f"sequential {t.name}: {first:.1f} s with compile, {run:.2f} s run")
    device = f"one {jax.devices()[0].platform.upper()} device"
    return {"configs": len(group.trials), "updates": n, "num_envs": base.num_envs, "rollout_steps": base.rollout_steps,
            "scenario": base.scenario, "method": base.method, "device": device,
            "vmapped_total_s": v_total, "sequential_total_s": s_total, "vmapped_run_s": v_run,
            "sequential_run_s": s_run, "speedup_total": s_total / v_total, "speedup_run": s_run / v_run}


def format_bench(b: dict) -> str:
    return (f"K = {b['configs']} configurations of `{b['scenario']}` / {b['method']}, {b['num_envs']} worlds x "
            f"{b['rollout_steps']} steps, {b['updates']} updates each, {b['device']}:\n\n"
            "| | one vmapped program | K sequential runs | ratio |\n|---|---:|---:|---:|\n"
            f"| wall time with compile | {b['vmapped_total_s']:.1f} s | {b['sequential_total_s']:.1f} s | "
            f"{b['speedup_total']:.2f}x |\n"
            f"| training run, compiled | {b['vmapped_run_s']:.2f} s | {b['sequential_run_s']:.2f} s | "
            f"{b['speedup_run']:.2f}x |\n")

"""Model-based hyperparameter search: Optuna's ask/tell over rounds of vmapped trials (``[optuna]`` in a sweep file).

Each round asks Optuna for ``batch`` configurations, trains them and all their seeds as ONE vmapped program (the
sweep's, compiled once for the whole search: every round has the same shapes and swept fields), and tells Optuna
each configuration's objective: a final metric of its learning curve (``success``, ``collision`` or
``episode_return``, the episode-weighted mean over the last ``last_updates`` updates), averaged over the seeds.
Only the value-only hyperparameters (``hparams.VALUE_FIELDS``) can be searched: any other field changes the
compiled program, and the members of one program must share it.

Pruning. At every multiple of ``updates_per_chunk`` before the end, each configuration reports the objective of its
curve so far, and the pruner (the median of the completed trials at the same update, by default) may prune it. A
member of a vmapped program cannot be dropped without compiling a smaller program, so a pruned configuration
keeps training alongside the others: it is marked (Optuna's PRUNED state with its last reported value, a
``PRUNED`` file in its trial folders, a note in the report) and is no longer reported or told a final value.
Pruning therefore saves compute only when it ends a round: once every configuration of the batch is pruned (or
has diverged) the round stops at that chunk. What it always does is let the sampler learn from a partial curve
that a region is poor.

Resuming. The study lives in memory, rebuilt at each round from the finished rounds' records
(``OUT/rounds/rNN.json``); a round's draws are written before it trains (``rNN.plan.json``) and asked again from
there, so a killed round resumes from its last checkpoint with the same configurations. The sampler is seeded per
round from (``seed``, round): a resumed search draws what an uninterrupted one would have.

``OUT/`` holds what a sweep's does (``sweep.json``, ``trials/cNN-sS/`` run folders, ``results.*``, ``report.md``
with a section on the search, ``curves.png``), with configurations numbered in the order Optuna asked for them,
and: ``rounds/rNN.plan.json`` and ``rNN.json`` (each round's draws, then every trial's state, value and reports),
``groups/rNN/checkpoints`` (the round's stacked state, for resuming), ``trials.csv`` (every Optuna trial, the
invalid draws included) and ``optuna.png`` (the objective over the trials and the values the pruner saw).

``optuna`` is imported only for a file with an ``[optuna]`` table (``pip install 'aswarm[optuna]'``).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import time
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np

from aswarm.agents import hparams
from aswarm.agents.config import TrainConfig
from aswarm.training import sweep

KEYS = ("objective", "direction", "rounds", "batch", "sampler", "seed", "startup_trials", "pruner", "prune_warmup",
        "prune_startup", "space")
# The objective's natural direction: the file may set another.
OBJECTIVES = {"success": "maximize", "collision": "minimize", "episode_return": "maximize"}
SAMPLERS = ("tpe", "random")
PRUNERS = ("median", "none")
RANGE_KEYS = ("low", "high", "log", "step", "int")
INSTALL = "pip install 'aswarm[optuna]'"
# A draw that makes an invalid configuration (gain_min >= gain_max) is failed and drawn again, this many times a
# batch at most: more means the space is mostly invalid, a mistake in the file.
MAX_REDRAWS = 20


def import_optuna():
    """The ``optuna`` module; a one-line ValueError saying how to install it when it is missing."""
    try:
        import optuna
    except ImportError:
        raise ValueError(f"an [optuna] search needs the optuna package: {INSTALL}") from None
    optuna.logging.set_verbosity(optuna.logging.WARNING)  # it logs every trial; the search logs its rounds
    return optuna


@dataclasses.dataclass(frozen=True)
class Param:
    """One searched field: a float or int range (``log``, ``step``) or a list of choices."""

    field: str
    kind: str  # "float", "int" or "categorical"
    low: float | None = None
    high: float | None = None
    log: bool = False
    step: float | None = None
    choices: tuple = ()

    def distribution(self):
        d = import_optuna().distributions
        if self.kind == "categorical":
            return d.CategoricalDistribution(self.choices)
        if self.kind == "int":
            return d.IntDistribution(int(self.low), int(self.high), log=self.log, step=int(self.step or 1))
        return d.FloatDistribution(self.low, self.high, log=self.log, step=self.step)

    def extremes(self) -> tuple:
        return self.choices if self.kind == "categorical" else (self.low, self.high)


@dataclasses.dataclass(frozen=True)
class OptunaSearch:
    """An ``[optuna]`` table, checked: what is searched, how, and for how long."""

    base: TrainConfig  # the top level and [fixed]; every trial is this with its drawn values
    space: tuple[Param, ...]
    objective: str  # one of OBJECTIVES
    direction: str  # "maximize" or "minimize"
    rounds: int
    batch: int  # configurations per round: one vmapped program of batch x seeds trials
    sampler: str
    seed: int
    startup_trials: int  # TPE draws at random until this many trials have finished
    pruner: str
    prune_warmup: int  # updates before the first pruning decision
    prune_startup: int  # completed trials before the first pruning decision

    @property
    def fields(self) -> tuple[str, ...]:
        """The program's swept fields: every searched one, whatever a round happens to draw."""
        return hparams.check_fields([p.field for p in self.space])

    def distributions(self) -> dict:
        return {p.field: p.distribution() for p in self.space}

    def configure(self, params: dict) -> TrainConfig:
        """The configuration of drawn ``params``; a ValueError when they make an invalid one."""
        return hparams.replaced(self.base, {f: float(v) for f, v in params.items()})

    def make_sampler(self, round_index: int):
        optuna = import_optuna()
        # Seeded per round, not once: the study is rebuilt each round, and a resumed search must draw the same.
        seed = int(np.random.SeedSequence([self.seed, round_index]).generate_state(1)[0])
        if self.sampler == "random":
            return optuna.samplers.RandomSampler(seed=seed)
        # constant_liar: a batch is asked before any of it is told; counting the batch's running trials as poor
        # keeps its draws apart instead of all at the same promising point.
        return optuna.samplers.TPESampler(seed=seed, n_startup_trials=self.startup_trials, constant_liar=True)

    def make_pruner(self):
        optuna = import_optuna()
        if self.pruner == "none":
            return optuna.pruners.NopPruner()
        return optuna.pruners.MedianPruner(n_startup_trials=self.prune_startup, n_warmup_steps=self.prune_warmup)


# --- the [optuna] table ------------------------------------------------------------------------------------------


def _int(where: str, value, low: int) -> int:
    value = sweep._coerce(where, int, value)
    if value < low:
        raise ValueError(f"{where}: invalid value {value}; allowed: an integer >= {low}")
    return value


def _choice(where: str, value, allowed: tuple[str, ...]) -> str:
    if value not in allowed:
        raise ValueError(f"{where}: invalid value {value!r}; allowed: {', '.join(allowed)}")
    return value


def _param(where: str, field: str, spec) -> Param:
    if isinstance(spec, list):
        if not spec:
            raise ValueError(f"{where}: empty list of choices; allowed: one value or more")
        choices = tuple(sweep._coerce(where, float, v) for v in spec)
        if len(set(choices)) != len(choices):
            raise ValueError(f"{where}: a choice is listed twice; allowed: distinct values")
        return Param(field, "categorical", choices=choices)
    if not isinstance(spec, dict):
        raise ValueError(f"{where}: invalid {spec!r}; allowed: a list of choices or {{low, high, log, step, int}}")
    extra = sorted(set(spec) - set(RANGE_KEYS))
    if extra or "low" not in spec or "high" not in spec:
        raise ValueError(f"{where}: invalid range {spec!r}; allowed keys: {', '.join(RANGE_KEYS)} (low and high "
                         "required)")
    is_int = sweep._coerce(where, bool, spec.get("int", False))
    kind = int if is_int else float
    lo, hi = sweep._coerce(where, kind, spec["low"]), sweep._coerce(where, kind, spec["high"])
    log = sweep._coerce(where, bool, spec.get("log", False))
    step = spec.get("step")
    if not lo < hi or (log and lo <= 0):
        raise ValueError(f"{where}: invalid range low={lo}, high={hi}; need low < high"
                         + (" and low > 0 for log = true" if log else ""))
    if step is not None:
        step = sweep._coerce(where, kind, step)
        if step <= 0 or log:
            raise ValueError(f"{where}: invalid step = {step}; allowed: a step > 0, without log = true")
        n = (hi - lo) / step
        if not math.isclose(n, round(n), rel_tol=0, abs_tol=1e-9):
            raise ValueError(f"{where}: invalid step = {step}; allowed: a step that divides high - low = {hi - lo}")
    return Param(field, "int" if is_int else "float", low=lo, high=hi, log=log, step=step)


def _check_extremes(name: str, space: list[Param], base: TrainConfig) -> None:
    """Each end of each range (each choice) must belong to some valid configuration, so that a range leaving a
    field's valid values fails now, not rounds later. The only constraint between value-only fields is a pair
    (gain_min < gain_max): an end is tried alone, then with each end of each other searched field."""
    for p in space:
        for v in p.extremes():
            tries = [{p.field: v}] + [{p.field: v, q.field: e} for q in space if q is not p for e in q.extremes()]
            errors = []
            for values in tries:
                try:
                    hparams.replaced(base, {f: float(x) for f, x in values.items()})
                    break
                except ValueError as e:
                    errors.append(e)
            else:
                raise ValueError(f"sweep {name}: [optuna.space] {p.field}: {errors[0]}")


def parse_table(name: str, table: dict, base: TrainConfig, fixed: dict, types: tuple[dict, dict]) -> OptunaSearch:
    """A sweep file's ``[optuna]`` table -> OptunaSearch; every error a one-line ValueError naming the key."""
    import_optuna()  # a missing package is an error of the file's, before anything compiles
    unknown = sorted(set(table) - set(KEYS))
    if unknown:
        raise ValueError(f"sweep {name}: [optuna] unknown key {unknown[0]!r}; allowed: {', '.join(KEYS)}")

    def where(key: str) -> str:
        return f"sweep {name}: [optuna] {key}"

    for key in ("rounds", "batch"):
        if key not in table:
            raise ValueError(f"{where(key)}: missing; an [optuna] search needs rounds = N and batch = N")
    objective = _choice(where("objective"), table.get("objective", "success"), tuple(OBJECTIVES))
    direction = _choice(where("direction"), table.get("direction", OBJECTIVES[objective]), ("maximize", "minimize"))
    rounds = _int(where("rounds"), table["rounds"], 1)
    batch = _int(where("batch"), table["batch"], 1)
    space_table = table.get("space")
    if not isinstance(space_table, dict) or not space_table:
        raise ValueError(f"sweep {name}: [optuna.space] is missing or empty; allowed: FIELD = {{low, high, log}} or "
                         f"FIELD = [choices] for one value-only hyperparameter or more")
    space = []
    for key, spec in sweep._flatten_env(space_table).items():
        w = f"sweep {name}: [optuna.space] {key}"
        sweep._field(w, key, *types)  # an unknown field gets the sweep's message, with the known ones
        if key not in hparams.VALUE_FIELDS:
            raise ValueError(f"{w}: not searchable: it changes the compiled program, and each round trains as one "
                             f"vmapped program; allowed: {', '.join(hparams.VALUE_FIELDS)}")
        if key in fixed:
            raise ValueError(f"{w}: both fixed and searched; allowed: one of the two")
        space.append(_param(w, key, spec))
    _check_extremes(name, space, base)
    return OptunaSearch(
        base=base, space=tuple(space), objective=objective, direction=direction, rounds=rounds, batch=batch,
        sampler=_choice(where("sampler"), table.get("sampler", "tpe"), SAMPLERS),
        seed=_int(where("seed"), table.get("seed", 0), 0),
        startup_trials=_int(where("startup_trials"), table.get("startup_trials", batch), 0),
        pruner=_choice(where("pruner"), table.get("pruner", "median"), PRUNERS),
        prune_warmup=_int(where("prune_warmup"), table.get("prune_warmup", 0), 0),
        prune_startup=_int(where("prune_startup"), table.get("prune_startup", batch), 0))


# --- the study ---------------------------------------------------------------------------------------------------


def _state(name: str):
    return getattr(import_optuna().trial.TrialState, name)


def rebuild_study(search: OptunaSearch, records: list[dict], round_index: int):
    """An in-memory study holding every trial of the finished ``records``, with round ``round_index``'s sampler."""
    optuna = import_optuna()
    study = optuna.create_study(direction=search.direction, sampler=search.make_sampler(round_index),
                                pruner=search.make_pruner())
    dists = search.distributions()
    for entry in sorted((t for rec in records for t in rec["trials"]), key=lambda t: t["number"]):
        study.add_trial(optuna.trial.create_trial(
            params=entry["params"], distributions=dists, state=_state(entry["state"]),
            value=entry["value"] if entry["state"] != "FAIL" else None,
            intermediate_values={int(k): v for k, v in entry["intermediate"].items()}))
        if study.trials[-1].number != entry["number"]:
            raise ValueError(f"invalid round records: trial {entry['number']} is missing its predecessors; "
                             "allowed: the rounds/ folder as the search wrote it")
    return study


def ask_round(search: OptunaSearch, study, round_index: int, plan: dict | None = None) -> tuple[list[dict], dict]:
    """(draws, {config index: optuna Trial}): ``batch`` valid configurations asked of ``study``.

    A draw that makes an invalid configuration is told FAIL and drawn again. With ``plan`` (the round's draws as
    written when it first started) the same trials are asked again, so a resumed round trains what it began.
    """
    optuna = import_optuna()
    dists = search.distributions()
    first = round_index * search.batch  # configurations are numbered c00, c01, ... in the order they were asked
    draws: list[dict] = []
    trials: dict = {}
    if plan is not None:
        for d in plan["draws"]:
            if d["config"] is None:
                study.add_trial(optuna.trial.create_trial(params=d["params"], distributions=dists,
                                                          state=_state("FAIL")))
            else:
                study.enqueue_trial(d["params"])
                trials[d["config"]] = study.ask(dists)
            if study.trials[-1].number != d["number"]:
                raise ValueError(f"invalid plan for round {round_index}: trial {d['number']} came back as "
                                 f"{study.trials[-1].number}; allowed: the rounds/ folder as the search wrote it")
        return list(plan["draws"]), trials
    while len(trials) < search.batch:
        if len(draws) >= MAX_REDRAWS * search.batch:
            raise ValueError(f"[optuna] drew {len(draws)} configurations for round {round_index} and only "
                             f"{len(trials)} were valid (the last: {draws[-1]['error']}); allowed: a space whose "
                             "points are valid configurations")
        trial = study.ask(dists)
        try:
            search.configure(trial.params)
        except ValueError as e:
            study.tell(trial, state=_state("FAIL"))
            draws.append({"number": trial.number, "config": None, "params": trial.params, "error": str(e)})
            continue
        c = first + len(trials)
        draws.append({"number": trial.number, "config": c, "params": trial.params})
        trials[c] = trial
    return draws, trials


def _mean(values) -> float:
    a = np.asarray(list(values), float)
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else math.nan


class Watch:
    """The runner's ``on_chunk`` for a round: reports each configuration's objective so far to Optuna and prunes.

    The values are read back from the trials' logs at fixed updates (multiples of ``updates_per_chunk`` before the
    end), not where chunks happen to end: a round resumed mid-chunk reports what an uninterrupted one would.
    """

    def __init__(self, search: OptunaSearch, study, trials: dict, dirs: dict[int, list[Path]], last_updates: int,
                 log: Callable[[str], None], label: str):
        self.search, self.study, self.trials, self.dirs = search, study, trials, dirs
        self.last_updates, self.log, self.label = last_updates, log, label
        self.reported: dict[int, dict[int, float]] = {c: {} for c in trials}
        self.pruned: dict[int, int] = {}  # config -> the update it was pruned at
        self.done_to = 0  # updates up to here are reported
        self.stopped = False  # the round was ended early: every configuration pruned or diverged

    def value(self, runs: list[list[dict]], step: int) -> float:
        """The objective over ``runs`` (one log per seed) as it stood after update ``step``."""
        return _mean(sweep.final_metrics([r for r in rows if r["update"] <= step], self.last_updates)
                     [self.search.objective] for rows in runs)

    def diverged(self, c: int) -> bool:
        from aswarm.training.runner import DIVERGED

        return any((d / DIVERGED).exists() for d in self.dirs[c])

    def catch_up(self, update: int) -> bool:
        """Report every update of the grid up to ``update`` not reported yet; True when no configuration is left
        to train for (every one pruned or diverged)."""
        from aswarm.training.runner import read_metrics

        every = self.search.base.updates_per_chunk
        total = self.search.base.num_updates
        steps = range((self.done_to // every + 1) * every, min(update, total - 1) + 1, every)
        runs = {c: [read_metrics(d) for d in ds] for c, ds in self.dirs.items()} if len(steps) else {}
        for step in steps:
            for c, trial in self.trials.items():
                if c in self.pruned or self.diverged(c):
                    continue
                v = self.value(runs[c], step)
                if not math.isfinite(v):  # no episode ended in the window yet: nothing to compare
                    continue
                trial.report(v, step)
                self.reported[c][step] = v
                if trial.should_prune():
                    self.study.tell(trial, state=_state("PRUNED"))
                    self.pruned[c] = step
                    for d in self.dirs[c]:
                        (d / "PRUNED").write_text(f"pruned by Optuna at update {step}: {self.search.objective} "
                                                  f"{v:.4g} (trained on in its vmapped program, not told again)\n")
                    self.log(f"{self.label}: c{c:02d} pruned at update {step} ({self.search.objective} {v:.3g})")
        self.done_to = max(self.done_to, update)
        return all(c in self.pruned or self.diverged(c) for c in self.trials)

    def __call__(self, update: int, metrics: dict) -> bool:
        self.stopped = self.catch_up(update)
        return self.stopped


# --- training ----------------------------------------------------------------------------------------------------


def _group(spec: sweep.SweepSpec, round_index: int, draws: list[dict]) -> sweep.Group:
    search = spec.optuna
    trials = tuple(sweep.Trial(f"c{d['config']:02d}-s{s}", d["config"],
                               dataclasses.replace(search.configure(d["params"]), seed=s))
                   for d in draws if d["config"] is not None for s in spec.seeds)
    return sweep.Group(round_index, trials, search.fields)


def _train_round(spec: sweep.SweepSpec, round_index: int, out: Path, built: tuple | None, mesh, progress: bool,
                 max_updates: int | None, log: Callable[[str], None]) -> tuple[dict | None, tuple]:
    """Ask, train and tell round ``round_index``; (its record, or None when ``max_updates`` stopped it; the
    program, built on the first round trained in this call and reused by the others)."""
    from aswarm.training import runner

    search = spec.optuna
    rdir = out / "rounds"
    records = [json.loads((rdir / f"r{r:02d}.json").read_text()) for r in range(round_index)]
    study = rebuild_study(search, records, round_index)
    plan_file = rdir / f"r{round_index:02d}.plan.json"
    plan = json.loads(plan_file.read_text()) if plan_file.exists() else None
    draws, trials = ask_round(search, study, round_index, plan)
    if plan is None:
        plan_file.write_text(json.dumps({"round": round_index, "draws": draws}, indent=2))
    group = _group(spec, round_index, draws)
    label = f"round {round_index}"
    log(f"{label}: " + "; ".join(f"c{d['config']:02d} {sweep._label(d['params'])}" for d in draws
                                 if d["config"] is not None))
    t0 = time.monotonic()
    if built is None:
        built = sweep.build_program(group, mesh)
    agent, init_fn, chunk_fn, mesh = built
    keys, values = sweep.group_args(group, mesh)
    tdirs = [out / "trials" / t.name for t in group.trials]
    for t, d in zip(group.trials, tdirs):
        d.mkdir(parents=True, exist_ok=True)
        runner.write_config(d, t.config)
    dirs = {c: [d for t, d in zip(group.trials, tdirs) if t.config_index == c] for c in trials}
    watch = Watch(search, study, trials, dirs, spec.last_updates, log, label)
    program = runner.Program(agent.env, init_fn, chunk_fn, (keys, values), mesh, stacked=True)
    total = search.base.num_updates
    try:
        res = runner.run_loop(program, group.trials[0].config, out / "groups" / f"r{round_index:02d}", tdirs,
                              progress=progress, max_updates=max_updates, desc=label, log=log, label=label,
                              on_chunk=watch)
        update = res.update
    except runner.TrainingDiverged as e:  # every trial: each folder holds its DIVERGED file
        log(f"{label}: every trial diverged ({e})")
        res, update = None, None
    if update is not None and update < total and not watch.stopped:
        return None, built
    if res is not None:
        sweep.save_trials(group, update, res.state, agent.env, tdirs)
        watch.catch_up(update)  # a round resumed at its end trains no chunk: its reports come from the logs
    entries = []
    for d in draws:
        c = d["config"]
        if c is None:
            entries.append({**d, "state": "FAIL", "value": None, "intermediate": {}, "pruned_at": None})
            continue
        reported = watch.reported[c]
        entry = {**d, "intermediate": {str(k): v for k, v in reported.items()}, "pruned_at": watch.pruned.get(c)}
        if c in watch.pruned:  # told already; Optuna's value for a pruned trial is its last report
            entry.update(state="PRUNED", value=reported[max(reported)])
        else:
            value = watch.value([runner.read_metrics(p) for p in dirs[c]], total)
            if watch.diverged(c) or not math.isfinite(value):
                entry.update(state="FAIL", value=None,
                             error="diverged" if watch.diverged(c) else
                             f"no episode ended in the last {spec.last_updates} updates")
                study.tell(trials[c], state=_state("FAIL"))
            else:
                entry.update(state="COMPLETE", value=value)
                study.tell(trials[c], value)
        entries.append(entry)
    return {"round": round_index, "updates": update, "stopped_early": watch.stopped,
            "wall_s": time.monotonic() - t0, "devices": int(mesh.devices.size), "trials": entries}, built


def run(spec: sweep.SweepSpec, out: str | Path, progress: bool = True, max_updates: int | None = None, mesh=None,
        log: Callable[[str], None] = print) -> dict | None:
    """Run (or resume) the [optuna] search of ``spec`` into ``out``; returns the results, or None when
    ``max_updates`` (updates per round in this call, for tests) stopped it early."""
    from aswarm.training import sharding

    search = spec.optuna
    import_optuna()
    if jax.process_count() > 1:
        raise ValueError(f"sweep {spec.name}: an [optuna] search runs on one host; allowed: a [grid] or [random] "
                         "sweep over several hosts")
    out = Path(out)
    k = search.batch * len(spec.seeds)
    if mesh is None:
        mesh = sharding.make_mesh(k, search.base.num_envs)  # fails before compiling, as a sweep does
    elif search.base.num_envs % dict(mesh.shape)["env"] or k % dict(mesh.shape)["trial"]:
        raise ValueError(f"invalid mesh {dict(mesh.shape)} for {k} trials of {search.base.num_envs} worlds: "
                         "allowed: axes that divide them")
    sweep._check_plan(spec, out)
    (out / "rounds").mkdir(parents=True, exist_ok=True)
    log(f"[optuna] {search.rounds} rounds of {search.batch} configurations x {len(spec.seeds)} seed(s), each round "
        f"one program; objective {search.objective} ({search.direction}); {sharding.describe(mesh)}")
    built = None
    records = []
    for r in range(search.rounds):
        path = out / "rounds" / f"r{r:02d}.json"
        if path.exists():
            records.append(json.loads(path.read_text()))
            log(f"round {r}: finished earlier, skipped")
            continue
        record, built = _train_round(spec, r, out, built, mesh, progress, max_updates, log)
        if record is None:
            return None
        path.write_text(json.dumps(record, indent=2))
        records.append(record)
        best = best_trial(records, search.direction)
        log(f"round {r}: {_round_summary(record, search.objective)}; best so far "
            + (f"c{best['config']:02d} {search.objective} {best['value']:.3g}" if best else "none"))
    results = summarize(spec, out, records)
    write_reports(results, out)
    return results


# --- results -----------------------------------------------------------------------------------------------------


def best_trial(records: list[dict], direction: str) -> dict | None:
    """The completed trial with the best value (Optuna's ``study.best_trial``), earliest on a tie."""
    done = [t for rec in records for t in rec["trials"] if t["state"] == "COMPLETE"]
    sign = -1.0 if direction == "maximize" else 1.0
    return min(done, key=lambda t: (sign * t["value"], t["number"])) if done else None


def _round_summary(record: dict, objective: str) -> str:
    states = [t["state"] for t in record["trials"] if t["config"] is not None]
    values = [f"c{t['config']:02d} {t['value']:.3g}" for t in record["trials"] if t["state"] == "COMPLETE"]
    extra = [f"{states.count(s)} {s.lower()}" for s in ("PRUNED", "FAIL") if s in states]
    ended = f", ended at update {record['updates']}" if record["stopped_early"] else ""
    return f"{objective} " + (", ".join(values) or "-") + (f" ({', '.join(extra)}{ended})" if extra else "")


def summarize(spec: sweep.SweepSpec, out: Path, records: list[dict]) -> dict:
    """The sweep's results (``sweep.summarize``) over the trained configurations, ranked by Optuna's value
    (completed trials first, then pruned, then failed), with the search's own record under ``"optuna"``."""
    search = spec.optuna
    entries = sorted((t for rec in records for t in rec["trials"] if t["config"] is not None),
                     key=lambda t: t["config"])
    realized = dataclasses.replace(spec, configs=tuple(search.configure(t["params"]) for t in entries),
                                   labels=tuple(sweep._label(t["params"]) for t in entries),
                                   points=tuple(t["params"] for t in entries))
    results = sweep.summarize(realized, out)
    by_config = {t["config"]: t for t in entries}
    for e in results["configs"]:
        t = by_config[e["config"]]
        e.update(number=t["number"], state=t["state"], value=t["value"], pruned_at=t["pruned_at"])
    sign = -1.0 if search.direction == "maximize" else 1.0
    order = {"COMPLETE": 0, "PRUNED": 1, "FAIL": 2}

    def key(e):
        v = e["value"]
        return order[e["state"]], math.inf if v is None or math.isnan(v) else sign * v, e["config"]

    results["configs"].sort(key=key)
    for r, e in enumerate(results["configs"], 1):
        e["rank"] = r
    best = best_trial(records, search.direction)
    if best is not None:
        best = {**best, "label": sweep._label(best["params"]),
                "trials": [f"c{best['config']:02d}-s{s}" for s in spec.seeds]}
    every = [t for rec in records for t in rec["trials"]]
    results["optuna"] = {
        "objective": search.objective, "direction": search.direction, "sampler": search.sampler,
        "seed": search.seed, "startup_trials": search.startup_trials, "pruner": search.pruner,
        "prune_warmup": search.prune_warmup, "prune_startup": search.prune_startup, "rounds": search.rounds,
        "batch": search.batch, "total_updates": search.base.num_updates, "best": best,
        "trials": sorted(every, key=lambda t: t["number"]),
        "counts": {s: sum(t["state"] == s for t in every) for s in order}}
    results["groups"] = [{k: v for k, v in rec.items() if k != "trials"} for rec in records]
    return results


def format_search(results: dict) -> str:
    """The markdown section on the search itself: settings, counts and the best trial."""
    o = results["optuna"]
    sampler = (f"TPE (seed {o['seed']}, the first {o['startup_trials']} trials at random)" if o["sampler"] == "tpe"
               else f"random (seed {o['seed']})")
    pruner = ("none" if o["pruner"] == "none" else f"median of the completed trials at the same update (once "
              f"{o['prune_startup']} have completed, after update {o['prune_warmup']})")
    c = o["counts"]
    lines = [f"Objective: {o['objective']} ({o['direction']}), the final metric averaged over the seeds. Sampler: "
             f"{sampler}. Pruner: {pruner}; a pruned configuration trains on in its vmapped program, its value is "
             f"its last report.", "",
             f"{o['rounds']} rounds of {o['batch']} configurations: {c['COMPLETE']} completed, {c['PRUNED']} "
             f"pruned, {c['FAIL']} failed.", ""]
    b = o["best"]
    if b is None:
        lines.append("Best trial: none completed.")
    else:
        lines.append(f"Best trial: c{b['config']:02d} (Optuna trial {b['number']}), {o['objective']} "
                     f"{b['value']:.4g}: {b['label']}. Its runs: {', '.join(b['trials'])}.")
    return "\n".join(lines)


def write_reports(results: dict, out: Path) -> list[Path]:
    """The sweep's reports plus ``trials.csv`` (every Optuna trial) and ``optuna.png``, and the search's section in
    ``report.md``."""
    out = Path(out)
    paths = sweep.write_reports(results, out)
    o = results["optuna"]
    with (out / "trials.csv").open("w", newline="") as f:
        fields = sorted({k for t in o["trials"] for k in t["params"]})
        w = csv.writer(f)
        w.writerow(["number", "config", "state", "value", "pruned_at", *fields, "error"])
        for t in o["trials"]:
            w.writerow([t["number"], "" if t["config"] is None else t["config"], t["state"],
                        "" if t["value"] is None else t["value"], "" if t["pruned_at"] is None else t["pruned_at"],
                        *[t["params"].get(k, "") for k in fields], t.get("error", "")])
    plot = plot_search(results, out)
    with (out / "report.md").open("a") as f:
        f.write(f"\n## Optuna search\n\n{format_search(results)}\n\n![objective over trials]({plot.name})\n")
    return [*paths, out / "trials.csv", plot]


def plot_search(results: dict, out: Path) -> Path:
    """Left: each trial's objective in the order asked, the best so far, and the rounds. Right: what each trial
    reported over its updates, pruned ones ending in a cross."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    o = results["optuna"]
    trials = sorted((t for t in o["trials"] if t["config"] is not None), key=lambda t: t["config"])
    sign = 1.0 if o["direction"] == "maximize" else -1.0
    colors = plt.get_cmap("viridis")(np.linspace(0, 0.9, max(o["rounds"], 1)))
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(13, 4.5))
    best, xs, ys = -math.inf, [], []
    for t in trials:
        rnd = t["config"] // o["batch"]
        if t["state"] == "COMPLETE":
            ax.scatter(t["config"], t["value"], color=colors[rnd], zorder=3)
            best = max(best, sign * t["value"])
        elif t["state"] == "PRUNED" and t["value"] is not None:
            ax.scatter(t["config"], t["value"], color=colors[rnd], marker="x", zorder=3)
        if math.isfinite(best):
            xs.append(t["config"])
            ys.append(sign * best)
        curve = sorted((int(s), v) for s, v in t["intermediate"].items())
        if t["state"] == "COMPLETE":
            curve.append((o["total_updates"], t["value"]))
        if curve:
            steps, vals = zip(*curve)
            ax2.plot(steps, vals, color=colors[rnd], alpha=0.7, marker="." if len(curve) == 1 else None)
            if t["state"] == "PRUNED":
                ax2.scatter(steps[-1], vals[-1], color=colors[rnd], marker="x", zorder=3)
    if xs:
        ax.step(xs, ys, where="post", color="k", lw=1, label="best so far")
        ax.legend(fontsize=8)
    for r in range(1, o["rounds"]):
        ax.axvline(r * o["batch"] - 0.5, color="0.7", ls="--", lw=0.8)
    failed = sum(t["state"] == "FAIL" for t in trials)
    ax.set_title(f"{o['objective']} per trial (x: pruned, last report" + (f"; {failed} failed" if failed else "")
                 + ")")
    ax.set_xlabel("trial (configuration, in the order asked; colour and dashes: rounds)")
    ax2.set_title("reported to the pruner")
    ax2.set_xlabel("update")
    for a in (ax, ax2):
        a.set_ylabel(o["objective"])
        a.grid(alpha=0.3)
    fig.suptitle(f"sweep {results['name']}: [optuna] search")
    fig.tight_layout()
    from aswarm.analysis.plots import save_figure

    path = save_figure(fig, out / "optuna.png", dpi=100)
    plt.close(fig)
    return path

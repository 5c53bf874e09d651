"""The ``aswarm`` command line."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from aswarm.analysis.protocol import EVAL_SEED


class _Parser(argparse.ArgumentParser):
    """Usage errors in one line: the full usage of ``aswarm train`` (every config field) buried the error."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _positive_int(text: str) -> int:
    vals = _positive_ints(text)
    if len(vals) != 1:
        raise argparse.ArgumentTypeError(f"invalid number {text!r}: allowed: one positive integer")
    return vals[0]


def _positive_ints(text: str) -> list[int]:
    try:
        vals = [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid list {text!r}: allowed: comma-separated positive integers") from None
    if not vals or min(vals) <= 0:
        raise argparse.ArgumentTypeError(f"invalid list {text!r}: allowed: comma-separated positive integers")
    return vals


def cmd_scenarios(args: argparse.Namespace) -> int:
    from aswarm.envs import registry, scenarios
    from aswarm.envs.presets import SCENARIOS

    rows = []
    for name, sc in SCENARIOS.items():
        cfg = registry.preset(name)
        geo = scenarios.geometry(cfg)
        moving = f"{cfg.min_moving}-{cfg.most_moving}" if cfg.num_moving else "0"
        task = f"{cfg.num_gates} gates in order" if sc.kind == "track" else "goal point"
        length = f"{scenarios.track_length(cfg):.1f} m" if sc.kind == "track" else "-"
        rows.append((name, str(cfg.num_agents), str(cfg.num_obstacles), moving, task, length,
                     f"{cfg.episode_seconds:g} s", str(len(geo.slot_pos)), sc.description))
    head = ("scenario", "drones", "static", "moving", "task", "lap", "limit", "slots", "description")
    widths = [max(len(r[i]) for r in rows + [head]) for i in range(len(head) - 1)]
    for r in [head, *rows]:
        print("  ".join(c.ljust(w) for c, w in zip(r[:-1], widths)) + "  " + r[-1])
    print("\nOverride any field, e.g. num_agents=8 or num_obstacles=4 (aswarm.envs.make(name, **overrides)).")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    if args.trainer:
        from aswarm.analysis import train_bench

        return train_bench.main(args)
    from aswarm.analysis import bench

    return bench.main(args)


def cmd_train(args: argparse.Namespace) -> int:
    from aswarm import config_args, envs
    from aswarm.agents.config import TrainConfig
    from aswarm.core.safety import SafetyFilterConfig
    from aswarm.training import runner

    fields = config_args.overrides(args, TrainConfig)
    safety = config_args.nested_overrides(args, "safety_filter", SafetyFilterConfig)
    if safety and args.config is None:  # --safety-filter.FIELD (or its old flat spelling, --gain-min ...)
        fields["safety_filter"] = SafetyFilterConfig(**safety)
    wandb = None
    if args.wandb:  # a missing package fails here, before anything compiles
        from aswarm.training import wandb_log

        wandb = wandb_log.WandbOptions(project=args.wandb_project, entity=args.wandb_entity, name=args.wandb_name,
                                       mode=args.wandb_mode)
        wandb_log.require()
    if args.resume:
        # Flags that may change (the budget, host-loop settings) are applied; any other is refused in one line.
        for flag, given in (("--env", args.env), ("--out", args.out), ("--config", args.config)):
            if given:
                raise ValueError(f"invalid {flag} with --resume: the run keeps its own; allowed with --resume: "
                                 f"{', '.join('--' + k.replace('_', '-') for k in runner.RESUMABLE)}, --quiet, "
                                 "--wandb")
        run_dir = runner.train(None, args.resume, resume=True, progress=not args.quiet, changes=fields, wandb=wandb)
    else:
        env_over = dict(sorted(config_args.parse_assignments(args.env or [], envs.EnvConfig).items()))
        if args.config is not None:  # the file's fields, then the flags; a bad file fails here in one line
            from aswarm.training import run_config

            # The filter's flags replace the file's [safety_filter] field by field, not as a whole.
            flags = {**fields, **{f"safety_filter.{k}": v for k, v in safety.items()}}
            config = run_config.load_file(args.config, flags, env_over)
        else:
            # Resolves the full env (the preset with the overrides) and checks it before anything compiles.
            config = TrainConfig(**fields, env_overrides=tuple(env_over.items()))
        run_dir = runner.train(config, args.out, progress=not args.quiet, wandb=wandb)
    _print_timing(run_dir)
    print(f"run folder: {run_dir}  (metrics.jsonl, tb/, checkpoints/, curves.png)")
    print(f"evaluate:   aswarm eval --checkpoint {run_dir} --episodes 1000")
    return 0


def _print_timing(run_dir: Path) -> None:
    """The run's own wall time and throughput (``timing.json``), so every user sees what a benchmark would."""
    import json

    from aswarm.training import runner

    path = Path(run_dir) / runner.TIMING
    if not path.exists():  # another process of a multi-host run wrote it
        return
    t = json.loads(path.read_text())
    line = f"trained {t['env_steps']:,} env steps in {runner.minutes_seconds(t['train_s'])}"
    if t["env_steps_per_s"]:
        line += f": {t['env_steps_per_s']:,.0f} env-steps/s"
    if t["steady_env_steps_per_s"]:
        line += (f" ({t['steady_env_steps_per_s']:,.0f} after the first chunk, which took {t['first_chunk_s']:.0f} s "
                 "with the compile)")
    print(line + f" on {t['devices']} device(s)")


def cmd_convert_run(args: argparse.Namespace) -> int:
    from aswarm.training import run_config

    path, filled = run_config.convert(args.run_dir)
    how = f"filled {len(filled)} missing env field(s) from the preset: {', '.join(filled)}" if filled else \
        "its env section was complete already"
    print(f"converted {path} ({how}; the original is config.json.orig)")
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    import json

    from aswarm.analysis import evaluate

    out_dir = evaluate.report_dir(args.checkpoint, args.out)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"invalid --out {str(out_dir)!r}: is a file; allowed: a folder")
    result = evaluate.evaluate_checkpoint(args.checkpoint, scenario=args.scenario, episodes=args.episodes,
                                          seed=args.seed, env_overrides=args.env or [],
                                          progress=lambda line: print(f"aswarm eval: {line}", file=sys.stderr,
                                                                      flush=True))
    json_path, csv_path = evaluate.write_report(result, out_dir)
    if args.json:
        print(json.dumps(result))
    else:
        print(evaluate.format_table(result))
    # With --json, stdout holds the JSON object alone.
    print(f"wrote {json_path} and {csv_path}", file=sys.stderr if args.json else sys.stdout)
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from aswarm.flight import export

    out = export.export(args.checkpoint, args.out, force=args.force, env_overrides=args.env)
    print(f"bundle: {out}  (policy.npz, manifest.json)")
    print(f"check it in the simulator: aswarm sitl --bundle {out} --episodes 200")
    return 0


def cmd_sitl(args: argparse.Namespace) -> int:
    import json

    from aswarm.flight import estimator, sitl

    if args.replay is not None:
        out = args.out or args.replay.with_name(args.replay.with_suffix("").name + "-sitl")
        result = sitl.replay_flight(args.bundle, args.replay, out, seed=args.seed,
                                    estimation=estimator.from_args(args))
        if args.json:
            print(json.dumps(result))
        else:
            print(f"simulated the flight's start for {result['seconds']:.1f} s: success {result['success']:.0f}, "
                  f"collision {result['collision']:.0f}; record {out}.npz")
            print(f"side by side: aswarm plot --flight {args.replay} --compare {out}.npz")
        return 0

    result = sitl.run_sitl(args.bundle, scenario=args.scenario, episodes=args.episodes, seed=args.seed,
                           noise=args.noise, latency_ms=args.latency, mass_scale=args.mass_scale,
                           thrust_scale=args.thrust_scale, env_overrides=args.env or [],
                           estimation=estimator.from_args(args), progress=not args.json)
    print(json.dumps(result) if args.json else sitl.format_table(result))
    return 0


def cmd_sweep(args: argparse.Namespace) -> int:
    from aswarm.training import sharding

    if args.coordinator is not None:  # several hosts: join before anything touches a device
        sharding.initialize(args.coordinator, args.num_processes, args.process_id)
    from aswarm.training import sweep

    spec = sweep.load(args.file, yes=args.yes)  # a bad file fails here, before anything compiles
    if args.bench:
        print(sweep.format_bench(sweep.bench_sweep(spec)))
        return 0
    out = args.out or Path("runs") / f"sweep-{spec.name}"
    results = sweep.run(spec, out, progress=not args.quiet)
    print(sweep.format_table(results))
    print(f"sweep folder: {out}  (results.csv, results.json, report.md, curves.png, trials/*/)")
    best = results["configs"][0]
    print(f"evaluate the best: aswarm eval --checkpoint {out / 'trials' / next(iter(best['trials']))}")
    return 0


def _record_episode(args: argparse.Namespace, need_attention: bool = False):
    """(agent's env, recorded Episode) of episode ``--episode-index`` of ``--seed``, as ``aswarm eval`` draws it."""
    import jax

    from aswarm.analysis import evaluate, plots

    if args.episode_index < 0:
        raise ValueError(f"invalid --episode-index {args.episode_index}: must be >= 0")
    config, agent, restored = evaluate.load_agent(args.checkpoint, args.scenario, args.env or [])
    if need_attention and not config.uses_attention:
        raise ValueError(f"method {config.method!r} has no attention network: --attention needs a checkpoint of "
                         "attention_cbf or attention_penalty")
    if not 0 <= getattr(args, "drone", 0) < agent.env.num_agents:
        raise ValueError(f"invalid --drone {args.drone}: allowed: 0 to {agent.env.num_agents - 1}")
    # split(key, N)[i] does not depend on N, so this is episode i of `aswarm eval --seed K`.
    key = jax.random.split(jax.random.PRNGKey(args.seed), args.episode_index + 1)[args.episode_index]
    return agent.env, plots.record_episode(agent, restored["params"], restored["obs_norm"], key)


def cmd_plot(args: argparse.Namespace) -> int:
    if args.curves:  # training curves of runs (their metrics.jsonl)
        from aswarm.analysis import plots
        from aswarm.training import runner

        if args.checkpoint is not None or args.flight is not None:
            raise ValueError("--curves, --checkpoint and --flight each name what to draw: allowed: one of them")
        for d in args.curves:
            if not (d / "metrics.jsonl").is_file():
                raise ValueError(f"invalid --curves {d}: no metrics.jsonl there; allowed: run folders")
        out = plots.check_output(args.out or Path("curves.png"))
        print(f"wrote {runner.plot_curves(args.curves[0], out, compare=args.curves[1:])}")
        return 0
    if args.flight is not None:  # a flight record of `aswarm fly` (numpy and matplotlib only)
        from aswarm.flight import record

        if args.checkpoint is not None:
            raise ValueError("--flight and --checkpoint both name what to draw: allowed: one of them")
        out = args.out or args.flight.with_suffix(".png")
        print(f"wrote {record.plot_flight(args.flight, out, compare=args.compare)}")
        return 0
    if args.checkpoint is None:
        raise ValueError("nothing to draw: allowed: --checkpoint RUN (a simulated episode) or --flight RECORD")
    from aswarm.analysis import plots

    args.out = args.out or Path("traj.png")
    plots.check_output(args.out)
    _, ep = _record_episode(args, need_attention=args.attention)
    if args.attention:
        path = plots.plot_attention(ep, args.out, drone=args.drone)
    else:
        path = plots.plot_trajectories(ep, args.out, three_d=not args.no_3d)
    print(f"wrote {path}")
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    from aswarm.analysis import render

    render.choose_output(args.out, True, True)  # bad options fail before anything compiles
    render.check_options(args.fps, args.width, args.height, args.camera)
    env, ep = _record_episode(args)
    path, fmt, backend = render.render_episode(ep, env.config, args.out, fps=args.fps, width=args.width,
                                               height=args.height, camera=args.camera)
    how = {"mp4": "mp4 via imageio-ffmpeg",
           "gif": "GIF via Pillow" + (": imageio-ffmpeg cannot be imported (reinstall aswarm, which depends on it)"
                                      if args.out.suffix.lower() == ".mp4" else ""),
           "png": "PNG frames: neither imageio-ffmpeg nor Pillow is installed"}[fmt]
    print(f"wrote {path} ({how}; MUJOCO_GL={backend})")
    return 0


def _wrap(text: str) -> str:
    import textwrap

    return textwrap.fill(text, 100)


def _train_epilog() -> str:
    """Every env field with its type and its value in the default scenario's preset (--help)."""
    import dataclasses

    from aswarm import config_args
    from aswarm.agents.config import TrainConfig
    from aswarm.envs import EnvConfig, registry

    preset = dataclasses.asdict(registry.preset(TrainConfig.scenario))
    rows = []
    for name, kind in config_args.leaf_types(EnvConfig).items():
        if name == "scenario":  # --scenario's
            continue
        value = preset
        for part in name.split("."):
            value = value[part]
        rows.append((name, config_args.kind_name(kind), repr(value)))
    width = max(len(r[0]) for r in rows)
    head = _wrap(f"environment fields (--env FIELD=VALUE, or an [env] table in --config): the defaults are the "
                 f"{TrainConfig.scenario!r} preset's; other scenarios change some (`aswarm scenarios`)")
    return head + ":\n" + "\n".join(f"  {n:<{width}}  {k:<5}  {v}" for n, k, v in rows)


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="aswarm", description=__doc__)
    from aswarm.flight import estimator

    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("scenarios", help="list the scenarios with their drones, obstacles and gates")
    s.set_defaults(func=cmd_scenarios)

    b = sub.add_parser("bench", help="environment throughput; writes BENCHMARKS.md")
    b.add_argument("--scenario", default="race")
    b.add_argument("--worlds", type=_positive_ints, default=[1, 64, 1024, 4096])
    b.add_argument("--steps", type=int, default=200, help="env steps per timed rollout")
    b.add_argument("--peer-venv", type=Path, default=Path(".venv-crazyflow"),
                   help="virtualenv holding crazyflow, created on first use")
    b.add_argument("--no-peer", action="store_true", help="skip the crazyflow comparison")
    b.add_argument("--out", type=Path, default=Path("BENCHMARKS.md"))
    b.add_argument("--trainer", action="store_true",
                   help="training instead: a timed `aswarm train` of the scenario's defaults and its evaluation, "
                        "where one update's time goes, and each method's update throughput")
    b.add_argument("--skip-run", action="store_true", help="with --trainer: skip the timed training run")
    b.add_argument("--run-dir", type=Path, default=None,
                   help="with --trainer: the timed run's folder (default runs/bench-SCENARIO-TIME)")
    b.add_argument("--episodes", type=_positive_int, default=1000,
                   help="with --trainer: unseen episodes the timed run's policy is evaluated on")
    b.set_defaults(func=cmd_bench)

    from aswarm import config_args
    from aswarm.agents.config import METHODS, TrainConfig
    from aswarm.core.safety import LEGACY_FIELDS, SafetyFilterConfig

    t = sub.add_parser("train", help="train a swarm policy (MAPPO with attention-CBF by default)",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description=_wrap("Every TrainConfig field is a flag; env fields go through --env "
                                         "FIELD=VALUE; --config FILE sets any of them from a file, and flags "
                                         "override it. Methods: "
                                         + "; ".join(f"{k}: {v}" for k, v in METHODS.items()) + "."),
                       epilog=_train_epilog())
    t.add_argument("--config", type=Path, default=None, metavar="FILE",
                   help="TOML file of config fields ([safety_filter], [env], [env.cf] tables; e.g. configs/race.toml) "
                        "or a run folder's config.json (reproduces that run's config); flags override it")
    t.add_argument("--out", type=Path, default=None, help="run folder (default runs/SCENARIO-METHOD-TIME)")
    t.add_argument("--resume", type=Path, default=None,
                   help="continue the run in this folder from its latest checkpoint, with its own config; only "
                   "--total-steps (extends the run), --checkpoint-minutes, --updates-per-chunk and --quiet "
                   "may be given")
    t.add_argument("--env", action="append", metavar="FIELD=VALUE",
                   help="env config field of a new run, nested ones dotted (cf.mass=0.03), repeatable")
    t.add_argument("--quiet", action="store_true", help="no progress bar")
    w = t.add_argument_group("Weights & Biases (pip install 'aswarm[wandb]')")
    w.add_argument("--wandb", action="store_true",
                   help="also log what TensorBoard gets to Weights & Biases, with the run's config")
    w.add_argument("--wandb-project", default="aswarm", metavar="NAME", help="default 'aswarm'")
    w.add_argument("--wandb-entity", default=None, metavar="NAME", help="team or user (default: your default entity)")
    w.add_argument("--wandb-name", default=None, metavar="NAME", help="run name (default: the run folder's name)")
    w.add_argument("--wandb-mode", choices=("online", "offline"), default=None,
                   help="default: WANDB_MODE if set, else online with an API key (WANDB_API_KEY or `wandb login`), "
                        "else offline (upload later with `wandb sync`)")
    config_args.add_fields(t, TrainConfig, skip=("env_overrides",))
    config_args.add_nested_fields(t, "safety_filter", SafetyFilterConfig, aliases=LEGACY_FIELDS)
    t.set_defaults(func=cmd_train)

    cv = sub.add_parser("convert-run", help="give an old run folder's config.json the full env it loads from",
                        description="Runs load their environment from config.json's env section as stored. This "
                        "fills the fields an old section lacks as the old loader did: the scenario's preset today "
                        "with the run's env_overrides.")
    cv.add_argument("run_dir", type=Path, help="run folder (holds config.json)")
    cv.set_defaults(func=cmd_convert_run)

    e = sub.add_parser("eval", help="evaluate a trained policy on unseen seeds")
    e.add_argument("--checkpoint", required=True, help="run folder, or 'pretrained'")
    e.add_argument("--scenario", default=None, help="default: the scenario it was trained on")
    e.add_argument("--episodes", type=int, default=1000)
    e.add_argument("--seed", type=int, default=EVAL_SEED, help="evaluation seed (training seeds are small integers)")
    e.add_argument("--env", action="append", metavar="FIELD=VALUE", help="env config override, repeatable")
    e.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    e.add_argument("--out", type=Path, default=None,
                   help="folder for eval_SCENARIO.json and .csv (default: the run folder; runs/eval for pretrained)")
    e.set_defaults(func=cmd_eval)

    x = sub.add_parser("export", help="write a policy bundle (numpy weights + manifest) for the flight side")
    x.add_argument("--checkpoint", required=True, help="run folder, or 'pretrained'")
    x.add_argument("--out", required=True, type=Path, help="bundle folder to create")
    x.add_argument("--force", action="store_true", help="replace an existing bundle")
    x.add_argument("--env", action="append", default=[], metavar="FIELD=VALUE",
                   help="fly another environment with the same observation layout, e.g. --env num_agents=16 --env "
                        "max_neighbours=3 for a 4-drone policy that observed its 3 others")
    x.set_defaults(func=cmd_export)

    si = sub.add_parser("sitl", help="fly a bundle's numpy runtime in closed loop against the simulator")
    si.add_argument("--bundle", required=True, type=Path, help="bundle folder from `aswarm export`")
    si.add_argument("--scenario", default=None, help="default: the scenario the bundle was trained on")
    si.add_argument("--episodes", type=int, default=200)
    si.add_argument("--seed", type=int, default=EVAL_SEED, help="evaluation seed, as for eval (same layouts)")
    si.add_argument("--noise", type=float, default=0.0, metavar="METRES",
                    help="std of Gaussian noise on the positions the runtime sees")
    si.add_argument("--latency", type=float, default=0.0, metavar="MS",
                    help="loop latency: whole control steps of it age the poses the runtime sees, the rest delays "
                         "its commands on the drone (a multiple of the onboard controller's tick, 10 ms)")
    si.add_argument("--mass-scale", type=float, default=1.0, help="the simulated drone's mass over the nominal")
    si.add_argument("--thrust-scale", type=float, default=1.0,
                    help="the simulated drone's thrust constant over the nominal (what the controller assumes)")
    si.add_argument("--env", action="append", metavar="FIELD=VALUE", help="env config override, repeatable")
    estimator.add_arguments(si)
    si.add_argument("--replay", type=Path, default=None, metavar="FLIGHT",
                    help="instead: one episode from a flight record's start (its drones' positions when the control "
                         "loop started, its course and obstacles), written as a flight record for a side-by-side")
    si.add_argument("--out", type=Path, default=None, help="--replay: record to write (default FLIGHT-sitl)")
    si.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    si.set_defaults(func=cmd_sitl)

    from aswarm.flight import fly as flight_fly

    # Listed for --help only: main() hands `aswarm fly` to the flight package before this parser is built.
    fl = sub.add_parser("fly", help="fly a bundle on Crazyflies with live motion capture (cflib, motioncapture), "
                                    "or rehearse it with --mocap mock --dry-run")
    flight_fly.add_arguments(fl)

    def episode_flags(q: argparse.ArgumentParser, required: bool = True) -> None:
        q.add_argument("--checkpoint", required=required, default=None, help="run folder, or 'pretrained'")
        q.add_argument("--scenario", default=None, help="default: the scenario it was trained on")
        q.add_argument("--seed", type=int, default=EVAL_SEED, help="evaluation seed, as for eval")
        q.add_argument("--episode-index", type=int, default=0, help="which episode of that seed (eval's order)")
        q.add_argument("--env", action="append", metavar="FIELD=VALUE", help="env config override, repeatable")

    pl = sub.add_parser("plot", help="trajectory figure (3D, top and side views) or attention figure of one episode, "
                                     "or a flight record's figure (--flight)")
    episode_flags(pl, required=False)
    pl.add_argument("--flight", type=Path, default=None, metavar="RECORD",
                    help="instead: a flight record of `aswarm fly` (NAME.npz): top view and altitude of mocap vs "
                         "onboard estimate, commands before/after the filter, battery")
    pl.add_argument("--curves", type=Path, nargs="+", default=None, metavar="RUN",
                    help="instead: the training curves of one or more runs on the same axes (default out: curves.png)")
    pl.add_argument("--compare", type=Path, default=None, metavar="RECORD",
                    help="with --flight: another record drawn beside it (e.g. `aswarm sitl --replay`'s)")
    pl.add_argument("--out", type=Path, default=None,
                    help="figure file (.png, .pdf or .svg; default traj.png, or RECORD.png with --flight)")
    pl.add_argument("--attention", action="store_true",
                    help="draw one drone's attention weights over time above its distance to each obstacle")
    pl.add_argument("--drone", type=int, default=0, help="the drone of the attention figure")
    pl.add_argument("--no-3d", action="store_true", help="top and side views only")
    pl.set_defaults(func=cmd_plot)

    r = sub.add_parser("render", help="video of one episode with MuJoCo's offscreen renderer")
    episode_flags(r)
    r.add_argument("--out", type=Path, default=Path("episode.mp4"),
                   help="video file: .mp4 (default episode.mp4; a .gif beside it where imageio-ffmpeg cannot be "
                        "imported) or .gif")
    r.add_argument("--fps", type=int, default=25)
    r.add_argument("--width", type=int, default=640)
    r.add_argument("--height", type=int, default=480)
    r.add_argument("--camera", choices=("follow", "overview"), default="follow",
                   help="follow: behind the swarm; overview: the whole arena from above")
    r.set_defaults(func=cmd_render)

    sw = sub.add_parser("sweep", help="train a hyperparameter sweep (configurations x seeds) in one program",
                        description="FILE is a TOML sweep file (see sweeps/). Configurations that differ only in "
                        "value-only hyperparameters train inside one jit with vmap; re-running resumes.")
    sw.add_argument("file", type=Path, help="sweep file, e.g. sweeps/race_lr.toml")
    sw.add_argument("--out", type=Path, default=None, help="sweep folder (default runs/sweep-NAME)")
    sw.add_argument("--quiet", action="store_true", help="no progress bar")
    sw.add_argument("--yes", action="store_true", help="run even more trials than the file's max_trials")
    sw.add_argument("--bench", action="store_true",
                    help="instead: time the configurations in one vmapped program vs one after another")
    sw.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                    help="several hosts: address of process 0 (jax.distributed.initialize)")
    sw.add_argument("--num-processes", type=int, default=1, help="several hosts: how many processes")
    sw.add_argument("--process-id", type=int, default=0, help="several hosts: this process, 0 to N-1")
    sw.set_defaults(func=cmd_sweep)
    return p


# Commands that train: on a CPU they split their worlds over the cores (sharding.use_cpu_cores).
_TRAINING = ("train", "sweep", "bench")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["fly"]:
        # The flight side runs next to real drones and must not import JAX (the full parser below imports
        # the trainer's config, and with it JAX): hand over to the flight package's own command line.
        from aswarm.flight import fly

        return fly.main(argv[1:])
    args = build_parser().parse_args(argv)
    if args.command in _TRAINING:
        from aswarm.training import sharding

        sharding.use_cpu_cores()
    try:
        return args.func(args)
    except ValueError as e:  # config, input and checkpoint errors: one line, non-zero exit
        print(f"aswarm {args.command}: error: {e}", file=sys.stderr)
        return 2
    except RuntimeError as e:  # training diverged
        print(f"aswarm {args.command}: error: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())

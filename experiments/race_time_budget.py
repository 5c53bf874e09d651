"""Where the race's mission time goes: the policy against the MPC, drone by drone and gate by gate (issue #13).

    python experiments/race_time_budget.py                           # the shipped race policy, 200 episodes
    python experiments/race_time_budget.py --checkpoint runs/race --episodes 100
    python experiments/race_time_budget.py --quick                   # 2 episodes, a short MPC: CI

Both fly the checkpoint's own environment from the same resets (episode i is ``aswarm eval --seed S``'s episode i,
as in ``race_vs_mpc.py``), recorded step by step: each drone's speed, its current gate, the command its flyer
asked for and the command the drone flew (after the policy's safety filter and the env's command acceleration
limit). Over the episodes both finished, the mission time (the last drone's finish) is split into the start
stagger, each drone's time per track segment, and how it flew: mean speed, path length, time spent slow
(< ``--slow`` m/s), the speed it asked for and the speed its filter let through. Writes ``OUT/race_time_budget.md``
and ``.json`` (``_quick`` with ``--quick``) and ``OUT/race_time_budget.png`` (speed along the track).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from aswarm.files import write_atomic

MATRIX_SEED = 50_000  # as race_vs_mpc.py: episodes no choice of the shipped policy was made on


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default="pretrained", help="run folder or shipped name (default: pretrained)")
    p.add_argument("--episodes", type=int, default=200)
    p.add_argument("--seed", type=int, default=MATRIX_SEED)
    p.add_argument("--slow", type=float, default=0.5, help="m/s: a flying drone under this speed counts as slow")
    p.add_argument("--quick", action="store_true", help="2 episodes and a short MPC plan: a pipeline check")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = p.parse_args(argv)
    if args.episodes <= 0:
        p.error(f"invalid --episodes {args.episodes}: must be > 0")
    if args.slow <= 0:
        p.error(f"invalid --slow {args.slow}: must be > 0 m/s")
    if args.quick:
        args.episodes = min(args.episodes, 2)
    return args


def trace(env, act, carry0, keys, steps: int) -> dict[str, np.ndarray]:
    """Fly ``keys`` worlds for ``steps`` env steps with ``act(carry, state, t) -> (carry, asked, sent)``.

    Returns [steps, episodes, n] arrays: speed (m/s), flying, target (the current waypoint), asked (|command
    the flyer asked for|) and flown (|command the drone flies|), and [episodes, n] release and finish times.
    A world is frozen once done, so its last records repeat its end."""
    import jax
    import jax.numpy as jnp

    from aswarm.envs.dynamics import drone_state

    reset, step = jax.vmap(env.reset), jax.vmap(env.step)
    n = env.num_agents

    def run(keys):
        s0 = reset(keys)

        def body(c, t):
            s, carry = c
            carry, asked, sent = act(carry, s, t)
            nxt = step(s, sent)
            s = jax.tree.map(lambda old, new: jnp.where(
                (s.done > 0).reshape((-1,) + (1,) * (old.ndim - 1)), old, new), s, nxt)
            vel = jax.vmap(lambda d: drone_state(d, n).vel)(s.data)
            rec = dict(speed=jnp.linalg.norm(vel, axis=-1), flying=env.flying(s) & ~s.tracker.collided,
                       target=s.tracker.target, asked=jnp.linalg.norm(asked, axis=-1),
                       flown=jnp.linalg.norm(env.applied_command(s), axis=-1))
            return (s, carry), rec

        (final, _), rec = jax.lax.scan(body, (s0, carry0), jnp.arange(steps))
        return rec, final.tracker.finish_time, final.tracker.finished, final.tracker.collided

    rec, finish, finished, collided = jax.device_get(jax.jit(run)(keys))
    out = {k: np.asarray(v) for k, v in rec.items()}
    out.update(finish=np.asarray(finish), finished=np.asarray(finished), collided=np.asarray(collided))
    return out


def budget(rec: dict, episodes: np.ndarray, release: np.ndarray, dt: float, slow: float) -> dict:
    """The time budget over ``episodes`` (indices): means per drone, per segment and of the mission."""
    e = episodes
    fly = rec["flying"][:, e]  # [T, E, n]
    steps_flying = fly.sum(0)  # [E, n]
    t_fly = steps_flying * dt
    speed = np.where(fly, rec["speed"][:, e], 0.0)
    asked = np.where(fly, rec["asked"][:, e], 0.0)
    flown = np.where(fly, rec["flown"][:, e], 0.0)
    slow_steps = (fly & (rec["speed"][:, e] < slow)).sum(0)
    per_flying = np.maximum(steps_flying.sum(), 1)
    # Time per segment: flying steps spent with each waypoint as the target (segment k ends at waypoint k).
    target = rec["target"][:, e]
    segments = int(target.max()) + 1
    seg = np.stack([(fly & (target == k)).sum(0) * dt for k in range(segments)])  # [K, E, n]
    seg_speed = np.stack([np.where(fly & (target == k), rec["speed"][:, e], 0.0).sum(0)
                          / np.maximum((fly & (target == k)).sum(0), 1) for k in range(segments)])
    mission = rec["finish"][e].max(-1)
    return {
        "episodes": int(len(e)),
        "mission_time": float(mission.mean()),
        "last_release": float(release.max()),
        "drone_flight_time": float(t_fly.mean()),
        "drone_flight_time_max": float(t_fly.max(-1).mean()),
        "mean_speed": float(speed.sum() / per_flying),
        "path_length": float((speed.sum(0) * dt).mean()),
        "slow_fraction": float(slow_steps.sum() / per_flying),
        "asked_speed": float(asked.sum() / per_flying),
        "flown_command_speed": float(flown.sum() / per_flying),
        "segment_time": seg.mean((1, 2)).tolist(),
        "segment_speed": seg_speed.mean((1, 2)).tolist(),
        "drone_flight_time_by_index": t_fly.mean(0).tolist(),
    }


def speed_profile(rec: dict, episodes: np.ndarray, segments: int, field: str = "speed") -> np.ndarray:
    """Mean of ``field`` (speed, or the asked command's) [segments, 10]: each segment's flying steps in ten equal
    parts of its own duration."""
    prof = np.zeros((segments, 10))
    count = np.zeros((segments, 10))
    fly, target, speed = rec["flying"][:, episodes], rec["target"][:, episodes], rec[field][:, episodes]
    for k in range(segments):
        mask = fly & (target == k)  # [T, E, n]
        idx = np.cumsum(mask, 0) - 1
        total = np.maximum(mask.sum(0, keepdims=True), 1)
        part = np.clip((idx * 10) // total, 0, 9)
        for b in range(10):
            sel = mask & (part == b)
            prof[k, b] += speed[sel].sum()
            count[k, b] += sel.sum()
    return prof / np.maximum(count, 1)


def compare(args: argparse.Namespace) -> tuple[dict, dict]:
    import jax
    import jax.numpy as jnp

    from aswarm.analysis import evaluate
    from aswarm.baselines import mpc

    _, agent, restored = evaluate.load_agent(args.checkpoint, None, None)
    env = agent.env
    cfg = env.config
    if env.kind != "track":
        raise SystemExit(f"invalid --checkpoint {args.checkpoint}: its scenario {cfg.scenario!r} is not a track")
    params, obs_norm = restored["params"], restored["obs_norm"]
    key = jax.random.PRNGKey(args.seed)
    keys = jax.random.split(key, args.episodes)
    steps = 8 if args.quick else cfg.max_steps

    def policy_act(carry, s, t):
        cmd, _, _ = agent.policy(params, obs_norm, s.obs, None)
        res = agent.filter_commands(params, obs_norm, s.obs, cmd, env.cylinder_accel(s), s.filter_obs,
                                    env.applied_command(s))
        return carry, cmd, res.u

    config = mpc.MPCConfig(samples=16, horizon=5) if args.quick else mpc.MPCConfig()
    planner = mpc.make_mpc_policy(env, config)
    k_act = jax.random.fold_in(key, 1)

    def mpc_act(carry, s, t):
        carry, cmd = planner.act(carry, s.obs, jax.random.fold_in(k_act, t))
        return carry, cmd, cmd

    recs = {"policy": trace(env, policy_act, jnp.zeros(()), keys, steps),
            "MPC": trace(env, mpc_act, planner.init((args.episodes,)), keys, steps)}
    release = np.arange(env.num_agents) * cfg.start_interval
    success = {k: r["finished"].all(-1) & ~r["collided"].any(-1) for k, r in recs.items()}
    both = np.flatnonzero(success["policy"] & success["MPC"])
    # A pipeline check (--quick) finishes no episode: its budget is over every episode, as far as they flew.
    used = both if len(both) else np.arange(args.episodes)
    result = {"checkpoint": str(args.checkpoint), "scenario": cfg.scenario, "controller": cfg.controller,
              "episodes": args.episodes, "seed": args.seed, "quick": args.quick, "slow": args.slow,
              "max_speed": cfg.max_speed, "command_accel_limit": cfg.command_accel_limit,
              "start_interval": cfg.start_interval, "both_finished": int(len(both)),
              "success": {k: float(v.mean()) for k, v in success.items()},
              "flyers": {k: budget(r, used, release, cfg.dt, args.slow) for k, r in recs.items()}}
    # Segments some flyer spent time in (the last waypoint stays the target once a drone has finished).
    times = np.array([f["segment_time"] for f in result["flyers"].values()])
    segments = int(np.flatnonzero(times.max(0) > 0).max()) + 1 if (times > 0).any() else 1
    for f in result["flyers"].values():
        f["segment_time"], f["segment_speed"] = f["segment_time"][:segments], f["segment_speed"][:segments]
    profiles = {k: (speed_profile(r, used, segments), speed_profile(r, used, segments, "asked"))
                for k, r in recs.items()}
    return result, profiles


def table(result: dict) -> str:
    f = result["flyers"]
    names = list(f)
    rows = [("mission time s (last drone's finish)", "mission_time", "{:.1f}"),
            ("last drone's release s (start stagger)", "last_release", "{:.1f}"),
            ("a drone's flight time s (release to finish)", "drone_flight_time", "{:.1f}"),
            ("mean speed m/s while flying", "mean_speed", "{:.2f}"),
            ("path length m per drone", "path_length", "{:.1f}"),
            (f"time slow (< {result['slow']:g} m/s) % of flying", "slow_fraction", "{:.1%}"),
            ("speed asked for m/s (the command before the filter)", "asked_speed", "{:.2f}"),
            ("command flown m/s (after filter and acceleration limit)", "flown_command_speed", "{:.2f}")]
    lines = ["| | " + " | ".join(names) + " | ratio |", "|---|" + "---:|" * (len(names) + 1)]
    for label, key, fmt in rows:
        vals = [f[k][key] for k in names]
        ratio = vals[0] / vals[1] if len(vals) == 2 and vals[1] else float("nan")
        lines.append(f"| {label} | " + " | ".join(fmt.format(v).replace("%", " %") for v in vals)
                     + f" | {ratio:.2f} |")
    seg = ["", "| segment ending at gate | " + " | ".join(f"{k}: s, m/s" for k in names) + " |",
           "|---|" + "---:|" * len(names)]
    for i in range(max(len(f[k]["segment_time"]) for k in names)):
        cells = [f"{f[k]['segment_time'][i]:.2f}, {f[k]['segment_speed'][i]:.2f}"
                 if i < len(f[k]["segment_time"]) else "–" for k in names]
        seg.append(f"| {i} | " + " | ".join(cells) + " |")
    return "\n".join(lines + seg)


def plot(profiles: dict, out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 3.2))
    for (name, (flown, asked)), colour in zip(profiles.items(), ("C0", "C1")):
        x = np.arange(flown.size) / 10
        ax.plot(x, flown.reshape(-1), marker=".", color=colour, label=f"{name}: speed flown")
        ax.plot(x, asked.reshape(-1), ls="--", color=colour, label=f"{name}: command asked (before the filter)")
    for i in range(1, max(p[0].shape[0] for p in profiles.values())):
        ax.axvline(i, color="0.8", lw=0.8)
    ax.set_xlabel("track segment (each in ten parts of its own duration; a line is a gate passed)")
    ax.set_ylabel("mean speed (m/s)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    path = out / "race_time_budget.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    result, profiles = compare(args)
    suffix = "_quick" if args.quick else ""
    args.out.mkdir(parents=True, exist_ok=True)
    command = "python experiments/race_time_budget.py " + " ".join(argv if argv is not None else sys.argv[1:])
    md = (f"# Where the race's mission time goes: the policy against the MPC (issue #13)\n\n"
          f"Command: `{command.strip()}`  \n"
          f"Policy `{result['checkpoint']}` on its own drone (`{result['controller']}` controller), "
          f"{result['episodes']} episodes from seed {result['seed']}, the same resets for both; success: policy "
          f"{100 * result['success']['policy']:.1f} %, MPC {100 * result['success']['MPC']:.1f} %. Means over the "
          f"{result['both_finished']} episodes both finished, per drone where a row says so. Velocity commands "
          f"are clipped at {result['max_speed']:g} m/s per axis and change at most "
          f"{result['command_accel_limit']:g} m/s² for both flyers; drones are released "
          f"{result['start_interval']:g} s apart.\n\n{table(result)}\n")
    write_atomic(args.out / f"race_time_budget{suffix}.md", md)
    write_atomic(args.out / f"race_time_budget{suffix}.json", json.dumps(result, indent=1))
    if not args.quick:
        plot(profiles, args.out)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())

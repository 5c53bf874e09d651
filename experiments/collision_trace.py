"""Why did a policy collide? Every collision episode of an evaluation, replayed and traced step by step.

    python experiments/collision_trace.py --checkpoint pretrained --episodes 2000 --seed 50000 \
        --out experiments/results/collision_trace/race

Pass 1 evaluates ``--episodes`` episodes as ``aswarm eval`` does (episode i starts from ``split(key, episodes)[i]``)
and finds the ones that end in a collision. Pass 2 flies those episodes again, alone, and records every step of the
drone that collided: its position and velocity, the policy's command, the filter's output and the command the drone
flies (after the command limit), the filter's slack and gain, the smallest barrier value of each group of the
filter's rows (``core.barriers.obs_rows``: taken at the look-ahead point) and the true gaps to each kind of hazard.

It prints one line per collision: kind, time, the group's smallest row value and the true gap over the last
``--window`` steps, how often the QP was infeasible there, how far the flown command lagged the filter's, the drone's
largest tilt there and its world's rotor time constant. A collision whose rows stayed positive to the end was not
seen by the filter's model (the look-ahead point kept clear while the drone did not); one after slack was spent came
from an infeasible QP; one with a tilt far past the controller's 20° is the drone losing its attitude.
``summary.json`` holds the lines, ``traces.npz`` the whole traces. Pass 2 runs each episode in a batch of its own;
where a replay does not collide again (another batch size may fuse the program differently), the line says so.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from aswarm.analysis.protocol import add_replay_arguments, filter_argument

# The row groups (core.barriers.row_groups) each collision kind maps to.
GROUP_OF_KIND = {"obstacle": ("cylinders",), "drone": ("neighbours",), "gate": ("gate", "prev_gate"),
                 "floor": ("floor",), "bounds": ("walls",)}
GAP_KINDS = ("obstacle", "drone", "gate", "floor")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_replay_arguments(p, episodes=2000)
    p.add_argument("--only", default=None, metavar="I,J,...",
                   help="trace these episodes of the --episodes split and skip pass 1 (e.g. another filter on the "
                        "collisions a first trace found)")
    p.add_argument("--window", type=int, default=25, help="steps before the collision the line summarises")
    p.add_argument("--out", default=None, help="folder for summary.json and traces.npz")
    args = p.parse_args(argv)
    if args.episodes <= 0 or args.window <= 0:
        p.error(f"invalid --episodes={args.episodes} / --window={args.window}: both must be > 0")
    fields = filter_argument(p, args.filter)
    try:
        only = None if args.only is None else [int(i) for i in args.only.split(",")]
    except ValueError:
        p.error(f"invalid --only={args.only!r}: allowed: episode numbers separated by commas, such as 3,17")
    if only is not None and not all(0 <= i < args.episodes for i in only):
        p.error(f"invalid --only={args.only!r}: allowed: episode numbers from 0 to {args.episodes - 1}")

    import jax
    import jax.numpy as jnp
    import numpy as np

    from aswarm.analysis import evaluate
    from aswarm.analysis.protocol import EVAL_SEED
    from aswarm.core import barriers
    from aswarm.core import geometry as geo
    from aswarm.envs import collisions as col
    from aswarm.envs.dynamics import drone_state
    from aswarm.envs.scenarios import cylinders_at

    seed = EVAL_SEED if args.seed is None else args.seed
    _, agent, restored = evaluate.load_agent(args.checkpoint, args.scenario, args.env, fields)
    env, params, obs_norm = agent.env, restored["params"], restored["obs_norm"]
    cfg, sf = env.config, agent.config.safety_filter
    key = jax.random.PRNGKey(seed)

    if only is None:
        rec, _, _ = evaluate.rollout_episodes(agent, params, obs_norm, env, args.episodes, key)
        hit = np.flatnonzero(np.asarray(rec["collision"]) > 0.5)
        print(f"{args.checkpoint}: {len(hit)} collision episodes in {args.episodes} (seed {seed})", flush=True)
    else:
        hit = np.asarray(only)

    layout = env.filter_layout if env.wide_filter else env.obs_layout
    groups = barriers.row_groups(layout)
    bounds = np.cumsum([0] + [k for _, k in groups])

    def trace(k):
        state = env.reset(k)
        r = cfg.cf.collision_radius

        def body(s, _):
            cmd, _, _ = agent.policy(params, obs_norm, s.obs, None)
            res = agent.filter_commands(params, obs_norm, s.obs, cmd, env.cylinder_accel(s), s.filter_obs,
                                        env.applied_command(s))
            rows_obs = s.obs if s.filter_obs is None else s.filter_obs
            gain = agent.filter_gain(params, obs_norm, s.obs)
            rows = barriers.filter_rows(layout, rows_obs, gain, sf, drone_radius=r,
                                        gate_half_opening=cfg.gate_half_opening, gate_bar=cfg.gate_bar,
                                        whole_swarm=barriers.sees_whole_swarm(layout, rows_obs))
            h = jnp.where(rows.mask, rows.h, geo.FAR)
            h_groups = jnp.stack([jnp.min(h[:, a:b], -1, initial=geo.FAR) for a, b in zip(bounds[:-1], bounds[1:])], -1)
            n2 = env.step(s, res.u)
            drone = drone_state(n2.data, cfg.num_agents)
            pos = drone.pos
            cyl_pos, _ = cylinders_at(n2.layout, n2.data.time)
            gaps = jnp.stack([
                jnp.min(geo.cylinder_clearance(pos, cyl_pos, n2.layout.cyl_radius, n2.layout.cyl_height,
                                               n2.layout.cyl_present, r), -1, initial=geo.FAR),
                jnp.min(geo.drone_clearance(pos, jnp.ones(cfg.num_agents, bool), r), -1, initial=geo.FAR),
                jnp.min(geo.gate_clearance(pos, n2.layout.gate_pos, geo.horizontal(n2.layout.gate_yaw),
                                           cfg.gate_half_opening, cfg.gate_bar, r), -1, initial=geo.FAR),
                pos[:, 2] - r], -1)
            x, y = drone.quat[:, 1], drone.quat[:, 2]  # body z against world z: 1 - 2(x² + y²)
            tilt = jnp.degrees(jnp.arccos(jnp.clip(1.0 - 2.0 * (x * x + y * y), -1.0, 1.0)))
            out = {"pos": pos, "vel": drone.vel, "tilt": tilt, "cmd": cmd, "u": res.u,
                   "flown": env.applied_command(n2), "slack": res.slack, "gain": gain, "h": h_groups, "gaps": gaps,
                   "collided": n2.tracker.collided, "kind": n2.tracker.collision_kind, "target": n2.tracker.target,
                   "finished": n2.tracker.finished}
            return n2, out

        drawn = state.onboard.params  # this world's rotor time constant (randomised per world), None if not drawn
        rotor_lag = jnp.asarray(cfg.cf.motor_tau if drawn is None else drawn.cf.motor_tau)
        return jax.lax.scan(body, state, None, length=cfg.max_steps)[1], rotor_lag

    run = jax.jit(trace)
    keys = jax.random.split(key, args.episodes)
    lines, traces = [], {}
    names = [g for g, _ in groups]
    for i in hit:
        tr, rotor_lag = jax.tree.map(np.asarray, run(keys[i]))
        collided = tr["collided"]
        if not collided.any():
            lines.append({"episode": int(i), "replayed": False})
            print(f"episode {i}: the replay did not collide (every drone finished: "
                  f"{bool(tr['finished'][-1].all())})", flush=True)
            continue
        step, drone = (int(x[0]) for x in np.nonzero(collided))  # the first step and drone
        kind = col.KINDS[int(tr["kind"][step, drone])]
        w = slice(max(0, step - args.window + 1), step + 1)
        group_idx = [names.index(g) for g in GROUP_OF_KIND.get(kind, ())]
        h_w = tr["h"][w, drone][:, group_idx].min(-1) if group_idx else np.full(step + 1 - w.start, np.nan)
        gap_w = tr["gaps"][w, drone][:, GAP_KINDS.index(kind)] if kind in GAP_KINDS else np.full(len(h_w), np.nan)
        lag = np.linalg.norm(tr["u"][w, drone] - tr["flown"][w, drone], axis=-1)
        line = {"episode": int(i), "replayed": True, "kind": kind, "drone": drone, "step": step,
                "time_s": round(step / cfg.policy_freq, 2), "gate": int(tr["target"][step, drone]),
                "speed": round(float(np.linalg.norm(tr["vel"][step, drone])), 3),
                "row_h_min": round(float(np.min(h_w)), 4), "row_h_last": round(float(h_w[-1]), 4),
                "gap_min_before": round(float(np.min(gap_w[:-1])) if len(gap_w) > 1 else float("nan"), 4),
                "infeasible_steps": int(np.sum(tr["slack"][w, drone] > evaluate.INFEASIBLE_SLACK)),
                "slack_max": round(float(tr["slack"][w, drone].max()), 4),
                "intervened_steps": int(np.sum(np.linalg.norm(tr["u"][w, drone] - tr["cmd"][w, drone], axis=-1)
                                               > 1e-3)),
                "flown_lag_max": round(float(lag.max()), 3), "gain_last": round(float(tr["gain"][step, drone]), 3),
                "tilt_max_deg": round(float(tr["tilt"][w, drone].max()), 1), "rotor_lag_s": round(float(rotor_lag), 4)}
        lines.append(line)
        traces.update({f"{i}/{k}": v[:step + 1] for k, v in tr.items()})
        print(json.dumps(line), flush=True)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        meta = {"checkpoint": args.checkpoint, "scenario": cfg.scenario, "env": args.env, "filter": fields,
                "episodes": args.episodes, "seed": seed, "collision_episodes": [int(i) for i in hit],
                "row_groups": names, "gap_kinds": list(GAP_KINDS), "lines": lines}
        tmp = out / "summary.json.tmp"
        tmp.write_text(json.dumps(meta, indent=1))
        tmp.replace(out / "summary.json")
        with open(out / "traces.npz.tmp", "wb") as f:
            np.savez_compressed(f, **traces)
        (out / "traces.npz.tmp").replace(out / "traces.npz")
        replayed = [line for line in lines if line["replayed"]]
        if replayed:
            plot(traces, replayed, names, args.window, cfg.policy_freq, out / "collisions.png")
        print(f"wrote {out / 'summary.json'}, {out / 'traces.npz'} and the figure collisions.png")
    return 0


def plot(traces: dict, lines: list[dict], groups: list[str], window: int, freq: float, path: Path) -> None:
    """One column per traced collision (at most 6): the collided drone's smallest row value per group of the
    filter's rows (at the look-ahead point) above, the QP's slack and how far the flown command lags the filter's
    below, over the last ``window`` steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    shown = lines[:6]
    fig, axes = plt.subplots(2, len(shown), figsize=(3.2 * len(shown), 5.2), sharex="col", squeeze=False)
    for col, line in enumerate(shown):
        ep, d, step = line["episode"], line["drone"], line["step"]
        w = slice(max(0, step - window + 1), step + 1)
        t = (np.arange(w.start, step + 1) - step) / freq
        h = traces[f"{ep}/h"][w, d]
        top, bottom = axes[0, col], axes[1, col]
        for g, name in enumerate(groups):
            if np.min(h[:, g]) < 1.5:  # groups far away all along say nothing here
                top.plot(t, h[:, g], color=f"C{g}", label=name)
        top.axhline(0.0, color="k", lw=0.6)
        top.set_title(f"episode {ep}, drone {d}: {line['kind']}", fontsize=9)
        bottom.plot(t, traces[f"{ep}/slack"][w, d], color="k", label="QP slack (m/s)")
        lag = np.linalg.norm(traces[f"{ep}/u"][w, d] - traces[f"{ep}/flown"][w, d], axis=-1)
        bottom.plot(t, lag, color="C6", label="|filtered − flown| (m/s)")
        bottom.set_xlabel("s before the collision")
    axes[0, 0].set_ylabel("smallest row value h (m)")
    for ax in axes[0]:
        ax.legend(fontsize=6)
    axes[1, 0].legend(fontsize=7)
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)


if __name__ == "__main__":
    sys.exit(main())

"""How the attention-CBF network's class-K gain varies with a drone's nearest hazard (issue #13: does the network
let a drone be permissive far from hazards and conservative near them?).

    python experiments/gain_profile.py --checkpoint runs/A --checkpoint runs/B --episodes 64 --seed 10000 \\
        --out experiments/results/gain_profile

For each checkpoint, ``episodes`` episodes of the deterministic, filtered policy (as ``aswarm eval`` flies them,
episode i from the i-th key of the seed); at every step of every drone still flying, the network's gain (what its
filter applies to every row but the moving cylinders' where ``moving_gain_max`` caps them) and
its smallest observed clearance to a cylinder or a neighbour (the observation's cylinder clearance; a neighbour's
centre distance less two drone radii). Writes ``gain_profile.md`` (the gain by clearance bin: mean, 5th and 95th
percentiles, and the share of drone-steps within 1 % of the top of the network's range) and ``gain_profile.png``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

# m: the clearance bins' edges (the last bin is open): the filter's margin is 0.13 m, and a drone at 1 m/s covers
# the outer bins' widths in under a second.
BIN_EDGES = (0.0, 0.1, 0.2, 0.4, 0.8, 1.6)
# A gain within this share of its range from the top counts as "at the top" (the network's saturated output).
TOP_SHARE = 0.01


def record(checkpoint: str, episodes: int, seed: int, env_overrides: list[str]) -> dict:
    """{gain, clearance: [drone-steps flying], gain_min, gain_max} of ``episodes`` episodes."""
    import jax
    import jax.numpy as jnp

    from aswarm.analysis.evaluate import load_agent
    from aswarm.core.layout import CYL, NBR

    config, agent, restored = load_agent(checkpoint, env_overrides=env_overrides)
    if not config.uses_attention:
        raise ValueError(f"checkpoint {checkpoint!r} has method {config.method!r}: its gain is the fixed one; "
                         "give an attention_cbf run")
    env, params, obs_norm = agent.env, restored["params"], restored["obs_norm"]
    layout, radius = env.obs_layout, env.config.cf.collision_radius

    def run(keys):
        def body(carry, _):
            s, ended = carry
            cmd, _, _ = agent.policy(params, obs_norm, s.obs, None)
            gain = agent.filter_gain(params, obs_norm, s.obs)
            _, cyl, nbr = layout.split(s.obs)
            c_cyl = jnp.where(CYL.present(cyl), CYL.get(cyl, "clearance"), jnp.inf)
            c_nbr = jnp.where(NBR.present(nbr), jnp.linalg.norm(NBR.get(nbr, "rel_pos"), axis=-1) - 2 * radius,
                              jnp.inf)
            clearance = jnp.minimum(jnp.min(c_cyl, -1, initial=jnp.inf), jnp.min(c_nbr, -1, initial=jnp.inf))
            flying = env.flying(s) & ~ended[:, None]  # a world keeps stepping after its episode ended
            res = agent.filter_commands(params, obs_norm, s.obs, cmd, env.cylinder_accel(s), s.filter_obs,
                                        env.applied_command(s))
            s = jax.vmap(env.step)(s, res.u)
            return (s, ended | (s.done > 0)), (gain, clearance, flying)

        state = jax.vmap(env.reset)(keys)
        _, out = jax.lax.scan(body, (state, jnp.zeros(keys.shape[0], bool)), None, length=env.config.max_steps)
        return out

    gain, clearance, flying = (np.asarray(x) for x in jax.jit(run)(jax.random.split(jax.random.PRNGKey(seed),
                                                                                      episodes)))
    net = agent.cbf  # its output range: the filter's, fitted to the drone
    return dict(gain=gain[flying], clearance=clearance[flying], gain_min=float(net.gain_min),
                gain_max=float(net.gain_max))


def profile(rec: dict) -> list[dict]:
    """One row per clearance bin: drone-steps, the gain's mean, 5th / 95th percentiles, share at the top."""
    top = rec["gain_max"] - TOP_SHARE * (rec["gain_max"] - rec["gain_min"])
    edges = (*BIN_EDGES, np.inf)
    rows = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        g = rec["gain"][(rec["clearance"] >= lo) & (rec["clearance"] < hi)]
        if g.size == 0:
            rows.append(dict(bin=(lo, hi), steps=0))
            continue
        rows.append(dict(bin=(lo, hi), steps=int(g.size), mean=float(g.mean()), p5=float(np.percentile(g, 5)),
                         p95=float(np.percentile(g, 95)), top=float(np.mean(g >= top))))
    return rows


def table(name: str, rec: dict, rows: list[dict]) -> str:
    lines = [f"### `{name}`", "",
             f"Gain range {rec['gain_min']:.3f}-{rec['gain_max']:.3f} /s (fitted to the drone); "
             f"{rec['gain'].size:,} drone-steps.", "",
             "| nearest hazard (m) | drone-steps | mean gain (1/s) | 5th-95th percentile | at the top of the range |",
             "|---|---:|---:|---|---:|"]
    for r in rows:
        lo, hi = r["bin"]
        span = f"{lo:.1f}-{hi:.1f}" if np.isfinite(hi) else f">= {lo:.1f}"
        if not r["steps"]:
            lines.append(f"| {span} | 0 | – | – | – |")
            continue
        lines.append(f"| {span} | {r['steps']:,} | {r['mean']:.3f} | {r['p5']:.3f}-{r['p95']:.3f} | "
                     f"{100 * r['top']:.1f} % |")
    return "\n".join(lines)


def plot(recs: dict[str, dict], out: Path) -> Path:
    """The mean gain of each clearance bin with its 5th-95th percentile band, one line per checkpoint."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    edges = np.asarray(BIN_EDGES)
    x = np.arange(len(edges))  # one slot per bin (the bins widen outwards), the open last one included
    for name, rec in recs.items():
        rows = profile(rec)
        seen = np.array([r["steps"] > 0 for r in rows])
        mean, lo, hi = (np.array([r.get(k, np.nan) for r in rows]) for k in ("mean", "p5", "p95"))
        line, = ax.plot(x[seen], mean[seen], "o-", label=name)
        ax.fill_between(x[seen], lo[seen], hi[seen], color=line.get_color(), alpha=0.15)
    ax.set_xticks(x, [f"{a:.1f}-{b:.1f}" for a, b in zip(edges[:-1], edges[1:])] + [f">{edges[-1]:.1f}"])
    ax.set_xlabel("nearest cylinder or neighbour: clearance bin (m)")
    ax.set_ylabel("filter gain (1/s): mean, 5th-95th percentile")
    ax.set_title("attention-CBF gain against the nearest hazard")
    ax.legend()
    fig.tight_layout()
    path = out / "gain_profile.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", action="append", required=True, help="repeatable: an attention_cbf run")
    ap.add_argument("--episodes", type=int, default=64)
    ap.add_argument("--seed", type=int, default=10_000)
    ap.add_argument("--env", action="append", default=[], metavar="FIELD=VALUE", help="env override, repeatable")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    if args.episodes <= 0:
        print(f"gain_profile: invalid --episodes {args.episodes}: must be > 0", file=sys.stderr)
        return 2
    try:
        recs = {c: record(c, args.episodes, args.seed, args.env) for c in args.checkpoint}
    except (ValueError, OSError) as e:
        print(f"gain_profile: {e}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    cmd = "python experiments/gain_profile.py " + " ".join(sys.argv[1:] if argv is None else argv)
    text = "\n\n".join([f"# Gain profile\n\nCommand: `{cmd}`; {args.episodes} episodes of seed {args.seed} each."]
                       + [table(c, r, profile(r)) for c, r in recs.items()]) + "\n"
    (args.out / "gain_profile.md").write_text(text)
    print(text)
    print(f"wrote {args.out / 'gain_profile.md'} and {plot(recs, args.out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

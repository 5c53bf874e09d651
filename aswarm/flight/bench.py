"""Per-step cost of the flight runtime (estimate + observation + actor + gain + filter), numpy only.

``python -m aswarm.flight.bench`` prints a markdown table. It needs no trained policy: the bundle
is synthetic (random weights of the default network sizes, the race's geometry), which costs the
same as a trained one. Two cases: the filter passes the command through, and the filter must solve
its QP for every drone (commands aimed at a neighbour).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from aswarm.core.layout import ObsLayout
from aswarm.core.observation import observe
from aswarm.flight import estimator, policy
from aswarm.flight import runtime as fc
from aswarm.flight.bundle import Bundle, bundle_from, make_manifest
from aswarm.flight.cbf import filter_from_obs


def synthetic_bundle(num_agents: int = 4, num_cylinders: int = 8, num_gates: int = 4, seed: int = 0,
                     actor_scale: float = 1.0) -> Bundle:
    """An in-memory bundle with random weights of the default sizes and the race's geometry."""
    rng = np.random.default_rng(seed)
    layout = ObsLayout(num_cylinders, num_agents - 1)
    d = layout.size

    def dense(name, n_in, n_out, bias=True, scale=1.0):
        out = {f"{name}/kernel": (rng.normal(size=(n_in, n_out)) * scale / np.sqrt(n_in)).astype(np.float32)}
        if bias:
            out[f"{name}/bias"] = (0.1 * rng.normal(size=n_out)).astype(np.float32)
        return out

    arrays = {"obs_norm/mean": rng.normal(size=d).astype(np.float32),
              "obs_norm/std": rng.uniform(0.5, 2.0, size=d).astype(np.float32)}
    arrays |= dense("actor/MLP_0/Dense_0", d, 64) | dense("actor/MLP_0/Dense_1", 64, 64)
    arrays |= dense("actor/MLP_0/Dense_2", 64, 6, scale=actor_scale)
    arrays["actor/MLP_0/Dense_2/bias"] *= actor_scale
    arrays |= dense("cbf/Dense_0", layout.own_dim, 64) | dense("cbf/W_Q", 64, 8, bias=False)
    arrays |= dense("cbf/W_K_cyl", layout.cyl_dim, 8, bias=False) | dense("cbf/W_K_nbr", layout.nbr_dim, 8, bias=False)
    arrays |= dense("cbf/W_V_cyl", layout.cyl_dim, 8, bias=False) | dense("cbf/W_V_nbr", layout.nbr_dim, 8, bias=False)
    arrays |= dense("cbf/MLP_0/Dense_0", 72, 64) | dense("cbf/MLP_0/Dense_1", 64, 64)
    arrays |= dense("cbf/MLP_0/Dense_2", 64, 2)
    yaw = np.arange(num_gates) * 2 * np.pi / num_gates + np.pi / 2
    gates = [[6.0 * np.cos(a - np.pi / 2), 4.0 * np.sin(a - np.pi / 2), 1.0, float(a)] for a in yaw]
    env = dict(num_agents=num_agents, num_cylinders=num_cylinders, num_gates=num_gates, max_speed=2.0, policy_freq=25,
               collision_radius=0.06, arena_low=[-8.0, -6.0, 0.0], arena_high=[8.0, 6.0, 3.0], gate_half_opening=0.3,
               gate_bar=0.05, goal_radius=0.2, episode_seconds=40.0, safety_margin=0.15)
    safety = dict(method="attention_cbf", enabled=True, gain_source="attention", fixed_gain=1.5, gain_min=0.3,
                  gain_max=2.0, penalty_max=2.0, margin=0.1, drone_radius=0.06, gate_half_opening=0.3, gate_bar=0.05,
                  floor_z=0.0, neighbour_share=0.5, rho=1e6, max_iter=16, tol=1e-6)
    manifest = make_manifest(
        scenario="race", kind="track" if num_gates else "crossing", env=env, env_overrides={},
        course={"gates": gates}, layout=layout,
        networks={"actor": {"activation": "tanh"}, "cbf": {"activation": "gelu_tanh"}}, safety_filter=safety,
        train_config={}, train_config_sha256="", source="synthetic", trained_updates=0,
        drone={"controller": "pid", "velocity_lag": list(estimator.FIRMWARE_PID_LAG)})
    manifest["arrays"] = {k: {"shape": list(v.shape), "dtype": "float32"} for k, v in arrays.items()}
    return bundle_from(manifest, arrays)


def _scene(n: int, m: int, rng, spacing: float):
    """Drones in a column heading for gate 0, cylinders beside the line (positions at t = 0)."""
    start = np.stack([np.full(n, 3.0) - spacing * np.arange(n), np.full(n, -3.5), np.full(n, 1.0)], -1)
    cyl = np.stack([np.linspace(-2.0, 6.0, m), np.full(m, -2.3) + 0.2 * rng.normal(size=m)], -1)
    return start, cyl


def measure(num_agents: int = 4, steps: int = 500, conflict: bool = False, seed: int = 0) -> dict[str, np.ndarray]:
    """Seconds per control step of each stage and of ``FlightController.step``; ``conflict`` makes the QP act."""
    rng = np.random.default_rng(seed)
    # Without conflict the actor commands a few cm/s, which the filter passes; with conflict the
    # drones sit inside each other's margin and every command needs the QP.
    b = synthetic_bundle(num_agents=num_agents, seed=seed, actor_scale=1.0 if conflict else 0.02)
    n, m = num_agents, b.layout.num_cylinders
    ctl = fc.FlightController(b, n)
    ctl.reset(gates=np.array(b.manifest["course"]["gates"]))
    # 0.2 m apart the drones are inside each other's filter margin (0.22 m between centres);
    # 0.8 m is the race's start spacing.
    start, cyl = _scene(n, m, rng, 0.2 if conflict else 0.8)
    obstacles = fc.Obstacles(pos=cyl, radius=np.full(m, 0.15))
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    times = {k: [] for k in ("estimate", "observe", "actor", "gain", "filter", "controller.step")}
    est = estimator.init((n,))
    sent = estimator.Commands.empty((), n, estimator.Commands.slots(fc.SafetyConfig().stale_after, b.rate_hz))
    wp = np.broadcast_to(np.array(b.manifest["course"]["gates"])[None, :, :3], (n, 4, 3))
    normals = np.zeros_like(wp)
    solved = []
    for k in range(steps):
        t = 0.02 * k
        # Hovering (mocap jitter only), or flying the column forwards at 0.5 m/s in the conflict case.
        pos = start + np.array([1.0, 0.0, 0.0]) * (0.5 * t % 2.0) * conflict + 0.001 * rng.normal(size=(n, 3))
        c0 = time.perf_counter()
        out = ctl.step(pos, quat, np.full(n, t), now=t, obstacles=obstacles)
        times["controller.step"].append(time.perf_counter() - c0)
        # The same stages one by one.
        c0 = time.perf_counter()
        est, _, _ = estimator.update(est, np.full(n, t), pos, quat, np.ones(n, bool), commands=sent)
        vel, ang = estimator.estimate(est)
        pos_now, vel = estimator.predict(est, np.array(t), sent)
        c1 = time.perf_counter()
        obs = observe(pos_now, quat, vel, ang, wp, normals, np.zeros(n, np.int64), np.ones(n, bool), cyl,
                      np.zeros_like(cyl), np.full(m, 0.15), np.ones(m, bool), 0.06, b.env["arena_low"],
                      b.env["arena_high"])
        c2 = time.perf_counter()
        nobs = policy.normalize(b.weights, obs)
        cmd = policy.actor_command(b.weights, nobs, 2.0)
        c3 = time.perf_counter()
        gain = policy.cbf_params(b.weights, b.layout, nobs, obs, gain_min=0.3, gain_max=2.0, penalty_max=2.0)[1]
        c4 = time.perf_counter()
        res = filter_from_obs(b.layout, obs, cmd, gain, 2.0, 0.06, b.safety, 0.3, 0.05)
        c5 = time.perf_counter()
        solved.append(np.mean(res.intervened))
        sent = sent.sent(np.array(t), res.u)
        for name, a, z in (("estimate", c0, c1), ("observe", c1, c2), ("actor", c2, c3), ("gain", c3, c4),
                           ("filter", c4, c5)):
            times[name].append(z - a)
        assert np.all(np.isfinite(out.velocity))
    out = {k: np.array(v[10:]) for k, v in times.items()}  # drop the warm-up steps
    out["qp_fraction"] = np.array(solved)
    return out


def table(num_agents: int = 4, steps: int = 500) -> str:
    """Markdown table: per stage, the median and the fastest step (the fastest is what an idle CPU gives)."""
    rows = ["| stage | filter passes: median (fastest), µs | most drones need the QP: median (fastest), µs |",
            "|---|---|---|"]
    free, busy = measure(num_agents, steps), measure(num_agents, steps, conflict=True)
    for k in free:
        if k == "qp_fraction":
            continue
        rows.append(f"| {k} | {1e6 * np.median(free[k]):.0f} ({1e6 * free[k].min():.0f}) "
                    f"| {1e6 * np.median(busy[k]):.0f} ({1e6 * busy[k].min():.0f}) |")
    rows.append(f"| drones whose command needed the QP | {100 * free['qp_fraction'].mean():.0f} % "
                f"| {100 * busy['qp_fraction'].mean():.0f} % |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--drones", type=int, default=4)
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--out", default=None, help="also write the table into this markdown file (BENCHMARKS.md)")
    args = p.parse_args(argv)
    if args.drones < 2 or args.steps < 20:
        raise SystemExit(f"invalid --drones {args.drones} / --steps {args.steps}: allowed: >= 2 drones, >= 20 steps")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    head = (f"Flight runtime per control step, {args.drones} drones, 8 cylinders (numpy {np.__version__}, "
            f"{os.cpu_count()} CPUs, load average {load:.1f} when it started):")
    body = table(args.drones, args.steps)
    print(head + "\n\n" + body)
    if args.out:
        # Imported here: aswarm.analysis.bench imports JAX, which the flight side must not need.
        from aswarm.analysis.bench import machine, write_section

        text = "\n".join(["## Flight runtime (`make bench-flight`)", "",
                          f"Command: `python -m aswarm.flight.bench --drones {args.drones} --steps {args.steps}`  ",
                          f"Machine: {machine()}  ", f"Date: {time.strftime('%Y-%m-%d')}  ", "", head, "", body])
        write_section(Path(args.out), text, "<!-- flight-bench:start -->", "<!-- flight-bench:end -->")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

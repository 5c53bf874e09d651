"""Sim-to-real robustness of exported policies: ``aswarm sitl`` (the numpy flight runtime, poses only) over a
fractional design of motion-capture noise, loop latency, mass and thrust constant.

    python experiments/robustness.py --bundle A=exports/race-dr --bundle B=exports/race-nodr --episodes 300

Design: noise {0, 2, 5, 10} mm x latency {0, 20, 40, 80} ms at the nominal drone (16 cells), then mass
{-10, 0, +10} % x thrust constant {-10, 0, +10} % at 5 mm and 40 ms (8 more cells): every cell up to 5 mm,
40 ms and +-10 % that the issue's target names is either in the full grid or at its hardest corner. Every
cell flies the same episodes (seed), so policies and cells differ only in what the design varies. Writes
``robustness.json`` and ``robustness.md`` (one table per policy: success % / collision-episode %).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

NOISE_MM = (0, 2, 5, 10)
LATENCY_MS = (0, 20, 40, 80)
SCALES = (0.9, 1.0, 1.1)


def design(noise_mm=NOISE_MM, latency_ms=LATENCY_MS, scales=SCALES) -> list[dict]:
    cells = [dict(noise_mm=n, latency_ms=lat, mass=1.0, thrust=1.0) for n in noise_mm for lat in latency_ms]
    cells += [dict(noise_mm=5, latency_ms=40, mass=m, thrust=t) for m in scales for t in scales
              if (m, t) != (1.0, 1.0)]
    return cells


def in_target(c: dict) -> bool:
    return c["noise_mm"] <= 5 and c["latency_ms"] <= 40


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--bundle", action="append", required=True, metavar="NAME=PATH", help="repeatable")
    p.add_argument("--episodes", type=int, default=300)
    p.add_argument("--noise", default=",".join(map(str, NOISE_MM)), help="mm, comma-separated (must hold 5)")
    p.add_argument("--latency", default=",".join(map(str, LATENCY_MS)), help="ms, comma-separated (must hold 40)")
    p.add_argument("--out", type=Path, default=Path("experiments/results"))
    p.add_argument("--seed", type=int, default=None, help="episodes' seed (default: the evaluation seed)")
    from aswarm.flight import estimator

    estimator.add_arguments(p)
    args = p.parse_args(argv)
    estimation = estimator.from_args(args)
    noise_mm = tuple(int(x) for x in args.noise.split(","))
    latency_ms = tuple(int(x) for x in args.latency.split(","))
    if 5 not in noise_mm or 40 not in latency_ms:
        p.error(f"invalid --noise {args.noise} / --latency {args.latency}: the mass x thrust block is flown at 5 mm "
                "and 40 ms, so both lists must hold them")
    bundles = dict(b.split("=", 1) for b in args.bundle)
    from aswarm.analysis.evaluate import wilson
    from aswarm.flight import sitl

    results = []
    for name, path in bundles.items():
        for c in design(noise_mm, latency_ms):
            t0 = time.perf_counter()
            r = sitl.run_sitl(path, episodes=args.episodes, noise=c["noise_mm"] / 1000, latency_ms=c["latency_ms"],
                              mass_scale=c["mass"], thrust_scale=c["thrust"], estimation=estimation,
                              **({} if args.seed is None else {"seed": args.seed}))
            row = {"policy": name, **c, "episodes": r["episodes"], "success_rate": r["success_rate"],
                   "collision_rate": r["collision_rate"], "seconds": time.perf_counter() - t0}
            results.append(row)
            print(json.dumps(row), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "robustness.json").write_text(json.dumps(results, indent=1))
    seed = "" if args.seed is None else f", seed {args.seed}"
    lines = [f"# Robustness in SITL ({args.episodes} episodes per cell{seed}, `python experiments/robustness.py`)", "",
             f"The runtime's velocity estimate: {estimation}", ""]
    for name in bundles:
        rows = [r for r in results if r["policy"] == name]
        lines += [f"## {name}: `{bundles[name]}`", "",
                  "Success % / collision-episode % (95 % Wilson interval of the collisions in brackets). Mass and "
                  "thrust constant at 100 % unless named.", "",
                  "| noise \\ latency | " + " | ".join(f"{lat} ms" for lat in latency_ms) + " |",
                  "|---|" + "---:|" * len(latency_ms)]
        for n in noise_mm:
            cells = []
            for lat in latency_ms:
                r = next(r for r in rows if (r["noise_mm"], r["latency_ms"], r["mass"], r["thrust"]) == (n, lat, 1, 1))
                cells.append(_cell(r, wilson))
            lines.append(f"| {n} mm | " + " | ".join(cells) + " |")
        lines += ["", "At 5 mm and 40 ms: mass (rows) x thrust constant (columns)", "",
                  "| mass \\ thrust | " + " | ".join(f"{round(100 * t)} %" for t in SCALES) + " |",
                  "|---|" + "---:|" * len(SCALES)]
        for m in SCALES:
            cells = [_cell(next(r for r in rows if (r["noise_mm"], r["latency_ms"], r["mass"], r["thrust"])
                                == (5, 40, m, t)), wilson) for t in SCALES]
            lines.append(f"| {round(100 * m)} % | " + " | ".join(cells) + " |")
        target = [r for r in rows if in_target(r)]
        worst_s = min(r["success_rate"] for r in target)
        worst_c = max(r["collision_rate"] for r in target)
        lines += ["", f"Target cells (<= 5 mm, <= 40 ms, +-10 %): worst success {100 * worst_s:.1f} %, worst "
                  f"collision-episode rate {100 * worst_c:.1f} % (target >= 99 % and <= 0.1 %).", ""]
    (args.out / "robustness.md").write_text("\n".join(lines))
    print(f"wrote {args.out / 'robustness.md'}")
    return 0


def _cell(r: dict, wilson) -> str:
    hits = round(r["collision_rate"] * r["episodes"])
    lo, hi = wilson(hits, r["episodes"])
    return f"{100 * r['success_rate']:.1f} / {100 * r['collision_rate']:.1f} [{100 * lo:.1f}, {100 * hi:.1f}]"


if __name__ == "__main__":
    raise SystemExit(main())

"""Two safety matrices side by side, cell by cell: e.g. the full method against the fixed-gain ablation (issue #13).

    python experiments/compare_matrices.py experiments/results/safety_matrix.json \\
        experiments/results/fixed_gain/safety_matrix.json --labels attention-CBF,fixed-gain \\
        --out experiments/results/fixed_gain/comparison.md

For every cell (and mode: simulation or SITL) that both matrices ran: each one's success and collision-episode
rates with their 95 % Wilson intervals, its mission time, and the difference of the collision and success rates
(first minus second) with a 95 % Newcombe interval (the hybrid score interval of a difference of two independent
proportions, built from the two Wilson intervals): an interval that excludes 0 is a difference the episodes
resolve. The matrices may fly different numbers of episodes (and so other resets of the same seed). Writes the
markdown table to ``--out`` (and prints it).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from aswarm.files import write_atomic


def newcombe(p1: float, ci1: tuple[float, float], p2: float, ci2: tuple[float, float]) -> tuple[float, float]:
    """95 % interval of p1 - p2 from each rate's 95 % Wilson interval (Newcombe 1998, method 10)."""
    d = p1 - p2
    return (d - math.hypot(p1 - ci1[0], ci2[1] - p2), d + math.hypot(ci1[1] - p1, p2 - ci2[0]))


def load(path: Path) -> dict[tuple[str, str], dict]:
    """{(cell, mode): result} of the cells a matrix ran (``safety_matrix.py``'s JSON)."""
    try:
        doc = json.loads(path.read_text())
        return {(c["cell"], c["mode"]): c["result"] for c in doc["cells"] if c.get("result")}
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise SystemExit(f"compare_matrices.py: error: cannot read the matrix {path}: {e}") from None


def _pct(rate: float, ci: tuple[float, float]) -> str:
    return f"{100 * rate:.1f} [{100 * ci[0]:.1f}, {100 * ci[1]:.1f}]"


def _diff(a: dict, b: dict, name: str) -> str:
    lo, hi = newcombe(a[f"{name}_rate"], a[f"{name}_ci95"], b[f"{name}_rate"], b[f"{name}_ci95"])
    d = a[f"{name}_rate"] - b[f"{name}_rate"]
    mark = "" if lo <= 0 <= hi else " *"
    return f"{100 * d:+.1f} [{100 * lo:+.1f}, {100 * hi:+.1f}]{mark}"


def table(first: dict, second: dict, labels: tuple[str, str]) -> str:
    a, b = labels
    lines = [f"| cell | episodes ({a} / {b}) | success % {a} | success % {b} | success difference | "
             f"collision-episode % {a} | collision-episode % {b} | collision difference | mission s ({a} / {b}) |",
             "|---|---:|---|---|---|---|---|---|---:|"]
    for key in (k for k in first if k in second):
        x, y = first[key], second[key]
        cell = key[0] + (" (SITL)" if key[1] == "sitl" else "")
        t = "/".join("–" if r["mission_time"] is None else f"{r['mission_time']:.1f}" for r in (x, y))
        lines.append(f"| {cell} | {x['episodes']} / {y['episodes']} | {_pct(x['success_rate'], x['success_ci95'])} | "
                     f"{_pct(y['success_rate'], y['success_ci95'])} | {_diff(x, y, 'success')} | "
                     f"{_pct(x['collision_rate'], x['collision_ci95'])} | "
                     f"{_pct(y['collision_rate'], y['collision_ci95'])} | {_diff(x, y, 'collision')} | {t} |")
    if len(lines) == 2:
        raise SystemExit("compare_matrices.py: error: the two matrices have no cell in common")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="compare_matrices.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("first", type=Path)
    p.add_argument("second", type=Path)
    p.add_argument("--labels", default="first,second", help="the two matrices' names, comma-separated")
    p.add_argument("--out", type=Path, default=None, help="markdown file to write (default: print only)")
    args = p.parse_args(argv)
    labels = tuple(s.strip() for s in args.labels.split(","))
    if len(labels) != 2 or not all(labels):
        p.error(f"invalid --labels {args.labels!r}: give two names, comma-separated")
    text = (f"# {labels[0]} against {labels[1]}\n\n`{args.first}` against `{args.second}`. Rates with 95 % Wilson "
            "intervals; differences are first minus second in points, with a 95 % Newcombe interval (* where it "
            "excludes 0).\n\n" + table(load(args.first), load(args.second), labels) + "\n")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(args.out, text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

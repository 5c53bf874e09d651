"""Step responses of the onboard controller models side by side (0 -> 1 m/s in x and in z, from hover), and
the characteristics the safety filter and the MPC are fitted to.

    python experiments/controller_step_response.py --out experiments/results/controller_step.png

Models: the firmware's controller_pid with rotor lag (the default drone), the same without rotor lag, the
firmware's Mellinger controller on full-state setpoints that integrate the command (here one per controller
tick), and the geometric controller every run before issue #12 trained on. Prints one Markdown table of
``analysis.step_response.characterise`` per model.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from aswarm import envs  # noqa: E402
from aswarm.analysis import step_response  # noqa: E402
from aswarm.core.safety import SafetyFilterConfig  # noqa: E402
from aswarm.envs.config import LEGACY_DRONE  # noqa: E402


def models() -> dict:
    pid = envs.preset("hover")
    return {
        "firmware PID, rotor lag 0.136 s (default)": pid,
        "firmware PID, no rotor lag": dataclasses.replace(pid, cf=dataclasses.replace(pid.cf, motor_tau=0.0)),
        "firmware Mellinger, rotor lag 0.136 s": envs.preset("hover", controller="mellinger"),
        "geometric (before issue #12)": envs.preset("hover", **LEGACY_DRONE),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("experiments/results/controller_step.png"))
    args = p.parse_args()
    fig, axes = plt.subplots(2, 2, figsize=(12, 6.5), sharex=True)
    rows = []
    for i, (name, cfg) in enumerate(models().items()):
        for col, (axis, label) in enumerate(((0, "x"), (2, "z"))):
            cmd = [0.0, 0.0, 0.0]
            cmd[axis] = 1.0
            r = step_response.step_response(cfg, cmd, seconds=2.5)
            axes[0, col].plot(r["t"], r["vel"][:, axis], color=f"C{i}", label=name)
            axes[1, col].plot(r["t"], r["tilt"] if axis == 0 else r["rpm"].mean(-1), color=f"C{i}")
            axes[0, col].set_title(f"0 -> 1 m/s in {label}")
        c = step_response.characterise(cfg)
        sf = SafetyFilterConfig().fitted(c.lag_xy, c.lag_z) if "no rotor lag" not in name else None
        rows.append(f"| {name} | {c.lag_xy:.2f} | {c.lag_z:.2f} | {c.accel_xy:.2f} | {c.climb:.2f} | {c.sink:.2f} | "
                    f"{c.stop_distance:.2f} | {f'{sf.gain_max:.2f}' if sf else '-'} |")
    for col in range(2):
        axes[0, col].axhline(1.0, color="k", lw=0.8, ls="--")
        axes[0, col].set_ylabel("velocity (m/s)")
        axes[1, col].set_xlabel("s")
    axes[1, 0].axhline(20.0, color="r", lw=0.8, ls="--", label="firmware tilt limit 20 deg")
    axes[1, 0].set_ylabel("tilt (deg)")
    axes[1, 0].legend(loc="upper right")
    axes[1, 1].set_ylabel("mean rotor speed (RPM)")
    axes[0, 0].legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=100)
    print("| model | lag xy (s) | lag z (s) | accel xy (m/s²) | climb (m/s²) | sink (m/s²) | stop from 2 m/s (m) "
          "| filter gain max (1/s) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    print("\n".join(rows))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

"""Step responses of the onboard velocity controller in MJX (a picture of what tests/test_controller.py checks).

    python experiments/controller_step_response.py --out experiments/results/controller_step.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from aswarm.envs.crazyflie import CrazyflieParams  # noqa: E402
from aswarm.envs.dynamics import DroneState, drone_state, physics_model, physics_step, set_drone_state  # noqa: E402
from aswarm.envs.mjx_import import mjx  # noqa: E402
from aswarm.envs.onboard_controller import ControllerGains, velocity_controller  # noqa: E402


def step_response(cmd: np.ndarray, seconds: float = 2.0, sim_freq: int = 250):
    cf, gains = CrazyflieParams(), ControllerGains()
    _, mx = physics_model(1, sim_freq, cf)
    s0 = DroneState(pos=jnp.array([[0.0, 0.0, 1.0]]), quat=jnp.array([[1.0, 0, 0, 0]]), vel=jnp.zeros((1, 3)),
                    ang_vel=jnp.zeros((1, 3)))

    @jax.jit
    def run(cmd):
        def body(d, _):
            rpm = velocity_controller(drone_state(d, 1), cmd[None], gains, cf)
            d = physics_step(mx, d, rpm, cf)
            return d, (drone_state(d, 1).vel[0], rpm[0])
        return jax.lax.scan(body, set_drone_state(mjx.make_data(mx), s0), None, length=int(seconds * sim_freq))[1]

    vel, rpm = run(jnp.asarray(cmd, jnp.float32))
    return np.arange(1, len(vel) + 1) / sim_freq, np.asarray(vel), np.asarray(rpm), cf.max_rpm


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--out", type=Path, default=Path("experiments/results/controller_step.png"))
    args = p.parse_args()
    fig, axes = plt.subplots(2, 3, figsize=(12, 5.5), sharex=True)
    for axis, name in enumerate("xyz"):
        cmd = np.zeros(3)
        cmd[axis] = 1.5
        t, vel, rpm, max_rpm = step_response(cmd)
        ax = axes[0, axis]
        ax.plot(t, vel[:, axis], label=f"v{name}")
        ax.axhline(1.5, color="k", lw=0.8, ls="--")
        ax.axhspan(1.35, 1.65, color="g", alpha=0.1, label="±10 %")
        ax.set_title(f"0 → 1.5 m/s on {name}")
        ax.set_ylabel("m/s")
        ax.legend(loc="lower right")
        axes[1, axis].plot(t, rpm)
        axes[1, axis].axhline(max_rpm, color="r", lw=0.8, ls="--")
        axes[1, axis].set_ylabel("motor RPM")
        axes[1, axis].set_xlabel("s")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=100)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

"""Does the onboard controller hold the drone under exploration-like commands, by rotor time constant?

    python experiments/mellinger_rotor_lag.py --worlds 16 --steps 100
    python experiments/mellinger_rotor_lag.py --controllers pid --taus 0.1 0.136 0.17 0.2 0.25 --worlds 64 --steps 150
    python experiments/mellinger_rotor_lag.py --controllers pid --spin-down identified symmetric --taus 0.136 0.2 0.25

Race env (randomised drone, 4 drones), Gaussian velocity commands of standard deviation ``--std`` m/s (the trainer's
initial exploration), a new one every policy step, through the command acceleration limit. Prints, per controller
and rotor time constant (the nominal one: the randomisation scales it by 0.7-1.3 per world), the worlds in which a
drone hit the floor within ``--steps`` policy steps. ``--spin-down identified`` slows the rotors down as the
identified ones do (``cf.motor_tau_down``, scaled with the time constant), ``symmetric`` with the time constant.
"""

from __future__ import annotations

import argparse
import dataclasses

import jax
import numpy as np

from aswarm import envs
from aswarm.envs.collisions import FLOOR


def floor_worlds(controller: str, motor_tau: float, worlds: int, steps: int, std: float, seed: int,
                 spin_down: str = "identified") -> int:
    base = envs.preset("race")
    down = base.cf.motor_tau_down * motor_tau / base.cf.motor_tau if spin_down == "identified" else 0.0
    env = envs.make("race", controller=controller,
                    cf=dataclasses.replace(base.cf, motor_tau=motor_tau, motor_tau_down=down))
    n = env.num_agents

    @jax.jit
    def run(key):
        k_reset, k_cmd = jax.random.split(key)
        s = jax.vmap(env.reset)(jax.random.split(k_reset, worlds))

        def body(s, k):
            s = jax.vmap(env.step)(s, std * jax.random.normal(k, (worlds, n, 3)))
            return s, (s.tracker.collision_kind == FLOOR).any(-1)

        return jax.lax.scan(body, s, jax.random.split(k_cmd, steps))[1].any(0)

    return int(np.sum(jax.device_get(run(jax.random.PRNGKey(seed)))))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--worlds", type=int, default=16)
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--std", type=float, default=0.3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--taus", type=float, nargs="+", default=[0.136, 0.1, 0.07, 0.05, 0.03])
    p.add_argument("--controllers", nargs="+", choices=("pid", "mellinger"), default=["pid", "mellinger"])
    p.add_argument("--spin-down", nargs="+", choices=("identified", "symmetric"), default=["identified"])
    args = p.parse_args()
    names = {"pid": "controller_pid", "mellinger": "Mellinger"}
    cols = [(c, d) for c in args.controllers for d in args.spin_down]
    print("| rotor time constant (s) | " + " | ".join(
        f"{names[c]}, {d} spin-down: worlds with a floor hit (of {args.worlds})" for c, d in cols) + " |")
    print("|---:|" + "---:|" * len(cols))
    for tau in args.taus:
        row = [floor_worlds(c, tau, args.worlds, args.steps, args.std, args.seed, d) for c, d in cols]
        print(f"| {tau:g} | " + " | ".join(str(x) for x in row) + " |", flush=True)


if __name__ == "__main__":
    main()

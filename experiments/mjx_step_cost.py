"""What one batched ``mjx.step`` of the stepped swarm model costs, and what its drawn parts would add.

    python experiments/mjx_step_cost.py                  # 1024 worlds of 4 drones, 20 steps, best of 5
    python experiments/mjx_step_cost.py --worlds 64 --drones 16
    python experiments/mjx_step_cost.py --stages         # and where one step's time goes, stage by stage

Times the physics model the environment steps (``scene.build_xml(physics_only=True)``: inertia only, the
unused stages off) against the same drones carrying the drawn geoms of the scene (body box, four rotor discs,
the floor), all massless and without contacts. The whole ``mjx.Data`` is carried through ``lax.scan``, as the
trainer carries it in its environment state, so XLA cannot drop the geoms' poses.

``--stages`` also times the stepped model's ``mjx.step`` cut after each of MJX's forward stages (its private
``mujoco.mjx._src`` modules: they may move between MuJoCo releases), each prefix carried through the same scan,
so the differences say where the physics' time goes (issue #15).
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import mujoco
from mujoco import mjx

from aswarm.envs import scene
from aswarm.envs.crazyflie import CrazyflieParams


def seconds(xml: str, worlds: int, steps: int, repeat: int, step=mjx.step) -> tuple[float, int]:
    """Best wall time of ``steps`` batched ``step(model, data)`` of ``worlds`` hovering-thrust worlds, and the
    model's geoms."""
    m = mujoco.MjModel.from_xml_string(xml)
    mx = mjx.put_model(m)
    d0 = mjx.make_data(mx)
    d0 = d0.replace(qpos=d0.qpos.at[2::7].set(1.0), xfrc_applied=d0.xfrc_applied.at[1:, 2].set(0.3))
    batch = jax.tree.map(lambda x: jnp.broadcast_to(x, (worlds, *x.shape)), d0)

    @jax.jit
    def run(d):
        return jax.lax.scan(lambda d, _: (jax.vmap(lambda x: step(mx, x))(d), None), d, None, length=steps)[0]

    batch = jax.block_until_ready(run(batch))
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        batch = jax.block_until_ready(run(batch))
        best = min(best, time.perf_counter() - t0)
    return best, m.ngeom


def stage_prefixes() -> dict[str, object]:
    """``mjx.step`` cut after each forward stage (cumulative), for an Euler model without constraints."""
    from mujoco.mjx._src import forward, smooth

    def upto(*fns):
        def step(m, d):
            for f in fns:
                d = f(m, d)
            return d
        return step

    kin = (smooth.kinematics, smooth.com_pos)
    pos = (forward.fwd_position,)
    vel = (*pos, forward.fwd_velocity)
    acc = (*vel, forward.fwd_actuation, forward.fwd_acceleration)
    return {
        "kinematics": upto(smooth.kinematics),
        "+ com_pos": upto(*kin),
        "+ crb (inertia)": upto(*kin, smooth.crb),
        "+ factor_m": upto(*kin, smooth.crb, smooth.factor_m),
        "fwd_position (all)": upto(*pos),
        "+ fwd_velocity (com_vel, rne)": upto(*vel),
        "+ actuation, acceleration": upto(*acc),
        "mjx.step (+ Euler)": mjx.step,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--worlds", type=int, default=1024)
    p.add_argument("--drones", type=int, default=4)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--sim-freq", type=int, default=500)
    p.add_argument("--stages", action="store_true", help="also time the stepped model stage by stage")
    a = p.parse_args()
    cf = CrazyflieParams()
    print(f"{a.worlds} worlds x {a.drones} drones, {a.steps} steps of 1/{a.sim_freq} s, {jax.devices()[0].platform}")
    rates = {}
    for name, xml in (("stepped model (inertia only)", scene.build_xml(a.drones, a.sim_freq, cf, physics_only=True)),
                      # Without cylinders and gates the drawn scene is the stepped model plus its geoms.
                      ("with the drawn geoms", scene.build_xml(a.drones, a.sim_freq, cf, physics_only=False))):
        s, ngeom = seconds(xml, a.worlds, a.steps, a.repeat)
        rates[name] = a.worlds * a.steps / s
        print(f"  {name:30s} {ngeom:3d} geoms  {1e3 * s:8.2f} ms  {rates[name] / 1e3:8.0f}k world-steps/s", flush=True)
    lean, drawn = rates.values()
    print(f"  ratio: {lean / drawn:.2f}x")
    if a.stages:
        xml = scene.build_xml(a.drones, a.sim_freq, cf, physics_only=True)
        times = {name: seconds(xml, a.worlds, a.steps, a.repeat, step)[0] for name, step in stage_prefixes().items()}
        total, before = times["mjx.step (+ Euler)"], 0.0
        print("  stepped model, cumulative stages (share of mjx.step added by each):")
        for name, s in times.items():
            print(f"    {name:32s} {1e3 * s:8.2f} ms  {100 * (s - before) / total:+6.1f} %", flush=True)
            before = s


if __name__ == "__main__":
    main()

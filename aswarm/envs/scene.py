"""MJCF of a swarm scene, built in code.

Two models come from one builder:

* the **scene** (``physics_only=False``): drones, floor, static and moving
  cylinders and square gates. Obstacles and gates are mocap bodies, so the
  per-episode layout is data written into ``mocap_pos``/``mocap_quat``. It is
  what the renderer and MuJoCo's viewer load.
* the **physics** (``physics_only=True``): the drones' bodies and inertia,
  nothing else. Contacts are off, so obstacles and gates exert no force;
  carrying their kinematics through every ``mjx.step`` cost 2.2x in
  throughput on a 2-core CPU (BENCHMARKS.md), so the stepped model leaves
  them out and collisions are computed analytically (``collisions.py``). It
  has no geoms either (the drones' are massless and only drawn: their poses
  took a quarter of ``mjx.step``), and the stages that would compute nothing
  in it (actuators, springs, dampers, sensors) are switched off.
"""

from __future__ import annotations

import mujoco

from aswarm.envs.crazyflie import CrazyflieParams

_NO_CONTACT = 'contype="0" conaffinity="0"'


def drone_body_xml(i: int, cf: CrazyflieParams, *, geoms: bool = True) -> str:
    """A free drone body; ``geoms=False``: its inertia only (the geoms are massless, they are only drawn)."""
    ix, iy, iz = cf.inertia
    a = cf.arm_length / 2**0.5
    rotors = "".join(
        f'<geom type="cylinder" size="0.023 0.002" pos="{x} {y} 0.012" rgba="0.2 0.2 0.2 0.6" {_NO_CONTACT} mass="0"/>'
        for x, y in ((a, -a), (-a, -a), (-a, a), (a, a))
    )
    body = (
        f'<geom name="drone{i}" type="box" size="{a} 0.006 {cf.body_half_height}" '
        f'rgba="0.1 0.4 0.9 1" {_NO_CONTACT} mass="0"/>{rotors}'
    ) if geoms else ""
    return (
        f'<body name="drone{i}" pos="0 0 1"><freejoint name="drone{i}"/>'
        f'<inertial pos="0 0 0" mass="{cf.mass}" diaginertia="{ix} {iy} {iz}"/>{body}</body>'
    )


def build_xml(
    num_agents: int,
    sim_freq: int,
    cf: CrazyflieParams,
    *,
    physics_only: bool,
    num_cylinders: int = 0,
    num_gates: int = 0,
    gate_half_opening: float = 0.3,
    gate_bar: float = 0.05,
    arena_half_extent: float = 10.0,
) -> str:
    opt = (
        f'<option timestep="{1.0 / sim_freq}" gravity="0 0 {-cf.gravity}" '
        'integrator="Euler" jacobian="sparse">'
        '<flag contact="disable" constraint="disable" eulerdamp="disable" actuation="disable" spring="disable" '
        'damper="disable" sensor="disable"/></option>'
    )
    world = [drone_body_xml(i, cf, geoms=not physics_only) for i in range(num_agents)]
    if not physics_only:
        world.insert(0, f'<geom name="floor" type="plane" size="{arena_half_extent} {arena_half_extent} 0.1" '
                     f'rgba="0.8 0.8 0.8 1" {_NO_CONTACT}/>')
        # Unit cylinders, resized per episode through geom_size when rendering.
        world += [
            f'<body name="cylinder{j}" mocap="true" pos="0 0 -10"><geom name="cylinder{j}" '
            f'type="cylinder" size="0.15 1" pos="0 0 1" rgba="0.9 0.6 0.1 1" {_NO_CONTACT}/></body>'
            for j in range(num_cylinders)
        ]
        c = gate_half_opening + gate_bar / 2
        h = gate_bar / 2
        bars = (
            f'<geom type="box" size="{h} {c + h} {h}" pos="0 0 {c}" rgba="0.1 0.8 0.2 1" {_NO_CONTACT}/>'
            f'<geom type="box" size="{h} {c + h} {h}" pos="0 0 {-c}" rgba="0.1 0.8 0.2 1" {_NO_CONTACT}/>'
            f'<geom type="box" size="{h} {h} {c}" pos="0 {c} 0" rgba="0.1 0.8 0.2 1" {_NO_CONTACT}/>'
            f'<geom type="box" size="{h} {h} {c}" pos="0 {-c} 0" rgba="0.1 0.8 0.2 1" {_NO_CONTACT}/>'
        )
        world += [
            f'<body name="gate{k}" mocap="true" pos="0 0 -10">{bars}</body>' for k in range(num_gates)
        ]
    return (
        '<mujoco model="aswarm">'
        f"{opt}"
        '<visual><global offwidth="1280" offheight="720"/></visual>'
        f'<worldbody><light pos="0 0 8" dir="0 0 -1" directional="true"/>{"".join(world)}</worldbody>'
        "</mujoco>"
    )


def build_model(*args, **kwargs) -> mujoco.MjModel:
    """Compile :func:`build_xml` into a MuJoCo model."""
    return mujoco.MjModel.from_xml_string(build_xml(*args, **kwargs))

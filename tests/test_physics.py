"""Physics against hand-derived numbers, and MJX against MuJoCo C."""

import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from aswarm.envs import scene
from aswarm.envs.crazyflie import CrazyflieParams
from aswarm.envs.dynamics import DroneState, physics_model, quat_to_rotmat, simulate_rpm

CF = CrazyflieParams()
SIM = 250


def start(n=1, z=1.0):
    return DroneState(pos=jnp.tile(jnp.array([0.0, 0.0, z]), (n, 1)), quat=jnp.tile(jnp.array([1.0, 0, 0, 0]), (n, 1)),
                      vel=jnp.zeros((n, 3)), ang_vel=jnp.zeros((n, 3)))


def test_constants_match_crazyflie_md():
    assert CF.hover_rpm == pytest.approx(14468.4, abs=0.1)
    assert CF.max_rpm == pytest.approx(21702.6, abs=0.1)
    # Torques from the documented per-motor formulas.
    f = np.array([1.0, 2.0, 3.0, 4.0])
    t, tx, ty, tz = CF.mixer() @ f
    arm = CF.arm_length / np.sqrt(2)
    assert t == pytest.approx(10.0)
    assert tx == pytest.approx(arm * (-f[0] - f[1] + f[2] + f[3]))
    assert ty == pytest.approx(arm * (-f[0] + f[1] + f[2] - f[3]))
    assert tz == pytest.approx(CF.km / CF.kf * (-f[0] + f[1] - f[2] + f[3]))


def test_hover_rpm_holds_position_for_one_second():
    tr = simulate_rpm(start(2), np.full((SIM, 2, 4), CF.hover_rpm), SIM)
    drift = np.abs(np.asarray(tr.pos[-1]) - np.asarray(start(2).pos)).max()
    assert drift < 1e-3
    assert float(tr.time[-1]) == pytest.approx(1.0, abs=1e-5)


def test_motors_off_falls_at_g():
    tr = simulate_rpm(start(), np.zeros((SIM, 1, 4)), SIM)
    vz = np.asarray(tr.vel[:, 0, 2])
    t = np.asarray(tr.time)
    assert vz[-1] == pytest.approx(-CF.gravity * t[-1], rel=1e-4)
    # Semi-implicit Euler: z_k = z_0 - g dt^2 k (k + 1) / 2.
    k = SIM
    assert float(tr.pos[-1, 0, 2]) == pytest.approx(1.0 - CF.gravity * (1 / SIM) ** 2 * k * (k + 1) / 2, abs=1e-4)


def test_yaw_step_on_ccw_motors_has_predicted_sign_and_magnitude():
    steps = 25  # 0.1 s
    rpm = np.full((steps, 1, 4), CF.hover_rpm)
    rpm[:, :, [0, 2]] *= 1.05  # motors 0 and 2 spin counter-clockwise
    tr = simulate_rpm(start(), rpm, SIM)
    # tau_z = km (-w0^2 + w1^2 - w2^2 + w3^2) = -2 km w_h^2 (1.05^2 - 1) < 0: clockwise yaw.
    tau_z = -2 * CF.km * CF.hover_rpm**2 * (1.05**2 - 1)
    expected = tau_z / CF.inertia[2] * steps / SIM
    w = np.asarray(tr.ang_vel[-1, 0])
    assert w[2] < 0
    assert w[2] == pytest.approx(expected, rel=1e-3)
    assert np.abs(w[:2]).max() < 1e-3 * abs(expected)  # no roll or pitch
    assert float(tr.vel[-1, 0, 2]) > 0  # more total thrust: climbs


def test_roll_step_on_left_motors_rolls_right_side_down():
    rpm = np.full((25, 1, 4), CF.hover_rpm)
    rpm[:, :, [2, 3]] *= 1.02  # left motors (+y) push harder: positive roll about x
    tr = simulate_rpm(start(), rpm, SIM)
    assert float(tr.ang_vel[-1, 0, 0]) > 0
    rot = np.asarray(quat_to_rotmat(tr.quat[-1, 0]))
    assert rot[1, 2] < 0  # body z tilts towards -y


def test_mjx_float32_matches_mujoco_c():
    # MuJoCo C steps the drawn scene (drone geoms, floor) and MJX the stepped model without geoms: they agree,
    # so the drawn geoms carry no physics.
    rng = np.random.default_rng(0)
    steps = SIM
    rpm = CF.hover_rpm * (1 + 0.02 * rng.standard_normal((steps, 2, 4)))
    init = DroneState(pos=jnp.array([[0.0, 0.0, 1.0], [1.0, 0.5, 1.2]]),
                      quat=jnp.tile(jnp.array([1.0, 0, 0, 0]), (2, 1)),
                      vel=jnp.array([[0.3, 0.0, 0.0], [0.0, -0.2, 0.1]]), ang_vel=jnp.zeros((2, 3)))
    tr = simulate_rpm(init, rpm, SIM)

    assert scene.build_model(2, SIM, CF, physics_only=True).ngeom == 0
    m = scene.build_model(2, SIM, CF, physics_only=False)
    assert m.ngeom > 2 and m.opt.timestep == pytest.approx(1 / SIM)
    d = mujoco.MjData(m)
    d.qpos[:] = np.concatenate([np.concatenate([init.pos[i], init.quat[i]]) for i in range(2)])
    d.qvel[:] = np.concatenate([np.concatenate([init.vel[i], init.ang_vel[i]]) for i in range(2)])
    mix = CF.mixer()
    for k in range(steps):
        for i in range(2):
            wrench = mix @ (CF.kf * np.clip(rpm[k, i], 0, CF.max_rpm) ** 2)
            rot = np.zeros(9)
            mujoco.mju_quat2Mat(rot, d.qpos[7 * i + 3: 7 * i + 7])
            rot = rot.reshape(3, 3)
            d.xfrc_applied[i + 1] = np.concatenate([rot[:, 2] * wrench[0], rot @ wrench[1:]])
        mujoco.mj_step(m, d)
    pos_c = d.qpos.reshape(2, 7)[:, :3]
    assert np.abs(np.asarray(tr.pos[-1]) - pos_c).max() < 1e-4
    assert np.abs(np.asarray(tr.quat[-1]) - d.qpos.reshape(2, 7)[:, 3:]).max() < 1e-4


def test_bad_rpm_shape_is_a_clear_error():
    with pytest.raises(ValueError, match=r"rpm must have shape \[T, n_drones, 4\]"):
        simulate_rpm(start(), np.zeros((10, 4)), SIM)
    _, mx = physics_model(1, SIM)
    assert mx.nv == 6

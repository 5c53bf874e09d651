"""The firmware's controller_mellinger and the full-state setpoints that carry a velocity command to it, against
hand-derived numbers.

Every expected number below is worked out from the firmware constants (controller_mellinger.c, CF_MASS 0.029 kg,
GRAVITY_MAGNITUDE 9.81) in the comment beside it, not read back from the code.
"""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from aswarm import envs
from aswarm.analysis import step_response
from aswarm.core.command import advance_reference, setpoint_position
from aswarm.envs import firmware_mellinger as mel
from aswarm.envs import firmware_pid
from aswarm.envs.dynamics import quat_to_rotmat

MEL = mel.FirmwareMellinger()
DT = 0.002  # ATTITUDE_RATE 500 Hz
ZERO = jnp.zeros((1, 3))
T_HOVER = 132000 * 0.029 * 9.81  # massThrust * mass * g = 37552.68 PWM: the feed-forward alone
S10 = math.sin(math.radians(10.0))


def _rot(axis: int, deg: float) -> jax.Array:
    half = math.radians(deg) / 2
    q = [math.cos(half), 0.0, 0.0, 0.0]
    q[1 + axis] = math.sin(half)
    return quat_to_rotmat(jnp.array([q]))


def _control(rot=None, ang_vel=ZERO, pos=ZERO, vel=ZERO, sp_pos=ZERO, sp_vel=ZERO, state=None):
    state = state or mel.MellingerState(integ=jnp.zeros((1, 6)), prev_rates=jnp.zeros((1, 2)))
    rot = _rot(0, 0.0) if rot is None else rot
    return mel.control(state, rot, ang_vel, pos, vel, sp_pos, sp_vel, MEL, DT)


def test_a_level_drone_on_its_setpoint_gets_the_feed_forward_thrust():
    _, motors = _control()
    np.testing.assert_allclose(motors[0], [T_HOVER] * 4, rtol=1e-6)


def test_rotation_errors_give_the_firmware_moments_on_the_legacy_mixer():
    # Rolled +10 deg about x (right side down), the setpoint level: Rdes = I, R - R^T has 2 sin 10 deg at [2, 1]
    # (no factor 1/2), M.x = -70000 * 0.347296 = -24310.7; the thrust is the force along the tilted body z.
    t = T_HOVER * math.cos(math.radians(10.0))
    r = -70000 * 2 * S10 / 2
    _, motors = _control(rot=_rot(0, 10.0))
    np.testing.assert_allclose(motors[0], [t - r, t - r, t + r, t + r], rtol=1e-5)  # the right motors push
    # Nose down +10 deg about y: the vee's y is 2 sin 10 deg, negated for the firmware's frame, so M.y = +24310.7
    # and the front motors (0 and 3) push.
    p = 70000 * 2 * S10 / 2
    _, motors = _control(rot=_rot(1, 10.0))
    np.testing.assert_allclose(motors[0], [t + p, t - p, t - p, t + p], rtol=1e-5)
    # Yawed +10 deg (counter-clockwise) from the setpoint's yaw 0: M.z = -60000 * 0.347296 + 500 * (-0.347296 *
    # 0.002) = -20838.1, yaw output -M.z: the counter-clockwise motors 0 and 2 push (a clockwise reaction).
    y = 60000 * 2 * S10 + 500 * 2 * S10 * DT
    st, motors = _control(rot=_rot(2, 10.0))
    np.testing.assert_allclose(motors[0], [T_HOVER + y, T_HOVER - y, T_HOVER + y, T_HOVER - y], rtol=1e-5)
    np.testing.assert_allclose(st.integ[0, 5], -2 * S10 * DT, rtol=1e-5)  # i_error_m_z


def test_moments_clamp_at_32000():
    # 30 deg of roll: 70000 * 2 sin 30 deg = 70000 > 32000, so each side gets 16000.
    t = T_HOVER * math.cos(math.radians(30.0))
    _, motors = _control(rot=_rot(0, 30.0))
    np.testing.assert_allclose(motors[0], [t + 16000, t + 16000, t - 16000, t - 16000], rtol=1e-5)


def test_a_position_error_tilts_the_desired_thrust():
    # 0.1 m behind the setpoint in x: force x = 0.4 * 0.1 + 0.05 * (0.1 * 0.002) = 0.04001 N, z = 0.28449 N,
    # so the desired body z leans 8.005 deg towards +x (nose down): from level, M.y = -70000 * 2 sin(8.005 deg).
    fx, fz = 0.4 * 0.1 + 0.05 * 0.1 * DT, 0.029 * 9.81
    theta = math.atan2(fx, fz)
    p = -70000 * 2 * math.sin(theta) / 2
    st, motors = _control(sp_pos=jnp.array([[0.1, 0.0, 0.0]]))
    np.testing.assert_allclose(motors[0], [T_HOVER + p, T_HOVER - p, T_HOVER - p, T_HOVER + p], rtol=1e-5)
    np.testing.assert_allclose(st.integ[0, 0], 0.1 * DT, rtol=1e-6)  # i_error_x, m s
    # A velocity error acts through kd: 0.5 m/s in y gives force y = 0.2 * 0.5 = 0.1 N, a bank towards +y (left
    # side down): the right motors (0, 1) push.
    _, motors = _control(sp_vel=jnp.array([[0.0, 0.5, 0.0]]))
    assert motors[0, 0] > motors[0, 2]


def test_the_rate_d_term_brakes_a_roll_and_no_thrust_means_no_torque():
    # Rolling at +100 deg/s since the last tick: kw * (-1.745) + 200 * -(1.745 - 0) / 0.002 < -32000, clamped.
    _, motors = _control(ang_vel=jnp.array([[math.radians(100.0), 0.0, 0.0]]))
    np.testing.assert_allclose(motors[0, 0] - motors[0, 2], 32000.0, rtol=1e-6)
    # 1 m above the setpoint: force z = 0.28449 - 1.25 < 0, so no thrust, no torques, and the integrals reset.
    state = mel.MellingerState(integ=jnp.full((1, 6), 0.1), prev_rates=jnp.zeros((1, 2)))
    st, motors = _control(rot=_rot(0, 10.0), pos=jnp.array([[0.0, 0.0, 1.0]]), state=state)
    np.testing.assert_array_equal(motors[0], np.zeros(4))
    np.testing.assert_array_equal(st.integ[0], np.zeros(6))


def test_hover_memory_holds_the_drones_weight():
    # A 27 g drone needs 36125.9 PWM (firmware_pid's thrust map); the feed-forward gives 132000 * 0.28449 N, so
    # the z integral holds (36125.9 / 132000 - 0.28449) / 0.05 = -0.21617 m s.
    hover = firmware_pid.hover_thrust(jnp.float32(0.027 * 9.8), 1.0, firmware_pid.FirmwarePid())
    st = mel.initial_state(ZERO, hover, MEL)
    np.testing.assert_allclose(st.integ[0, 2], (0.06615 / 0.12 * 65535 / 132000 - 0.029 * 9.81) / 0.05, rtol=1e-5)
    _, motors = mel.control(st, _rot(0, 0.0), ZERO, ZERO, ZERO, ZERO, ZERO, MEL, DT)
    np.testing.assert_allclose(motors[0], [hover] * 4, rtol=1e-4)
    # Beyond i_range_z the integral stops at 0.4 (a much heavier drone sags instead).
    st = mel.initial_state(ZERO, jnp.float32(60000.0), MEL)
    np.testing.assert_allclose(st.integ[0, 2], 0.4)


def test_the_setpoint_moves_with_the_command_and_stays_on_its_leash():
    ref, cmd = np.zeros((1, 3)), np.array([[1.0, 0.0, -0.5]])
    # Held 0.04 s: the setpoint sits halfway along, the reference moves the whole way.
    np.testing.assert_allclose(setpoint_position(ref, cmd, 0.04), [[0.02, 0.0, -0.01]])
    np.testing.assert_allclose(advance_reference(ref, cmd, 0.04, np.zeros((1, 3)), 0.3), [[0.04, 0.0, -0.02]])
    # A drone 0.5 m behind: the reference is pulled to 0.3 m ahead of it, along the line between them.
    out = advance_reference(ref, np.zeros((1, 3)), 0.04, np.array([[-0.5, 0.0, 0.0]]), 0.3)
    np.testing.assert_allclose(out, [[-0.2, 0.0, 0.0]], atol=1e-12)
    # The same numbers in JAX (the env's) and numpy (the flight side's).
    jout = advance_reference(jnp.asarray(ref), jnp.zeros((1, 3)), 0.04, jnp.array([[-0.5, 0.0, 0.0]]), 0.3)
    np.testing.assert_allclose(jout, out, atol=1e-7)


@pytest.fixture(scope="module")
def mellinger_drone():
    return envs.preset("hover", controller="mellinger")


def test_mellinger_drone_hovers_and_tracks_velocity_steps(mellinger_drone):
    still = step_response.step_response(mellinger_drone, (0.0, 0.0, 0.0), seconds=1.0)
    assert np.max(np.abs(still["vel"])) < 2e-3
    x = step_response.step_response(mellinger_drone, (1.0, 0.0, 0.0), seconds=4.0)
    z = step_response.step_response(mellinger_drone, (0.0, 0.0, 1.0), seconds=4.0)
    np.testing.assert_allclose(x["vel"][-1], [1.0, 0.0, 0.0], atol=0.03)
    np.testing.assert_allclose(z["vel"][-1], [0.0, 0.0, 1.0], atol=0.03)
    # No tilt limit in Mellinger: a 2 m/s step tilts the drone past the PID's 20 degrees.
    fast = step_response.step_response(mellinger_drone, (2.0, 0.0, 0.0), seconds=1.0)
    assert fast["tilt"].max() > 20.0


def test_randomised_mellinger_gains_differ_across_worlds():
    env = envs.make("hover", controller="mellinger")
    states = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), 4))
    kp = np.asarray(states.onboard.params.mellinger.kp_xy)
    assert len(set(kp.tolist())) == 4 and np.all((kp >= 0.4 * 0.9) & (kp <= 0.4 * 1.1))
    # One factor per world scales every gain: kR / kp stays the firmware's 70000 / 0.4.
    np.testing.assert_allclose(np.asarray(states.onboard.params.mellinger.kr_xy) / kp, 70000 / 0.4, rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(states.onboard.params.mellinger.mass), np.float32(0.029))


@pytest.mark.parametrize("change, message", [
    ({"controller": "lee"}, r"invalid controller='lee': allowed: pid, mellinger, geometric"),
    ({"controller": "mellinger", "sim_freq": 250}, r"invalid sim_freq=250: controller 'mellinger' runs at the "),
    ({"reference_leash": 0.0}, r"invalid reference_leash=0.0: must be > 0 m"),
    ({"mellinger": dataclasses.replace(MEL, kp_xy=-0.4)}, r"invalid mellinger.kp_xy=-0.4: must be > 0"),
])
def test_bad_mellinger_settings_are_one_line(change, message):
    with pytest.raises(ValueError, match=message):
        envs.make("hover", **change)

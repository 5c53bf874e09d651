"""The firmware's controller_pid, the rotor lag and domain randomisation against hand-derived numbers.

Every expected number below is worked out from the firmware constants (platform_defaults_cf2.h) in the comment
beside it, not read back from the code.
"""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from aswarm import envs
from aswarm.analysis import step_response
from aswarm.envs import firmware_pid as fw
from aswarm.envs.config import LEGACY_DRONE
from aswarm.envs.crazyflie import SPIN_DOWN_REFERENCE_RPM
from aswarm.envs.dynamics import rotor_lag
from aswarm.envs.randomization import OFF, Randomization

PID = fw.FirmwarePid()
LEVEL = jnp.array([[1.0, 0.0, 0.0, 0.0]])
ZERO = jnp.zeros((1, 3))


def _state(thrust=36000.0, attitude=(0.0, 0.0, 0.0)) -> fw.PidState:
    return fw.PidState(integ=jnp.zeros((1, 9)), prev=jnp.zeros((1, 6)), attitude=jnp.array([attitude]),
                       thrust=jnp.array([thrust]))


def test_velocity_loop_tilts_and_thrusts_as_the_firmware_constants_say():
    dt = 0.01  # POSITION_RATE 100 Hz
    s = fw.velocity_loop(_state(), LEVEL, ZERO, jnp.array([[0.5, 0.0, 0.1]]), PID, dt)
    # pitch = -(kp e + ki e dt) = -(25 * 0.5 + 1 * 0.5 * 0.01) = -12.505 deg (nose down to speed up in x)
    np.testing.assert_allclose(s.attitude[0], [0.0, -12.505, 0.0], atol=1e-4)
    # thrust = (25 * 0.1 + 15 * 0.1 * 0.01) * 1000 + 36000 = 38515 PWM
    np.testing.assert_allclose(s.thrust[0], 38515.0, rtol=1e-6)
    # roll = -(25 * 0.5 + 0.005) for +y: the left side goes down
    s = fw.velocity_loop(_state(), LEVEL, ZERO, jnp.array([[0.0, 0.5, 0.0]]), PID, dt)
    np.testing.assert_allclose(s.attitude[0, 0], -12.505, atol=1e-4)
    # 1 m/s of error asks 25 deg: the PID's own limit is 20 * 1.1 = 22, the clamp after it 20 (PID_VEL_PITCH_MAX)
    s = fw.velocity_loop(_state(), LEVEL, ZERO, jnp.array([[1.0, -1.0, 0.0]]), PID, dt)
    np.testing.assert_allclose(s.attitude[0, :2], [20.0, -20.0], atol=1e-5)
    # sinking at -2 m/s asks 36000 - 50 * 1000: the z PID's limit 65535 / 2 / 1000 then PID_VEL_THRUST_MIN 20000
    s = fw.velocity_loop(_state(), LEVEL, ZERO, jnp.array([[0.0, 0.0, -2.0]]), PID, dt)
    np.testing.assert_allclose(s.thrust[0], 20000.0)


def test_velocity_loop_works_in_the_body_yaw_frame():
    # Yawed 90 deg left: a world +y command is body +x, so it pitches (nose down), not rolls.
    yawed = jnp.array([[math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]])
    s = fw.velocity_loop(_state(), yawed, ZERO, jnp.array([[0.0, 0.5, 0.0]]), PID, 0.01)
    np.testing.assert_allclose(s.attitude[0, :2], [0.0, -12.505], atol=1e-3)


def test_attitude_and_rate_loops_and_the_legacy_power_distribution():
    dt = 0.002  # ATTITUDE_RATE 500 Hz
    st, motors = fw.attitude_loop(_state(attitude=(-10.0, 0.0, 0.0)), LEVEL, ZERO, PID, dt)
    # rate setpoint = 6 * (-10) + 3 * (-10 * 0.002) = -60.06 deg/s
    # roll output  = 250 * (-60.06) + 500 * (-60.06 * 0.002) = -15075.06; each side gets half
    r = -15075.06 / 2
    np.testing.assert_allclose(motors[0], [36000 - r, 36000 - r, 36000 + r, 36000 + r], rtol=1e-5)
    np.testing.assert_allclose(st.integ[0, 3], -0.02, rtol=1e-5)  # the attitude integral, deg s
    # Pitch up (firmware pitch is nose-up positive): front motors (0 and 3) speed up.
    _, motors = fw.attitude_loop(_state(attitude=(0.0, 10.0, 0.0)), LEVEL, ZERO, PID, dt)
    p = 15075.06 / 2
    np.testing.assert_allclose(motors[0], [36000 + p, 36000 - p, 36000 - p, 36000 + p], rtol=1e-5)
    # A yaw setpoint of +10 deg (counter-clockwise): 6 * 10 + 1 * 0.02 = 60.02 deg/s, output 120 * 60.02
    # + 16.7 * 0.12004 = 7204.4; the counter-clockwise motors 0 and 2 slow down.
    _, motors = fw.attitude_loop(_state(attitude=(0.0, 0.0, 10.0)), LEVEL, ZERO, PID, dt)
    y = 120 * 60.02 + 16.7 * 60.02 * dt
    np.testing.assert_allclose(motors[0], [36000 - y, 36000 + y, 36000 - y, 36000 + y], rtol=1e-5)


def test_rate_loop_saturates_to_int16_and_the_cap_takes_the_excess_off_all_motors():
    # 90 deg of roll error: 250 * (6 * 90 + ...) > 32767, so the output is 32767 and each side gets 16383.5.
    _, motors = fw.attitude_loop(_state(thrust=60000.0, attitude=(-90.0, 0.0, 0.0)), LEVEL, ZERO, PID, 0.002)
    half = 32767 / 2
    excess = 60000 + half - 65535
    np.testing.assert_allclose(motors[0], [65535, 65535, 60000 - half - excess, 60000 - half - excess], rtol=1e-6)


def test_d_term_acts_on_the_measured_rate():
    # Rolling at +100 deg/s since the last tick (prev 0): rate D = 2.5 * -(100 - 0) / 0.002 = -125000 -> saturated.
    st = _state()
    _, motors = fw.attitude_loop(st, LEVEL, jnp.array([[math.radians(100.0), 0.0, 0.0]]), PID, 0.002)
    assert motors[0, 0] > motors[0, 2]  # it brakes the roll: the right motors (0, 1) push harder


def test_thrust_map_gives_the_hover_speed_and_cuts_below_thrust_min():
    cf = envs.make("hover").config.cf
    hover = fw.hover_thrust(jnp.float32(cf.mass * cf.gravity), 1.0, PID)
    # 0.027 kg * 9.8 / 4 = 0.06615 N per motor = 36125.9 of 65535 * 0.12 N; close to PID_VEL_THRUST_BASE 36000
    np.testing.assert_allclose(hover, 0.06615 / 0.12 * 65535, rtol=1e-6)
    rpm = fw.motor_rpm(jnp.array([hover, 1000.0]), PID, cf.kf)
    np.testing.assert_allclose(rpm[0], cf.hover_rpm, rtol=1e-5)  # 14468.4 RPM, gym-pybullet-drones' hover
    assert rpm[1] == 0.0  # 1000 / 65535 * 0.12 N < THRUST_MIN 0.0128 N


def test_rotor_lag_follows_the_analytic_first_order_response():
    tau, dt, target = 0.136, 0.002, 20000.0
    rpm = jnp.array(10000.0)
    for _ in range(50):
        rpm = rotor_lag(rpm, target, tau, dt)
    # 0.1 s: 20000 - 10000 exp(-0.1 / 0.136) = 15206.3
    np.testing.assert_allclose(rpm, target - 10000 * math.exp(-0.1 / tau), rtol=1e-5)


def test_rotors_slow_down_quadratically_as_identified():
    tau, tau_down, hover, dt = 0.136, 0.108, SPIN_DOWN_REFERENCE_RPM, 0.002
    assert hover == pytest.approx(14468.4, abs=0.1)  # sqrt(0.027 * 9.8 / (4 * 3.16e-10)): the default's hover

    def run(rpm, target, steps):
        rpm = jnp.asarray(rpm)
        for _ in range(steps):
            rpm = rotor_lag(rpm, jnp.asarray(target), tau, dt, tau_down, hover)
        return float(rpm)

    # A motor cut from hover: d rpm/dt = -k rpm^2 gives rpm0 / (1 + k rpm0 t), k rpm0 = 1 / (2 tau_down) about
    # hover: after 0.1 s 14468.4 / (1 + 0.1 / 0.216) = 9889.8 RPM (the first-order lag would leave 6944).
    np.testing.assert_allclose(run(hover, 0.0, 50), hover / (1 + 0.1 / (2 * tau_down)), rtol=1e-5)
    # Asked 100 RPM below hover it closes the gap with the time constant tau_down (linearised about hover):
    # 100 exp(-0.05 / 0.108) = 62.9 RPM left after 0.05 s.
    np.testing.assert_allclose(run(hover, hover - 100, 25) - (hover - 100), 100 * math.exp(-0.05 / tau_down),
                               rtol=5e-3)
    # Exact: one step of 0.1 s lands where 50 of 2 ms do, from far above the target too.
    one = float(rotor_lag(jnp.asarray(20000.0), jnp.asarray(5000.0), tau, 0.1, tau_down, hover))
    np.testing.assert_allclose(run(20000.0, 5000.0, 50), one, rtol=1e-5)
    # Speeding up is the first-order lag, as without tau_down.
    np.testing.assert_allclose(run(10000.0, 20000.0, 50), 20000 - 10000 * math.exp(-0.1 / tau), rtol=1e-5)


@pytest.fixture(scope="module")
def pid_drone():
    return envs.preset("hover")


def test_pid_drone_hovers_and_its_tilt_saturates_at_20_degrees(pid_drone):
    still = step_response.step_response(pid_drone, (0.0, 0.0, 0.0), seconds=1.0)
    assert np.max(np.abs(still["vel"])) < 1e-3  # the z integral starts at the hover thrust
    # 2 m/s (the speed limit) of error asks 25 * 2 = 50 deg: the setpoint sits at the 20 deg limit until the
    # error is below 20 / 25 = 0.8 m/s, and the drone accelerates at g tan(20 deg) = 3.567 m/s^2 meanwhile.
    fast = step_response.step_response(pid_drone, (2.0, 0.0, 0.0), seconds=1.0)
    assert 19.0 < fast["tilt"].max() < 21.5  # the attitude PI loop overshoots its setpoint by a few percent
    acc = np.diff(fast["vel"][:, 0]) * 100.0
    late = acc[40:60]  # 0.4-0.6 s: the tilt has reached the limit, the velocity is still below 1.2 m/s
    np.testing.assert_allclose(late.mean(), 9.8 * math.tan(math.radians(20.0)), rtol=0.06)


def test_pid_drone_tracks_velocity_steps(pid_drone):
    x = step_response.step_response(pid_drone, (1.0, 0.0, 0.0), seconds=2.5)
    z = step_response.step_response(pid_drone, (0.0, 0.0, 1.0), seconds=2.5)
    np.testing.assert_allclose(x["vel"][-1], [1.0, 0.0, 0.0], atol=0.03)
    np.testing.assert_allclose(z["vel"][-1], [0.0, 0.0, 1.0], atol=0.03)


def test_randomised_parameters_differ_across_worlds_and_repeat_from_the_key():
    env = envs.make("hover", randomize=Randomization(mocap_delay=(0, 1)))
    keys = jax.random.split(jax.random.PRNGKey(3), 64)
    a = jax.jit(jax.vmap(env.reset))(keys).onboard.params
    b = jax.jit(jax.vmap(env.reset))(keys).onboard.params
    for leaf_a, leaf_b in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(leaf_a, leaf_b)
    r = env.config.randomize
    mass = np.asarray(a.cf.mass) / env.config.cf.mass
    assert mass.std() > 0.03 and r.mass[0] <= mass.min() and mass.max() <= r.mass[1] + 1e-6
    assert len(np.unique(np.asarray(a.latency_ticks))) == 8  # 0..7 ticks: 0 to 2 steps of 4 ticks, floored
    assert set(np.unique(np.asarray(a.mocap_delay))) == {0.0, 1.0}
    np.testing.assert_allclose(np.asarray(a.pid.rate_kp) / 250.0, np.asarray(a.pid.att_kp) / 6.0, rtol=1e-5)
    assert np.asarray(a.mocap_noise).max() <= 0.005


def test_latency_delays_the_command_by_whole_controller_ticks():
    env = envs.make("hover", randomize=OFF)
    p = env.default_params
    earlier = jnp.stack([jnp.full((1, 3), 1.0), jnp.full((1, 3), 2.0)])  # last step's, the one before
    now = jnp.zeros((1, 3))
    got = [float(env._command(now, earlier, t, p.replace(latency_ticks=jnp.float32(6.0)))[0, 0]) for t in range(4)]
    assert got == [2.0, 2.0, 1.0, 1.0]  # 6 ticks late: ticks 0-1 hold the command of 2 steps ago


def test_seen_velocity_is_the_flight_runtimes_estimate_from_the_noisy_positions():
    from aswarm.flight import estimator

    # 3 mm of noise in every episode, no delay: what the policy sees is the line through the last 4 noisy
    # positions at the policy rate, as the flight runtime fits it to the poses motion capture gives it.
    r = Randomization(mocap_noise=(0.003, 0.003), velocity_window=4)
    env = envs.make("hover", randomize=r)
    step, s = jax.jit(env.step), jax.jit(env.reset)(jax.random.PRNGKey(0))
    vel = env.obs_layout.own_slices["vel"]
    line = estimator.EstimatorConfig(window=4, velocity="window")
    est = estimator.init((1,), line)
    for k in range(8):
        if k:
            s = step(s, jnp.array([[0.8, -0.4, 0.3]]))
        seen = np.asarray(s.onboard.pos_history[0], np.float64)  # the noisy position the policy saw
        est, _, _ = estimator.update(est, np.full(1, k / env.config.policy_freq), seen, np.array([[1.0, 0, 0, 0]]),
                                     np.ones(1, bool), line)
        if k >= 3:  # a full window (the env starts its window at the true start position)
            want, _ = estimator.estimate(est, line)
            np.testing.assert_allclose(s.obs[0, vel], want[0], atol=2e-4, err_msg=f"step {k}")
    # The noise is in it: 3 mm over 4 poses at 25 Hz moves the slope by centimetres per second.
    true = np.asarray(s.data.qvel[:3])
    assert 1e-3 < np.abs(np.asarray(s.obs[0, vel]) - true).max() < 0.5
    # Without the window, the true velocity.
    plain = envs.make("hover", randomize=Randomization(mocap_noise=(0.003, 0.003)))
    s = jax.jit(plain.reset)(jax.random.PRNGKey(0))
    assert s.onboard.pos_history is None


@pytest.mark.parametrize("field, value, message", [
    ("velocity_window", 1, r"invalid randomize.velocity_window=1: allowed: 0 \(true velocities\) or an integer >= 2"),
    ("mass", (-0.1, 1.1), r"invalid randomize.mass=\(-0.1, 1.1\): allowed: scales > 0"),
    ("mass", (1.2, 0.8), r"invalid randomize.mass=\(1.2, 0.8\): allowed: finite numbers with low <= high"),
    ("latency", (-1.0, 2.0), r"invalid randomize.latency=\(-1.0, 2.0\): allowed: values >= 0"),
    ("mocap_delay", (0, 1.5), r"invalid randomize.mocap_delay=\(0, 1.5\): allowed: whole policy steps"),
])
def test_bad_randomisation_range_is_one_line(field, value, message):
    with pytest.raises(ValueError, match=message):
        Randomization(**{field: value})


def test_bad_controller_settings_are_one_line():
    with pytest.raises(ValueError, match=r"invalid sim_freq=250: controller 'pid' runs at the firmware's rates"):
        envs.make("hover", sim_freq=250)
    with pytest.raises(ValueError, match=r"invalid cf.motor_tau=-0.1: must be >= 0"):
        envs.make("hover", cf=dataclasses.replace(envs.preset("hover").cf, motor_tau=-0.1))


def test_the_geometric_drone_is_still_there():
    env = envs.make("hover", **LEGACY_DRONE)
    assert env.config.controller == "geometric" and not env.lag and not env.randomize

"""Environment API: shapes, resets, purity under jit/vmap/scan, wrappers, episode outcome, bad input."""

import dataclasses
import math

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from aswarm import envs
from aswarm.core import geometry as geo
from aswarm.core.command import limit_change
from aswarm.core.safety import SafetyFilterConfig
from aswarm.envs.dynamics import DroneState, set_drone_state
from aswarm.envs.randomization import OFF


@pytest.fixture(scope="module")
def race():
    return envs.make("race")


@pytest.mark.parametrize("name", envs.names())
def test_every_scenario_resets_with_documented_shapes(name):
    env = envs.make(name)
    s = jax.jit(env.reset)(jax.random.PRNGKey(0))
    n = env.num_agents
    chex.assert_shape(s.obs, (n, env.observation_size))
    chex.assert_shape(s.critic_obs, (env.critic_observation_size,))
    chex.assert_shape([s.reward, s.cost], (n,))
    chex.assert_shape([s.done, s.truncated], ())
    assert env.action_size == 3
    own, cyl, nbr = env.obs_layout.split(s.obs)
    chex.assert_shape(own, (n, env.obs_layout.own_dim))
    chex.assert_shape(cyl, (n, env.config.num_cylinders, env.obs_layout.cyl_dim))
    chex.assert_shape(nbr, (n, n - 1, env.obs_layout.nbr_dim))
    assert sum(f["size"] for f in env.obs_layout.describe()) == env.observation_size
    assert np.isfinite(np.asarray(s.obs)).all()
    # Layout is valid: cylinders do not overlap each other or the starts.
    lay = s.layout
    c = np.asarray(lay.cyl_center)
    if len(c) > 1:
        d = np.linalg.norm(c[:, None] - c[None], axis=-1) + np.eye(len(c)) * 9
        assert d.min() > 2 * env.config.obstacle_radius
    gaps = geo.cylinder_clearance(lay.start_pos, lay.cyl_center, lay.cyl_radius, lay.cyl_height, lay.cyl_present,
                                  env.config.cf.collision_radius)
    assert float(jnp.min(gaps, initial=geo.FAR)) > 0


def test_same_key_same_layout_different_keys_differ(race):
    reset = jax.jit(race.reset)
    a, b, c = reset(jax.random.PRNGKey(3)), reset(jax.random.PRNGKey(3)), reset(jax.random.PRNGKey(4))
    chex.assert_trees_all_equal(a.layout, b.layout)
    assert not np.allclose(a.layout.cyl_center, c.layout.cyl_center)
    assert not np.allclose(a.layout.gate_pos, c.layout.gate_pos)


def test_nominal_layout_without_jitter_is_fixed_up_to_slot_choice():
    env = envs.make("race", layout_jitter=0.0)
    reset = jax.jit(env.reset)
    a, b = reset(jax.random.PRNGKey(0)), reset(jax.random.PRNGKey(1))
    np.testing.assert_allclose(a.layout.gate_pos, b.layout.gate_pos)
    np.testing.assert_allclose(a.layout.start_pos, b.layout.start_pos)


def test_jit_vmap_and_scan_of_the_step_agree(race):
    # The jitted step is the reference: an op-by-op call of the race step (some 300 one-op programs and their
    # dispatch) cost this test half its time and checks nothing the compiled call does not (jit is the stricter:
    # a step that branched in Python on a traced value would fail there).
    key = jax.random.PRNGKey(0)
    s0 = jax.jit(race.reset)(key)
    action = jnp.tile(jnp.array([1.0, -0.5, 0.2]), (race.num_agents, 1))
    jitted = jax.jit(race.step)(s0, action)
    batched = jax.jit(jax.vmap(race.step))(jax.tree.map(lambda x: jnp.stack([x, x]), s0), jnp.stack([action, action]))
    scanned = jax.lax.scan(lambda s, _: (race.step(s, action), None), s0, None, length=1)[0]
    assert not np.allclose(jitted.obs, s0.obs)  # the step moved the drones
    for other in (jax.tree.map(lambda x: x[1], batched), scanned):
        np.testing.assert_allclose(jitted.obs, other.obs, atol=1e-5)
        np.testing.assert_allclose(jitted.reward, other.reward, atol=1e-5)


def test_vmapped_autoreset_rollout_in_scan():
    env = envs.make("hover", episode_seconds=0.2)  # 10 steps per episode
    wenv = envs.wrap_for_training(env, 3)
    s = jax.jit(wenv.reset)(jax.random.PRNGKey(0))
    chex.assert_shape(s.obs, (3, 1, env.observation_size))

    def body(s, _):
        s = wenv.step(s, jnp.zeros((3, 1, 3)))
        return s, (s.done, s.truncated, s.tracker.steps, s.info["final_obs"], s.obs)

    _, (done, trunc, steps, final_obs, obs) = jax.jit(lambda s: jax.lax.scan(body, s, None, length=25))(s)
    assert np.asarray(done[9]).tolist() == [1.0] * 3 and np.asarray(trunc[9]).tolist() == [1.0] * 3
    assert np.asarray(steps[9]).tolist() == [0, 0, 0]  # auto-reset started a new episode
    assert np.asarray(done[19]).tolist() == [1.0] * 3
    assert not np.allclose(final_obs[9], obs[9])  # final obs of the old episode kept apart


@pytest.mark.parametrize("clearance,bonus", [(0.0, 10.0), (0.5, 10.0), (0.0, None)])
def test_race_gate_passage_advances_target_and_pays_bonus(clearance, bonus):
    # bonus None: the default, no gate bonus since session 34 (the passing step pays its progress only)
    extra = {} if bonus is None else {"gate_bonus": bonus}
    env = envs.make("race", num_agents=1, num_obstacles=0, layout_jitter=0.0, randomize=OFF,
                    wrong_side_clearance=clearance, **extra)
    s = jax.jit(env.reset)(jax.random.PRNGKey(0))
    g, yaw = s.layout.gate_pos[0], s.layout.gate_yaw[0]
    normal = jnp.array([jnp.cos(yaw), jnp.sin(yaw), 0.0])
    start = DroneState(pos=(g - 0.3 * normal)[None], quat=jnp.array([[1.0, 0, 0, 0]]), vel=(normal * 1.0)[None],
                       ang_vel=jnp.zeros((1, 3)))
    s = s.replace(data=set_drone_state(s.data, start))
    step = jax.jit(env.step)
    f = env.obs_layout.own_slices
    s = step(s, (normal * 1.0)[None])
    # Before the plane: no gate passed yet, and the direction points at gate 0's centre.
    np.testing.assert_array_equal(s.obs[0, f["prev_gate_rel"]], 0.0)
    np.testing.assert_array_equal(s.obs[0, f["prev_gate_normal"]], 0.0)
    to_gate = np.asarray(g - s.data.qpos[:3])
    np.testing.assert_allclose(s.obs[0, f["target_dir"]], to_gate / np.linalg.norm(to_gate), atol=1e-5)
    rewards, positions, targets = [], [np.asarray(s.data.qpos[:3])], []
    for _ in range(30):
        s = step(s, (normal * 1.0)[None])
        rewards.append(float(s.reward[0]))
        positions.append(np.asarray(s.data.qpos[:3]))
        targets.append(int(s.tracker.target[0]))
    assert int(s.tracker.target[0]) == 1 and not bool(s.tracker.collided[0])
    # The passing step's reward by hand, in gate 0's frame: the bonus plus the fall in |along| + 2 off + 2 past,
    # where past the plane the offset counts at least `clearance`, on the step through the opening too: on the
    # axis the jump to 0.5 m takes 1 m of progress back, about the whole bonus (as session 33's default trained,
    # README).
    c = env.config
    side, g_np = np.array([-np.sin(yaw), np.cos(yaw), 0.0]), np.asarray(g)

    def to_go(pos):
        along, off = (pos - g_np) @ np.asarray(normal), np.hypot((pos - g_np) @ side, pos[2] - g_np[2])
        off = max(off, clearance) if along > 0 else off
        return abs(along) + c.lateral_weight * off + c.wrong_side_weight * max(along, 0.0)

    k = targets.index(1)
    by_hand = c.gate_bonus + c.progress_weight * (to_go(positions[k]) - to_go(positions[k + 1])) - c.time_penalty * c.dt
    assert rewards[k] == pytest.approx(by_hand, abs=1e-3)
    if bonus is None:  # the default: no bonus, so no spike on the passing step (a step moves ~4 cm, 0.4 each)
        assert c.gate_bonus == 0.0 and abs(rewards[k]) < 1.0
    else:
        assert (rewards[k] > bonus * 0.9) if clearance == 0.0 else (rewards[k] < bonus * 0.1)
    np.testing.assert_allclose(s.obs[0, :3], s.data.qpos[:3] - s.layout.gate_pos[1], atol=1e-5)
    # Past it: gate 0 is now the gate passed last, with its direction of passage.
    np.testing.assert_allclose(s.obs[0, f["prev_gate_rel"]], s.data.qpos[:3] - g, atol=1e-5)
    np.testing.assert_allclose(s.obs[0, f["prev_gate_normal"]], normal, atol=1e-6)


def test_track_progress_weighs_the_offset_from_the_gate_axis_and_its_wrong_side():
    env = envs.make("race", num_agents=3, num_obstacles=0, layout_jitter=0.0, randomize=OFF)
    assert env.config.wrong_side_clearance == 0.0  # the default since session 34
    s = jax.jit(env.reset)(jax.random.PRNGKey(0))
    g, yaw = s.layout.gate_pos[0], s.layout.gate_yaw[0]
    normal = jnp.array([jnp.cos(yaw), jnp.sin(yaw), 0.0])
    side = jnp.array([-jnp.sin(yaw), jnp.cos(yaw), 0.0])
    up = jnp.array([0.0, 0.0, 1.0])
    pos = jnp.stack([g - 0.5 * normal, g + 0.5 * normal, g + 0.3 * side - 0.4 * up + 0.2 * normal])
    w, k = env.config.wrong_side_weight, env.config.lateral_weight
    # on the axis in front: the distance; past the plane: + w * depth; off the axis: + k * offset
    np.testing.assert_allclose(env._to_go(pos, s.layout, jnp.zeros(3, jnp.int32)),
                               [0.5, 0.5 + w * 0.5, 0.2 + w * 0.2 + k * 0.5], rtol=1e-5)
    # wrong_side_clearance 0.5 (the default in session 33): past the plane an offset under 0.5 counts as 0.5; in
    # front it is the offset
    clamped = envs.make("race", num_agents=3, num_obstacles=0, layout_jitter=0.0, randomize=OFF,
                        wrong_side_clearance=0.5)
    near_past, in_front = g + 0.2 * (side + normal), g + 0.3 * side - 0.2 * normal
    far_past = g + 0.7 * side + 0.2 * normal
    np.testing.assert_allclose(clamped._to_go(jnp.stack([near_past, in_front, far_past]), s.layout,
                                              jnp.zeros(3, jnp.int32)),
                               [0.2 + w * 0.2 + k * 0.5, 0.2 + k * 0.3, 0.2 + w * 0.2 + k * 0.7], rtol=1e-5)
    goals = envs.make("obstacles")
    sg = jax.jit(goals.reset)(jax.random.PRNGKey(0))
    p = sg.layout.waypoints[:, 0] + jnp.array([0.0, 0.0, 0.7])
    np.testing.assert_allclose(goals._to_go(p, sg.layout, jnp.zeros(4, jnp.int32)), 0.7, rtol=1e-5)


def test_staggered_track_start_holds_each_drone_until_its_release_time():
    env = envs.make("race", num_agents=3, num_obstacles=0, start_interval=0.1, policy_freq=50, randomize=OFF,
                    command_accel_limit=0.0)  # the climb command at once, not ramped
    s = jax.jit(env.reset)(jax.random.PRNGKey(0))
    step = jax.jit(env.step)
    start = np.asarray(s.layout.start_pos)
    cmd = jnp.tile(jnp.array([0.0, 0.0, 1.0]), (3, 1))
    for _ in range(6):  # 0.12 s: drone 0 released at 0, drone 1 at 0.1 s, drone 2 at 0.2 s
        s = step(s, cmd)
        assert float(s.reward[2]) == 0.0 and float(s.cost[2]) == 0.0
    z = np.asarray(s.data.qpos.reshape(3, 7)[:, 2]) - start[:, 2]
    assert z[0] > 0.005 and 0.0 < z[1] < z[0] / 5 and abs(z[2]) < 1e-3, z  # the controller lags the command


def _layouts(env, episodes: int = 512):
    return jax.jit(jax.vmap(lambda k: env.reset(k).layout))(jax.random.split(jax.random.PRNGKey(3), episodes))


def _narrowest_static_gaps(env, lay) -> np.ndarray:
    c, static = np.asarray(lay.cyl_center), np.asarray(lay.cyl_present & (lay.cyl_amplitude == 0))
    gap = np.linalg.norm(c[:, :, None] - c[:, None], axis=-1) - 2 * env.config.obstacle_radius
    pair = static[:, :, None] & static[:, None] & ~np.eye(c.shape[1], dtype=bool)
    return np.where(pair, gap, np.inf).min(axis=(1, 2))


def test_layouts_leave_every_gap_between_cylinders_wide_enough_for_the_filter():
    for name in ("obstacles", "race", "lab"):
        one, many = envs.make(name, layout_draws=1), envs.make(name)
        lay_one, lay_many = _layouts(one), _layouts(many)
        loose, kept = _narrowest_static_gaps(one, lay_one), _narrowest_static_gaps(many, lay_many)
        assert np.all(kept >= many.config.min_obstacle_gap), name
        # Draw 0 is the layout a single draw gives: where it keeps the rule, it is the one used.
        fine = loose >= many.config.min_obstacle_gap
        same = np.all(np.asarray(lay_one.cyl_center) == np.asarray(lay_many.cyl_center), axis=(1, 2))
        np.testing.assert_array_equal(same, fine, err_msg=name)
        if name == "obstacles":  # without the rule the grid often left gaps the filter (0.32 m) cannot pass
            assert np.mean(loose < 0.32) > 0.1


def test_max_moving_fixes_how_many_of_the_slots_move():
    def moving_counts(**overrides):
        env = envs.make("dynamic", **overrides)
        lay = _layouts(env)
        return np.sum(np.asarray(lay.cyl_present & (lay.cyl_amplitude > 0)), axis=1)

    assert set(moving_counts().tolist()) == {1, 2, 3}  # the preset: 1 to 3 of its 3 slots
    for k in (1, 2, 3):
        np.testing.assert_array_equal(moving_counts(min_moving=k, max_moving=k), k)


def test_moving_speed_scale_draws_each_moving_cylinders_speed():
    base = _layouts(envs.make("dynamic"))
    fast = _layouts(envs.make("dynamic", moving_speed_scale=(1.0, 1.5)))
    omega0 = 2 * np.pi / 4.0  # the default period, 4 s
    np.testing.assert_allclose(np.asarray(base.cyl_omega), omega0, rtol=1e-6)  # (1, 1): one speed, as always
    w = np.asarray(fast.cyl_omega) / omega0
    assert w.min() >= 1.0 - 1e-6 and w.max() <= 1.5 + 1e-6 and np.std(w) > 0.05  # spread over the range
    # Only the speeds differ: the same cylinders, where they were, at the same phases.
    np.testing.assert_array_equal(np.asarray(base.cyl_center), np.asarray(fast.cyl_center))
    np.testing.assert_array_equal(np.asarray(base.cyl_phase), np.asarray(fast.cyl_phase))
    with pytest.raises(ValueError, match=r"invalid moving_speed_scale=\(1.5, 1.0\): allowed: LOW,HIGH"):
        envs.make("dynamic", moving_speed_scale=(1.5, 1.0))


def test_reaching_the_goal_finishes_with_success_metrics():
    env = envs.make("hover", layout_jitter=0.0)
    s = jax.jit(env.reset)(jax.random.PRNGKey(0))
    step = jax.jit(env.step)
    while not bool(s.done):
        s = step(s, jnp.clip(-2.0 * s.obs[:, :3], -1.0, 1.0))  # fly at the goal
    m = {k: float(v) for k, v in s.metrics.items()}
    assert m["success"] == 1.0 and m["collision"] == 0.0 and m["progress"] == 1.0
    assert 0 < m["mission_time"] < env.config.episode_seconds
    assert m["mean_speed"] > 0.1
    assert float(s.truncated) == 0.0


@pytest.mark.parametrize("n", [1, 16])
def test_number_of_drones_is_configurable(n):
    env = envs.make("race", num_agents=n)
    s = jax.jit(env.step)(jax.jit(env.reset)(jax.random.PRNGKey(0)), jnp.zeros((n, 3)))
    chex.assert_shape(s.obs, (n, env.observation_size))
    assert not bool(s.done)


def test_paper_reward_is_inverse_distance(race):
    # Every drone flying from the first step; observations without motion-capture noise.
    env = envs.make("race", reward="paper", start_interval=0.0, randomize=OFF)
    s = jax.jit(env.step)(jax.jit(env.reset)(jax.random.PRNGKey(0)), jnp.zeros((4, 3)))
    d = jnp.linalg.norm(s.obs[:, :3], axis=-1)
    np.testing.assert_allclose(s.reward, 1 / (d + 0.001), rtol=1e-4)


def test_command_rate_penalty_charges_the_change_of_command():
    # The same steps with and without the penalty: rewards differ by w ||u_t - u_(t-1)||^2 per drone (the
    # command before the first step is 0), and nothing else changes.
    cmds = jnp.array([[[1.0, 0.0, 0.5]], [[-1.0, 0.5, 0.5]]])
    rewards = {}
    for w in (0.0, 0.3):
        env = envs.make("hover", command_rate_penalty=w, randomize=OFF, command_accel_limit=0.0)
        step, s = jax.jit(env.step), jax.jit(env.reset)(jax.random.PRNGKey(0))
        rewards[w] = []
        for u in cmds:
            s = step(s, u)
            rewards[w].append(float(s.reward[0]))
    np.testing.assert_allclose(np.subtract(rewards[0.0], rewards[0.3]), [0.3 * 1.25, 0.3 * 4.25], rtol=1e-4)


def test_command_accel_limit_ramps_the_command_the_drone_receives():
    # 5 m/s² at 25 Hz: the received command moves at most 0.2 m/s per axis per step from the last one (0 before
    # the first step); a command within reach arrives as it is.
    env = envs.make("hover", command_accel_limit=5.0, randomize=OFF)
    step, s = jax.jit(env.step), jax.jit(env.reset)(jax.random.PRNGKey(0))
    got = []
    for u in ([2.0, -2.0, 0.1], [2.0, -2.0, 0.1], [0.0, 0.0, 0.0], [0.3, -0.3, 0.05]):
        s = step(s, jnp.array([u]))
        got.append(np.asarray(s.onboard.commands[0, 0]))
    np.testing.assert_allclose(got, [[0.2, -0.2, 0.1], [0.4, -0.4, 0.1], [0.2, -0.2, 0.0], [0.3, -0.3, 0.05]],
                               atol=1e-6)
    # The numpy side (the flight runtime's) gives the same numbers.
    np.testing.assert_allclose(limit_change(np.array([2.0, -2.0, 0.1]), np.array([0.2, -0.2, 0.1]), 0.2),
                               got[1], atol=1e-7)
    off = envs.make("hover", randomize=OFF, command_accel_limit=0.0)
    s = jax.jit(off.step)(jax.jit(off.reset)(jax.random.PRNGKey(0)), jnp.array([[2.0, -2.0, 0.1]]))
    np.testing.assert_array_equal(s.onboard.commands[0, 0], np.float32([2.0, -2.0, 0.1]))


def test_cost_rises_inside_the_safety_margin():
    env = envs.make("obstacles", num_agents=1, num_obstacles=1, layout_jitter=0.0, randomize=OFF)
    s = jax.jit(env.reset)(jax.random.PRNGKey(0))
    p = s.layout.start_pos[0]
    gap = 0.05  # inside the 0.15 m margin, outside collision
    x = p[0] + gap + env.config.obstacle_radius + env.config.cf.collision_radius
    s = s.replace(layout=s.layout.replace(cyl_center=jnp.array([[x, p[1]]])))
    s = jax.jit(env.step)(s, jnp.zeros((1, 3)))
    assert 0.5 < float(s.cost[0]) < 0.8 and not bool(s.tracker.collided[0])


@pytest.mark.parametrize("direction", [-1.0, 1.0])
def test_moving_cost_horizon_counts_where_the_cylinder_will_be(direction):
    # One cylinder 0.9 m (surface gap) ahead of the hovering drone along x, sweeping along x with amplitude 0.8 m
    # and omega = pi /s from phase 0: its centre at time t is x0 + direction * 0.8 sin(pi t). Coming at the drone
    # (direction -1) it turns back 0.1 m off at t = 0.5 s, inside the 0.5 s horizon after the first step (t = 0.04)
    # and inside the 0.15 m margin, so the cost is (0.15 - gap) / 0.15, where now (0.8 m) and 0.2 s ahead
    # (0.9 - 0.8 sin(0.24 pi) = 0.35 m) it is 0. Going away (direction +1) nothing is inside the margin.
    costs = {}
    for horizon in (0.0, 0.2, 0.5):
        env = envs.make("obstacles", num_agents=1, num_obstacles=1, layout_jitter=0.0, randomize=OFF,
                        moving_cost_horizon=horizon)
        s = jax.jit(env.reset)(jax.random.PRNGKey(0))
        reach = env.config.obstacle_radius + env.config.cf.collision_radius
        x0 = s.layout.start_pos[0, 0] + 0.9 + reach
        s = s.replace(layout=s.layout.replace(
            cyl_center=jnp.array([[x0, s.layout.start_pos[0, 1]]]), cyl_axis=jnp.array([[direction, 0.0]]),
            cyl_amplitude=jnp.array([0.8]), cyl_omega=jnp.array([math.pi]), cyl_phase=jnp.array([0.0])))
        s = jax.jit(env.step)(s, jnp.zeros((1, 3)))
        costs[horizon] = float(s.cost[0])
        t, pos = float(s.data.time), np.asarray(s.data.qpos[:2], np.float64)
    assert not bool(s.tracker.collided[0])
    assert abs(t - 0.04) < 1e-6
    gap = math.hypot(x0 - 0.8 - pos[0], float(s.layout.start_pos[0, 1]) - pos[1]) - reach  # at the turn
    if direction < 0:
        assert 0.09 < gap < 0.11  # the drone hovers (it moved under 1 cm)
        np.testing.assert_allclose(costs[0.5], (0.15 - gap) / 0.15, atol=2e-3)
    else:
        assert costs[0.5] == 0.0
    assert costs[0.0] == 0.0 and costs[0.2] == 0.0


# --------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "name,overrides,message",
    [
        ("nowhere", {}, r"unknown scenario 'nowhere': allowed: hover, obstacles, race"),
        ("race", {"num_agents": 0}, r"invalid num_agents=0: must be between 1 and 64"),
        ("race", {"num_agents": -3}, r"invalid num_agents=-3"),
        ("race", {"num_obstacles": 40}, r"cannot place num_obstacles \+ num_moving = 40 cylinders .* at most 13 fit"),
        ("race", {"max_speed": math.nan}, r"invalid max_speed=nan: must be a finite number"),
        ("race", {"policy_freq": 60}, r"invalid policy_freq=60: must divide ctrl_freq=100"),
        ("race", {"sim_freq": 100, "ctrl_freq": 50, "controller": "geometric"},
         r"invalid sim_freq=100: must be >= 240"),
        ("race", {"warp_drive": 1}, r"unknown env config field 'warp_drive'"),
        ("race", {"reward": "money"}, r"invalid reward='money': allowed: shaped, paper"),
        ("obstacles", {"layout_draws": 0}, r"invalid layout_draws=0: must be >= 1"),
        ("obstacles", {"min_obstacle_gap": -0.1}, r"invalid min_obstacle_gap=-0.1: must be >= 0"),
        ("race", {"command_rate_penalty": -0.5}, r"invalid command_rate_penalty=-0.5: must be >= 0"),
        ("race", {"command_accel_limit": -3.0}, r"invalid command_accel_limit=-3.0: must be >= 0"),
        ("dynamic", {"moving_cost_horizon": -0.5}, r"invalid moving_cost_horizon=-0.5: must be >= 0"),
        ("dynamic", {"max_moving": 4},
         r"invalid max_moving=4: allowed: -1 \(num_moving\) or min_moving=1 to num_moving=3"),
        ("dynamic", {"min_moving": 2, "max_moving": 1},
         r"invalid max_moving=1: allowed: -1 \(num_moving\) or min_moving=2"),
    ],
)
def test_bad_config_is_a_clear_error(name, overrides, message):
    with pytest.raises(ValueError, match=message):
        envs.make(name, **overrides)


def test_bad_actions_are_clear_errors(race):
    s = jax.jit(race.reset)(jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match=r"action has shape \(4,\): allowed shape is \(4, 3\)"):
        race.step(s, jnp.zeros(4))
    with pytest.raises(ValueError, match=r"action has shape \(4, 2\)"):
        jax.jit(race.step)(s, jnp.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"action contains NaN or Inf"):
        race.step(s, jnp.full((4, 3), jnp.nan))
    # Inside jit a NaN cannot raise: it becomes a hover command, never a NaN state.
    out = jax.jit(race.step)(s, jnp.full((4, 3), jnp.nan))
    assert np.isfinite(np.asarray(out.obs)).all()


def test_scene_model_holds_obstacles_and_gates_as_mocap_bodies():
    import mujoco

    from aswarm.envs import scene

    cfg = envs.make("race").config
    m = scene.build_model(cfg.num_agents, cfg.sim_freq, cfg.cf, physics_only=False,
                          num_cylinders=cfg.num_cylinders, num_gates=cfg.num_gates)
    assert m.nmocap == cfg.num_cylinders + cfg.num_gates
    physics = scene.build_model(cfg.num_agents, cfg.sim_freq, cfg.cf, physics_only=True)
    assert physics.nmocap == 0 and physics.nv == m.nv == 6 * cfg.num_agents
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    assert np.isfinite(d.xpos).all()


@pytest.mark.parametrize("n", [16, 32, 64])
def test_crossing_swarms_start_apart_inside_the_arena_in_lines_of_at_most_16(n):
    env = envs.make("obstacles", num_agents=n, max_neighbours=3, layout_jitter=0.0)
    lay = jax.jit(env.reset)(jax.random.PRNGKey(0)).layout
    start, goal = np.asarray(lay.start_pos), np.asarray(lay.waypoints)[:, 0]
    lo, hi = np.array(env.config.arena_low), np.array(env.config.arena_high)
    for p in (start, goal):
        gap = np.linalg.norm(p[:, None] - p[None], axis=-1) + np.eye(n) * 9
        assert gap.min() == pytest.approx(5.0 / 15, abs=1e-5)  # 16 lanes over 5 m of the 7 m wide arena
        assert np.all(p[:, :2] >= lo[:2] + 0.4 - 1e-5) and np.all(p[:, :2] <= hi[:2] - 0.4 + 1e-5)
    # Jittered the most (0.2 m), a goal still lies outside the filter's wall barrier (drone radius + default margin).
    assert np.all(goal[:, 0] + 0.2 <= hi[0] - (env.config.cf.collision_radius + SafetyFilterConfig().margin))
    lines = sorted(set(np.round(start[:, 0], 4)))
    assert len(lines) == n // 16  # 32: lines at x = -4 and -4.5; 64: -4, -4.367, -4.733, -5.1 (1.1 m of room)
    assert lines[-1] == pytest.approx(-4.0) and (n < 64 or lines[0] == pytest.approx(-5.1))
    # Mirrored: every drone crosses the same 8 m (plus its line's depth on both sides).
    np.testing.assert_allclose(goal[:, 0] + start[:, 0], 0.0, atol=1e-5)


def test_layout_digest_changes_with_the_layouts_and_only_with_them(monkeypatch):
    """What the safety matrix's cache keys on: session 28's move of the crossing's back line (CROSSING_WALL_GAP)
    changes the 64-drone crossing's digest and leaves the 16-drone one's, whose lines did not move."""
    from aswarm.envs import scenarios
    from aswarm.envs.registry import preset

    small, large = (dataclasses.replace(preset("obstacles"), num_agents=n, max_neighbours=3) for n in (16, 64))
    before = [scenarios.layout_digest(c, 0, count=2) for c in (small, large)]
    assert before[0] == scenarios.layout_digest(small, 0, count=2)
    assert before[0] != scenarios.layout_digest(small, 1, count=2)
    monkeypatch.setattr(scenarios, "CROSSING_WALL_GAP", 0.3)
    after = [scenarios.layout_digest(c, 0, count=2) for c in (small, large)]
    assert after[0] == before[0] and after[1] != before[1]


def test_the_filters_observation_adds_nearest_neighbours_after_the_policys_own():
    """``filter_neighbours``: the safety filter's observation (``State.filter_obs``) holds the K_f nearest drones,
    through the same motion-capture noise and delay, and begins with the policy's observation, which is the one the
    env gives without the field (so a policy flies as it was trained)."""
    from aswarm.core.layout import neighbour_slots, observed_neighbours

    # (drones, max_neighbours, filter_neighbours) -> (policy's rows, filter's rows)
    assert neighbour_slots(4, 0, 8) == (3, 3)  # every other drone observed: nothing to add
    assert neighbour_slots(32, 3, 8) == (3, 8)
    assert neighbour_slots(6, 3, 8) == (3, 5)  # at most every other drone
    assert neighbour_slots(16, 3, 2) == (3, 3) and neighbour_slots(16, 3, 0) == (3, 3)
    # what simulator and flight runtime ask observe() for: 0 keeps every other drone in index order
    assert [observed_neighbours(*a) for a in ((4, 0, 8), (32, 3, 8), (6, 3, 8), (16, 3, 2))] == [0, 8, 5, 3]
    kw = dict(num_agents=6, max_neighbours=2, randomize=dataclasses.replace(
        envs.EnvConfig().randomize, mocap_noise=(0.005, 0.005), mocap_delay=(1, 1)))
    wide, narrow = envs.make("obstacles", filter_neighbours=4, **kw), envs.make("obstacles", filter_neighbours=0, **kw)
    assert (wide.filter_layout.num_neighbours, narrow.filter_layout.num_neighbours) == (4, 2)
    cmd = jnp.tile(jnp.array([[1.0, 0.3, 0.2]]), (6, 1))
    states = []
    for env in (wide, narrow):
        s = jax.jit(env.reset)(jax.random.PRNGKey(5))
        states.append((s, jax.jit(env.step)(s, cmd)))
    for sw, sn in zip(*states):
        np.testing.assert_array_equal(sw.obs, sn.obs)
        np.testing.assert_array_equal(sw.critic_obs, sn.critic_obs)
        f = np.asarray(sw.filter_obs)
        assert f.shape == (6, wide.filter_layout.size) and sn.filter_obs is None
        np.testing.assert_array_equal(f[:, :wide.observation_size], sw.obs)
        nbr = wide.filter_layout.split(f)[2]  # [n, 4, 7]: the 4 nearest, nearest first
        dist = np.linalg.norm(nbr[..., :3], axis=-1)
        assert np.all(nbr[..., 6] == 1) and np.all(np.diff(dist, axis=-1) >= 0)
    with pytest.raises(ValueError, match=r"invalid filter_neighbours=-1: must be >= 0"):
        envs.make("obstacles", filter_neighbours=-1)

"""Environment parameters as data: one compiled program for many values, equal to envs built with them."""

import dataclasses
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from aswarm import envs
from aswarm.envs import params as env_params
from aswarm.envs.params import EnvParams
from aswarm.envs.wrappers import AutoResetWrapper

STEPS = 8
# 5 steps an episode: the 8-step rollout crosses an auto-reset, which must keep each world's params. The
# command steps at once (no acceleration limit), so a changed drone flies measurably differently in 5 steps.
BASE = dict(num_agents=2, episode_seconds=0.2, command_accel_limit=0.0)


def _config(**changes):
    """The hover preset with nested changes ``cf.mass=...``, ``gains.kp_vel_xy=...``, ``max_speed=...``."""
    cfg = envs.registry.preset("hover", **BASE)
    for key, value in changes.items():
        group, _, name = key.rpartition(".")
        if group:
            value = dataclasses.replace(getattr(cfg, group), **{name: value})
            name = group
        cfg = dataclasses.replace(cfg, **{name: value})
    return cfg


# World 0 the defaults, then a heavier drone, a lighter drone with softer velocity gains and a lower speed limit.
WORLDS = [{}, {"cf.mass": 0.034}, {"cf.mass": 0.022, "gains.kp_vel_xy": 2.5, "max_speed": 1.2}]


def _rollout(env):
    """jit(vmap) of reset(key, params) + STEPS auto-resetting steps under a fixed command: [B, T, n*7] qpos and
    [B, T] mass of the state (the defaults' where params is None)."""
    wenv = AutoResetWrapper(env)
    action = jnp.array([[1.5, -0.5, 0.8], [-0.7, 1.0, -0.3]])

    def one(key, params):
        s = wenv.reset(key, params)

        def body(s, _):
            s = wenv.step(s, action)
            return s, (s.data.qpos, env.params(s.params).cf.mass)

        return jax.lax.scan(body, s, None, length=STEPS)[1]

    return jax.jit(jax.vmap(one))


@pytest.fixture(scope="module")
def swept():
    env = envs.SwarmEnv(_config())
    batch = env_params.stack([EnvParams.from_config(_config(**w)) for w in WORLDS])
    keys = jnp.stack([jax.random.PRNGKey(5)] * len(WORLDS))
    qpos, mass = _rollout(env)(keys, batch)
    return env, keys, batch, np.asarray(qpos), np.asarray(mass)


def test_one_program_vmapped_over_params_matches_an_env_per_config(swept):
    env, keys, batch, qpos, mass = swept
    # Each world keeps its own params through the auto-reset.
    np.testing.assert_array_equal(mass, np.broadcast_to(np.asarray(batch.cf.mass)[:, None], mass.shape))
    for i, j in itertools.combinations(range(len(WORLDS)), 2):  # no world flies another's params
        assert np.abs(qpos[i] - qpos[j]).max() > 1e-3, f"worlds {i} and {j} flew alike: {WORLDS[i]}, {WORLDS[j]}"
    # The last world, which changes every kind of field, against its config's own program (each such program is a
    # compile of its own: world 1, a mass alone, is covered by its mass above and by its own flight).
    ref = np.asarray(_rollout(envs.SwarmEnv(_config(**WORLDS[-1])))(keys[:1], None)[0])[0]
    np.testing.assert_allclose(qpos[-1], ref, rtol=0, atol=1e-5, err_msg=f"world {len(WORLDS) - 1}: {WORLDS[-1]}")


def test_default_params_are_the_configs_and_reset_without_params_uses_them(swept):
    env, keys, _, qpos, _ = swept
    cfg, p = env.config, env.default_params
    assert np.float32(cfg.cf.max_rpm) == p.cf.max_rpm and np.float32(cfg.cf.mass) == p.cf.mass
    assert p.gains.max_accel_xy == np.float32(cfg.cf.gravity * np.tan(np.deg2rad(cfg.gains.max_tilt_deg)))
    assert p.time_penalty_per_step == np.float32(cfg.time_penalty * cfg.dt)
    assert np.array_equal(p.cf.mixer, cfg.cf.mixer())
    # reset(key) keeps None in the state: step reads the defaults as constants, as before params were data
    # (bit for bit: tools' golden check); the same values as data fly the same to float32 rounding.
    implicit = _rollout(env)(keys[:1], None)[0]
    np.testing.assert_allclose(qpos[0], np.asarray(implicit)[0], rtol=0, atol=1e-5)
    assert jax.eval_shape(env.reset, keys[0]).params is None
    # VmapWrapper: one params for every world, or one per world.
    wenv = envs.VmapWrapper(env)
    np.testing.assert_array_equal(jax.jit(wenv.reset)(keys, p).params.cf.mass, np.full(len(WORLDS), p.cf.mass))


def test_moving_obstacles_take_the_params_motion():
    cfg = envs.registry.preset("dynamic", num_moving=1, min_moving=1)
    env = envs.SwarmEnv(cfg)
    other = dataclasses.replace(cfg, moving_amplitude=0.5, moving_period=2.0)
    lay = jax.jit(jax.vmap(env.reset))(jnp.stack([jax.random.PRNGKey(1)] * 2),
                              env_params.stack([env.default_params, EnvParams.from_config(other)])).layout
    moving = ~(np.arange(cfg.num_cylinders) < cfg.num_obstacles)
    np.testing.assert_allclose(lay.cyl_amplitude[:, moving], [[0.8], [0.5]])
    np.testing.assert_allclose(lay.cyl_omega[:, moving], [[2 * np.pi / 4.0], [2 * np.pi / 2.0]], rtol=1e-6)
    assert np.all(np.asarray(lay.cyl_amplitude)[:, ~moving] == 0)


def test_params_of_a_wrong_structure_or_shape_fail_clearly(swept):
    env = swept[0]
    key = jax.random.PRNGKey(0)
    with pytest.raises(ValueError, match=r"invalid params of type dict: allowed: EnvParams"):
        env.reset(key, {"mass": 0.03})
    p = env.default_params
    with pytest.raises(ValueError, match=r"invalid params.cf.inertia of shape \(2,\): allowed shape \(3,\)"):
        env.reset(key, p.replace(cf=p.cf.replace(inertia=jnp.ones(2))))
    moon = dataclasses.replace(env.config, cf=dataclasses.replace(env.config.cf, gravity=1.62))
    with pytest.raises(ValueError, match=r"invalid params of type EnvParams: allowed: .*cf.gravity"):
        env.reset(key, EnvParams.from_config(moon))

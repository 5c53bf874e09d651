"""Episode metrics on hand-built situations, and how evaluation aggregates them into a report."""

import csv
import json
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from aswarm import envs
from aswarm.analysis import evaluate
from aswarm.envs import collisions as col
from aswarm.envs.dynamics import DroneState, set_drone_state

N = 3
# Drones 1 and 2 hover out of the way: 3 m apart, over 2 m from the test area round the origin,
# 3 m from the nearest gate of the nominal track (no jitter).
PARKED = [(-2.0, 1.5, 1.0), (-2.0, -1.5, 1.0)]


@pytest.fixture(scope="module")
def env():
    return envs.make("race", num_agents=N, layout_jitter=0.0)


@pytest.fixture(scope="module")
def step(env):
    return jax.jit(env.step)


@pytest.fixture(scope="module")
def base(env):
    """The reset state with every cylinder removed."""
    s = jax.jit(env.reset)(jax.random.PRNGKey(0))
    return s.replace(layout=s.layout.replace(cyl_present=jnp.zeros_like(s.layout.cyl_present)))


def place(state, pos, vel=None):
    """``state`` with the drones at rest (or at ``vel``) at ``pos`` [n, 3], level."""
    pos = jnp.asarray(pos, jnp.float32)
    vel = jnp.zeros_like(pos) if vel is None else jnp.asarray(vel, jnp.float32)
    drones = DroneState(pos=pos, quat=jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (len(pos), 1)), vel=vel,
                        ang_vel=jnp.zeros_like(pos))
    return state.replace(data=set_drone_state(state.data, drones))


def with_cylinder(state, centre, radius=0.15):
    lay = state.layout
    return state.replace(layout=lay.replace(
        cyl_center=lay.cyl_center.at[0].set(jnp.asarray(centre, jnp.float32)),
        cyl_radius=lay.cyl_radius.at[0].set(radius), cyl_amplitude=lay.cyl_amplitude.at[0].set(0.0),
        cyl_present=lay.cyl_present.at[0].set(True)))


def fly(step, state, cmd, steps):
    cmd = jnp.asarray(cmd, jnp.float32)
    for _ in range(steps):
        state = step(state, cmd)
        if float(state.done):
            break
    return state


def cmd_for(drone0):
    return [drone0] + [(0.0, 0.0, 0.0)] * (N - 1)


def test_known_collision_with_an_obstacle(env, step, base):
    r = env.config.cf.collision_radius
    gap = 0.01
    s = with_cylinder(base, (0.0, 0.0), radius=0.15)
    s = place(s, [(-(0.15 + r + gap), 0.0, 1.0), *PARKED], vel=[(1.5, 0, 0), (0, 0, 0), (0, 0, 0)])
    s = fly(step, s, cmd_for((2.0, 0.0, 0.0)), 1)  # 1.5 m/s for 20 ms covers the 1 cm gap
    m = {k: float(v) for k, v in s.metrics.items()}
    assert float(s.done) == 1.0 and float(s.truncated) == 0.0
    assert m["collision"] == 1.0 and m["collision_obstacle"] == 1.0
    assert m["collision_drone"] == m["collision_gate"] == m["collision_floor"] == m["collision_bounds"] == 0.0
    assert m["drone_collision"] == pytest.approx(1 / N)
    assert m["success"] == 0.0 and m["min_clearance"] < 0.0
    assert int(s.tracker.collision_kind[0]) == col.OBSTACLE
    assert float(s.reward[0]) == -env.config.collision_penalty and float(s.cost[0]) == 1.0


def test_known_collisions_between_drones_and_with_the_floor(env, step, base):
    r = env.config.cf.collision_radius
    # Drones 0 and 1 head-on, 1 cm apart: both collide, one episode-level drone collision.
    s = place(base, [(0.0, 0.0, 1.0), (2 * r + 0.01, 0.0, 1.0), PARKED[1]],
              vel=[(1.0, 0, 0), (-1.0, 0, 0), (0, 0, 0)])
    s = fly(step, s, [(1.0, 0, 0), (-1.0, 0, 0), (0, 0, 0)], 1)
    m = {k: float(v) for k, v in s.metrics.items()}
    assert m["collision_drone"] == 1.0 and m["collision_obstacle"] == 0.0 and m["collision_floor"] == 0.0
    assert m["drone_collision"] == pytest.approx(2 / N)
    # Drone 0 just above the floor, falling.
    s = place(base, [(0.0, 0.0, r + 0.005), *PARKED], vel=[(0, 0, -1.0), (0, 0, 0), (0, 0, 0)])
    s = fly(step, s, cmd_for((0.0, 0.0, -2.0)), 1)
    m = {k: float(v) for k, v in s.metrics.items()}
    assert m["collision_floor"] == 1.0 and m["collision_drone"] == 0.0
    assert m["drone_collision"] == pytest.approx(1 / N)


def _gate_at_origin(state):
    """Gate 0 moved to the origin at 1 m, passage along +x (its bars at y = +-0.325)."""
    lay = state.layout
    gate_pos = lay.gate_pos.at[0].set(jnp.array([0.0, 0.0, 1.0]))
    return state.replace(layout=lay.replace(gate_pos=gate_pos, gate_yaw=lay.gate_yaw.at[0].set(0.0),
                                            waypoints=jnp.broadcast_to(gate_pos, lay.waypoints.shape)))


@pytest.mark.parametrize("lateral,passed", [(0.0, True), (1.0, False)])
def test_known_gate_pass_and_miss(env, step, base, lateral, passed):
    s = place(_gate_at_origin(base), [(-0.5, lateral, 1.0), *PARKED], vel=[(1.0, 0, 0), (0, 0, 0), (0, 0, 0)])
    s = fly(step, s, cmd_for((1.0, 0.0, 0.0)), 50)  # 1 s: crosses the gate plane at x = 0 either way
    assert float(s.metrics["collision"]) == 0.0
    assert float(s.data.qpos[0]) > 0.3  # drone 0 really went past the plane
    target = np.asarray(s.tracker.target)
    if passed:
        assert target.tolist() == [1, 0, 0]
        assert float(s.metrics["progress"]) == pytest.approx(1 / env.num_waypoints / N)
    else:
        assert target.tolist() == [0, 0, 0]
        assert float(s.metrics["progress"]) == 0.0


def test_known_clearance(env, step, base):
    """Flying along y = 0 past a cylinder at (0, 0.5): the closest gap is 0.5 - radius - drone radius."""
    r = env.config.cf.collision_radius
    s = with_cylinder(base, (0.0, 0.5), radius=0.15)
    s = place(s, [(-1.0, 0.0, 1.0), *PARKED], vel=[(1.0, 0, 0), (0, 0, 0), (0, 0, 0)])
    s = fly(step, s, cmd_for((1.0, 0.0, 0.0)), 100)
    assert float(s.metrics["collision"]) == 0.0
    assert float(s.data.qpos[0]) > 0.5
    assert float(s.metrics["min_clearance"]) == pytest.approx(0.5 - 0.15 - r, abs=1e-3)


def test_known_separation(env, step, base):
    """Hovering at x = 0, 1, 3 m: nearest neighbours 1, 1, 2 m, so the mean separation is 4/3 m."""
    s = place(base, [(0.0, 0.0, 1.0), (1.0, 0.0, 1.0), (3.0, 0.0, 1.0)])
    s = fly(step, s, np.zeros((N, 3)), 20)
    assert float(s.metrics["collision"]) == 0.0 and int(s.tracker.steps) == 20
    assert float(s.metrics["mean_separation"]) == pytest.approx(4 / 3, abs=1e-3)


# ------------------------------------------------------------------ aggregation


def _rec(success, collision, **extra):
    n = len(success)
    rec = {k: np.zeros(n) for k in ("drone_success", "drone_collision", "progress", "min_clearance",
                                    "mean_separation", "mission_time", "mean_speed", "episode_return")}
    rec.update({f"collision_{k}": np.zeros(n) for k in evaluate.COLLISION_KINDS})
    rec.update(success=np.asarray(success, float), collision=np.asarray(collision, float))
    rec.update({k: np.asarray(v, float) for k, v in extra.items()})
    return rec


def test_wilson_matches_hand_computed_intervals():
    # 8 of 10: p = 0.8, z = 1.96: centre = (0.8 + 0.19208) / 1.38416, half = 1.96 sqrt(0.0169604) / 1.38416.
    lo, hi = evaluate.wilson(8, 10)
    assert lo == pytest.approx(0.49016, abs=1e-5) and hi == pytest.approx(0.94332, abs=1e-5)
    # 0 of 20: the upper bound is z^2 / (n + z^2).
    assert evaluate.wilson(0, 20) == pytest.approx((0.0, 1.96**2 / (20 + 1.96**2)))
    assert evaluate.wilson(20, 20)[1] == 1.0
    assert all(math.isnan(x) for x in evaluate.wilson(0, 0))


def test_summarize_hand_made_episodes():
    rec = _rec(success=[1, 1, 1, 1, 1, 1, 1, 1, 0, 0], collision=[0] * 8 + [1, 1],
               collision_obstacle=[0] * 8 + [1, 0], collision_drone=[0] * 8 + [1, 1],
               drone_collision=[0] * 8 + [0.25, 0.5], mission_time=[10, 12, 14, 16, 10, 12, 14, 16, 3, 40],
               min_clearance=[0.5] * 8 + [-0.1, -0.02], mean_separation=np.arange(10), progress=[1] * 8 + [0.5, 0])
    out = evaluate.summarize(rec, intervention_rate=0.25)
    assert out["success_rate"] == 0.8 and out["success_ci95"] == pytest.approx((0.49016, 0.94332), abs=1e-5)
    assert out["collision_rate"] == 0.2 and out["collision_ci95"] == pytest.approx(evaluate.wilson(2, 10))
    assert out["collision_obstacle_rate"] == 0.1 and out["collision_drone_rate"] == 0.2
    assert out["collision_gate_rate"] == out["collision_floor_rate"] == out["collision_bounds_rate"] == 0.0
    assert out["collision_gate_ci95"] == pytest.approx(evaluate.wilson(0, 10))
    assert out["drone_collision_rate"] == pytest.approx(0.075)
    assert out["mission_time"] == 13.0 and out["successful_episodes"] == 8  # successes only, not 14.7
    assert out["min_clearance"] == pytest.approx(0.3880) and out["min_clearance_worst"] == -0.1
    assert out["mean_separation"] == 4.5 and out["progress"] == pytest.approx(0.85)
    assert out["filter_intervention_rate"] == 0.25
    none = evaluate.summarize(_rec(success=[0, 0], collision=[1, 0]))
    assert none["mission_time"] is None and none["success_ci95"] == pytest.approx(evaluate.wilson(0, 2))
    with pytest.raises(ValueError, match="invalid episodes=0"):
        evaluate.summarize(_rec(success=[], collision=[]))


def _report():
    out = {"checkpoint": "runs/x", "method": "attention_cbf", "scenario": "race", "episodes": 10, "seed": 3,
           "trained_updates": 7, "env_overrides": ["num_agents=4"], "episodes_ended": 10}
    out.update(evaluate.summarize(_rec(success=[1] * 8 + [0, 0], collision=[0] * 9 + [1],
                                       mission_time=[12.0] * 10)))
    return out


def test_report_files_json_and_csv(tmp_path):
    result = _report()
    json_path, csv_path = evaluate.write_report(result, tmp_path / "out")
    assert json_path.name == "eval_race.json" and csv_path.name == "eval_race.csv"
    back = json.loads(json_path.read_text())
    assert back["success_rate"] == 0.8 and back["collision_rate"] == 0.1 and back["episodes"] == 10
    rows = list(csv.DictReader(csv_path.open()))
    assert len(rows) == 1
    row = rows[0]
    assert float(row["success_rate"]) == 0.8 and float(row["success_ci95_lo"]) == pytest.approx(0.49016, abs=1e-5)
    assert float(row["collision_obstacle_rate"]) == 0.0 and float(row["mission_time"]) == 12.0
    assert json.loads(row["env_overrides"]) == ["num_agents=4"]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["eval_race.csv", "eval_race.json"]  # no temps
    assert evaluate.report_dir("pretrained") == evaluate.PRETRAINED_REPORT_DIR
    assert evaluate.report_dir("runs/r") == evaluate.Path("runs/r")
    assert evaluate.report_dir("runs/r", tmp_path) == tmp_path
    table = evaluate.format_table(result)
    assert "by obstacle" in table and "mean of the 8 successful episodes" in table


def test_cli_eval_writes_report_and_keeps_stdout_json(tmp_path, monkeypatch, capsys):
    from aswarm import cli

    monkeypatch.setattr(evaluate, "evaluate_checkpoint", lambda *a, **k: _report())
    assert cli.main(["eval", "--checkpoint", str(tmp_path), "--json", "--out", str(tmp_path / "o")]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["success_rate"] == 0.8
    assert "eval_race.json" in captured.err
    assert (tmp_path / "o" / "eval_race.csv").exists()
    assert cli.main(["eval", "--checkpoint", str(tmp_path)]) == 0  # default: into the run folder
    assert (tmp_path / "eval_race.json").exists() and "95% CI" in capsys.readouterr().out
    (tmp_path / "file").write_text("x")
    assert cli.main(["eval", "--checkpoint", str(tmp_path), "--out", str(tmp_path / "file")]) == 2
    err = capsys.readouterr().err.strip()
    assert "is a file; allowed: a folder" in err and len(err.splitlines()) == 1


class _Clock(NamedTuple):
    """A stand-in world for the evaluation loop: it ends at its drawn step ``end`` and then starts again."""

    t: jax.Array
    end: jax.Array
    obs: jax.Array
    filter_obs: None
    done: jax.Array
    metrics: dict


class _ClockEnv:
    num_agents = 2

    def __init__(self, max_steps: int):
        self.config = type("Config", (), {"max_steps": max_steps})()

    def reset(self, key):
        end = 2 + jax.random.randint(key, (), 0, 5)  # 2 to 6 steps
        return _Clock(jnp.zeros((), jnp.int32), end, jnp.zeros((2, 1)), None, jnp.zeros(()), self._metrics(0, end))

    def _metrics(self, t, end):
        return {"episode_length": jnp.asarray(t, jnp.float32), "drawn_end": jnp.asarray(end, jnp.float32)}

    def step(self, s, u):
        t = s.t + 1
        done = t == s.end
        return s._replace(t=jnp.where(done, 0, t), done=done.astype(jnp.float32), metrics=self._metrics(t, s.end))

    def cylinder_accel(self, s):
        return None

    def applied_command(self, s):
        return None


class _HoverAgent:
    def policy(self, params, obs_norm, obs, key):
        return jnp.zeros(obs.shape[:-1] + (3,)), None, None

    def filter_commands(self, params, obs_norm, obs, cmd, *rest):
        z = jnp.zeros(cmd.shape[:-1])
        return type("Filtered", (), {"u": cmd, "intervened": z, "slack": z, "escaped": z})()


def test_an_evaluation_batch_stops_when_its_last_episode_ends():
    # Worlds end after 2 to 6 steps on a 20-step clock: the batch stops at the latest end, each episode recorded at
    # its own; a batch of one world stops at its own end.
    env, lines = _ClockEnv(20), []
    rec, ended, stats = evaluate.rollout_with_filter_stats(_HoverAgent(), None, None, env, 6, jax.random.PRNGKey(0),
                                                           progress=lines.append)
    drawn = np.asarray(rec["drawn_end"])
    assert np.asarray(ended).all() and drawn.min() >= 2 and drawn.max() <= 6 and len(set(drawn)) > 1
    np.testing.assert_array_equal(rec["episode_length"], drawn)
    assert lines[-1] == f"episodes 1-6 of 6: all ended by step {int(drawn.max())} of 20"
    assert float(stats.infeasible_rate) == 0.0
    lines.clear()
    rec, _, _ = evaluate.rollout_with_filter_stats(_HoverAgent(), None, None, env, 3, jax.random.PRNGKey(0), batch=1,
                                                   progress=lines.append)
    assert [line for line in lines if "all ended" in line] == [
        f"episodes {i + 1}-{i + 1} of 3: all ended by step {int(e)} of 20" for i, e in enumerate(rec["drawn_end"])]

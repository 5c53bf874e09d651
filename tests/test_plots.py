"""Figures and the video from a short episode of an untrained policy; the plot and render commands."""

import dataclasses
import struct
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.training.acme import running_statistics
from drones import GEOMETRIC

from aswarm import cli
from aswarm.agents.config import TrainConfig
from aswarm.agents.train import Agent
from aswarm.analysis import plots, render
from aswarm.training import checkpoint, runner

# 50 policy steps with 2 drones and 3 cylinders: a third less to compile than the full race.
# Exact observations: the recording is checked against the true poses.
SHORT = GEOMETRIC + (("episode_seconds", 1.0), ("num_agents", 2), ("num_obstacles", 3))


def png_size(path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", head[16:24])


@pytest.fixture(scope="module")
def policy():
    agent = Agent.build(TrainConfig(scenario="race", env_overrides=SHORT))
    params = jax.jit(agent.init_params)(jax.random.PRNGKey(0))
    obs_norm = running_statistics.init_state(jax.ShapeDtypeStruct((agent.env.observation_size,), jnp.float32))
    return agent, params, obs_norm


@pytest.fixture(scope="module")
def episode(policy):
    return plots.record_episode(*policy, jax.random.PRNGKey(1))


def test_recorded_episode_is_consistent(policy, episode):
    agent = policy[0]
    n, m = agent.env.num_agents, agent.env.obs_layout.num_cylinders
    t = len(episode.time)
    assert 2 <= t <= agent.env.config.max_steps + 1
    assert episode.pos.shape == (t, n, 3) and episode.quat.shape == (t, n, 4)
    assert episode.attention.shape == (t, n, m + n - 1) and episode.clearance.shape == (t, n, m)
    assert episode.nbr_gap.shape == episode.nbr_index.shape == (t, n, n - 1) and episode.cyl_pos.shape == (t, m, 2)
    # All neighbours in index order: drone i's rows are the other drones, while they fly.
    others = np.array([[j for j in range(n) if j != i] for i in range(n)])
    seen = episode.nbr_index >= 0
    assert seen[0].all() and np.all(np.where(seen, episode.nbr_index, others[None]) == others[None])
    gap0 = np.linalg.norm(episode.pos[0, others] - episode.pos[0, :, None], axis=-1) - 2 * episode.drone_radius
    np.testing.assert_allclose(episode.nbr_gap[0], gap0, atol=1e-5)
    assert np.all(np.diff(episode.time) > 0)
    np.testing.assert_allclose(episode.attention.sum(-1), 1.0, atol=1e-5)  # every hazard is present here
    np.testing.assert_allclose(episode.pos[0], np.asarray(episode.layout.start_pos), atol=1e-6)
    assert episode.metrics["episode_length"] == t - 1


def test_track_coordinate_follows_the_current_segment():
    start = np.array([0.0, 0.0, 1.0])
    gates = np.array([[2.0, 0.0, 1.0], [2.0, 3.0, 1.0]])
    pos = np.array([[-1.0, 0.5, 1], [1.0, 0.3, 1], [2.5, 0.0, 1], [2.1, 1.0, 1], [2.0, 9.0, 1]])
    target = np.array([0, 0, 0, 1, 1])
    # Behind the start is negative; past a gate while still heading for it stops at the gate.
    np.testing.assert_allclose(plots.track_coordinate(pos, target, start, gates), [-1.0, 1.0, 2.0, 3.0, 5.0])


def test_trajectory_and_attention_figures(tmp_path, episode):
    traj = plots.plot_trajectories(episode, tmp_path / "traj.png", dpi=50)
    assert png_size(traj) == (18 * 50, 6 * 50) and traj.stat().st_size > 10_000
    flat = plots.plot_trajectories(episode, tmp_path / "flat.png", three_d=False, dpi=50)
    assert png_size(flat) == (12 * 50, 6 * 50)
    attn = plots.plot_attention(episode, tmp_path / "attn.png", drone=1, dpi=50)
    assert png_size(attn) == (10 * 50, int(6.5 * 50)) and attn.stat().st_size > 5_000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["attn.png", "flat.png", "traj.png"]  # no temps left
    with pytest.raises(ValueError, match="has no attention network"):
        plots.plot_attention(dataclasses.replace(episode, attention=None, method="mappo"), tmp_path / "a.png")
    with pytest.raises(ValueError, match="invalid drone=9: allowed: 0 to 1"):
        plots.plot_attention(episode, tmp_path / "a.png", drone=9)
    with pytest.raises(ValueError, match=r"allowed file types: \.png, \.pdf, \.svg"):
        plots.plot_trajectories(episode, tmp_path / "traj.jpg")


def test_render_gives_an_mp4_by_default_or_a_clear_message(tmp_path, policy, episode):
    try:
        path, fmt, backend = render.render_episode(episode, policy[0].env.config, tmp_path / "ep.mp4", fps=10,
                                                   width=96, height=72)
    except render.RenderUnavailable as e:
        assert len(str(e).splitlines()) == 1 and "MUJOCO_GL=egl" in str(e)
        return
    # imageio-ffmpeg is a dependency: the default output is an mp4 (an ISO media file: its first box is 'ftyp').
    assert backend in render.GL_BACKENDS and (path, fmt) == (tmp_path / "ep.mp4", "mp4")
    assert path.read_bytes()[4:8] == b"ftyp" and sorted(p.name for p in tmp_path.iterdir()) == ["ep.mp4"]
    import imageio_ffmpeg

    frames, _ = imageio_ffmpeg.count_frames_and_secs(str(path))
    stride = max(1, round(episode.policy_freq / 10))
    held = int(episode.policy_freq / stride)  # the last frame, held for a second
    assert frames == len(range(0, len(episode.time), stride)) + held
    assert cli.build_parser().parse_args(["render", "--checkpoint", "x"]).out.suffix == ".mp4"
    # A .gif when asked for one (Pillow, which Matplotlib depends on).
    path, fmt, _ = render.render_episode(episode, policy[0].env.config, tmp_path / "ep.gif", fps=10, width=96,
                                         height=72, backends=(backend,))
    from PIL import Image

    assert fmt == "gif"
    with Image.open(path) as im:
        # Pillow merges identical consecutive frames (the held ending), so at most as many as the mp4.
        assert im.size == (96, 72) and 2 <= im.n_frames <= frames


def test_render_without_a_gl_backend_is_a_one_line_error(tmp_path, policy, episode):
    with pytest.raises(render.RenderUnavailable, match=r"^no OpenGL context .*MUJOCO_GL=bogus") as e:
        render.render_episode(episode, policy[0].env.config, tmp_path / "ep.gif", fps=10, width=32, height=32,
                              backends=("bogus",))
    assert len(str(e.value).splitlines()) == 1
    with pytest.raises(ValueError, match="invalid fps=0"):
        render.render_episode(episode, policy[0].env.config, tmp_path / "ep.gif", fps=0)


def test_video_format_fallbacks_and_png_frames(tmp_path):
    assert render.choose_output("a/race.mp4", True, True) == (render.Path("a/race.mp4"), "mp4")
    assert render.choose_output("race.mp4", False, True) == (render.Path("race.gif"), "gif")
    assert render.choose_output("race.mp4", False, False) == (render.Path("race_frames"), "png")
    with pytest.raises(ValueError, match=r"invalid --out 'race.avi': allowed file types: \.mp4, \.gif"):
        render.choose_output("race.avi", True, True)
    frames = [np.full((4, 6, 3), v, np.uint8) for v in (0, 128)]
    render._encode(iter(frames), tmp_path / "f", "png", 10.0)
    from PIL import Image

    with Image.open(tmp_path / "f" / "frame_00001.png") as im:
        assert im.size == (6, 4) and np.asarray(im)[0, 0].tolist() == [128, 128, 128]


class _Policy(NamedTuple):
    params: dict
    obs_norm: object
    update: jax.Array


def _fake_run(tmp_path, method: str):
    """A run folder holding an (untrained, constant) policy, as `aswarm train` leaves one."""
    config = TrainConfig(scenario="race", method=method, env_overrides=SHORT)
    agent = Agent.build(config)
    run = tmp_path / method
    run.mkdir()
    runner.write_config(run, config)
    obs_norm = running_statistics.init_state(jax.ShapeDtypeStruct((agent.env.observation_size,), jnp.float32))
    params = jax.tree.map(lambda x: np.full(x.shape, 0.01, x.dtype), jax.eval_shape(agent.init_params,
                                                                                 jax.random.PRNGKey(0)))
    checkpoint.save(checkpoint.manager(run), 1, _Policy(params, obs_norm, jnp.ones((), jnp.int32)))
    return run


def test_cli_plot_errors_are_one_line_with_exit_code_2(tmp_path, capsys):
    for argv in (["plot", "--checkpoint", str(tmp_path / "missing"), "--out", str(tmp_path / "t.png")],
                 ["plot", "--checkpoint", str(tmp_path), "--out", str(tmp_path / "t.jpg")],
                 ["render", "--checkpoint", str(tmp_path), "--out", str(tmp_path / "v.avi")],
                 ["render", "--checkpoint", str(tmp_path), "--width", "4000"]):
        assert cli.main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"aswarm {argv[0]}: error: ") and len(err.splitlines()) == 1, err
    run = _fake_run(tmp_path, "mappo")
    assert cli.main(["plot", "--checkpoint", str(run), "--attention", "--out", str(tmp_path / "a.png")]) == 2
    assert "has no attention network" in capsys.readouterr().err
    assert cli.main(["plot", "--checkpoint", str(run), "--episode-index", "-1"]) == 2
    assert "invalid --episode-index -1" in capsys.readouterr().err


def test_cli_plot_draws_an_episode(tmp_path, capsys, monkeypatch, episode):
    run = _fake_run(tmp_path, "attention_cbf")
    calls = []

    def record(agent, params, obs_norm, key):  # the recording itself is tested above; this saves a compile
        calls.append((agent.config.method, agent.env.config.episode_seconds, np.asarray(key)))
        return episode

    monkeypatch.setattr(plots, "record_episode", record)
    out = tmp_path / "attn.png"
    argv = ["plot", "--checkpoint", str(run), "--seed", "7", "--episode-index", "2", "--out"]
    assert cli.main([*argv, str(out), "--attention", "--drone", "1"]) == 0
    assert capsys.readouterr().out.strip() == f"wrote {out}" and png_size(out) == (1000, 650)
    assert cli.main([*argv, str(tmp_path / "traj.png"), "--no-3d"]) == 0
    assert png_size(tmp_path / "traj.png") == (1200, 600)
    # render: a video, or (no GL backend here) the one-line error with a non-zero exit code.
    argv = ["render", "--checkpoint", str(run), "--fps", "5", "--width", "64", "--height", "48", "--out"]
    code = cli.main([*argv, str(tmp_path / "v.mp4")])
    out, err = capsys.readouterr()
    assert (code == 0 and "wrote " in out and "MUJOCO_GL=" in out) or (code == 1 and len(err.splitlines()) == 1)
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    monkeypatch.setattr(render, "GL_BACKENDS", ("bogus",))
    assert cli.main([*argv, str(tmp_path / "w.gif")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("aswarm render: error: no OpenGL context") and len(err.splitlines()) == 1
    method, seconds, key = calls[0]
    assert method == "attention_cbf" and seconds == 1.0  # the run's own env overrides
    # Episode 2 of `aswarm eval --seed 7`.
    np.testing.assert_array_equal(key, np.asarray(jax.random.split(jax.random.PRNGKey(7), 10)[2]))


def test_cli_plot_curves_draws_runs_on_the_same_axes(tmp_path, capsys):
    import json

    runs = []
    for name, rate in (("a", 0.01), ("b", 0.03)):  # two runs learning at different rates
        run = tmp_path / name
        run.mkdir()
        rows = [{"update": u, "env_steps": 2048 * u, "episode/success": min(1.0, rate * u),
                 "episode/episode_return": 10 * rate * u, "train/explained_variance": 0.5} for u in range(1, 41)]
        (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
        runs.append(str(run))
    one, both = tmp_path / "one.png", tmp_path / "both.png"
    assert cli.main(["plot", "--curves", runs[0], "--out", str(one)]) == 0
    assert cli.main(["plot", "--curves", *runs, "--out", str(both)]) == 0
    assert capsys.readouterr().out.split() == ["wrote", str(one), "wrote", str(both)]
    assert png_size(both) == (1430, 715) and both.read_bytes() != one.read_bytes()
    assert cli.main(["plot", "--curves", runs[0], str(tmp_path), "--out", str(both)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"aswarm plot: error: invalid --curves {tmp_path}: no metrics.jsonl there; allowed: run folders"


@pytest.mark.parametrize("drones", [2, 16])
def test_a_swarms_legend_goes_below_the_views(drones):
    from matplotlib.figure import Figure

    fig = Figure(layout="constrained")
    ax = fig.add_subplot()
    for i in range(drones):
        ax.plot([0, 1], [i, i], label=f"drone {i}")
    plots.place_legend(fig, ax, drones)
    inside = drones <= plots.LEGEND_INSIDE_DRONES
    assert (ax.get_legend() is not None) == inside
    assert len(fig.legends) == (0 if inside else 1)
    if not inside:
        assert [t.get_text() for t in fig.legends[0].get_texts()] == [f"drone {i}" for i in range(drones)]

"""A video of one recorded episode with MuJoCo's offscreen renderer.

MuJoCo picks its OpenGL backend from ``MUJOCO_GL`` once, when ``mujoco`` is first imported, and the
recording has imported it long before. So the frames are drawn in a child process (``python -m
aswarm.analysis.render``, which imports numpy and mujoco only) started with ``MUJOCO_GL=egl``, then ``osmesa``
(or only the backend the user set): the first that gives a context draws the video. Where none does,
:class:`RenderUnavailable` says so in one line.

The parent builds the full scene model (drones, cylinders and gates as mocap bodies, ``scene.py``) and
hands the child the MJCF and, per frame, the drones' ``qpos``, the mocap poses and a camera. The child
encodes an mp4 with imageio-ffmpeg (a dependency of aswarm, with its own ffmpeg binary: the default), or a GIF
with Pillow when asked for one or when imageio-ffmpeg cannot be imported, else it writes PNG frames, and renames
the result into place when complete.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import zlib
from pathlib import Path

import numpy as np

GL_BACKENDS = ("egl", "osmesa")
CAMERAS = ("follow", "overview")
NO_CONTEXT = 3  # the child's exit code when no OpenGL context can be made
MAX_SIZE = (1280, 720)  # the scene's offscreen buffer (scene.py <visual><global offwidth/offheight>)


class RenderUnavailable(RuntimeError):
    """No OpenGL context for offscreen rendering on this machine."""


def _importable(name: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(name) is not None


def choose_output(out: str | Path, have_ffmpeg: bool, have_pillow: bool) -> tuple[Path, str]:
    """(path, format) actually written for a requested ``out``: format is "mp4", "gif" or "png".

    An mp4 (the default) needs imageio-ffmpeg, which aswarm depends on; where it cannot be imported a GIF is
    written beside (same stem) with Pillow, and without Pillow a folder ``<stem>_frames`` of PNG files. A
    requested ``.gif`` needs Pillow the same way.
    """
    out = Path(out)
    suffix = out.suffix.lower()
    if suffix not in (".mp4", ".gif"):
        raise ValueError(f"invalid --out {str(out)!r}: allowed file types: .mp4, .gif")
    if suffix == ".mp4" and have_ffmpeg:
        return out, "mp4"
    if have_pillow:
        return out.with_suffix(".gif"), "gif"
    return out.with_name(out.stem + "_frames"), "png"


def camera_track(pos: np.ndarray, flying: np.ndarray, dt: float, camera: str, arena_low, arena_high,
                 start_heading: float = 0.0) -> dict:
    """Per-frame camera: lookat [F, 3], azimuth [F] (deg), distance and elevation, from positions [F, n, 3].

    "follow" trails the swarm: it looks at the mean of the drones still flying, from behind their mean
    velocity, both smoothed (0.5 s and 1.5 s) so the picture does not shake. "overview" shows the arena.
    """
    if camera not in CAMERAS:
        raise ValueError(f"invalid camera={camera!r}: allowed: {', '.join(CAMERAS)}")
    frames = len(pos)
    lo, hi = np.asarray(arena_low, float), np.asarray(arena_high, float)
    if camera == "overview":
        centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, 0.5])
        return dict(lookat=np.tile(centre, (frames, 1)), azimuth=np.full(frames, 90.0),
                    distance=1.15 * float(np.max(hi[:2] - lo[:2])), elevation=-55.0)
    weight = np.where(flying.any(1, keepdims=True), flying, True).astype(float)  # all drones once none flies
    centre = np.sum(pos * weight[..., None], 1) / np.sum(weight, 1)[:, None]
    look, heading = np.empty_like(centre), np.empty(frames)
    look[0], heading[0] = centre[0], start_heading
    a_pos, a_head = min(1.0, dt / 0.5), min(1.0, dt / 1.5)
    for f in range(1, frames):
        look[f] = look[f - 1] + a_pos * (centre[f] - look[f - 1])
        step = centre[f] - centre[f - 1]
        if np.linalg.norm(step[:2]) > 1e-3 * dt:
            want = np.arctan2(step[1], step[0])
            # Turn the short way round.
            delta = (want - heading[f - 1] + np.pi) % (2 * np.pi) - np.pi
            heading[f] = heading[f - 1] + a_head * delta
        else:
            heading[f] = heading[f - 1]
    return dict(lookat=look, azimuth=np.degrees(heading), distance=3.5, elevation=-30.0)


def check_options(fps: int, width: int, height: int, camera: str, policy_freq: int | None = None) -> None:
    """Raise ValueError for video options that cannot work (before anything is recorded)."""
    if fps < 1 or (policy_freq is not None and fps > policy_freq):
        rate = f" ({policy_freq} Hz)" if policy_freq else ""
        raise ValueError(f"invalid fps={fps}: allowed: 1 to the policy rate{rate}")
    if not (16 <= width <= MAX_SIZE[0] and 16 <= height <= MAX_SIZE[1]):
        raise ValueError(f"invalid size {width}x{height}: allowed: 16x16 to {MAX_SIZE[0]}x{MAX_SIZE[1]}")
    if camera not in CAMERAS:
        raise ValueError(f"invalid camera={camera!r}: allowed: {', '.join(CAMERAS)}")


def frame_spec(ep, env_config, *, fps: int, width: int, height: int, camera: str) -> dict:
    """Everything the child needs to draw ``ep`` (a plots.Episode): MJCF, per-frame qpos, mocap poses, camera."""
    import mujoco

    from aswarm.envs import scene

    check_options(fps, width, height, camera, ep.policy_freq)
    cfg = env_config
    n, m, g = ep.num_agents, ep.num_cylinders, len(ep.layout.gate_pos)
    half = max(abs(v) for v in (*cfg.arena_low[:2], *cfg.arena_high[:2])) + 2.0
    xml = scene.build_xml(n, cfg.sim_freq, cfg.cf, physics_only=False, num_cylinders=m, num_gates=g,
                          gate_half_opening=cfg.gate_half_opening, gate_bar=cfg.gate_bar, arena_half_extent=half)
    model = mujoco.MjModel.from_xml_string(xml)
    stride = max(1, round(ep.policy_freq / fps))
    # Every stride-th record, then the last one held for a second so the ending can be seen.
    idx = np.arange(0, len(ep.time), stride)
    idx = np.concatenate([idx, np.full(int(ep.policy_freq / stride), len(ep.time) - 1)])
    frames = len(idx)
    qpos = np.concatenate([ep.pos[idx], ep.quat[idx]], -1).reshape(frames, -1)

    lay = ep.layout
    mocap_pos = np.zeros((frames, model.nmocap, 3))
    mocap_quat = np.tile([1.0, 0.0, 0.0, 0.0], (frames, model.nmocap, 1))
    geom_size, geom_pos, geom_rgba = model.geom_size.copy(), model.geom_pos.copy(), model.geom_rgba.copy()
    for j in range(m):
        mid = model.body(f"cylinder{j}").mocapid[0]
        gid = model.geom(f"cylinder{j}").id
        # The scene's unit cylinder is resized to this episode's radius and height; absent ones sink.
        geom_size[gid, :2] = lay.cyl_radius[j], lay.cyl_height[j] / 2
        geom_pos[gid, 2] = lay.cyl_height[j] / 2
        z = 0.0 if lay.cyl_present[j] else -lay.cyl_height[j] - 10.0
        mocap_pos[:, mid] = np.concatenate([ep.cyl_pos[idx, j], np.full((frames, 1), z)], -1)
    for k in range(g):
        mid = model.body(f"gate{k}").mocapid[0]
        yaw = lay.gate_yaw[k]
        mocap_pos[:, mid] = lay.gate_pos[k]
        mocap_quat[:, mid] = [np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]
    from matplotlib import colormaps

    cmap = colormaps["tab10"]
    for i in range(n):
        geom_rgba[model.geom(f"drone{i}").id] = cmap(i % 10)
    # Start behind the swarm, facing its first gate or goal.
    ahead = lay.waypoints[:, 0].mean(0) - ep.pos[0].mean(0)
    heading = float(np.arctan2(ahead[1], ahead[0]))
    cam = camera_track(ep.pos[idx], ep.flying[idx], stride / ep.policy_freq, camera, cfg.arena_low,
                       cfg.arena_high, start_heading=heading)
    return dict(xml=np.array(xml), qpos=qpos, mocap_pos=mocap_pos, mocap_quat=mocap_quat, geom_size=geom_size,
                geom_pos=geom_pos, geom_rgba=geom_rgba, lookat=cam["lookat"], azimuth=cam["azimuth"],
                distance=np.array(cam["distance"]), elevation=np.array(cam["elevation"]),
                fps=np.array(ep.policy_freq / stride), width=np.array(width), height=np.array(height))


def render_episode(ep, env_config, out: str | Path = "episode.mp4", *, fps: int = 25, width: int = 640,
                   height: int = 480, camera: str = "follow", backends: tuple[str, ...] | None = None,
                   timeout_s: float = 600.0) -> tuple[Path, str, str]:
    """Render ``ep`` to a video; returns (path written, format "mp4"/"gif"/"png", MUJOCO_GL backend).

    Raises :class:`RenderUnavailable` where no backend gives an OpenGL context.
    """
    check_options(fps, width, height, camera, ep.policy_freq)
    target, fmt = choose_output(out, _importable("imageio_ffmpeg"), _importable("PIL"))
    spec = frame_spec(ep, env_config, fps=fps, width=width, height=height, camera=camera)
    if backends is None:
        user = os.environ.get("MUJOCO_GL", "").strip().lower()
        backends = (user,) if user else GL_BACKENDS
    target.parent.mkdir(parents=True, exist_ok=True)
    failures = []
    with tempfile.TemporaryDirectory(prefix="aswarm-render-") as tmp:
        spec_path = Path(tmp) / "frames.npz"
        np.savez(spec_path, **spec)
        for backend in backends:
            env = {**os.environ, "MUJOCO_GL": backend, "PYOPENGL_PLATFORM": backend}
            if backend not in ("egl", "osmesa"):
                env.pop("PYOPENGL_PLATFORM")
            proc = subprocess.run([sys.executable, "-m", "aswarm.analysis.render", str(spec_path), str(target), fmt],
                                  env=env, capture_output=True, text=True, timeout=timeout_s)
            if proc.returncode == 0:
                return target, fmt, backend
            reason = (proc.stderr.strip().splitlines() or [f"exit code {proc.returncode}"])[-1]
            # A broken driver may crash instead of refusing a context: that backend failed, try the next.
            failures.append((proc.returncode, f"MUJOCO_GL={backend}: {reason}"))
    tried = "; ".join(text for _, text in failures)
    if all(code == NO_CONTEXT for code, _ in failures):
        raise RenderUnavailable(f"no OpenGL context for offscreen rendering ({tried}): install EGL or OSMesa, "
                                "or draw the episode with `aswarm plot` instead")
    raise RuntimeError(f"rendering failed ({tried})")


# ------------------------------------------------------------------ the child process
def _png_bytes(rgb: np.ndarray) -> bytes:
    """A PNG file of an [H, W, 3] uint8 image (no dependency beyond zlib)."""
    import struct

    h, w, _ = rgb.shape
    raw = b"".join(b"\x00" + rgb[y].tobytes() for y in range(h))  # filter type 0 on every row

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))


def _encode(frames, target: Path, fmt: str, fps: float) -> None:
    """Write the frames (an iterator of [H, W, 3] uint8) to a temporary name, then rename it to ``target``."""
    tmp = target.with_name(f".{target.stem}.{os.getpid()}.tmp{target.suffix}")
    if fmt == "mp4":
        import imageio_ffmpeg

        writer = None
        for rgb in frames:
            if writer is None:
                writer = imageio_ffmpeg.write_frames(str(tmp), (rgb.shape[1], rgb.shape[0]), fps=fps,
                                                     macro_block_size=1, quality=7)
                writer.send(None)
            writer.send(np.ascontiguousarray(rgb))
        writer.close()
    elif fmt == "gif":
        from PIL import Image

        # GIF stores every frame; a 256-colour palette each keeps a 40 s episode to tens of MB.
        images = [Image.fromarray(rgb).quantize(colors=256, method=Image.Quantize.MEDIANCUT) for rgb in frames]
        images[0].save(tmp, save_all=True, append_images=images[1:], duration=int(round(1000 / fps)), loop=0)
    else:
        tmp.mkdir(parents=True)
        for f, rgb in enumerate(frames):
            (tmp / f"frame_{f:05d}.png").write_bytes(_png_bytes(rgb))
        if target.exists():
            shutil.rmtree(target)
    os.replace(tmp, target)


def _child_main(argv: list[str]) -> int:
    spec_path, target, fmt = argv
    spec = dict(np.load(spec_path))
    width, height = int(spec["width"]), int(spec["height"])
    try:
        import mujoco

        model = mujoco.MjModel.from_xml_string(str(spec["xml"]))
        renderer = mujoco.Renderer(model, height, width)
    except Exception as e:  # any backend failure means the same thing here: no context
        print(f"{type(e).__name__}: {str(e).strip().splitlines()[0] if str(e).strip() else 'no context'}",
              file=sys.stderr)
        return NO_CONTEXT
    model.geom_size[:] = spec["geom_size"]
    model.geom_pos[:] = spec["geom_pos"]
    model.geom_rgba[:] = spec["geom_rgba"]
    data = mujoco.MjData(model)
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.distance, cam.elevation = float(spec["distance"]), float(spec["elevation"])

    def frames():
        for f in range(len(spec["qpos"])):
            data.qpos[:] = spec["qpos"][f]
            data.mocap_pos[:] = spec["mocap_pos"][f]
            data.mocap_quat[:] = spec["mocap_quat"][f]
            mujoco.mj_forward(model, data)
            cam.lookat[:] = spec["lookat"][f]
            cam.azimuth = float(spec["azimuth"][f])
            renderer.update_scene(data, camera=cam)
            yield renderer.render()

    _encode(frames(), Path(target), fmt, float(spec["fps"]))
    renderer.close()
    return 0


if __name__ == "__main__":
    sys.exit(_child_main(sys.argv[1:]))

"""Figures of one recorded episode: trajectories (the paper's Fig. 5/6) and attention over time.

:func:`record_episode` runs the deterministic, filtered policy for one episode inside ``jit`` and
returns an :class:`Episode` of host arrays; the plotting functions are pure functions of that data,
so tests draw them from an untrained policy. Matplotlib is used without pyplot (``Figure`` and the
Agg canvas), so importing this module changes no global backend.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from aswarm.core import geometry as geo
from aswarm.core.layout import NBR
from aswarm.envs import collisions as col
from aswarm.envs.dynamics import drone_state
from aswarm.envs.presets import SCENARIOS
from aswarm.envs.scenarios import Layout, cylinders_at

FORMATS = (".png", ".pdf", ".svg")
CLEARANCE_CAP = 6.0  # m: the attention figure's distance axis stops here, so near misses stay readable


@dataclasses.dataclass(frozen=True)
class Episode:
    """One recorded episode as host numpy arrays; T instants: the reset state and each step up to the end."""

    method: str
    scenario: str
    kind: str  # "track", "crossing" or "hover" (scenarios.SCENARIOS)
    time: np.ndarray  # [T] s
    pos: np.ndarray  # [T, n, 3] m, world
    quat: np.ndarray  # [T, n, 4] [w, x, y, z]
    flying: np.ndarray  # [T, n] bool: neither finished nor collided
    target: np.ndarray  # [T, n] index of the current gate or goal
    cyl_pos: np.ndarray  # [T, M, 2] cylinder centres
    clearance: np.ndarray  # [T, n, M] m, surface gap drone-cylinder; NaN for absent cylinders
    nbr_gap: np.ndarray  # [T, n, K] m, surface gap to each observed neighbour, in observation order; NaN if absent
    nbr_index: np.ndarray  # [T, n, K] which drone each observed neighbour is; -1 if absent
    attention: np.ndarray | None  # [T, n, M + K] weights (cylinders, then neighbours); None without
    layout: Layout  # numpy leaves
    finished: np.ndarray  # [n] bool at the end
    collided: np.ndarray  # [n] bool at the end
    collision_kind: tuple[str, ...]  # [n] collisions.KINDS name ("none" without a collision)
    metrics: dict  # the episode's SwarmEnv metrics, floats
    gate_half_opening: float
    gate_bar: float
    drone_radius: float
    arena_low: tuple[float, float, float]
    arena_high: tuple[float, float, float]
    policy_freq: int

    @property
    def num_agents(self) -> int:
        return self.pos.shape[1]

    @property
    def num_cylinders(self) -> int:
        return self.cyl_pos.shape[1]

    def last_index(self, drone: int) -> int:
        """Index of the drone's last instant worth drawing: where it finished or collided, else the end."""
        stopped = np.flatnonzero(~self.flying[:, drone])
        return int(stopped[0]) if len(stopped) else len(self.time) - 1


def observed_neighbours(env, pos: jax.Array, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(surface gap [n, K], drone index [n, K]) of each drone's observed neighbour rows; NaN and -1 where absent.

    Read from the observation, so it holds for every neighbour mode (all in index order, or the K nearest)."""
    r = env.config.cf.collision_radius
    nbr = env.obs_layout.split(obs)[2]  # [n, K, 7]
    present = NBR.present(nbr)
    rel = NBR.get(nbr, "rel_pos")
    gap = jnp.where(present, jnp.linalg.norm(rel, axis=-1) - 2 * r, jnp.nan)
    # The neighbour is the drone at the observed offset (to float round-off): the nearest one to that point.
    seen = pos[:, None] + rel  # [n, K, 3]
    index = jnp.argmin(jnp.linalg.norm(seen[:, :, None] - pos[None, None], axis=-1), axis=-1)
    return gap, jnp.where(present, index, -1)


def record_episode(agent, params, obs_norm, key: jax.Array, env=None) -> Episode:
    """Fly one episode (layout from ``key``) with the deterministic, filtered policy, as ``aswarm eval`` does.

    ``env`` defaults to ``agent.env``. The state is frozen once ``done``, so the last record is the end.
    """
    env = env or agent.env
    cfg = env.config
    n, r = env.num_agents, cfg.cf.collision_radius
    with_attention = agent.config.uses_attention

    def snapshot(s, params, obs_norm):
        ds = drone_state(s.data, n)
        cyl, _ = cylinders_at(s.layout, s.data.time)
        lay = s.layout
        clear = geo.cylinder_clearance(ds.pos, cyl, lay.cyl_radius, lay.cyl_height, lay.cyl_present, r)
        gap, index = observed_neighbours(env, ds.pos, s.obs)
        att = agent.cbf_params(params, obs_norm, s.obs)[1] if with_attention else jnp.zeros(())
        tr = s.tracker
        return dict(time=s.data.time, pos=ds.pos, quat=ds.quat, flying=~(tr.finished | tr.collided),
                    target=tr.target, done=s.done, cyl_pos=cyl, clearance=clear, nbr_gap=gap, nbr_index=index,
                    attention=att)

    # params and obs_norm are arguments, not constants: one compiled program serves every checkpoint.
    def run(key, params, obs_norm):
        s0 = env.reset(key)

        def body(s, _):
            cmd, _, _ = agent.policy(params, obs_norm, s.obs, None)
            safe, _, _ = agent.safe_command(params, obs_norm, s.obs, cmd, env.cylinder_accel(s), s.filter_obs,
                                            env.applied_command(s))
            nxt = env.step(s, safe)
            # Once done the state stays put: the final carry is the state the episode ended in.
            s = jax.tree.map(lambda old, new: jnp.where(s.done > 0, old, new), s, nxt)
            return s, snapshot(s, params, obs_norm)

        final, rec = jax.lax.scan(body, s0, None, length=cfg.max_steps)
        first = snapshot(s0, params, obs_norm)
        rec = jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), first, rec)
        return rec, final.tracker, final.metrics, final.layout

    # Concrete, strongly typed leaves: a fresh and a restored policy then share one compiled program (a Python
    # float in a fresh running-statistics state would otherwise be weakly typed and compile a second one).
    params, obs_norm = jax.tree.map(lambda x: jnp.asarray(np.asarray(x)), (params, obs_norm))
    rec, tracker, metrics, layout = jax.device_get(jax.jit(run)(key, params, obs_norm))
    done = np.asarray(rec["done"]) > 0
    end = int(np.argmax(done)) if done.any() else len(done) - 1  # the reset state is never done
    rec = {k: np.asarray(v)[: end + 1] for k, v in rec.items()}
    clearance = np.where(np.asarray(layout.cyl_present)[None, None], rec["clearance"], np.nan)
    kinds = tuple(col.KINDS[int(k)] for k in np.asarray(tracker.collision_kind))
    return Episode(
        method=agent.config.method, scenario=cfg.scenario, kind=SCENARIOS[cfg.scenario].kind,
        time=rec["time"], pos=rec["pos"], quat=rec["quat"], flying=rec["flying"].astype(bool),
        target=rec["target"], cyl_pos=rec["cyl_pos"], clearance=clearance, nbr_gap=rec["nbr_gap"],
        nbr_index=rec["nbr_index"],
        attention=rec["attention"] if with_attention else None, layout=jax.tree.map(np.asarray, layout),
        finished=np.asarray(tracker.finished), collided=np.asarray(tracker.collided), collision_kind=kinds,
        metrics={k: float(v) for k, v in metrics.items()}, gate_half_opening=cfg.gate_half_opening,
        gate_bar=cfg.gate_bar, drone_radius=r, arena_low=tuple(cfg.arena_low), arena_high=tuple(cfg.arena_high),
        policy_freq=cfg.policy_freq,
    )


# ------------------------------------------------------------------ geometry helpers (pure numpy)
def track_coordinate(pos: np.ndarray, target: np.ndarray, start: np.ndarray, gate_pos: np.ndarray) -> np.ndarray:
    """[T] distance along the racing line (m) of positions [T, 3] whose current gate is ``target`` [T].

    The racing line is the polyline start -> gate 0 -> ... -> gate G-1 in the horizontal plane. A point
    heading for gate k is projected onto the segment that ends at gate k, so the coordinate follows the
    drone's own progress and does not jump between segments at a corner; before the start it is negative.
    """
    nodes = np.concatenate([np.asarray(start)[None, :2], np.asarray(gate_pos)[:, :2]], 0)  # [G + 1, 2]
    seg = np.diff(nodes, axis=0)  # [G, 2]
    length = np.linalg.norm(seg, axis=-1)
    cum = np.concatenate([[0.0], np.cumsum(length)])
    k = np.clip(np.asarray(target), 0, len(seg) - 1)
    t = np.sum((pos[:, :2] - nodes[k]) * seg[k], -1) / np.maximum(length[k] ** 2, 1e-12)
    t = np.where(k == 0, np.minimum(t, 1.0), np.clip(t, 0.0, 1.0))
    return cum[k] + t * length[k]


def _nearest_track_coordinate(xy: np.ndarray, start: np.ndarray, gate_pos: np.ndarray) -> np.ndarray:
    """[P] distance along the racing line of the nearest point to each of [P, 2] (for obstacles)."""
    g = len(gate_pos)
    pts = np.concatenate([np.asarray(xy), np.full((len(xy), 1), 0.0)], -1)
    cands = np.stack([track_coordinate(pts, np.full(len(xy), k), start, gate_pos) for k in range(g)], -1)
    nodes = np.concatenate([np.asarray(start)[None, :2], np.asarray(gate_pos)[:, :2]], 0)
    seg = np.diff(nodes, axis=0)
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(seg, axis=-1))])
    # The point of each segment at that coordinate, and its distance to the obstacle.
    frac = (cands - cum[:-1]) / np.maximum(np.linalg.norm(seg, axis=-1), 1e-12)
    on = nodes[:-1] + frac[..., None] * seg
    best = np.argmin(np.linalg.norm(on - np.asarray(xy)[:, None], axis=-1), -1)
    return cands[np.arange(len(xy)), best]


def _gate_lateral(yaw: np.ndarray) -> np.ndarray:
    return np.stack([-np.sin(yaw), np.cos(yaw)], -1)


def _colours(n: int) -> list:
    from matplotlib import colormaps

    cmap = colormaps["tab10" if n <= 10 else "turbo"]
    return [cmap(i if n <= 10 else i / max(n - 1, 1)) for i in range(n)]


def check_output(out: str | Path) -> Path:
    out = Path(out)
    if out.suffix.lower() not in FORMATS:
        raise ValueError(f"invalid --out {str(out)!r}: allowed file types: {', '.join(FORMATS)}")
    return out


def save_figure(fig, out: Path, dpi: float | None = None) -> Path:
    """Write ``fig`` to ``out`` (at ``dpi``, else the figure's) atomically."""
    out.parent.mkdir(parents=True, exist_ok=True)
    # Written beside the target and renamed, so a reader never sees half a figure.
    tmp = out.with_name(f".{out.stem}.{os.getpid()}.tmp{out.suffix}")
    fig.savefig(tmp, dpi=dpi or fig.dpi)
    os.replace(tmp, out)
    return out


# ------------------------------------------------------------------ trajectories
LEGEND_INSIDE_DRONES = 4  # more drones than this: the legend goes below the views


def place_legend(fig, ax, drones: int) -> None:
    """The drones' legend: in ``ax``'s corner for a few drones, below the figure for a swarm, whose legend inside
    would hide the crowd it labels (a race-16 jam sits under it at the first gate)."""
    if drones <= LEGEND_INSIDE_DRONES:
        ax.legend(fontsize=7, loc="upper right")
    else:
        fig.legend(*ax.get_legend_handles_labels(), fontsize=7, loc="outside lower center", ncol=min(drones, 8))


def plot_trajectories(ep: Episode, out: str | Path, *, three_d: bool = True, dpi: int = 100,
                      title: str | None = None) -> Path:
    """Write the trajectory figure: 3D view (optional), top view (x-y) and side view (along the track vs z).

    Each drone's path is cut where it finished (star), collided (cross) or the episode ended. Cylinders
    are circles of their radius; a moving one also shows its sweep (centre +- amplitude along its axis).
    Gates are bars across their opening with an arrow in the direction of passage.
    """
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle, Polygon

    out = check_output(out)
    n = ep.num_agents
    colours = _colours(n)
    lay = ep.layout
    present = np.flatnonzero(lay.cyl_present)
    fig = Figure(figsize=(18, 6) if three_d else (12, 6), dpi=dpi, layout="constrained")
    # The 3D view's labels stick out of its box, which the layout engine does not see: give it a wider cell.
    grid = fig.add_gridspec(1, 3, width_ratios=(1.3, 1, 1)) if three_d else fig.add_gridspec(1, 2)
    ax3 = fig.add_subplot(grid[0], projection="3d") if three_d else None
    top = fig.add_subplot(grid[-2])
    side = fig.add_subplot(grid[-1])
    lo, hi = np.asarray(ep.arena_low), np.asarray(ep.arena_high)
    c = ep.gate_half_opening + ep.gate_bar / 2
    is_track = ep.kind == "track" and len(lay.gate_pos) > 0
    start = lay.start_pos[0]

    # Top view.
    top.add_patch(Polygon([(lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1])], closed=True,
                          fill=False, ls="--", ec="0.6", lw=1))
    for j in present:
        centre, rad, amp = lay.cyl_center[j], lay.cyl_radius[j], lay.cyl_amplitude[j]
        if amp > 0:
            a, b = centre - amp * lay.cyl_axis[j], centre + amp * lay.cyl_axis[j]
            top.plot(*np.stack([a, b]).T, color="tab:orange", lw=2, alpha=0.6, solid_capstyle="round")
            for end in (a, b):
                top.add_patch(Circle(end, rad, fc="none", ec="tab:orange", ls=":", lw=1))
            top.add_patch(Circle(centre, rad, fc="tab:orange", alpha=0.35, ec="none"))
        else:
            top.add_patch(Circle(centre, rad, fc="tab:orange", alpha=0.8, ec="darkorange"))
        top.annotate(f"o{j}", centre, xytext=(4, 4), textcoords="offset points", fontsize=7, color="saddlebrown")
    for k in range(len(lay.gate_pos) if is_track else 0):
        g, lat = lay.gate_pos[k, :2], _gate_lateral(lay.gate_yaw[k])
        normal = np.array([np.cos(lay.gate_yaw[k]), np.sin(lay.gate_yaw[k])])
        top.plot(*np.stack([g - c * lat, g + c * lat]).T, color="forestgreen", lw=4, solid_capstyle="butt")
        top.annotate("", g + 0.5 * normal, g, arrowprops=dict(arrowstyle="->", color="forestgreen"))
        top.annotate(f"G{k + 1}", g + (c + 0.15) * lat, fontsize=8, color="forestgreen")
    if ep.kind != "track":
        goals = lay.waypoints[:, 0]
        for i in range(n):
            top.plot(*goals[i, :2], marker="P", ms=8, color=colours[i], mec="k", ls="none")

    # Side view: distance along the racing line for a track, else x.
    if is_track:
        for j in present:
            ends = lay.cyl_center[j][None] + np.array([[-1.0], [1.0]]) * lay.cyl_amplitude[j] * lay.cyl_axis[j]
            s = _nearest_track_coordinate(ends, start, lay.gate_pos)
            s_lo, s_hi = s.min() - lay.cyl_radius[j], s.max() + lay.cyl_radius[j]
            side.axvspan(s_lo, s_hi, ymax=min(1.0, lay.cyl_height[j] / hi[2]), color="tab:orange",
                         alpha=0.15 if lay.cyl_amplitude[j] > 0 else 0.3, lw=0)
            side.annotate(f"o{j}", ((s_lo + s_hi) / 2, 0.05 * hi[2]), fontsize=7, ha="center", color="saddlebrown")
        gate_s = track_coordinate(lay.gate_pos, np.arange(len(lay.gate_pos)), start, lay.gate_pos)
        for k, (s, z) in enumerate(zip(gate_s, lay.gate_pos[:, 2])):
            side.plot([s, s], [0, z - c], color="forestgreen", lw=2)  # the post
            side.plot([s, s], [z - c, z + c], color="forestgreen", lw=1, ls=":")  # the opening
            for zz in (z - c, z + c):
                side.plot([s - 0.15, s + 0.15], [zz, zz], color="forestgreen", lw=4, solid_capstyle="butt")
            side.annotate(f"G{k + 1}", (s, z + c + 0.08), fontsize=8, ha="center", color="forestgreen")
        side.set_xlabel("distance along the racing line (m)")
    else:
        for j in present:
            x, rad, amp = lay.cyl_center[j, 0], lay.cyl_radius[j], lay.cyl_amplitude[j] * abs(lay.cyl_axis[j, 0])
            side.axvspan(x - amp - rad, x + amp + rad, ymax=min(1.0, lay.cyl_height[j] / hi[2]), color="tab:orange",
                         alpha=0.15 if lay.cyl_amplitude[j] > 0 else 0.3, lw=0)
        for i in range(n):
            side.plot(*lay.waypoints[i, 0, [0, 2]], marker="P", ms=8, color=colours[i], mec="k", ls="none")
        side.set_xlim(lo[0] - 0.3, hi[0] + 0.3)
        side.set_xlabel("x (m)")

    # The paths.
    for i in range(n):
        last = ep.last_index(i)
        p = ep.pos[: last + 1, i]
        label = f"drone {i}"
        if ep.collided[i]:
            label += f" (hit {ep.collision_kind[i]})"
        elif ep.finished[i]:
            label += f" (finished {ep.time[last]:.1f} s)"
        end_marker = "X" if ep.collided[i] else ("*" if ep.finished[i] else None)
        s = track_coordinate(p, ep.target[: last + 1, i], start, lay.gate_pos) if is_track else p[:, 0]
        for ax, xs, ys in ((top, p[:, 0], p[:, 1]), (side, s, p[:, 2])):
            ax.plot(xs, ys, color=colours[i], lw=1.6, label=label if ax is top else None)
            ax.plot(xs[0], ys[0], marker="o", color=colours[i], ms=5)
            if end_marker:
                ax.plot(xs[-1], ys[-1], marker=end_marker, color=colours[i], ms=11, mec="k")
        if ax3 is not None:
            ax3.plot(p[:, 0], p[:, 1], p[:, 2], color=colours[i], lw=1.6)
            if end_marker:
                ax3.plot(*p[-1], marker=end_marker, color=colours[i], ms=9, mec="k")

    if ax3 is not None:
        _draw_3d_scene(ax3, ep, is_track)
        ax3.set_xlim(lo[0], hi[0])
        ax3.set_ylim(lo[1], hi[1])
        ax3.set_zlim(0, hi[2])
        ax3.set_box_aspect((hi[0] - lo[0], hi[1] - lo[1], hi[2] * 1.5))
        ax3.set_xlabel("x (m)")
        ax3.set_ylabel("y (m)")
        ax3.set_zlabel("z (m)")
        ax3.view_init(elev=35, azim=-60)
    top.set_xlim(lo[0] - 0.3, hi[0] + 0.3)
    top.set_ylim(lo[1] - 0.3, hi[1] + 0.3)
    top.set_aspect("equal")
    top.set_xlabel("x (m)")
    top.set_ylabel("y (m)")
    top.set_title("top view")
    place_legend(fig, top, n)
    side.set_ylim(0, hi[2])
    side.set_ylabel("z (m)")
    side.set_title("side view")
    m = ep.metrics
    outcome = "success" if m.get("success", 0) > 0.5 else ("collision" if m.get("collision", 0) > 0.5 else "time out")
    fig.suptitle(title or f"{ep.method} on {ep.scenario}: {outcome}, {ep.time[-1]:.1f} s, "
                          f"progress {m.get('progress', 0.0):.2f}")
    return save_figure(fig, out)


def _draw_3d_scene(ax, ep: Episode, is_track: bool) -> None:
    lay = ep.layout
    ring = np.linspace(0, 2 * np.pi, 24)
    for j in np.flatnonzero(lay.cyl_present):
        x = lay.cyl_center[j, 0] + lay.cyl_radius[j] * np.cos(ring)
        y = lay.cyl_center[j, 1] + lay.cyl_radius[j] * np.sin(ring)
        z = np.array([0.0, min(lay.cyl_height[j], ep.arena_high[2])])
        alpha = 0.15 if lay.cyl_amplitude[j] > 0 else 0.35
        ax.plot_surface(np.stack([x, x]), np.stack([y, y]), np.repeat(z[:, None], len(ring), 1),
                        color="tab:orange", alpha=alpha, lw=0)
    if is_track:
        c = ep.gate_half_opening + ep.gate_bar / 2
        for g, yaw in zip(lay.gate_pos, lay.gate_yaw):
            lat = np.array([*_gate_lateral(yaw), 0.0])
            up = np.array([0.0, 0.0, 1.0])
            corners = np.stack([g + a * lat + b * up for a, b in ((-c, -c), (c, -c), (c, c), (-c, c), (-c, -c))])
            ax.plot(*corners.T, color="forestgreen", lw=2.5)
            ax.plot([g[0], g[0]], [g[1], g[1]], [0, g[2] - c], color="forestgreen", lw=1.5)


# ------------------------------------------------------------------ attention
def plot_attention(ep: Episode, out: str | Path, *, drone: int = 0, dpi: int = 100) -> Path:
    """Write the attention figure of one drone: its attention weights over time (top) above its clearance to
    each obstacle and each other drone (bottom), sharing the time axis; one colour per obstacle in both."""
    from matplotlib.figure import Figure

    out = check_output(out)
    if ep.attention is None:
        raise ValueError(f"method {ep.method!r} has no attention network: the attention figure needs "
                         "attention_cbf or attention_penalty")
    n, m = ep.num_agents, ep.num_cylinders
    if not 0 <= drone < n:
        raise ValueError(f"invalid drone={drone}: allowed: 0 to {n - 1}")
    last = ep.last_index(drone)
    t = ep.time[: last + 1]
    alpha = ep.attention[: last + 1, drone]  # [T, M + K]
    present = np.flatnonzero(ep.layout.cyl_present)
    cyl_colours = _colours(max(m, 1))
    index = ep.nbr_index[: last + 1, drone]  # [T, K]
    fig = Figure(figsize=(10, 6.5), dpi=dpi, layout="constrained")
    ax_a, ax_d = fig.subplots(2, 1, sharex=True)
    for j in present:
        ax_a.plot(t, alpha[:, j], color=cyl_colours[j], lw=1.5, label=f"obstacle o{j}")
        ax_d.plot(t, ep.clearance[: last + 1, drone, j], color=cyl_colours[j], lw=1.5)
    for q in range(index.shape[1]):
        seen = index[:, q][index[:, q] >= 0]
        if len(seen) and np.all(seen == seen[0]):  # always the same drone (all neighbours, in index order)
            label = f"drone {seen[0]}"
        else:  # a slot of the K nearest: which drone it is changes
            label = f"neighbour slot {q} (nearest first)"
        style = dict(color="0.35", lw=1.0, ls=(0, (4, 1 + 2 * q)))
        ax_a.plot(t, alpha[:, m + q], label=label, **style)
        ax_d.plot(t, ep.nbr_gap[: last + 1, drone, q], **style)
    ax_d.axhline(0.0, color="red", lw=0.8)
    if ep.collided[drone] or ep.finished[drone]:
        what = f"hit {ep.collision_kind[drone]}" if ep.collided[drone] else "finished"
        for ax in (ax_a, ax_d):
            ax.axvline(t[-1], color="k", lw=0.8, ls="--")
        ax_a.annotate(what, (t[-1], 1.02), ha="right", fontsize=8)
    ax_a.set_ylim(-0.02, 1.05)
    ax_a.set_ylabel("attention weight")
    ax_a.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5))
    ax_d.set_ylim(min(-0.1, float(np.nanmin(ep.clearance[: last + 1, drone], initial=0.0))), CLEARANCE_CAP)
    ax_d.set_ylabel(f"clearance (m, capped at {CLEARANCE_CAP:g})")
    ax_d.set_xlabel("time (s)")
    fig.suptitle(f"{ep.method} on {ep.scenario}: attention of drone {drone}")
    return save_figure(fig, out)

"""Sampling-based MPC (MPPI) baseline for the velocity-command interface of the learned policy.

Decentralised: every drone plans for itself, in its own frame, from its own observation row only
(the same input the learned actor gets), so it runs in the same evaluation harness. Neighbours and
cylinders are predicted at constant velocity over the horizon.

Model (velocity level, measured on the environment; see :class:`MPCConfig`): the onboard controller
tracks a world-frame velocity command ``u`` through a first-order lag of gain ``k = vel_gain``
(τ = 0.25 s); horizontally the acceleration follows its demand through the attitude loop, a second
lag ``τ_tilt``, and starts from the acceleration implied by the observed tilt::

    p' = v,   v_xy' = a_xy,   a_xy' = (k (u_xy − v_xy) − a_xy) / τ_tilt,   v_z' = k (u_z − v_z)

It is stepped exactly (zero-order hold, matrices computed once) over each plan step, with ``u`` first
limited so that the demand ``k (u − v)`` respects the controller's tilt and climb limits. Over 1 s of
random ±2 m/s command steps it predicts the position within 5.5 cm on average (a pure 0.25 s lag: 15 cm).

Planner (Williams et al.'s MPPI): K command sequences ``U + ε`` (``horizon`` plan steps of ``plan_dt``;
ε Gaussian, AR(1) in time, from a bank drawn once) are rolled out through the model with ``lax.scan``
(``vmap`` over samples), scored, and averaged with weights ``softmax(−S / λ)``. The first command is
applied; the sequence is warm-started from step to step. Two extra candidates ride along each step: the
previous plan itself and "hover".

The plan is an explicit carry (:class:`MPCCarry`): ``policy.init(lead)`` then
``carry, cmd = policy.act(carry, obs, key)``, pure, jittable and vmappable.

Costs per plan step (the weights are :class:`MPCConfig` fields):
- progress: distance to the current target, the goal or the gate. For a gate it is measured with the
  offset from the gate's axis weighed ``gate_lateral_weight`` times, so that the drone lines up before
  the plane; past the plane without having crossed it, from 1 m in front of the gate plus that 1 m, so
  that a missed gate is flown around and re-entered; a sample whose path crosses the plane forwards
  through the opening switches to the distance to the next gate minus a bonus;
- barriers ``w (1 − d / margin)²`` for d < margin, plus ``collision_cost`` where d < 0, for the
  clearance d to cylinders (vertical, infinite), to neighbours, to the frames (4 bars and the post) of
  the current gate and of the gate passed last (remembered in the carry), to the floor and to the
  ceiling. The current gate's frame is checked at the plane-crossing point when a step crosses the
  plane, so that a coarse step cannot jump through a bar;
- shadow: how far cylinders block the straight line to the aim point, a cost-to-go beyond the horizon;
- smoothness: ``‖u_k − u_{k−1}‖²``, with u_{−1} the command given last step.

Measured (2-core AMD EPYC shared with a training run, jax 0.10.2 on CPU):
``python -m aswarm.baselines.mpc --scenario race --episodes 1000 --bench``: success 100 % (95 % CI 99.6–100),
collision 0 % (0–0.4), mission 15.4 s, 398 s wall with compile; ``obstacles``: 100 % / 0 %, 104 s.
On 200 episodes: ``lab`` 99.0 % / 1.0 % (gate), ``dynamic`` 99.0 % / 1.0 % (moving cylinder).
Planning with the defaults (K = 64, H = 12) at 256 worlds takes 66–112 µs per drone-step on race
(load-dependent; the env step itself takes 14) and 72 µs on obstacles; K = 32 halves it (30 µs)
and still scored 100 % on 200 episodes of each. Work per drone-step: K·H = 768 rollout steps of
~540 hand-counted FLOPs on race (~400 on obstacles): ~0.4 MFLOP; XLA's cost analysis, which counts
every elementwise op (compares, selects), gives 1.34 and 0.65 M.

Cylinder heights are not in the observation: they are treated as infinite, as they reach the ceiling
in every scenario. The arena's walls are not either (only the altitude is): they are not modelled.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from aswarm.analysis.protocol import EVAL_SEED
from aswarm.core import geometry
from aswarm.core.layout import CYL, NBR
from aswarm.envs.swarm_env import SwarmEnv


@dataclasses.dataclass(frozen=True)
class MPCConfig:
    """MPPI settings. Defaults tuned on 200 episodes each of ``obstacles`` and ``race`` (seed 10000), then
    checked on 1000 (module docstring); the model's on step responses of the environment."""

    # Planner.
    horizon: int = 12  # plan steps: 1.2 s, longer than a stop from 2 m/s (~0.6 s with the lag)
    plan_dt: float = 0.1  # s per plan step (>= the env step; the model is stepped exactly over it)
    samples: int = 64  # K rollouts per drone per control step (incl. the previous plan and hover)
    temperature: float = 1.0  # λ, in cost units
    noise_std: tuple[float, float, float] = (0.6, 0.6, 0.3)  # σ per axis, m/s
    # AR(1) correlation of the noise between plan steps (0: white). Correlated noise shifts a whole
    # stretch of the path sideways, where white noise mostly averages out and only adds jerk.
    noise_correlation: float = 0.8
    # The noise comes from a bank of this many N(0, 1) sequences drawn once (a power of two); each step and
    # drone picks K of them and flips each axis's sign at random. Drawing K·H·3 fresh normals with
    # jax.random cost 260 µs per drone-step on 2 cores, more than all the rollouts together.
    noise_bank: int = 4096
    # Model, measured on the env (step response of `vel` to a velocity command in "hover"). These four are the
    # geometric controller's; with fit_to_drone, make_mpc_policy measures them on the env's own drone instead
    # (fit_to_drone below).
    fit_to_drone: bool = True
    vel_gain: float = 4.0  # 1/s: vz reaches 63 % in 0.25 s, the onboard velocity loop's gain
    tilt_lag: float = 0.075  # s: the horizontal response lags vz's by ~65 ms (attitude loop); best open-loop fit
    max_accel_xy: float = 9.8 * math.tan(math.radians(30.0))  # m/s²: the controller's 30° tilt limit
    accel_z: tuple[float, float] = (-5.0, 7.0)  # m/s², the controller's sink / climb limits
    # Costs (per plan step; distances in m).
    progress_weight: float = 1.0  # per m of distance to the current target
    shadow_weight: float = 1.0  # per m by which a cylinder blocks the straight line to the target
    shadow_margin: float = 0.2  # m added to a cylinder's reach for that line
    gate_lateral_weight: float = 2.0  # offset from the gate's axis counts this much more than distance along it
    gate_bonus: float = 5.0  # per plan step spent after crossing the gate through its opening
    goal_bonus: float = 5.0  # per plan step after the path entered the goal sphere
    obstacle_weight: float = 20.0
    obstacle_margin: float = 0.1
    neighbour_weight: float = 20.0
    neighbour_margin: float = 0.25
    gate_weight: float = 20.0
    gate_margin: float = 0.1
    floor_weight: float = 20.0
    floor_margin: float = 0.25
    collision_cost: float = 50.0  # multiplies each hazard's weight where its clearance is negative
    smooth_weight: float = 0.2  # per (m/s)² change between consecutive commands

    def __post_init__(self) -> None:
        for name in ("horizon", "samples"):
            if not isinstance(getattr(self, name), int) or getattr(self, name) < (1 if name == "horizon" else 3):
                raise ValueError(f"invalid {name}={getattr(self, name)!r}: must be an integer >= "
                                 f"{1 if name == 'horizon' else 3}")
        for name in ("plan_dt", "temperature", "vel_gain", "tilt_lag", "max_accel_xy", "obstacle_margin",
                     "neighbour_margin", "gate_margin", "floor_margin"):
            if not getattr(self, name) > 0:
                raise ValueError(f"invalid {name}={getattr(self, name)!r}: must be > 0")
        if self.noise_bank < 1 or self.noise_bank & (self.noise_bank - 1):
            raise ValueError(f"invalid noise_bank={self.noise_bank!r}: must be a power of two")
        if not 0.0 <= self.noise_correlation < 1.0:
            raise ValueError(f"invalid noise_correlation={self.noise_correlation!r}: must be in [0, 1)")
        if len(self.noise_std) != 3 or min(self.noise_std) < 0:
            raise ValueError(f"invalid noise_std={self.noise_std!r}: three values >= 0 (m/s per axis)")


class MPCCarry(NamedTuple):
    """Warm start kept between control steps; leading axes ``[..., n]`` as the observations."""

    nominal: jax.Array  # [..., n, H, 3] planned commands (m/s, world), already shifted by one env step
    last_cmd: jax.Array  # [..., n, 3] command given at the previous step (the env zeroes it for finished
    # or not yet released drones; the MPC cannot tell from the observation)
    # Gates (track scenarios): the observation shows the current gate only, so the one just passed is
    # remembered, dead-reckoned with the observed velocity, to keep its frame in the cost while flying out
    # of it (on the tight `lab` track, 29 % of episodes clipped the gate just passed without this).
    target: jax.Array  # [..., n, 7] last step's gate: centre minus drone position (m), normal, valid flag
    passed_gate: jax.Array  # [..., n, 7] the gate passed last, same layout


class MPCPolicy(NamedTuple):
    """``init(lead_shape) -> carry``; ``act(carry, obs [..., n, D], key) -> (carry, cmd [..., n, 3])``."""

    init: Callable[..., MPCCarry]
    act: Callable[[MPCCarry, jax.Array, jax.Array], tuple[MPCCarry, jax.Array]]


class _Scene(NamedTuple):
    """One drone's view from its obs row, in a frame at its own xy with z measured from the floor."""

    z0: jax.Array  # [] altitude
    vel: jax.Array  # [3]
    acc_xy: jax.Array  # [2] horizontal acceleration implied by the tilt
    target: jax.Array  # [3] current gate centre or goal
    normal: jax.Array  # [3] gate passage direction, horizontal unit (0 for a goal)
    next_target: jax.Array  # [3]
    cyl_xy: jax.Array  # [M, 2]
    cyl_vel: jax.Array  # [M, 2]
    cyl_reach: jax.Array  # [M] cylinder radius + drone radius
    cyl_present: jax.Array  # [M] bool
    nbr_pos: jax.Array  # [N, 3]
    nbr_vel: jax.Array  # [N, 3] absolute
    nbr_present: jax.Array  # [N] bool
    passed_centre: jax.Array  # [3] the gate passed last (see MPCCarry.passed_gate)
    passed_normal: jax.Array  # [3]
    passed_valid: jax.Array  # [] bool


def _barrier(d: jax.Array, margin: float, collision_cost: float) -> jax.Array:
    """0 beyond ``margin``, (1 − d/margin)² inside it, plus ``collision_cost`` at negative clearance."""
    return jnp.square(jnp.maximum(1.0 - d / margin, 0.0)) + collision_cost * (d < 0)


def _tilt_acceleration(quat: jax.Array, g: float) -> jax.Array:
    """[2] horizontal acceleration of a drone holding altitude at attitude ``quat`` [w, x, y, z]."""
    w, x, y, z = quat[0], quat[1], quat[2], quat[3]
    b3 = jnp.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])
    return g * b3[:2] / jnp.maximum(b3[2], 0.5)


def _expm(m: np.ndarray) -> np.ndarray:
    """Matrix exponential by scaling and squaring of a Taylor series (small matrices, host side)."""
    s = max(0, int(np.ceil(np.log2(max(np.abs(m).sum(1).max(), 1e-12)))) + 1)
    a = m / 2.0**s
    out, term = np.eye(len(m)), np.eye(len(m))
    for i in range(1, 20):
        term = term @ a / i
        out = out + term
    for _ in range(s):
        out = out @ out
    return out


def _zero_order_hold(config: MPCConfig) -> tuple[np.ndarray, np.ndarray]:
    """Exact discretisation over ``plan_dt`` of the linear model under a held command.

    Horizontal, per axis, state [p, v, a]: p' = v, v' = a, a' = (k (u − v) − a) / τ_tilt.
    Vertical, state [p, v]: p' = v, v' = k (u − v). Returns the [4, 4] and [3, 3] transition
    matrices of the state augmented with the command (last row/column).
    """
    k, tau = config.vel_gain, config.tilt_lag
    mxy = np.zeros((4, 4))
    mxy[0, 1], mxy[1, 2], mxy[2, 1], mxy[2, 2], mxy[2, 3] = 1.0, 1.0, -k / tau, -1.0 / tau, k / tau
    mz = np.zeros((3, 3))
    mz[0, 1], mz[1, 1], mz[1, 2] = 1.0, -k, k
    return _expm(mxy * config.plan_dt), _expm(mz * config.plan_dt)


def _noise_bank(config: MPCConfig) -> np.ndarray:
    """[bank, H, 3] unit-variance sequences, AR(1) in time with ``noise_correlation`` (drawn once, seed 0)."""
    white = np.random.default_rng(0).standard_normal((config.noise_bank, config.horizon, 3))
    rho = config.noise_correlation
    out = np.empty_like(white)
    out[:, 0] = white[:, 0]
    for i in range(1, config.horizon):
        out[:, i] = rho * out[:, i - 1] + math.sqrt(1.0 - rho * rho) * white[:, i]
    return out


def fit_to_drone(config: MPCConfig, env: SwarmEnv) -> MPCConfig:
    """``config`` with its model measured on ``env``'s drone (``analysis.step_response.characterise``): the
    vertical gain from the 63 % rise of a z step, the acceleration limits from the steepest 0.1 s of 2 m/s
    steps, and the tilt lag that makes the model's 0 -> 1 m/s x step closest to the drone's (least squares
    over 1.5 s, on a 2 ms grid of lags)."""
    if not config.fit_to_drone:
        return config
    from aswarm.analysis import step_response

    c = step_response.characterise(env.config)
    x = step_response.step_response(env.config, (1.0, 0.0, 0.0))
    t, v = x["t"], x["vel"][:, 0]
    k, dt = 1.0 / c.lag_z, float(t[1] - t[0])
    keep = t <= 1.5

    taus = np.arange(0.002, 0.3, 0.002)
    vel, acc, out = np.zeros_like(taus), np.zeros_like(taus), []
    for _ in range(len(t)):  # every lag at once; 100 Euler substeps per sample
        for _ in range(100):
            acc += (np.minimum(k * (1.0 - vel), c.accel_xy) - acc) / taus * (dt / 100)
            vel += acc * (dt / 100)
        out.append(vel.copy())
    err = np.sum((np.asarray(out)[keep] - v[keep, None]) ** 2, axis=0)
    return dataclasses.replace(config, fit_to_drone=False, vel_gain=k, tilt_lag=float(taus[int(np.argmin(err))]),
                               max_accel_xy=c.accel_xy, accel_z=(-c.sink, c.climb))


def make_mpc_policy(env: SwarmEnv, config: MPCConfig = MPCConfig(), *, unroll: bool = False) -> MPCPolicy:
    """MPPI for ``env``'s drones; returns pure ``init`` and ``act`` (see :class:`MPCPolicy`). The model is
    fitted to the env's drone first (:func:`fit_to_drone`) unless ``config.fit_to_drone`` is off.

    ``unroll`` unrolls the horizon's ``scan``: only for counting FLOPs, as XLA's cost analysis counts a
    loop body once whatever its trip count.
    """
    config = fit_to_drone(config, env)
    cfg = env.config
    layout = env.obs_layout
    own_sl = layout.own_slices
    if config.plan_dt < cfg.dt - 1e-9:
        raise ValueError(f"invalid plan_dt={config.plan_dt!r}: must be >= the env step {cfg.dt:g} s")
    h, k = config.horizon, config.samples
    n = cfg.num_agents
    r = cfg.cf.collision_radius
    track = env.kind == "track"
    ceiling = cfg.arena_high[2]
    sigma = jnp.asarray(config.noise_std, jnp.float32)
    bank = jnp.asarray(_noise_bank(config), jnp.float32)
    sign_shift = jnp.array([29, 30, 31], jnp.uint32)
    zxy, zz = (m.tolist() for m in _zero_order_hold(config))
    # Command bounds that keep the acceleration demand at the start of a plan step within the controller's
    # limits: the linear model cannot saturate, the real drone does (this keeps the model's mean error at
    # 1 s at 5.5 cm for random ±2 m/s steps, against 21 cm without it).
    du_xy = config.max_accel_xy / config.vel_gain
    du_z = (config.accel_z[0] / config.vel_gain, config.accel_z[1] / config.vel_gain)
    shift = min(cfg.dt / config.plan_dt, 1.0)  # the plan advances by one env step between calls

    def scene(row: jax.Array, passed_gate: jax.Array) -> _Scene:
        own, cyl, nbr = layout.split(row)
        z0 = own[own_sl["altitude"]][0]
        here = jnp.array([0.0, 0.0, 1.0]) * z0
        vel = own[own_sl["vel"]]
        cyl_xy, gap = CYL.get(cyl, "rel_xy"), CYL.get(cyl, "clearance")
        return _Scene(
            z0=z0, vel=vel, acc_xy=_tilt_acceleration(own[own_sl["quat"]], cfg.cf.gravity),
            target=here - own[own_sl["target_rel"]], normal=own[own_sl["target_normal"]],
            next_target=here - own[own_sl["next_target_rel"]], cyl_xy=cyl_xy, cyl_vel=CYL.get(cyl, "vel_xy"),
            cyl_reach=jnp.linalg.norm(cyl_xy, axis=-1) - gap, cyl_present=CYL.present(cyl),
            nbr_pos=NBR.get(nbr, "rel_pos") + here, nbr_vel=NBR.get(nbr, "rel_vel") + vel,
            nbr_present=NBR.present(nbr),
            passed_centre=passed_gate[0:3] + here, passed_normal=passed_gate[3:6], passed_valid=passed_gate[6] > 0.5,
        )

    def remember_gates(row: jax.Array, target: jax.Array, passed_gate: jax.Array):
        """Carry the last gate passed: (target [7], passed_gate [7]) of the previous step -> this step's."""
        own = row[:layout.own_dim]
        moved = own[own_sl["vel"]] * cfg.dt  # dead reckoning over the last env step
        now = jnp.concatenate([-own[own_sl["target_rel"]], own[own_sl["target_normal"]], jnp.ones(1)])
        before = target.at[:3].add(-moved)
        # Gates are metres apart, so a jump of the current gate's centre means the last one was passed.
        switched = (before[6] > 0.5) & (jnp.linalg.norm(now[:3] - before[:3]) > 0.5)
        return now, jnp.where(switched, before, passed_gate.at[:3].add(-moved))

    def model_step(x, u):
        """One plan step: x = (px, py, pz, vx, vy, vz, ax, ay) scalars, u = (ux, uy, uz) held."""
        px, py, pz, vx, vy, vz, ax, ay = x
        ux, uy, uz = u
        dx, dy = ux - vx, uy - vy
        scale = jnp.minimum(1.0, du_xy * jax.lax.rsqrt(dx * dx + dy * dy + 1e-12))
        ux, uy = vx + scale * dx, vy + scale * dy
        uz = jnp.clip(uz, vz + du_z[0], vz + du_z[1])
        (_, a01, a02, b0), (_, a11, a12, b1), (_, a21, a22, b2) = zxy[:3]
        (_, c01, d0), (_, c11, d1) = zz[:2]
        return (px + a01 * vx + a02 * ax + b0 * ux, py + a01 * vy + a02 * ay + b0 * uy, pz + c01 * vz + d0 * uz,
                a11 * vx + a12 * ax + b1 * ux, a11 * vy + a12 * ay + b1 * uy, c11 * vz + d1 * uz,
                a21 * vx + a22 * ax + b2 * ux, a21 * vy + a22 * ay + b2 * uy)

    def shadow(sc: _Scene, t, px, py, aim_x, aim_y):
        """Σ over cylinders of how far each one blocks the straight line from (px, py) to the aim point (m).

        A cost-to-go beyond the horizon: the distance alone makes the drone wait behind a cylinder that sits
        on the line to its target, because every detour looks worse within a short horizon.
        """
        cx, cy = sc.cyl_xy[:, 0] + t * sc.cyl_vel[:, 0], sc.cyl_xy[:, 1] + t * sc.cyl_vel[:, 1]
        sx, sy = aim_x - px, aim_y - py
        w = jnp.clip(((cx - px) * sx + (cy - py) * sy) / (sx * sx + sy * sy + 1e-9), 0.0, 1.0)
        gap = jnp.sqrt(jnp.square(px + w * sx - cx) + jnp.square(py + w * sy - cy) + 1e-12)
        blocked = jnp.maximum(sc.cyl_reach + config.shadow_margin - gap, 0.0)
        return jnp.sum(jnp.where(sc.cyl_present, blocked, 0.0))

    def gate_terms(sc: _Scene, t, prev, p, passed):
        """Progress and frame cost of one step towards a gate; updates ``passed``."""
        c, nrm = sc.target, sc.normal
        s0 = (prev[0] - c[0]) * nrm[0] + (prev[1] - c[1]) * nrm[1]
        s1 = (p[0] - c[0]) * nrm[0] + (p[1] - c[1]) * nrm[1]
        l0 = -(prev[0] - c[0]) * nrm[1] + (prev[1] - c[1]) * nrm[0]
        l1 = -(p[0] - c[0]) * nrm[1] + (p[1] - c[1]) * nrm[0]
        v0, v1 = prev[2] - c[2], p[2] - c[2]
        crosses = (s0 < 0) != (s1 < 0)
        frac = s0 / jnp.where(crosses, s0 - s1, 1.0)
        hl, hv = l0 + frac * (l1 - l0), v0 + frac * (v1 - v0)
        through = crosses & (s0 < 0) & (jnp.maximum(jnp.abs(hl), jnp.abs(hv)) < cfg.gate_half_opening)
        passed = passed | through
        # Frame clearance where a bar can be hit: at the plane when the step crosses it.
        d_frame = geometry.frame_distance(jnp.where(crosses, 0.0, s1), jnp.where(crosses, hl, l1),
                                          jnp.where(crosses, hv, v1), cfg.gate_half_opening, cfg.gate_bar, c[2])
        d_frame = d_frame - cfg.gate_bar / 2 - r
        # To go before the gate: distance to its centre with the offset from its axis weighed more than the
        # distance along it, so that the drone lines up before the plane (aimed straight at the centre, it
        # reached the plane of a gate seen from the side still moving sideways, and hit the bar). Past the
        # plane without having crossed it, the same measure from 1 m in front of the gate plus that 1 m:
        # always dearer than the right side, so a missed gate is flown around and re-entered. After
        # crossing: the distance to the next gate, less a bonus.
        wrong_side = s1 > 0
        lateral2 = config.gate_lateral_weight**2 * (l1 * l1 + v1 * v1)
        funnel = jnp.where(wrong_side, jnp.sqrt(jnp.square(s1 + 1.0) + lateral2) + 1.0, jnp.sqrt(s1 * s1 + lateral2))
        nx, ny, nz = p[0] - sc.next_target[0], p[1] - sc.next_target[1], p[2] - sc.next_target[2]
        onward = (jnp.sqrt(nx * nx + ny * ny + nz * nz) - jnp.linalg.norm(sc.next_target - c)
                  - config.gate_bonus / config.progress_weight)
        aim = jnp.where(passed, sc.next_target, jnp.where(wrong_side, c - nrm, c))
        to_go = jnp.where(passed, onward, funnel) + config.shadow_weight * shadow(sc, t, p[0], p[1], aim[0], aim[1])
        progress = config.progress_weight * to_go
        # The gate passed last: its frame is behind the drone, the point itself is checked.
        q = [p[i] - sc.passed_centre[i] for i in range(3)]
        pn = sc.passed_normal
        d_old = geometry.frame_distance(q[0] * pn[0] + q[1] * pn[1], -q[0] * pn[1] + q[1] * pn[0], q[2],
                                        cfg.gate_half_opening, cfg.gate_bar, sc.passed_centre[2]) - cfg.gate_bar / 2 - r
        d_frame = jnp.where(sc.passed_valid, jnp.minimum(d_frame, d_old), d_frame)
        frame = config.gate_weight * _barrier(d_frame, config.gate_margin, config.collision_cost)
        return progress + frame, passed

    def goal_terms(sc: _Scene, t, prev, p, passed):
        c = sc.target
        # Distance from the goal to the step's segment: the env checks arrival at every physics step.
        ex, ey, ez = p[0] - prev[0], p[1] - prev[1], p[2] - prev[2]
        w = jnp.clip(((c[0] - prev[0]) * ex + (c[1] - prev[1]) * ey + (c[2] - prev[2]) * ez)
                     / (ex * ex + ey * ey + ez * ez + 1e-9), 0.0, 1.0)
        d_seg = jnp.sqrt(jnp.square(prev[0] + w * ex - c[0]) + jnp.square(prev[1] + w * ey - c[1])
                         + jnp.square(prev[2] + w * ez - c[2]))
        passed = passed | (d_seg < 0.75 * cfg.goal_radius)
        dist = jnp.sqrt(jnp.square(p[0] - c[0]) + jnp.square(p[1] - c[1]) + jnp.square(p[2] - c[2]))
        to_go = dist + config.shadow_weight * shadow(sc, t, p[0], p[1], c[0], c[1])
        return config.progress_weight * jnp.where(passed, -config.goal_bonus / config.progress_weight, to_go), passed

    def rollout_cost(sc: _Scene, u_seq: jax.Array, u_last: jax.Array) -> jax.Array:
        """Total cost [] of one command sequence ``u_seq`` [H, 3]; scalar per-axis state so that the batched
        arrays are [drones, samples] with no small minor axis."""

        def body(carry, inp):
            x, passed, u_prev = carry
            ux, uy, uz, t = inp
            prev = x[:3]
            x = model_step(x, (ux, uy, uz))
            p = x[:3]
            task, passed = (gate_terms if track else goal_terms)(sc, t, prev, p, passed)
            dx, dy = p[0] - (sc.cyl_xy[:, 0] + t * sc.cyl_vel[:, 0]), p[1] - (sc.cyl_xy[:, 1] + t * sc.cyl_vel[:, 1])
            d_cyl = jnp.sqrt(dx * dx + dy * dy + 1e-12) - sc.cyl_reach
            c_cyl = jnp.sum(jnp.where(sc.cyl_present, _barrier(d_cyl, config.obstacle_margin,
                                                                config.collision_cost), 0.0))
            nx = p[0] - (sc.nbr_pos[:, 0] + t * sc.nbr_vel[:, 0])
            ny = p[1] - (sc.nbr_pos[:, 1] + t * sc.nbr_vel[:, 1])
            nz = p[2] - (sc.nbr_pos[:, 2] + t * sc.nbr_vel[:, 2])
            d_nbr = jnp.sqrt(nx * nx + ny * ny + nz * nz + 1e-12) - 2 * r
            c_nbr = jnp.sum(jnp.where(sc.nbr_present, _barrier(d_nbr, config.neighbour_margin,
                                                                config.collision_cost), 0.0))
            c_floor = (_barrier(p[2] - r, config.floor_margin, config.collision_cost)
                       + _barrier(ceiling - p[2], config.floor_margin, config.collision_cost))
            jerk = jnp.square(ux - u_prev[0]) + jnp.square(uy - u_prev[1]) + jnp.square(uz - u_prev[2])
            cost = (task + config.obstacle_weight * c_cyl + config.neighbour_weight * c_nbr
                    + config.floor_weight * c_floor + config.smooth_weight * jerk)
            return (x, passed, (ux, uy, uz)), cost

        x0 = (jnp.zeros(()), jnp.zeros(()), sc.z0, sc.vel[0], sc.vel[1], sc.vel[2], sc.acc_xy[0], sc.acc_xy[1])
        times = config.plan_dt * jnp.arange(1, h + 1)
        init = (x0, jnp.zeros((), bool), (u_last[0], u_last[1], u_last[2]))
        _, costs = jax.lax.scan(body, init, (u_seq[:, 0], u_seq[:, 1], u_seq[:, 2], times), unroll=unroll)
        return jnp.sum(costs)

    def plan_one(nominal: jax.Array, u_last: jax.Array, target: jax.Array, passed_gate: jax.Array, row: jax.Array,
                  key: jax.Array):
        """One drone: its carry (nominal [H, 3], last command [3], gates [7] and [7]) and obs row [D]
        -> (its next carry, command [3])."""
        target, passed_gate = remember_gates(row, target, passed_gate)
        sc = scene(row, passed_gate)
        bits = jax.random.bits(key, (k,))  # low bits pick a bank entry, the top three flip the axes' signs
        signs = 1.0 - 2.0 * ((bits[:, None] >> sign_shift) & 1).astype(jnp.float32)
        eps = bank[(bits & (config.noise_bank - 1)).astype(jnp.int32)] * (signs * sigma)[:, None, :]
        eps = eps.at[0].set(0.0)  # the previous plan itself
        cand = jnp.clip(nominal[None] + eps, -cfg.max_speed, cfg.max_speed)
        cand = cand.at[1].set(0.0)  # hover: always available as a safe fallback
        costs = jax.vmap(rollout_cost, in_axes=(None, 0, None))(sc, cand, u_last)
        weights = jax.nn.softmax(-(costs - jnp.min(costs)) / config.temperature)
        plan = jnp.einsum("k,khd->hd", weights, cand)
        cmd = plan[0]
        # Warm start: advance the plan by one env step (linear interpolation between plan knots).
        nxt = jnp.concatenate([plan[1:], plan[-1:]], 0)
        return MPCCarry((1.0 - shift) * plan + shift * nxt, cmd, target, passed_gate), cmd

    def init(lead_shape: tuple[int, ...] = ()) -> MPCCarry:
        lead = tuple(lead_shape) + (n,)
        return MPCCarry(nominal=jnp.zeros(lead + (h, 3)), last_cmd=jnp.zeros(lead + (3,)),
                        target=jnp.zeros(lead + (7,)), passed_gate=jnp.zeros(lead + (7,)))

    def act(carry: MPCCarry, obs: jax.Array, key: jax.Array) -> tuple[MPCCarry, jax.Array]:
        lead = obs.shape[:-1]
        flat = int(np.prod(lead))
        keys = jax.random.split(key, flat)
        flat_carry = jax.tree.map(lambda x: x.reshape(flat, *x.shape[len(lead):]), carry)
        new, cmd = jax.vmap(plan_one)(*flat_carry, obs.reshape(flat, -1), keys)
        return jax.tree.map(lambda x: x.reshape(*lead, *x.shape[1:]), new), cmd.reshape(*lead, 3)

    return MPCPolicy(init=init, act=act)


# ------------------------------------------------------------------ evaluation
def rollout_mpc(env: SwarmEnv, config: MPCConfig, episodes: int, key: jax.Array,
                chunk: int = 50, reset_keys: jax.Array | None = None) -> dict[str, jax.Array]:
    """Run ``episodes`` vmapped worlds with the MPC until every one has ended.

    Returns each episode's metrics (``env.metrics`` on its first ``done`` step), ``[episodes]`` arrays,
    as :func:`aswarm.analysis.evaluate.rollout_episodes` records them. Steps run in chunks of ``chunk`` inside
    a ``while_loop`` that stops once all episodes have ended, so fast successes cost less than the time limit.
    ``reset_keys`` ([episodes] keys) start the worlds where a policy's evaluation starts them (episode i of
    ``aswarm eval --seed S`` resets with ``split(PRNGKey(S), episodes)[i]``), for a comparison on the same
    episodes; by default they come from ``key``.
    """
    policy = make_mpc_policy(env, config)
    reset, step = jax.vmap(env.reset), jax.vmap(env.step)
    if reset_keys is not None and reset_keys.shape[0] != episodes:
        raise ValueError(f"invalid reset_keys: {reset_keys.shape[0]} keys for {episodes} episodes: allowed: one each")

    # The reset keys are an argument, not a constant of the program: the same episodes drawn otherwise (another
    # policy's seed, the keys in another order) then run the same compiled program.
    def run(key, keys):
        k_reset, k_act = jax.random.split(key)
        state = reset(jax.random.split(k_reset, episodes) if keys is None else keys)
        rec = jax.tree.map(jnp.zeros_like, state.metrics)
        ended = jnp.zeros(episodes, bool)

        def body(c, _):
            s, carry, rec, ended, t = c
            carry, cmd = policy.act(carry, s.obs, jax.random.fold_in(k_act, t))
            s = step(s, cmd)
            first = (s.done > 0) & ~ended
            rec = jax.tree.map(lambda r, m: jnp.where(first, m, r), rec, s.metrics)
            return (s, carry, rec, ended | first, t + 1), None

        def chunk_body(c):
            return jax.lax.scan(body, c, None, length=chunk)[0]

        init = (state, policy.init((episodes,)), rec, ended, jnp.zeros((), jnp.int32))
        out = jax.lax.while_loop(lambda c: ~jnp.all(c[3]), chunk_body, init)
        return out[2]

    return jax.jit(run)(key, reset_keys)


def time_per_step(env: SwarmEnv, config: MPCConfig, worlds: int = 256, repeats: int = 5) -> dict[str, float]:
    """Measured planning time per control step (µs per drone-step) at ``worlds`` worlds, and XLA's FLOP count."""
    policy = make_mpc_policy(env, config)
    state = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), worlds))
    carry = policy.init((worlds,))
    act = jax.jit(policy.act)
    unrolled = jax.jit(make_mpc_policy(env, config, unroll=True).act)
    analysis = unrolled.lower(carry, state.obs, jax.random.PRNGKey(1)).compile().cost_analysis()
    analysis = analysis[0] if isinstance(analysis, list | tuple) else analysis
    flops = float(analysis.get("flops", float("nan"))) if analysis else float("nan")
    jax.block_until_ready(act(carry, state.obs, jax.random.PRNGKey(1)))
    best = float("inf")
    for i in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(act(carry, state.obs, jax.random.PRNGKey(2 + i)))
        best = min(best, time.perf_counter() - t0)
    drone_steps = worlds * env.num_agents
    return {"us_per_drone_step": 1e6 * best / drone_steps, "flops_per_drone_step": flops / drone_steps,
            "worlds": worlds}


def main(argv: list[str] | None = None) -> int:
    """``python -m aswarm.baselines.mpc --scenario race --episodes 64``: success and collision rates of the MPC."""
    from aswarm import config_args, envs
    from aswarm.analysis.evaluate import summarize

    p = argparse.ArgumentParser(description=main.__doc__)
    p.add_argument("--scenario", default="race")
    p.add_argument("--episodes", type=int, default=64)
    p.add_argument("--seed", type=int, default=EVAL_SEED)
    p.add_argument("--env", action="append", default=[], metavar="FIELD=VALUE", help="EnvConfig override")
    p.add_argument("--mpc", action="append", default=[], metavar="FIELD=VALUE", help="MPCConfig override")
    p.add_argument("--bench", action="store_true", help="also time one control step at 256 worlds")
    args = p.parse_args(argv)
    env = envs.make(args.scenario, **config_args.parse_assignments(args.env, envs.EnvConfig))
    config = MPCConfig(**config_args.parse_assignments(args.mpc, MPCConfig))
    t0 = time.perf_counter()
    rec = jax.block_until_ready(rollout_mpc(env, config, args.episodes, jax.random.PRNGKey(args.seed)))
    wall = time.perf_counter() - t0
    s = summarize(rec)
    print(f"MPC (MPPI K={config.samples}, H={config.horizon} x {config.plan_dt:g} s) on {args.scenario}: "
          f"{args.episodes} episodes, seed {args.seed}, {wall:.0f} s incl. compile")
    for name in ("success", "collision"):
        lo, hi = s[f"{name}_ci95"]
        print(f"  {name + ' rate':16s} {100 * s[name + '_rate']:6.1f} %   95% CI [{100 * lo:.1f}, {100 * hi:.1f}]")
    for name, value in s.items():  # the other figures of `aswarm eval`'s report
        if isinstance(value, float) and name not in ("success_rate", "collision_rate"):
            print(f"  {name:24s} {value:8.3f}")
    if args.bench:
        b = time_per_step(env, config)
        print(f"  planning: {b['us_per_drone_step']:.1f} µs per drone-step at {b['worlds']} worlds, "
              f"{b['flops_per_drone_step'] / 1e6:.2f} MFLOP per drone-step (XLA cost analysis)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

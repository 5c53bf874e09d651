"""Velocity and body angular rate from timestamped mocap poses.

Mocap gives positions and orientations only; the policy also observes the world-frame velocity and
the body-frame angular rate. Both are estimated as the slope of a least-squares line through the
last ``window`` poses of each drone, using their actual timestamps:

- velocity: the slope of the positions;
- angular rate: the slope of the rotation vectors ``log(q_last⁻¹ ⊗ q_i)`` of the window's
  orientations relative to the latest one. For a constant body rate ω, ``q_i = q_last ⊗ exp(ω (t_i −
  t_last) / 2)``, so the slope is ω expressed in the body frame, as the simulator observes it.

A line fit averages out independent jitter (its slope's noise falls as window^-1.5 against a
two-point difference's) at the price of a lag of about half the window; a window of 4 at the shipped
25 Hz lags 60 ms (15 ms on 100 Hz poses).

``velocity="model"`` trades that lag for knowledge the runtime has: the commands it sent. A drone behind
its onboard velocity controller follows a command u roughly as a first-order lag, v' = (u - v) / tau
(tau measured on the simulated drone's step response, per axis: the bundle's ``drone.velocity_lag``).
A Kalman filter per axis on (position, velocity) predicts with that model between poses and corrects
with every pose, so its velocity does not lag (the model carries it) and its noise is what the
position residuals let through; ``accel_noise`` (m/s^2, the model's error over one pose interval) sets
how far it trusts the model over the poses. A sample whose timestamp does not advance is a repeated
frame and is ignored; a jump faster than ``max_speed`` m/s is treated as a mocap glitch (a swapped or
mislabelled marker) and rejected.
The state is plain arrays (pure functions, leading batch axes ``...``, ``n`` drones).
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from aswarm.core.estimation import slope_weights


@dataclasses.dataclass(frozen=True)
class EstimatorConfig:
    window: int = 4  # poses in the least-squares fit (>= 2); the angular rate always uses it
    max_speed: float = 10.0  # m/s; a faster jump between two poses is rejected as a glitch
    velocity: str = "model"  # see VELOCITY_ESTIMATES
    # s, the drone's horizontal and vertical velocity lag (model); None: the bundle's (FlightController), else
    # FIRMWARE_PID_LAG
    lag: tuple[float, float] | None = None
    accel_noise: float = 0.5  # m/s^2, the model's acceleration error (model)
    pos_noise: float = 0.002  # m, the poses' noise (model)
    # model: the policy sees position and velocity carried from the pose's time to the step's, with the commands
    # flown since (a pose that is 40 ms old at 2 m/s is 8 cm behind the drone); the policy trained on the present
    predict: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.window, int) or self.window < 2:
            raise ValueError(f"invalid window={self.window!r}: must be an integer >= 2")
        if not self.max_speed > 0:
            raise ValueError(f"invalid max_speed={self.max_speed!r}: must be > 0")
        if self.velocity not in VELOCITY_ESTIMATES:
            raise ValueError(f"invalid velocity={self.velocity!r}: allowed: {', '.join(VELOCITY_ESTIMATES)}")
        if self.lag is not None and (len(self.lag) != 2 or not all(np.isfinite(x) and x > 0 for x in self.lag)):
            raise ValueError(f"invalid lag={self.lag!r}: allowed: two finite time constants > 0 s "
                             "(horizontal, vertical)")
        for name in ("accel_noise", "pos_noise"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"invalid {name}={v!r}: must be a finite number > 0")


# s, 63 % of a 1 m/s step in x and in z of the firmware-PID drone with rotor lag (analysis.step_response)
FIRMWARE_PID_LAG = (0.34, 0.22)

# "model": a Kalman filter driven by the commands sent; "window": the least-squares slope of the last poses.
VELOCITY_ESTIMATES = ("model", "window")


@dataclasses.dataclass(frozen=True)
class EstimatorState:
    """The last ``window`` accepted poses of each drone, newest last (unfilled slots have ``count`` < window)."""

    t: np.ndarray  # [..., n, W] s
    pos: np.ndarray  # [..., n, W, 3]
    quat: np.ndarray  # [..., n, W, 4] wxyz, unit (either sign: the rate uses the shorter rotation)
    count: np.ndarray  # [..., n] int, accepted poses (capped at W)
    # velocity="model" only (None otherwise): the filter's position and velocity [..., n, 3] at the newest pose
    # and its covariance per axis [..., n, 3, 3] as (P_pp, P_pv, P_vv).
    kf_pos: np.ndarray | None = None
    kf_vel: np.ndarray | None = None
    kf_cov: np.ndarray | None = None


def init(shape: tuple[int, ...], config: EstimatorConfig = EstimatorConfig()) -> EstimatorState:
    """Empty state for drones of batch shape ``shape`` (e.g. ``(worlds, n)``)."""
    W = config.window
    quat = np.zeros(shape + (W, 4))
    quat[..., 0] = 1.0
    kf = {}
    if config.velocity == "model":
        kf = dict(kf_pos=np.zeros(shape + (3,)), kf_vel=np.zeros(shape + (3,)), kf_cov=np.zeros(shape + (3, 3)))
    return EstimatorState(t=np.full(shape + (W,), -np.inf), pos=np.zeros(shape + (W, 3)), quat=quat,
                          count=np.zeros(shape, np.int64), **kf)


# q ⊗ b = L(q) b with L(q)[i, j] = SIGN[i, j] q[IDX[i, j]]; CONJ_SIGN folds in q -> conj(q).
_IDX = np.array([[0, 1, 2, 3], [1, 0, 3, 2], [2, 3, 0, 1], [3, 2, 1, 0]])
_SIGN = np.array([[1.0, -1, -1, -1], [1, 1, -1, 1], [1, 1, 1, -1], [1, -1, 1, 1]])
_CONJ_SIGN = _SIGN * np.array([1.0, -1, -1, -1])[_IDX]


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of [..., 4] wxyz quaternions."""
    return ((a[..., _IDX] * _SIGN) @ b[..., None])[..., 0]


def quat_log(q: np.ndarray) -> np.ndarray:
    """Rotation vector [..., 3] (rad) of unit quaternions [..., 4], taking the shorter way round."""
    v = q[..., 1:] * np.where(q[..., :1] < 0, -1.0, 1.0)
    s = np.sqrt((v * v).sum(-1))
    angle = 2.0 * np.arctan2(s, np.abs(q[..., 0]))
    # angle / s -> 2 as s -> 0 (small rotation): the limit keeps it finite.
    big = s > 1e-12
    scale = np.divide(angle, s, out=_filled(s.shape, 2.0), where=big)
    return v * scale[..., None]


def _filled(shape: tuple[int, ...], value: float) -> np.ndarray:
    """np.full without its Python-level overhead (this runs on a few numbers every control step)."""
    a = np.empty(shape)
    a.fill(value)
    return a


@dataclasses.dataclass(frozen=True)
class Commands:
    """The velocity setpoints sent lately, oldest first: ``u[k]`` [..., n, 3] was sent at ``t[k]`` [...] (s, the poses'
    clock; -inf: an empty slot) and flown until the next one was sent. Before the oldest, the oldest is assumed."""

    t: np.ndarray  # [K, ...]
    u: np.ndarray  # [K, ..., n, 3]

    @classmethod
    def empty(cls, shape: tuple[int, ...], n: int, slots: int) -> Commands:
        """No command yet for a batch ``shape`` of ``n`` drones, keeping the last ``slots``."""
        return cls(t=np.full((slots,) + shape, -np.inf), u=np.zeros((slots,) + shape + (n, 3)))

    @staticmethod
    def slots(oldest_pose: float, rate_hz: float) -> int:
        """Commands to keep so that a pose up to ``oldest_pose`` s old and one pose interval more are covered."""
        return int(np.ceil(oldest_pose * rate_hz)) + 2

    def sent(self, t: np.ndarray, u: np.ndarray) -> Commands:
        """With ``u`` [..., n, 3] sent at ``t`` [...] (the oldest slot drops out)."""
        return Commands(t=np.concatenate([self.t[1:], np.asarray(t, np.float64)[None]]),
                        u=np.concatenate([self.u[1:], np.asarray(u, np.float64)[None]]))


def update(state: EstimatorState, t: np.ndarray, pos: np.ndarray, quat: np.ndarray, valid: np.ndarray,
           config: EstimatorConfig = EstimatorConfig(), commands: Commands | np.ndarray | None = None,
           ) -> tuple[EstimatorState, np.ndarray, np.ndarray]:
    """Push one pose per drone: t [..., n], pos [..., n, 3], quat [..., n, 4] (unit), valid [..., n] bool.

    ``commands``: what the drones flew since their previous poses, the model estimate's input: the
    :class:`Commands` sent lately, or one array [..., n, 3] flown throughout (zero if None). Returns the new
    state, ``accepted`` [..., n] (a new pose entered the window) and ``glitch`` [..., n] (a valid, newer
    pose was rejected for an implausible jump).
    """
    last_t = state.t[..., -1]
    newer = valid & (t > last_t)
    check = newer & (state.count > 0)  # a newer pose after an earlier one: a jump to check
    dt = np.subtract(t, last_t, out=_filled(t.shape, np.inf), where=check)
    step = pos - state.pos[..., -1, :]
    jump = np.sqrt((step * step).sum(-1))
    glitch = jump > config.max_speed * dt  # (dt is inf where there is nothing to check)
    accept = newer & ~glitch
    t_new = np.concatenate([state.t[..., 1:], t[..., None]], -1)
    pos_new = np.concatenate([state.pos[..., 1:, :], pos[..., None, :]], -2)
    quat_new = np.concatenate([state.quat[..., 1:, :], quat[..., None, :]], -2)
    count = np.minimum(state.count + 1, config.window)
    if not accept.all():  # in flight every drone's pose is usually new: nothing to keep then
        a3 = accept[..., None, None]
        t_new = np.where(accept[..., None], t_new, state.t)
        pos_new = np.where(a3, pos_new, state.pos)
        quat_new = np.where(a3, quat_new, state.quat)
        count = np.where(accept, count, state.count)
    kf = {}
    if config.velocity == "model":
        kf = _kalman(state, t, pos, commands, accept, config)
    return EstimatorState(t=t_new, pos=pos_new, quat=quat_new, count=count, **kf), accept, glitch


def _kalman(state: EstimatorState, t, pos, commands, accept, config: EstimatorConfig) -> dict:
    """The model estimate's predict (over each drone's time since its last pose) and correct (with its new pose)."""
    first = accept & (state.count == 0)
    # Drones without a new pose (their t may be NaN or -inf) or with their first: no time passes, nothing changes.
    end = np.where(accept, t, 0.0)
    start = np.where(accept & ~first, state.t[..., -1], end)
    p, v, P = _propagate(state.kf_pos, state.kf_vel, state.kf_cov, start, end, commands, config)
    r2 = config.pos_noise**2
    s = P[..., 0] + r2
    k_p, k_v = P[..., 0] / s, P[..., 1] / s
    res = np.where(accept[..., None], pos, p) - p
    p_new, v_new = p + k_p * res, v + k_v * res
    cov = np.stack([(1 - k_p) * P[..., 0], (1 - k_p) * P[..., 1], P[..., 2] - k_v * P[..., 1]], -1)
    # A drone's first pose: its position, at rest, as unsure of its velocity as of a second's worth of the model error.
    f = first[..., None]
    p_new = np.where(f, pos, p_new)
    v_new = np.where(f, 0.0, v_new)
    cov = np.where(f[..., None], np.array([r2, 0.0, config.accel_noise**2]), cov)
    keep = ~accept[..., None]
    return dict(kf_pos=np.where(keep, state.kf_pos, p_new), kf_vel=np.where(keep, state.kf_vel, v_new),
                kf_cov=np.where(keep[..., None], state.kf_cov, cov))


def _propagate(p, v, P, start, end, commands, config: EstimatorConfig):
    """The model from times ``start`` to ``end`` [..., n] (end >= start), flying ``commands``: exact for a
    first-order velocity lag under piecewise-constant commands. ``P`` (per axis (P_pp, P_pv, P_vv)) grows with
    the model error; None: positions and velocities only."""
    lag_xy, lag_z = config.lag or FIRMWARE_PID_LAG
    tau = np.array([lag_xy, lag_xy, lag_z])
    if commands is None or not isinstance(commands, Commands):
        u = np.zeros(p.shape) if commands is None else np.asarray(commands, np.float64)
        pieces = [((end - start)[..., None], u)]
    else:  # each command's share of [start, end]: from its send time (the oldest's: -inf) to the next one's
        t = commands.t[..., None]  # [K, ..., 1]
        lo = np.maximum(start, t)
        lo[0] = start
        hi = np.empty(lo.shape)
        np.minimum(end, t[1:], out=hi[:-1])
        hi[-1] = end
        h = np.maximum(hi - lo, 0.0)
        pieces = [(h[k][..., None], commands.u[k]) for k in np.nonzero(h.reshape(len(h), -1).any(1))[0]]
    q = config.accel_noise**2
    for h, u in pieces:
        a = np.exp(-h / tau)
        b = tau * (1.0 - a)  # position gained per unit of initial velocity
        p, v = p + b * v + (h - b) * u, a * v + (1.0 - a) * u
        if P is not None:
            # Acceleration error q per unit time, as a constant acceleration over the piece.
            P = np.stack([P[..., 0] + 2 * b * P[..., 1] + b * b * P[..., 2] + q * h**4 / 4,
                          a * (P[..., 1] + b * P[..., 2]) + q * h**3 / 2, a * a * P[..., 2] + q * h**2], -1)
    return p, v, P


def predict(state: EstimatorState, now: np.ndarray, commands: Commands | np.ndarray | None,
            config: EstimatorConfig = EstimatorConfig()) -> tuple[np.ndarray, np.ndarray]:
    """The model estimate's (position, velocity) [..., n, 3] carried from each drone's newest pose to ``now``
    [...] with the commands flown since: what it most likely is when the command computed from it flies."""
    t_last = state.t[..., -1]
    end = np.maximum(np.broadcast_to(np.asarray(now, np.float64)[..., None], t_last.shape), t_last)
    start = np.where(np.isfinite(t_last), t_last, end)
    p, v, _ = _propagate(state.kf_pos, state.kf_vel, None, start, end, commands, config)
    return p, v


def _slope(t: np.ndarray, y: np.ndarray, w: np.ndarray | None) -> np.ndarray:
    """Weighted least-squares slope of y [..., W, k] against t [..., W] (weights w [..., W] in {0, 1}, None: all 1)."""
    # Times relative to the newest sample (no large offsets); unfilled slots hold -inf and weight 0.
    if w is None:  # full windows, the steady state: the line the simulator fits too (core.estimation)
        return (slope_weights(t - t[..., -1:])[..., None, :] @ y)[..., 0, :]
    sw = np.maximum(w.sum(-1, keepdims=True), 1.0)
    tc = np.subtract(t, t[..., -1:], out=np.zeros(t.shape), where=w > 0)
    dt = (tc - (w * tc).sum(-1, keepdims=True) / sw) * w
    den = (dt * dt).sum(-1, keepdims=True)
    # Σ dt_i (y_i − ȳ) = Σ dt_i y_i since Σ dt_i = 0.
    num = (dt[..., None, :] @ y)[..., 0, :]
    return np.divide(num, den, out=np.zeros(num.shape), where=den > 0)


def estimate(state: EstimatorState, config: EstimatorConfig = EstimatorConfig()) -> tuple[np.ndarray, np.ndarray]:
    """(velocity [..., n, 3] world m/s, angular rate [..., n, 3] body rad/s); zero until 2 poses are in."""
    W = config.window
    full = bool(state.count.size) and int(state.count.min()) >= W
    w = None if full else (np.arange(W) >= W - state.count[..., None]).astype(np.float64)
    q_last = state.quat[..., -1, :]
    rel = quat_log(state.quat @ (q_last[..., _IDX] * _CONJ_SIGN).swapaxes(-1, -2))  # conj(q_last) ⊗ q_i, [..., W, 3]
    if config.velocity == "model":
        return state.kf_vel.copy(), _slope(state.t, rel, w)
    rates = _slope(state.t, np.concatenate([state.pos, rel], -1), w)
    return rates[..., :3], rates[..., 3:]


def latest(state: EstimatorState) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t [..., n], pos [..., n, 3], quat [..., n, 4]) of the newest accepted pose."""
    return state.t[..., -1], state.pos[..., -1, :], state.quat[..., -1, :]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The velocity estimate's options, as ``aswarm sitl`` and ``aswarm fly`` take them."""
    d = EstimatorConfig()
    p.add_argument("--velocity-estimate", choices=VELOCITY_ESTIMATES, default=d.velocity,
                   help="model: a Kalman filter on the drone's measured velocity lag, driven by the commands sent; "
                        "window: the least-squares slope of the last poses (default %(default)s)")
    p.add_argument("--estimator-window", type=int, default=d.window, metavar="POSES",
                   help="poses in the least-squares fit (the velocity for 'window', the angular rate always; "
                        "default %(default)s)")
    p.add_argument("--accel-noise", type=float, default=d.accel_noise, metavar="M/S2",
                   help="'model': the model's acceleration error, how little it is trusted (default %(default)s)")
    p.add_argument("--pos-noise", type=float, default=d.pos_noise, metavar="METRES",
                   help="'model': the poses' noise (default %(default)s)")


def from_args(args: argparse.Namespace) -> EstimatorConfig:
    """The :class:`EstimatorConfig` of :func:`add_arguments`' options (``ValueError`` naming a bad value)."""
    return EstimatorConfig(window=args.estimator_window, velocity=args.velocity_estimate,
                           accel_noise=args.accel_noise, pos_noise=args.pos_noise)

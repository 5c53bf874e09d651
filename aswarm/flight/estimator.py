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
25 Hz lags 60 ms (15 ms on 100 Hz poses). A sample whose timestamp does not advance is a repeated
frame and is ignored; a jump faster than ``max_speed`` m/s is treated as a mocap glitch (a swapped or
mislabelled marker) and rejected.
The state is plain arrays (pure functions, leading batch axes ``...``, ``n`` drones).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from aswarm.core.estimation import slope_weights


@dataclasses.dataclass(frozen=True)
class EstimatorConfig:
    window: int = 4  # poses in the least-squares fit (>= 2)
    max_speed: float = 10.0  # m/s; a faster jump between two poses is rejected as a glitch

    def __post_init__(self) -> None:
        if not isinstance(self.window, int) or self.window < 2:
            raise ValueError(f"invalid window={self.window!r}: must be an integer >= 2")
        if not self.max_speed > 0:
            raise ValueError(f"invalid max_speed={self.max_speed!r}: must be > 0")


@dataclasses.dataclass(frozen=True)
class EstimatorState:
    """The last ``window`` accepted poses of each drone, newest last (unfilled slots have ``count`` < window)."""

    t: np.ndarray  # [..., n, W] s
    pos: np.ndarray  # [..., n, W, 3]
    quat: np.ndarray  # [..., n, W, 4] wxyz, unit (either sign: the rate uses the shorter rotation)
    count: np.ndarray  # [..., n] int, accepted poses (capped at W)


def init(shape: tuple[int, ...], config: EstimatorConfig = EstimatorConfig()) -> EstimatorState:
    """Empty state for drones of batch shape ``shape`` (e.g. ``(worlds, n)``)."""
    W = config.window
    quat = np.zeros(shape + (W, 4))
    quat[..., 0] = 1.0
    return EstimatorState(t=np.full(shape + (W,), -np.inf), pos=np.zeros(shape + (W, 3)), quat=quat,
                          count=np.zeros(shape, np.int64))


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


def update(state: EstimatorState, t: np.ndarray, pos: np.ndarray, quat: np.ndarray, valid: np.ndarray,
           config: EstimatorConfig = EstimatorConfig()) -> tuple[EstimatorState, np.ndarray, np.ndarray]:
    """Push one pose per drone: t [..., n], pos [..., n, 3], quat [..., n, 4] (unit), valid [..., n] bool.

    Returns the new state, ``accepted`` [..., n] (a new pose entered the window) and ``glitch``
    [..., n] (a valid, newer pose was rejected for an implausible jump).
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
    return EstimatorState(t=t_new, pos=pos_new, quat=quat_new, count=count), accept, glitch


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
    rel = state.quat @ (q_last[..., _IDX] * _CONJ_SIGN).swapaxes(-1, -2)  # conj(q_last) ⊗ q_i, [..., W, 4]
    rates = _slope(state.t, np.concatenate([state.pos, quat_log(rel)], -1), w)
    return rates[..., :3], rates[..., 3:]


def latest(state: EstimatorState) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t [..., n], pos [..., n, 3], quat [..., n, 4]) of the newest accepted pose."""
    return state.t[..., -1], state.pos[..., -1, :], state.quat[..., -1, :]

"""Forward passes of the exported networks in numpy, matching the JAX ones in ``aswarm.agents``.

- Normalizer: brax's ``running_statistics.normalize(obs, state, max_abs_value=OBS_NORM_CLIP)``, i.e.
  ``clip((obs - mean) / std, -10, 10)`` with ``std`` stored as such (not a variance).
- Actor (``networks.Actor``): tanh MLP to 6 numbers, ``[loc (3) | scale (3)]``. The deterministic
  command is the mean of brax's ``NormalTanhDistribution`` pushed through its tanh, times the
  maximum speed: ``tanh(loc) * max_speed`` (the scale only matters for sampling).
- Attention-CBF network (``networks.AttentionCBF``): flax's ``nn.gelu``, whose default is the tanh
  approximation, then attention over present hazards and an MLP to ``[penalty, gain]``.

Everything runs in float64 on float32 weights: at these sizes it costs nothing, and the result is
then the float32 network's up to its own rounding.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping

import numpy as np

from aswarm.core.layout import OBS_NORM_CLIP, PRESENT_THRESHOLD, ObsLayout

NORMALIZER_MAX_ABS = OBS_NORM_CLIP
_SQRT_2_OVER_PI = math.sqrt(2.0 / math.pi)


# The activations' constants as 0-d float64 arrays: numpy treats a Python float operand as a "weak"
# scalar, which costs about half an array operation more each time, and these run on a few hundred
# numbers per control step. Same numbers: the activations compute in float64 (as everything here).
_C_GELU = np.array(0.044715)
_C_SQRT_2_OVER_PI = np.array(_SQRT_2_OVER_PI)
_ONE, _HALF = np.array(1.0), np.array(0.5)


def gelu_tanh(x: np.ndarray) -> np.ndarray:
    """flax ``nn.gelu`` (= ``jax.nn.gelu(approximate=True)``), in float64."""
    x = np.asarray(x, np.float64)
    y = x * x
    y *= _C_GELU
    y += _ONE
    y *= x
    y *= _C_SQRT_2_OVER_PI
    np.tanh(y, out=y)
    y += _ONE
    y *= _HALF
    y *= x
    return y


def softplus(x: np.ndarray) -> np.ndarray:
    return np.logaddexp(x, 0.0)


def sigmoid(x: np.ndarray) -> np.ndarray:
    # The logistic function written with tanh: never overflows, and costs 4 array operations.
    y = np.multiply(x, _HALF, dtype=np.float64)
    np.tanh(y, out=y)
    y *= _HALF
    y += _HALF
    return y


ACTIVATIONS = {"tanh": np.tanh, "gelu_tanh": gelu_tanh, "relu": lambda x: np.maximum(x, 0.0),
               "silu": lambda x: x * sigmoid(x)}

Layer = tuple[np.ndarray, np.ndarray]  # (kernel [in, out], bias [out])


@dataclasses.dataclass(frozen=True)
class PolicyWeights:
    """The exported arrays, arranged for the forward passes (float64)."""

    mean: np.ndarray  # [D] observation normalizer
    std: np.ndarray  # [D]
    actor: tuple[Layer, ...]  # hidden layers then the output layer (6)
    cbf_state: Layer  # own features -> h
    cbf_query: np.ndarray  # [state_hidden, d]
    # Keys and values of both hazard kinds in one block matrix [cyl_dim + nbr_dim, 2d]: a cylinder's
    # features fill the first cyl_dim inputs, a neighbour's the rest (zeros elsewhere add exactly 0).
    cbf_key_value: np.ndarray
    cbf_head: tuple[Layer, ...]  # [h | context] -> [penalty, gain] (pre-activation)
    actor_activation: str = "tanh"
    cbf_activation: str = "gelu_tanh"


def _mlp_layers(arrays: Mapping[str, np.ndarray], prefix: str) -> tuple[Layer, ...]:
    layers, i = [], 0
    while f"{prefix}/Dense_{i}/kernel" in arrays:
        layers.append((np.asarray(arrays[f"{prefix}/Dense_{i}/kernel"], np.float64),
                       np.asarray(arrays[f"{prefix}/Dense_{i}/bias"], np.float64)))
        i += 1
    if not layers:
        raise ValueError(f"missing array {prefix}/Dense_0/kernel: allowed: a bundle written by `aswarm export`")
    return tuple(layers)


def weights_from_arrays(arrays: Mapping[str, np.ndarray], actor_activation: str = "tanh",
                        cbf_activation: str = "gelu_tanh") -> PolicyWeights:
    """Arrange a bundle's flat ``{name: array}`` (names like ``actor/MLP_0/Dense_0/kernel``)."""
    for act in (actor_activation, cbf_activation):
        if act not in ACTIVATIONS:
            raise ValueError(f"unsupported activation {act!r}: allowed: {', '.join(ACTIVATIONS)}")

    def get(name):
        if name not in arrays:
            raise ValueError(f"missing array {name!r}: allowed: a bundle written by `aswarm export`")
        return np.asarray(arrays[name], np.float64)

    return PolicyWeights(
        mean=get("obs_norm/mean"), std=get("obs_norm/std"),
        actor=_mlp_layers(arrays, "actor/MLP_0"),
        cbf_state=(get("cbf/Dense_0/kernel"), get("cbf/Dense_0/bias")),
        cbf_query=get("cbf/W_Q/kernel"),
        cbf_key_value=np.block([[get("cbf/W_K_cyl/kernel"), get("cbf/W_V_cyl/kernel")],
                                [get("cbf/W_K_nbr/kernel"), get("cbf/W_V_nbr/kernel")]]),
        cbf_head=_mlp_layers(arrays, "cbf/MLP_0"),
        actor_activation=actor_activation, cbf_activation=cbf_activation,
    )


def normalize(w: PolicyWeights, obs: np.ndarray) -> np.ndarray:
    x = obs - w.mean
    x /= w.std
    # np.clip, as two in-place ufuncs (np.clip's own overhead is a few array operations' worth).
    np.maximum(x, -NORMALIZER_MAX_ABS, out=x)
    return np.minimum(x, NORMALIZER_MAX_ABS, out=x)


def _dense(x: np.ndarray, layer: Layer) -> np.ndarray:
    y = x @ layer[0]
    y += layer[1]
    return y


def mlp(x: np.ndarray, layers: tuple[Layer, ...], activation: str) -> np.ndarray:
    act = ACTIVATIONS[activation]
    for layer in layers[:-1]:
        x = act(_dense(x, layer))
    return _dense(x, layers[-1])


def actor_command(w: PolicyWeights, nobs: np.ndarray, max_speed: float) -> np.ndarray:
    """Deterministic velocity commands [..., n, 3] (m/s, world) from normalized observations [..., n, D]."""
    out = mlp(nobs, w.actor, w.actor_activation)
    return np.tanh(out[..., :3]) * max_speed


@functools.lru_cache(maxsize=32)
def _presence_columns(layout: ObsLayout) -> np.ndarray:
    """Where the presence flags of the M cylinders then the n - 1 neighbours sit in an observation row."""
    cols = np.array(layout.presence_columns, dtype=np.intp)
    cols.setflags(write=False)
    return cols


def hazard_mask(layout: ObsLayout, raw_obs: np.ndarray) -> np.ndarray:
    """[..., M + n - 1] presence flags read from *raw* observations (as ``networks.hazard_mask``)."""
    return raw_obs[..., _presence_columns(layout)] > PRESENT_THRESHOLD


def cbf_params(w: PolicyWeights, layout: ObsLayout, nobs: np.ndarray, raw_obs: np.ndarray, *, gain_min: float,
               gain_max: float, penalty_max: float) -> tuple[np.ndarray, np.ndarray]:
    """(penalty, gain) [..., n] of the attention-CBF network; the gain is the filter's class-K gain (1/s)."""
    out = _cbf_head(w, layout, nobs, raw_obs)
    return np.minimum(softplus(out[..., 0]), penalty_max), _gain(out, gain_min, gain_max)


def cbf_gain(w: PolicyWeights, layout: ObsLayout, nobs: np.ndarray, raw_obs: np.ndarray, *, gain_min: float,
             gain_max: float) -> np.ndarray:
    """The gain of :func:`cbf_params` alone (all the safety filter uses)."""
    return _gain(_cbf_head(w, layout, nobs, raw_obs), gain_min, gain_max)


def _gain(out: np.ndarray, gain_min: float, gain_max: float) -> np.ndarray:
    return gain_min + (gain_max - gain_min) * sigmoid(out[..., 1])


def _cbf_head(w: PolicyWeights, layout: ObsLayout, nobs: np.ndarray, raw_obs: np.ndarray) -> np.ndarray:
    """The attention-CBF network's output [..., n, 2] before its activations: (penalty, gain)."""
    act = ACTIVATIONS[w.cbf_activation]
    own, cyl, nbr = layout.split(nobs)
    M, K, c = layout.num_cylinders, layout.num_neighbours, layout.cyl_dim
    h = act(_dense(own, w.cbf_state))
    q = h @ w.cbf_query
    d = q.shape[-1]
    feats = np.zeros(own.shape[:-1] + (M + K, c + layout.nbr_dim))
    feats[..., :M, :c] = cyl
    feats[..., M:, c:] = nbr
    kv = feats @ w.cbf_key_value  # [..., H, 2d]
    if M + K:
        mask = hazard_mask(layout, raw_obs)
        logits = (kv[..., :d] @ q[..., None])[..., 0] / math.sqrt(d)
        # As in JAX: absent hazards get logit -1e9, and the weights are masked after the softmax,
        # so with no hazard present the context is exactly zero.
        logits = np.where(mask, logits, -1e9)
        e = np.exp(logits - logits.max(-1, keepdims=True))
        alpha = e * (mask / e.sum(-1, keepdims=True))
        context = (alpha[..., None, :] @ kv[..., d:])[..., 0, :]
    else:
        context = np.zeros(q.shape)
    return mlp(np.concatenate([h, context], -1), w.cbf_head, w.cbf_activation)

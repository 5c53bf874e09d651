"""Hyperparameters that change only values, so many of them can share one compiled trainer.

``make_train(config, sweep_fields=(...))`` reads the listed fields from ``TrainState.hparams``
(scalars, traced) instead of from the frozen config (Python floats), so
``jax.vmap(init)(keys, values)`` with ``values = {field: [K]}`` and a vmapped ``update_chunk``
train K configurations in one program. Every other field (network sizes, number of worlds,
method, env settings) changes shapes or code and needs its own compile.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from aswarm.agents.config import TrainConfig

# Read inside the jitted update (losses, GAE, optimizer) or by the CBF network's output scaling.
VALUE_FIELDS: tuple[str, ...] = (
    "actor_lr", "critic_lr", "cbf_lr", "max_grad_norm", "clip", "gae_lambda", "gamma", "cbf_coef", "value_coef",
    "entropy_coef", "cost_limit", "lagrange_init", "penalty_max", "gain_min", "gain_max", "correction_penalty",
)
# The subset the attention-CBF network reads: it is rebuilt with traced bounds when any is swept.
NETWORK_FIELDS: tuple[str, ...] = ("penalty_max", "gain_min", "gain_max")


# Hyperparameters held in TrainConfig.safety_filter (swept under their field names there).
SAFETY_FIELDS: tuple[str, ...] = ("gain_min", "gain_max")


def value(config: TrainConfig, field: str):
    """The config's value of hyperparameter ``field``."""
    return getattr(config.safety_filter if field in SAFETY_FIELDS else config, field)


def replaced(config: TrainConfig, values: Mapping) -> TrainConfig:
    """``config`` with hyperparameters ``values`` ({field: value}) set."""
    safety = {f: v for f, v in values.items() if f in SAFETY_FIELDS}
    top = {f: v for f, v in values.items() if f not in SAFETY_FIELDS}
    if safety:
        top["safety_filter"] = dataclasses.replace(config.safety_filter, **safety)
    return dataclasses.replace(config, **top)


def check_fields(fields: Sequence[str]) -> tuple[str, ...]:
    """Sorted, de-duplicated ``fields``; a ValueError for one that is not a value-only hyperparameter."""
    for f in fields:
        if f not in VALUE_FIELDS:
            raise ValueError(f"invalid sweep field {f!r}: allowed (value-only hyperparameters): "
                             f"{', '.join(VALUE_FIELDS)}")
    return tuple(sorted(set(fields)))


def check_values(fields: tuple[str, ...], values: Mapping | None) -> dict:
    """``values`` as a dict holding exactly ``fields``; a ValueError names what is missing or extra."""
    values = dict(values or {})
    if set(values) != set(fields):
        raise ValueError(f"invalid hparams keys {sorted(values)}: allowed: exactly the sweep fields {list(fields)}")
    return values


def resolve(config: TrainConfig, values: Mapping, gain_scale: float = 1.0) -> dict:
    """Every value field: the traced value where swept, else the config's Python float (the default numbers).

    ``gain_scale``: the factor the safety filter's gains were fitted to the drone by (``SafetyFilterConfig.fitted``),
    applied to ``gain_min`` and ``gain_max``, swept or not: the CBF network's output range and its loss's target
    are then the fitted range the filter flies."""
    h = {f: values[f] if f in values else value(config, f) for f in VALUE_FIELDS}
    if gain_scale != 1.0:  # (a static choice: an unfitted config keeps its exact numbers)
        h.update({f: h[f] * gain_scale for f in SAFETY_FIELDS})
    return h


def values_of(config: TrainConfig, fields: Sequence[str]) -> dict:
    """The ``hparams`` of one configuration: float32 scalars of ``fields``."""
    return {f: jnp.asarray(value(config, f), jnp.float32) for f in check_fields(fields)}


def stack(configs: Sequence[TrainConfig], fields: Sequence[str]) -> dict:
    """``{field: [K] float32}`` over ``configs``: the batched ``hparams`` for ``jax.vmap(init)``."""
    fields = check_fields(fields)
    return {f: np.asarray([value(c, f) for c in configs], np.float32) for f in fields}


def varying(configs: Sequence[TrainConfig]) -> tuple[str, ...]:
    """The value fields whose values differ between ``configs``."""
    return tuple(f for f in VALUE_FIELDS if len({value(c, f) for c in configs}) > 1)


def index(tree, i: int):
    """Trial ``i`` of a stacked pytree (leading axis)."""
    return jax.tree.map(lambda x: x[i], tree)

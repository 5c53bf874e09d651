"""numpy as :func:`aswarm.core.geometry.namespace` hands it to the shared array-API code.

It is numpy itself, except for the few functions the shared builders (observations, barrier rows,
geometry) call many times on every control step of the flight runtime: numpy's own versions of
these are Python wrappers (argument checks, dispatch, ``out``/``where`` handling) that cost a few
microseconds each, more than the work on a swarm's small arrays. The replacements call the same C
routines directly and return the same arrays, value for value (a sum is the same ``add.reduce``, a
stack the same copy), so the flight runtime's numbers do not change. JAX never sees this module.
"""

from __future__ import annotations

import functools
import types

import numpy as np


class _Numpy(types.ModuleType):
    def __getattr__(self, name: str):
        # Everything not defined below is numpy's own, looked up once and then kept as an attribute.
        value = getattr(np, name)
        setattr(self, name, value)
        return value


NUMPY = _Numpy("numpy", "numpy with cheaper calls for the shared array-API code (aswarm.core.numpy_namespace)")


# Each replacement takes the arguments the shared code passes; any other keyword goes to numpy's own function.
def _sum(x, axis=None, dtype=None, keepdims: bool = False, **other):
    """``np.sum`` is this reduction behind a Python wrapper."""
    if other:
        return np.sum(x, axis=axis, dtype=dtype, keepdims=keepdims, **other)
    return np.add.reduce(x, axis=axis, dtype=dtype, keepdims=keepdims)


def _any(x, axis=None, keepdims: bool = False, **other):
    """``np.any`` is this reduction behind a Python wrapper."""
    if other:
        return np.any(x, axis=axis, keepdims=keepdims, **other)
    return np.logical_or.reduce(x, axis=axis, keepdims=keepdims)


def _stack(arrays, axis: int = 0, **other):
    """``np.stack``: a new axis on each array (all of one shape), then one concatenation."""
    if other:
        return np.stack(arrays, axis=axis, **other)
    arrays = [a if isinstance(a, np.ndarray) else np.asarray(a) for a in arrays]
    ndim = arrays[0].ndim
    if not -ndim - 1 <= axis <= ndim:
        return np.stack(arrays, axis=axis)  # numpy's own error
    pos = axis if axis >= 0 else axis + ndim + 1
    index = (slice(None),) * pos + (None,)
    return np.concatenate([a[index] for a in arrays], axis=pos)


def _zeros_like(x, dtype=None, **other):
    if other or not isinstance(x, np.ndarray):
        return np.zeros_like(x, dtype=dtype, **other)
    return np.zeros(x.shape, dtype=x.dtype if dtype is None else dtype)


def _ones_like(x, dtype=None, **other):
    if other or not isinstance(x, np.ndarray):
        return np.ones_like(x, dtype=dtype, **other)
    return np.ones(x.shape, dtype=x.dtype if dtype is None else dtype)


def _reshape(x, shape, **other):
    return x.reshape(shape) if isinstance(x, np.ndarray) and not other else np.reshape(x, shape, **other)


@functools.lru_cache(maxsize=64)
def _along_axis_index(shape: tuple[int, ...], axis: int) -> tuple:
    """The index ``np.take_along_axis`` builds for every axis but ``axis`` (an arange along it), built once per
    shape; ``axis``'s entry is left None for the indices."""
    index = []
    for dim, n in enumerate(shape):
        if dim == axis:
            index.append(None)
        else:
            r = np.arange(n).reshape((1,) * dim + (-1,) + (1,) * (len(shape) - dim - 1))
            r.setflags(write=False)
            index.append(r)
    return tuple(index)


def _take_along_axis(arr, indices, axis: int):
    """``np.take_along_axis``: the same fancy index, with the aranges of the other axes kept between calls."""
    if not (isinstance(arr, np.ndarray) and isinstance(indices, np.ndarray) and indices.dtype.kind in "iu"
            and isinstance(axis, int) and indices.ndim == arr.ndim and -arr.ndim <= axis < arr.ndim):
        return np.take_along_axis(arr, indices, axis=axis)  # numpy's own checks and errors
    axis %= arr.ndim
    index = list(_along_axis_index(arr.shape, axis))
    index[axis] = indices
    return arr[tuple(index)]


(NUMPY.sum, NUMPY.any, NUMPY.stack, NUMPY.zeros_like, NUMPY.ones_like, NUMPY.reshape,
 NUMPY.take_along_axis) = _sum, _any, _stack, _zeros_like, _ones_like, _reshape, _take_along_axis

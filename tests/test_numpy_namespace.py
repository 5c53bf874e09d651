"""The numpy namespace of the shared array-API code (aswarm.core.numpy_namespace) returns numpy's arrays bit for bit."""

import numpy as np
import pytest

from aswarm.core import geometry
from aswarm.core.numpy_namespace import NUMPY


def _same(a, b):
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def test_numpy_arrays_get_the_namespace_and_everything_else_is_numpys():
    x = np.zeros(3)
    assert geometry.namespace(x) is NUMPY and geometry.namespace(1.0, x) is NUMPY
    assert geometry.namespace(1.0) is np  # no array: numpy itself
    assert NUMPY.where is np.where and NUMPY.inf == np.inf and NUMPY.float32 is np.float32


def test_replaced_functions_return_numpys_arrays_bit_for_bit():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(2, 4, 3))
    x[0, 0] = -0.0
    for axis in (None, 0, -1, -2):
        _same(NUMPY.sum(x * x, axis=axis), np.sum(x * x, axis=axis))
        _same(NUMPY.any(x > 1.0, axis=axis), np.any(x > 1.0, axis=axis))
    _same(NUMPY.sum(x > 0, axis=-1), np.sum(x > 0, axis=-1))  # booleans count as integers
    _same(NUMPY.sum(x, axis=-1, where=x > 0), np.sum(x, axis=-1, where=x > 0))  # other keywords: numpy's own
    assert NUMPY.zeros_like(x, order="F").flags.f_contiguous
    parts = [x, -x, 2 * x]
    for axis in (0, 1, 3, -1, -2, -4):
        _same(NUMPY.stack(parts, axis=axis), np.stack(parts, axis=axis))
    _same(NUMPY.stack([1.0, 2.0]), np.stack([1.0, 2.0]))
    with pytest.raises(np.exceptions.AxisError):
        NUMPY.stack(parts, axis=4)
    for like in (NUMPY.zeros_like, NUMPY.ones_like):
        ref = np.zeros_like if like is NUMPY.zeros_like else np.ones_like
        _same(like(x[..., 0]), ref(x[..., 0]))
        _same(like(x, dtype=bool), ref(x, dtype=bool))
        _same(like(2.0), ref(2.0))
    _same(NUMPY.reshape(x, (8, 3)), np.reshape(x, (8, 3)))
    idx = rng.integers(0, 4, (2, 3, 1))
    for axis in (1, -2):
        _same(NUMPY.take_along_axis(x, idx, axis=axis), np.take_along_axis(x, idx, axis=axis))
    order = np.argsort(x[..., 0], axis=-1)
    _same(NUMPY.take_along_axis(x[..., 0], order, axis=-1), np.take_along_axis(x[..., 0], order, axis=-1))
    _same(NUMPY.take_along_axis(x, idx[:1], axis=-2), np.take_along_axis(x, idx[:1], axis=-2))  # broadcast
    with pytest.raises(IndexError):
        NUMPY.take_along_axis(x, idx.astype(float), axis=-2)

"""experiments/filter_binding.py: which rows took a command's speed, against hand-built active sets."""

import jax.numpy as jnp
import numpy as np
from experiment_scripts import load


def test_attribute_by_hand():
    # Three drones, rows [cylinder | gate bar x 2] (groups at offsets 0, 1, 3). Drone 0 asked 2 m/s along x and got
    # 1 with its cylinder row binding. Drone 1 got what it asked (a binding row changed nothing: it counts nowhere).
    # Drone 2 was changed but is not flying (finished): it counts nowhere.
    active = jnp.asarray([[True, False, False], [True, False, False], [True, False, False]])
    cmd = jnp.asarray([[2.0, 0.0, 0.0], [0.5, 0.0, 0.0], [2.0, 0.0, 0.0]])
    u = jnp.asarray([[1.0, 0.0, 0.0], [0.5, 0.0, 0.0], [1.0, 0.0, 0.0]])
    flying = jnp.asarray([True, True, False])
    tight, lost = load("filter_binding").attribute(active, u, cmd, flying, [0, 1, 3])
    np.testing.assert_array_equal(np.asarray(tight), [[True, False], [False, False], [False, False]])
    np.testing.assert_allclose(np.asarray(lost), [1.0, 0.0, 0.0])
    # A sideways change takes no speed along the ask: 2 m/s along x flown as (2, 1) with a gate row binding loses
    # nothing, and the gate group is the one counted.
    tight, lost = load("filter_binding").attribute(jnp.asarray([[False, True, False]]), jnp.asarray([[2.0, 1.0, 0.0]]),
                                                   cmd[:1], flying[:1], [0, 1, 3])
    np.testing.assert_array_equal(np.asarray(tight), [[False, True]])
    np.testing.assert_allclose(np.asarray(lost), [0.0])

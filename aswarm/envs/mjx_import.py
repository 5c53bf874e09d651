"""``mjx``, imported quietly.

mujoco-mjx prints "Failed to import warp" on stdout when the optional Warp GPU
backend is absent (every CPU machine); that would corrupt machine-readable
output such as ``--json``. Import ``mjx`` from here instead.
"""

import contextlib
import io

with contextlib.redirect_stdout(io.StringIO()):
    from mujoco import mjx  # noqa: F401

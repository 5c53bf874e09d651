import os
import tempfile

# Tests run on the CPU whatever the machine has.
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402

# Many tests compile the same programs (each run builds fresh closures): a persistent cache
# turns the repeats into cache hits.
jax.config.update("jax_compilation_cache_dir", os.path.join(tempfile.gettempdir(), "aswarm-test-jax-cache"))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)

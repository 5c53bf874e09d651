import os
import tempfile
from importlib.metadata import version

# Tests run on the CPU whatever the machine has.
os.environ.setdefault("JAX_PLATFORMS", "cpu")
# Tests compile many small programs and run each briefly, so the suite's time is mostly XLA:CPU compiling. Without
# LLVM's optimisations it compiles them in about two thirds of the time, and without its newer fusion emitters
# (the older loop emitters generate far less code) in about half of that again; the slower code costs less than
# the compile saves (BENCHMARKS.md, "Test suite"). Subprocesses that tests start inherit them. Programs of
# `aswarm` itself, outside the tests, compile with XLA's defaults.
# jaxlib 0.11 dropped the older emitters (and their flag), and XLA aborts the whole process, silently under
# pytest's capture, on a flag it does not know.
_JAXLIB = tuple(int(part) for part in version("jaxlib").split(".")[:2])
TEST_XLA_FLAGS = "--xla_backend_optimization_level=0" + (
    " --xla_cpu_use_fusion_emitters=false" if _JAXLIB < (0, 11) else "")
if TEST_XLA_FLAGS not in os.environ.get("XLA_FLAGS", ""):  # (pytest-xdist's workers inherit it)
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {TEST_XLA_FLAGS}".strip()

import jax  # noqa: E402

# Many tests compile the same programs (each run builds fresh closures): a persistent cache
# turns the repeats into cache hits.
jax.config.update("jax_compilation_cache_dir", os.path.join(tempfile.gettempdir(), "aswarm-test-jax-cache"))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)

# The longest files first. `make test` runs `pytest -n 2 --dist loadfile`: each file runs whole on one of two
# workers (its module fixtures, such as a tiny trained run, are built once), and handing out the long files
# first keeps both workers busy to the end (a long file started last left one worker idle for minutes).
LONGEST_FIRST = ("test_train.py", "test_sharding.py", "test_recovery.py", "test_sweep.py", "test_env.py",
                 "test_flight.py", "test_paper_table.py", "test_export.py", "test_plots.py")


def pytest_collection_modifyitems(items) -> None:
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: order within a file is kept

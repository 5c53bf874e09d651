import os

# Tests run on the CPU whatever the machine has; two host devices let sharding tests run here.
os.environ.setdefault("JAX_PLATFORMS", "cpu")

"""The evaluation protocol's constants, free of JAX (the command line reads them to build its flags)."""

# Evaluation draws its layouts from this seed on; training seeds are small integers, so every evaluated
# episode is unseen in training. eval, sitl, plot, render, the MPC and the experiments all start here.
EVAL_SEED = 10_000

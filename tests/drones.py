"""The drone for tests that test something else (the trainer, checkpoints, sharding, plots, export).

The geometric drone of before issue #12 (``envs.config.LEGACY_DRONE``) as env overrides: 250 Hz physics, no
rotor lag, nothing randomised. Its programs compile in about three quarters of the firmware drone's time (500 Hz
loops, the PID cascade, randomisation), and the suite's time is mostly compiling. The firmware drone has tests of
its own (test_firmware_pid.py, test_env.py, test_safety_filter_env.py, test_train.py's hover learning test).
"""

GEOMETRIC = (("controller", "geometric"), ("sim_freq", 250), ("ctrl_freq", 250), ("cf.motor_tau", 0.0),
             ("randomize.enabled", False), ("command_accel_limit", 0.0))
# The same as `aswarm train` flags.
GEOMETRIC_FLAGS = tuple(f"--env={k}={str(v).lower()}" for k, v in GEOMETRIC)

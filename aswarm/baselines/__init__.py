"""Non-learning baselines (sampling MPC)."""

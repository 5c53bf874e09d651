"""The shared contract of simulator, filter, MPC and flight runtime: free of JAX, written once against the array API."""

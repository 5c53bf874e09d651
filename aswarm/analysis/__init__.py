"""Evaluation, figures, videos and benchmarks of trained policies."""

"""experiments/band_at_gate.py: the gap from a gate's exit to a moving cylinder's swept band, by hand."""

import math

import numpy as np
from experiment_scripts import load


def test_exit_gaps_by_hand():
    # Gate 0 at the origin passed along +x; gate 1 at (5, 0) passed along -x; gate 2 at (0, 5) passed along +y.
    # Cylinder 0 (radius 0.2) sweeps y in [-0.3, 1.3] at x = 1: past gate 0's plane, its band 1 - 0.2 from gate 0's
    # centre and 4 - 0.2 from gate 1's. Cylinder 1 moves at x = -0.5 (before gate 0's plane, past gate 1's, 5.3 m
    # off); cylinder 2 is static and cylinder 3 absent, both right past gate 0. Nothing moving lies past gate 2.
    gate_pos = np.array([[0.0, 0.0, 1.0], [5.0, 0.0, 1.0], [0.0, 5.0, 1.0]])
    gate_yaw = np.array([0.0, math.pi, math.pi / 2])
    center = np.array([[1.0, 0.5], [-0.5, 0.0], [0.5, 0.0], [0.4, 0.0]])
    axis = np.array([[0.0, 1.0], [0.0, 1.0], [0.0, 1.0], [0.0, 1.0]])
    amplitude = np.array([0.8, 0.8, 0.0, 0.8])
    radius = np.full(4, 0.2)
    present = np.array([True, True, True, False])
    gaps = load("band_at_gate").exit_gaps(gate_pos, gate_yaw, center, axis, amplitude, radius, present)
    np.testing.assert_allclose(gaps[:2], [0.8, 3.8], atol=1e-9)
    assert gaps[2] == np.inf


def test_replayed_reads_the_episode_lines():
    log = ("200 episodes in one batch: 79.5% success, 41 failed\nepisode 2: 60.0 s, 1 of 4 finished\n"
           "  drone 1 legs\nepisode 13: 60.0 s, 0 of 4 finished\n")
    assert load("band_at_gate").replayed(log) == [2, 13]

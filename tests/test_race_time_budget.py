"""experiments/race_time_budget.py: the time budget of recorded flights, against hand-counted numbers."""

import numpy as np
import pytest
from experiment_scripts import load


def _module():
    return load("race_time_budget")


def test_the_budget_splits_flight_time_by_segment_and_speed_hand_counted():
    mod = _module()
    # One episode, two drones, steps of 0.5 s. Drone 0 flies steps 0-3 (segment 0 for two steps at 1 and 0.2 m/s,
    # then segment 1 at 2 m/s); drone 1 is released at step 2 and flies steps 2-5, all in segment 0 at 0.4 m/s.
    T = 6
    fly = np.zeros((T, 1, 2), bool)
    fly[0:4, 0, 0] = True
    fly[2:6, 0, 1] = True
    speed = np.zeros((T, 1, 2))
    speed[:, 0, 0] = [1.0, 0.2, 2.0, 2.0, 0.0, 0.0]
    speed[:, 0, 1] = 0.4
    target = np.zeros((T, 1, 2), int)
    target[2:, 0, 0] = 1
    asked = np.where(fly, 2.0, 0.0)
    flown = np.where(fly, 1.0, 0.0)
    rec = dict(flying=fly, speed=speed, target=target, asked=asked, flown=flown,
               finish=np.array([[2.0, 3.0]]))
    b = mod.budget(rec, np.array([0]), release=np.array([0.0, 1.0]), dt=0.5, slow=0.5)
    assert b["mission_time"] == 3.0 and b["last_release"] == 1.0
    assert b["drone_flight_time"] == pytest.approx(2.0)  # both fly 4 steps of 0.5 s
    # Speeds over the 8 flying drone-steps: (1 + 0.2 + 2 + 2 + 4 x 0.4) / 8.
    assert b["mean_speed"] == pytest.approx(6.8 / 8)
    assert b["path_length"] == pytest.approx((5.2 * 0.5 + 1.6 * 0.5) / 2)
    assert b["slow_fraction"] == pytest.approx(5 / 8)  # 0.2 once and 0.4 four times
    assert b["asked_speed"] == 2.0 and b["flown_command_speed"] == 1.0
    # Segment 0: drone 0 for 1 s, drone 1 for 2 s; segment 1: drone 0 for 1 s, drone 1 none (mean over drones).
    assert b["segment_time"] == pytest.approx([1.5, 0.5])
    assert b["segment_speed"][0] == pytest.approx((0.6 + 0.4) / 2)
    prof = mod.speed_profile(rec, np.array([0]), 2)
    assert prof.shape == (2, 10) and prof[1, 0] == pytest.approx(2.0)

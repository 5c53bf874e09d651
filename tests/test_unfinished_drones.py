"""experiments/unfinished_drones.py: the rows of a timed-out episode, against a hand-built one."""

import numpy as np
import pytest
from experiment_scripts import load


def _module():
    return load("unfinished_drones")


def test_unfinished_rows_by_hand():
    # 4 drones, 4 instants: drone 0 finished, drone 3 collided, drones 1 and 2 still flying; drone 1 hovers 3-4-5
    # from where drone 2 ends.
    pos = np.zeros((4, 4, 3))
    pos[:, 2] = [[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [2.0, 0.0, 1.0], [2.0, 0.0, 1.0]]  # stopped for the last step
    pos[:, 1] = [3.0, 4.0, 1.0]
    pos[:, 3] = [2.0, 0.5, 1.0]  # nearer to drone 2 than drone 1 is, but out of the episode
    goal = np.array([[9.0, 9.0, 1.0], [3.0, 4.0, 2.0], [5.0, 4.0, 1.0], [0.0, 0.0, 1.0]])
    finished, collided = np.array([True, False, False, False]), np.array([False, False, False, True])
    flying = np.broadcast_to(~(finished | collided), (4, 4))
    rows = _module().unfinished(pos, goal, finished, collided, flying, steps_back=2)
    assert [r["drone"] for r in rows] == [1, 2]
    r = rows[1]
    np.testing.assert_allclose(r["gap"], 5.0)  # (2, 0) to (5, 4)
    np.testing.assert_allclose(r["nearest"], np.hypot(1.0, 4.0))  # drone 1; the collided drone 3 is not flying
    np.testing.assert_allclose(r["moved"], 1.0)  # instant 1 to 3: x 1 -> 2
    np.testing.assert_allclose([rows[0]["gap"], rows[0]["moved"]], [1.0, 0.0])


def test_alone_drone_has_no_nearest():
    pos = np.zeros((2, 2, 3))
    pos[:, 1, 0] = 1.0
    flying = np.array([[True, True], [False, True]])
    rows = _module().unfinished(pos, np.ones((2, 3)), np.array([True, False]), np.zeros(2, bool), flying, 5)
    assert rows[0]["nearest"] == float("inf") and rows[0]["moved"] == 0.0


def test_legs_by_hand():
    # 2 drones at 1 s instants: drone 0 reaches waypoint 0 at 2 s and waypoint 1 at 5 s; drone 1 only waypoint 0,
    # at 4 s; the index stays at the last waypoint + 1 once reached.
    time = np.arange(7.0)
    target = np.array([[0, 0], [0, 0], [1, 0], [1, 0], [1, 1], [2, 1], [2, 1]])
    assert _module().legs(target, time) == [[(0, 2.0), (1, 3.0)], [(0, 4.0)]]
    # drone 1 still flying at 6 s: its open leg to waypoint 1, 2 s so far
    assert _module().legs(target, time, np.array([False, True]))[1] == [(0, 4.0), (1, 2.0)]


def test_gate_sides_by_hand():
    # One gate at the origin passed along +y, half opening 0.4. Drone 0 crosses the plane 1 m to the side (beside
    # the gate: not counted, its target stays 0) and ends 0.5 m past it; drone 1 crosses inside the opening (its
    # target goes to 1: done, NaN after).
    gate_pos, gate_yaw = np.zeros((1, 3)), np.array([np.pi / 2])
    pos = np.zeros((3, 2, 3))
    pos[:, 0] = [[1.0, -0.5, 0.0], [1.0, 0.2, 0.0], [1.0, 0.5, 0.0]]
    pos[:, 1] = [[0.1, -0.5, 0.1], [0.1, 0.3, 0.1], [0.1, 0.6, 0.1]]
    target = np.array([[0, 0], [0, 1], [0, 1]])
    beside, side = _module().gate_sides(pos, target, gate_pos, gate_yaw, 0.4)
    assert beside.tolist() == [1, 0]
    np.testing.assert_allclose(side[:, 0], [-0.5, 0.2, 0.5], atol=1e-12)
    assert side[0, 1] == -0.5 and np.isnan(side[1:, 1]).all()


def test_bad_only_gets_a_one_line_error(capsys):
    for only, allowed in (("6,x", "episode numbers separated by commas"), ("8", "episode numbers from 0 to 7")):
        with pytest.raises(SystemExit) as e:
            _module().main(["--checkpoint", "pretrained", "--only", only])
        assert e.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert f"invalid --only={only!r}" in err and allowed in err


def test_sweep_gap_by_hand():
    # Cylinder 0 (radius 0.2) sweeps x in [-0.8, 0.8] at y = 0; cylinder 1 is static and cylinder 2 absent, both
    # nearer. A drone (radius 0.05) at (0.5, 1.0) is 1 m off the band's middle: 1 - 0.2 - 0.05; at (2.0, 0.0), 1.2
    # m beyond the end of the sweep: 1.2 - 0.25.
    center = np.array([[0.0, 0.0], [0.5, 1.1], [2.0, 0.1]])
    axis = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 0.0]])
    amplitude, radius = np.array([0.8, 0.0, 0.8]), np.full(3, 0.2)
    present = np.array([True, True, False])
    gap = _module().sweep_gap
    np.testing.assert_allclose(gap(np.array([0.5, 1.0, 1.0]), center, axis, amplitude, radius, present, 0.05), 0.75)
    np.testing.assert_allclose(gap(np.array([2.0, 0.0, 1.0]), center, axis, amplitude, radius, present, 0.05), 0.95)
    assert gap(np.zeros(3), center, axis, np.zeros(3), radius, present, 0.05) == float("inf")

"""experiments/sitl_trace.py: the sorting of SITL's failed episodes, on hand-built steps."""

from types import SimpleNamespace

import numpy as np
import pytest
from experiment_scripts import load

trace = load("sitl_trace")


def _step(rec, pos, done, success, collision, finished=None, seen=None, nominal=None, sent=None):
    sensed = SimpleNamespace(pos=np.array(pos, float), done=np.array(done, float),
                             metrics={"success": np.array(success, float), "collision": np.array(collision, float)})
    out = None if finished is None else SimpleNamespace(
        finished=np.array(finished, bool), position=np.array(seen, float), nominal=np.array(nominal, float),
        velocity=np.array(sent, float))
    rec(sensed, out)


def test_failed_episodes_are_sorted_into_runtime_finishes_and_time_outs():
    # Four worlds of two drones, goals at the origin and at (5, 0, 0), radius 0.2. World 0 succeeds; world 1 fails
    # though the runtime finished both drones: drone 1's true path stayed 0.25 m from its goal while the runtime saw it
    # 0.15 m away; world 2 times out with drone 0 asking 1 m/s and let through 0.1 (held); world 3 collides.
    goals = np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]])
    rec = trace.Recorder()
    true0 = np.broadcast_to(goals + [[0.3, 0, 0], [0, 0.3, 0]], (4, 2, 3))
    true1 = np.broadcast_to(goals + [[0.1, 0, 0], [0, 0.25, 0]], (4, 2, 3))
    seen1 = np.broadcast_to(goals + [[0.1, 0, 0], [0, 0.15, 0]], (4, 2, 3))
    nominal = np.zeros((4, 2, 3))
    nominal[2, 0] = [1.0, 0.0, 0.0]
    sent = np.zeros((4, 2, 3))
    sent[2, 0] = [0.1, 0.0, 0.0]
    no = np.zeros(4)
    _step(rec, true0, no, no, no, np.zeros((4, 2), bool), true0, nominal, sent)
    # World 3 ends (a collision) at the second step: its outcome is read there and kept.
    _step(rec, true1, [0, 0, 0, 1], no, [0, 0, 0, 1], [[1, 1], [1, 1], [0, 1], [0, 0]], seen1, nominal, sent)
    _step(rec, true1, [0, 0, 0, 1], no, no, [[1, 1], [1, 1], [0, 1], [0, 0]], seen1, nominal, sent)
    _step(rec, true1, [1, 1, 1, 1], [1, 0, 0, 0], no)  # after the last step: no runtime answer
    failed = trace.classify(rec, goals, 0.2)
    assert [f["episode"] for f in failed] == [1, 2]
    one, two = failed
    assert one["kind"] == "finished by the runtime alone" and [d["drone"] for d in one["drones"]] == [1]
    assert one["drones"][0]["closest_true"] == pytest.approx(0.25)
    assert one["drones"][0]["at_finish"] == pytest.approx(0.15)
    assert two["kind"] == "time-out" and [d["drone"] for d in two["drones"]] == [0]
    d = two["drones"][0]
    assert d["asked"] == pytest.approx(1.0) and d["let"] == pytest.approx(0.1) and d["held"]
    assert d["to_goal"] == pytest.approx(0.1)


def test_a_track_bundle_is_refused(tmp_path, capsys):
    from aswarm.flight import bench, bundle

    b = bench.synthetic_bundle()
    bundle.write_bundle(tmp_path / "b", dict(b.arrays),
                        {k: v for k, v in b.manifest.items() if k not in ("arrays", "npz_sha256")})
    assert trace.main(["--bundle", str(tmp_path / "b")]) == 2
    assert "invalid bundle" in capsys.readouterr().err

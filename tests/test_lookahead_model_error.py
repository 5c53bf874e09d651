"""experiments/lookahead_model_error.py: the fit recovers the look-ahead of velocity responses known in closed form."""

import numpy as np
import pytest
from experiment_scripts import load
from scipy.linalg import expm


def _second_order(w, z, dt, u_seq):
    """p, v, a after each step (and at the start) of (1/w²) v'' + (2z/w) v' + v = u, u held over each step: exact
    (the matrix exponential of the linear system), per horizontal axis."""
    # state (p, v, a): p' = v, v' = a, a' = w² (u − v) − 2 z w a
    A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, -w * w, -2 * z * w]])
    B = np.array([0.0, 0.0, w * w])
    M = expm(np.block([[A, B[:, None]], [np.zeros((1, 4))]]) * dt)  # exact with u constant over dt
    x = np.zeros((2, 3))
    out = [x.copy()]
    for u in u_seq:
        x = np.stack([M[:3, :3] @ x[i] + M[:3, 3] * u[i] for i in range(2)])
        out.append(x.copy())
    return np.stack(out)  # [T + 1, 2 axes, 3]


def test_fit_recovers_a_second_order_response_exactly_and_a_first_order_one_from_c1_alone():
    mod = load("lookahead_model_error")
    rng = np.random.default_rng(0)
    dt, w, z, steps = 0.04, 9.0, 0.7, 400
    u = np.repeat(rng.uniform(-2, 2, (steps // 10, 2)), 10, 0)  # held 0.4 s each
    x = _second_order(w, z, dt, u)
    pad = np.zeros((1, steps + 1, 1))
    p, v, a = (np.concatenate([x[None, :, :, i], pad], -1) for i in range(3))
    cmd = np.concatenate([np.concatenate([np.zeros((1, 2)), u])[None], pad], -1)  # command flown before sample t
    keep = np.ones((1, steps + 1), bool)
    fits = mod.fit(p, v, a, cmd, dt, keep)
    np.testing.assert_allclose(fits["second"][0], [2 * z / w, 1 / w**2], rtol=1e-6)
    assert fits["second"][1].max() < 1e-6
    assert fits["first"][1].max() > 0.1  # a first-order look-ahead cannot follow it
    # A first-order lag (tau): q = p + tau v is exact, and the second-order fit finds c2 = 0.
    tau = 0.25
    e = np.exp(-dt / tau)
    vel = [np.zeros(2)]
    pos = [np.zeros(2)]
    for uk in u:
        pos.append(pos[-1] + uk * dt + (vel[-1] - uk) * tau * (1 - e))
        vel.append(uk + (vel[-1] - uk) * e)
    pos, vel = np.stack(pos)[None], np.stack(vel)[None]
    acc = np.concatenate([np.zeros((1, 1, 2)), np.diff(vel, axis=1) / dt], 1)  # any acceleration: its weight is 0
    p1, v1, a1 = (np.concatenate([x, pad], -1) for x in (pos, vel, acc))
    fits = mod.fit(p1, v1, a1, cmd, dt, keep)
    np.testing.assert_allclose(fits["first"][0], [tau], rtol=1e-6)
    assert fits["first"][1].max() < 1e-6
    np.testing.assert_allclose(fits["second"][0], [tau, 0.0], atol=1e-6)
    # The attitude's acceleration in place of a: the same fit where they are the same.
    fits = mod.fit(p, v, a, cmd, dt, keep, tilt=a)
    np.testing.assert_allclose(fits["tilt"][0], fits["second"][0], rtol=1e-9)


def test_script_runs_small_and_rejects_bad_sizes(tmp_path, capsys):
    mod = load("lookahead_model_error")
    assert mod.main(["--drones", "2", "--seconds", "2", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "p + c1 v + c2 a, fitted" in out and "the filter's look-ahead" in out and "a from the attitude" in out
    assert (tmp_path / "lookahead_model_error.json").exists()
    with pytest.raises(SystemExit) as exit_:
        mod.main(["--drones", "0"])
    assert exit_.value.code == 2

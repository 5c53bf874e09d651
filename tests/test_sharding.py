"""Several devices and hosts: the tiny sweep laid out over 2 devices, or 2 processes, equals it on one device.

Both run in subprocesses: the number of CPU devices (``--xla_force_host_platform_device_count``) and
``jax.distributed.initialize`` must be set before JAX starts.
"""

import os
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import jax
import numpy as np
import pytest
from curves import assert_same_curve, assert_same_params
from drones import GEOMETRIC

from aswarm.analysis import evaluate
from aswarm.training import runner

ROOT = Path(__file__).resolve().parent.parent
CI_SWEEP = ROOT / "sweeps" / "ci_tiny.toml"
TRIALS = ("c00-s0", "c00-s1", "c01-s0", "c01-s1")

# One process, two devices: the same sweep on one device and with the 4 trials split 2 + 2 (the layout a sweep
# takes where its trials divide over the devices). Each trial's worlds split 4 + 4 (rollout per device, gradients
# averaged by an all-reduce) runs in the two processes below: the same program over a process boundary (the
# suite's time goes to compiling, and one layout per program is enough).
DEVICES = """
import sys
import jax, numpy as np
from aswarm.training import sweep
from aswarm.training import sharding
spec, out = sweep.load(sys.argv[1]), sys.argv[2]
devs = np.asarray(jax.devices(), dtype=object)
assert devs.size == 2, devs
for name, grid in {"one": devs[:1].reshape(1, 1), "trials": devs.reshape(2, 1)}.items():
    sweep.run(spec, f"{out}/{name}", progress=False, mesh=jax.sharding.Mesh(grid, sharding.AXES), log=print)
"""

# Then `aswarm train` over one device (--devices 1), and over both (the default) stopped after 1 update and resumed
# on them, on the geometric drone (tests/drones.py), in the same process (each process costs its imports). (An
# uninterrupted run on both devices as well cost the suite a third program trace for what the resumed one shows:
# resuming is exact on one device, test_train.py.) Hover with MAPPO, as the sweep: laying the worlds out over devices
# is the same for every scenario and method, and obstacles with the attention-CBF cost 13 s more to compile here.
TRAIN = """
from aswarm import cli
from aswarm.agents.config import TrainConfig
from aswarm.training import runner
geometric = GEOMETRIC
small = dict(scenario="hover", method="mappo", num_envs=16, rollout_steps=8, minibatches=2,
             total_steps=16 * 8 * 3, updates_per_chunk=1)
flags = [f"--{k.replace('_', '-')}={v}" for k, v in small.items()] + [f"--env={k}={v}" for k, v in geometric]
small["env_overrides"] = geometric
assert cli.main(["train", *flags, "--devices", "1", "--quiet", "--out", f"{out}/train/one"]) == 0
runner.train(TrainConfig(**small), f"{out}/train/two", progress=False, max_updates=1)
assert len(runner.read_metrics(f"{out}/train/two")) == 1
runner.train(None, f"{out}/train/two", resume=True, progress=False)
""".replace("GEOMETRIC", repr(GEOMETRIC))

# Two processes on loopback, one CPU device each, every trial's worlds split across them.
HOSTS = """
import sys
from aswarm.training import sharding
sharding.initialize(sys.argv[3], 2, int(sys.argv[4]))
import jax, numpy as np
from aswarm.training import sweep
assert jax.process_count() == 2 and len(jax.devices()) == 2 and len(jax.local_devices()) == 1
mesh = jax.sharding.Mesh(np.asarray(jax.devices(), dtype=object).reshape(1, 2), sharding.AXES)
sweep.run(sweep.load(sys.argv[1]), sys.argv[2], progress=False, mesh=mesh, log=print)
"""


# Other devices sum in another order: curves agree to 2e-3 of their scale after 3-4 updates (seen in CI:
# explained variance 3.5e-4 apart on a curve reaching 1.1, cost excess 5e-5 apart on one reaching 0.17).
SCALE_RTOL = 2e-3


def _env(devices: int) -> dict:
    # XLA_FLAGS: the tests' own (conftest.py) and the number of devices.
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(ROOT),
               XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={devices}")
    # The children share the tests' persistent compilation cache (conftest.py).
    env.update(JAX_COMPILATION_CACHE_DIR=os.path.join(tempfile.gettempdir(), "aswarm-test-jax-cache"),
               JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0.5")
    return env


def _assert_same(a: Path, b: Path) -> None:
    """Metrics of every update and final params of every trial agree to float tolerance."""
    for t in TRIALS:
        rows_a, rows_b = runner.read_metrics(a / "trials" / t), runner.read_metrics(b / "trials" / t)
        assert len(rows_a) == len(rows_b) == 4
        for name in rows_a[0]:
            assert_same_curve([r[name] for r in rows_b], [r[name] for r in rows_a], SCALE_RTOL, f"{b.name}/{t} {name}")
        pa, pb = evaluate.load(a / "trials" / t)[1]["params"], evaluate.load(b / "trials" / t)[1]["params"]
        assert_same_params(pb, pa, err_msg=f"{b.name}/{t}")


@pytest.fixture(scope="module")
def two_devices(tmp_path_factory):
    out = tmp_path_factory.mktemp("devices")
    proc = subprocess.run([sys.executable, "-c", DEVICES + TRAIN, str(CI_SWEEP), str(out)], env=_env(2), cwd=ROOT,
                          capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "2 on trials x 1 on worlds" in proc.stdout
    return out


def test_two_devices_equal_one(two_devices):
    _assert_same(two_devices / "one", two_devices / "trials")


def test_two_processes_on_loopback_train_together(two_devices, tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = tmp_path / "hosts"
    procs = [subprocess.Popen([sys.executable, "-c", HOSTS, str(CI_SWEEP), str(out), f"127.0.0.1:{port}", str(i)],
                              env=_env(1), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for i in range(2)]
    logs = []
    try:
        for p in procs:
            stdout, stderr = p.communicate(timeout=900)
            logs.append((p.returncode, stdout, stderr))
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    for i, (rc, _, stderr) in enumerate(logs):
        assert rc == 0, f"process {i}: {stderr[-3000:]}"
    assert "2 device(s) (2 process(es), cpu): 1 on trials x 2 on worlds" in logs[0][1]
    assert "group 0" not in logs[1][1]  # only process 0 reports and writes
    _assert_same(two_devices / "one", out)


def test_train_splits_its_worlds_over_the_devices_and_resumes_on_them(two_devices):
    import json

    runs = two_devices / "train"
    devices = {r: json.loads((runs / r / "config.json").read_text())["train"]["devices"] for r in ("two", "one")}
    assert devices == {"two": 2, "one": 1}
    two, one = (runner.read_metrics(runs / r) for r in ("two", "one"))
    assert len(two) == len(one) == 3  # on 2 devices: 1 update, interrupted, 2 more after the resume
    for name in two[0]:
        assert_same_curve([r[name] for r in two], [r[name] for r in one], SCALE_RTOL, name)
    # Params: per array, the difference is float round-off relative to the whole array (seen: 2e-4 at most). A few
    # entries of the critics' input layer differ more on their own (seen: 2e-4 on an EPYC, 3.4e-3 on a Xeon, 1 of
    # 52,736): inputs that barely vary get a tiny normalizer std, and Adam's step on a near-zero gradient amplifies
    # the other summation order.
    pa, pb = (evaluate.load(runs / r)[1]["params"] for r in ("two", "one"))
    for x, y in zip(jax.tree.leaves(pa), jax.tree.leaves(pb)):
        x, y = np.asarray(x), np.asarray(y)
        assert np.linalg.norm(x - y) <= 1e-3 * np.linalg.norm(x) + 1e-6
        assert np.mean(np.abs(x - y) > 1e-3) <= 1e-3 and np.max(np.abs(x - y)) <= 1e-2


def test_training_mesh_errors_name_the_bad_device_count():
    from aswarm.training import sharding

    n = len(jax.local_devices())
    assert sharding.training_mesh(16).devices.size == max(k for k in range(1, n + 1) if 16 % k == 0)
    with pytest.raises(ValueError, match=rf"invalid devices={n + 1}: this process has {n} \(cpu\); allowed: 0 to {n}"):
        sharding.training_mesh(16, n + 1)

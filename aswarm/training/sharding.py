"""Data-parallel training over every device (and host) with JAX's own SPMD partitioner.

The train state is laid out over a 2-D ``jax.sharding.Mesh`` with axes ``("trial", "env")``:
a sweep's stacked trials are split along ``trial`` (they never talk to each other), and each
trial's batch of worlds along ``env``. Parameters and optimizer state are replicated over ``env``.
``jit`` with these in/out shardings lets XLA partition the rollout by world. The learner keeps
one device's algorithm: the rollout is gathered for the global minibatch shuffle, then
``rows_constraint`` (``make_train(shard_rows=...)``) splits each minibatch's rows over the
devices, each takes the gradient of its rows, and an all-reduce averages them, so every device
applies the same update. The numbers are those of one device up to the order of floating-point
sums (tests/test_sharding.py).

``aswarm train`` (``runner.py``) lays one run out the same way over :func:`training_mesh`. On a CPU,
:func:`use_cpu_cores` makes each core a device first: one XLA:CPU device runs most of the learner's
small ops on one thread, and two devices on two cores trained 1.33x faster (BENCHMARKS.md).

Several hosts: call :func:`initialize` (``jax.distributed.initialize``) first in every process;
``jax.devices()`` then lists the devices of all hosts and the same code runs on all of them::

    # on host i of N (same command everywhere, only --process-id differs)
    aswarm sweep sweeps/race_lr.toml --coordinator HOST0:1234 --num-processes N --process-id i
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

AXES = ("trial", "env")


def initialize(coordinator: str, num_processes: int, process_id: int) -> None:
    """Join a multi-process run (before anything touches a device); a ValueError for bad arguments."""
    host, _, port = coordinator.rpartition(":")
    if not host or not port.isdigit():
        raise ValueError(f"invalid coordinator {coordinator!r}: allowed: HOST:PORT, e.g. 10.0.0.1:1234")
    if num_processes < 1:
        raise ValueError(f"invalid num_processes={num_processes}: must be >= 1")
    if not 0 <= process_id < num_processes:
        raise ValueError(f"invalid process_id={process_id}: allowed: 0 to {num_processes - 1}")
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes,
                               process_id=process_id)


def use_cpu_cores() -> int | None:
    """Expose each CPU core this process may use as a JAX CPU device; returns how many, or None if unchanged.

    Must run before anything touches a device. Leaves a count the user chose (``JAX_NUM_CPU_DEVICES``,
    ``--xla_force_host_platform_device_count``) alone. Harmless on a GPU machine: it changes only the
    CPU platform, and the default devices stay the GPUs.
    """
    if os.environ.get("JAX_NUM_CPU_DEVICES") or "xla_force_host_platform_device_count" in os.environ.get(
            "XLA_FLAGS", ""):
        return None
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    try:
        jax.config.update("jax_num_cpu_devices", cores)
    except RuntimeError:  # a backend is already up (a library or test touched a device): keep its layout
        return None
    return cores


def training_mesh(num_envs: int, devices: int = 0) -> Mesh:
    """Mesh of one training run: its worlds over ``devices`` of this process's devices (0: as many as divide
    ``num_envs``); a ValueError naming the bad value when that cannot be laid out."""
    local = jax.local_devices()
    if devices > len(local):
        raise ValueError(f"invalid devices={devices}: this process has {len(local)} "
                         f"({local[0].platform}); allowed: 0 to {len(local)}")
    if devices and num_envs % devices:
        raise ValueError(f"invalid devices={devices}: must divide num_envs={num_envs}")
    n = devices or max(k for k in range(1, len(local) + 1) if num_envs % k == 0)
    return make_mesh(1, num_envs, local[:n])


def make_mesh(num_trials: int, num_envs: int, devices: list | None = None) -> Mesh:
    """Mesh over ``devices`` (default all, of all hosts): as many devices on ``trial`` as divide the trials,
    the rest on ``env``, which must divide ``num_envs``."""
    devices = list(jax.devices() if devices is None else devices)
    t = math.gcd(num_trials, len(devices))
    e = len(devices) // t
    if num_envs % e:
        raise ValueError(f"invalid num_envs={num_envs} for {len(devices)} devices and {num_trials} trials: "
                         f"allowed: a multiple of {e}")
    return Mesh(np.asarray(devices, dtype=object).reshape(t, e), AXES)


def state_shardings(mesh: Mesh, state, stacked: bool):
    """NamedShardings for a TrainState (``stacked``: with a leading trial axis): worlds on ``env``."""
    lead = ("trial",) if stacked else ()
    rest = jax.tree.map(lambda _: NamedSharding(mesh, P(*lead)), state)
    worlds = jax.tree.map(lambda _: NamedSharding(mesh, P(*lead, "env")), state.env_state)
    return rest.replace(env_state=worlds)


def put(tree, sharding: NamedSharding):
    """Host arrays (the same on every process) -> global arrays laid out by ``sharding``; multi-host safe."""
    def one(x):
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, sharding, lambda idx: x[idx], dtype=x.dtype)

    return jax.tree.map(one, tree)


def for_checkpoint(tree):
    """A fetched tree with numpy leaves only, for orbax: the same on every host, and readable on one machine.

    Orbax refuses host-local jax.Arrays when there are several processes, and an array spread over N
    hosts restores only onto N hosts ("Topology mismatch"); numpy leaves are written once, by
    process 0. brax's ``UInt64`` (the normalizer's count) turns its leaves into jax.Arrays whenever
    it is rebuilt, so it is rebuilt here without its ``__post_init__``.
    """
    from brax.training.types import UInt64

    def host(x):
        if isinstance(x, UInt64):
            y = object.__new__(UInt64)
            object.__setattr__(y, "hi", np.asarray(x.hi))
            object.__setattr__(y, "lo", np.asarray(x.lo))
            return y
        return np.asarray(x)

    return jax.tree.map(host, tree, is_leaf=lambda x: isinstance(x, UInt64))


def fetch(tree):
    """Global arrays -> numpy on every process (gathers shards held by other hosts)."""
    if jax.process_count() == 1:
        return jax.device_get(tree)
    # Some leaves come back as single-device jax.Arrays, which orbax refuses to save on several hosts.
    return jax.tree.map(np.asarray, multihost_utils.process_allgather(tree, tiled=True))


def rows_constraint(mesh: Mesh) -> Callable[[jax.Array], jax.Array]:
    """For ``make_train(shard_rows=...)``: minibatches ``[num_minibatches, rows, ...]`` with rows on ``env``.

    Without it XLA gathered the whole rollout onto every device and ran the learner replicated; with
    it each device takes the loss and gradient of its rows and an all-reduce averages them. Under a
    vmap over trials, pass ``spmd_axis_name="trial"`` so the trial axis stays split too.
    """
    spec = NamedSharding(mesh, P(None, "env"))
    return lambda x: jax.lax.with_sharding_constraint(x, spec)


def sharded_fns(init: Callable, update_chunk: Callable, like, mesh: Mesh, stacked: bool):
    """``(init, update_chunk)`` jitted with the state laid out over ``mesh``.

    ``init`` and ``update_chunk`` are the trainer's (vmapped over trials when ``stacked``); ``like`` is
    an abstract state (``jax.eval_shape`` of init) giving the tree structure.
    """
    st = state_shardings(mesh, like, stacked)
    lead = NamedSharding(mesh, P("trial") if stacked else P())
    init_fn = jax.jit(init, out_shardings=st)
    # The chunk length is static (a scan length); metrics come back [trial, update] or [update].
    chunk_fn = jax.jit(update_chunk, static_argnums=1, in_shardings=(st,), out_shardings=(st, lead),
                       donate_argnums=0)
    return init_fn, chunk_fn


def describe(mesh: Mesh) -> str:
    shape = dict(mesh.shape)
    return (f"{mesh.devices.size} device(s) ({jax.process_count()} process(es), {mesh.devices.flat[0].platform}): "
            f"{shape['trial']} on trials x {shape['env']} on worlds")

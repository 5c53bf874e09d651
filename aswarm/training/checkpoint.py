"""Orbax checkpoints of a training run.

Orbax writes each step to a temporary directory and renames it only when the
save is complete, so a crash while saving never leaves a broken latest step.
A step damaged afterwards (a truncated file) is skipped on resume, and each step
carries a fingerprint of what shapes the state, so a checkpoint is never
restored into a configuration it was not written for.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from aswarm.agents.config import TrainConfig


class CheckpointError(ValueError):
    """A checkpoint that cannot be read or does not fit the configuration."""


# What shapes the policy item (params, observation normaliser) and, with STATE_KEYS, the whole train state.
POLICY_KEYS = ("method", "actor_hidden", "critic", "critic_hidden", "cbf_hidden", "cbf_embed", "cbf_state_hidden",
               "obs_size", "num_cylinders", "num_neighbours")
STATE_KEYS = POLICY_KEYS + ("num_agents", "num_obstacles", "num_moving", "num_gates", "max_neighbours", "num_envs")
# Unreadable steps are moved here on resume (outside checkpoints/, where orbax would list them again).
UNREADABLE_DIR = "checkpoints-unreadable"


def fingerprint(config: TrainConfig, env) -> dict:
    """What fixes the shapes of a train state of ``config`` on ``env`` (JSON-ready)."""
    fp = {"method": config.method, "actor_hidden": list(config.actor_hidden),
          "critic": config.critic, "critic_hidden": list(config.critic_hidden), "cbf_hidden": list(config.cbf_hidden),
          "cbf_embed": config.cbf_embed, "cbf_state_hidden": config.cbf_state_hidden,
          "obs_size": int(env.observation_size), "num_cylinders": int(env.obs_layout.num_cylinders),
          "num_neighbours": int(env.obs_layout.num_neighbours), "num_agents": int(env.num_agents),
          "num_obstacles": int(env.config.num_obstacles), "num_moving": int(env.config.num_moving),
          "num_gates": int(env.config.num_gates), "max_neighbours": int(env.config.max_neighbours),
          "num_envs": config.num_envs}
    assert set(fp) == set(STATE_KEYS)
    return fp


class _Manager(ocp.CheckpointManager):
    """A checkpoint manager that knows the fingerprint of the run it saves and restores for (None: unchecked)."""

    fingerprint: dict | None = None


def manager(run_dir: Path, max_to_keep: int = 3, fingerprint: dict | None = None) -> ocp.CheckpointManager:
    """The run's checkpoints; with ``fingerprint``, every save stores it and every restore checks it."""
    opts = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, enable_async_checkpointing=False,
                                        cleanup_tmp_directories=True)
    mngr = _Manager(Path(run_dir).absolute() / "checkpoints", options=opts, item_names=("state", "policy"))
    mngr.fingerprint = fingerprint
    return mngr


def stored_fingerprint(mngr: ocp.CheckpointManager, step: int) -> dict | None:
    """The fingerprint saved with ``step``; None for checkpoints written before fingerprints existed."""
    # Read from orbax's step metadata file: CheckpointManager.metadata() logs a warning per item.
    path = Path(mngr.directory) / str(step) / "_CHECKPOINT_METADATA"
    try:
        return json.loads(path.read_text()).get("custom_metadata", {}).get("fingerprint")
    except (OSError, ValueError, AttributeError):
        return None


def check_fingerprint(mngr: ocp.CheckpointManager, step: int, item: str = "state") -> None:
    """Refuse in one line a checkpoint written for other shapes than the manager's run (a no-op when either
    side has no fingerprint)."""
    want = getattr(mngr, "fingerprint", None)
    have = stored_fingerprint(mngr, step)
    if want is None or have is None:
        return
    want = json.loads(json.dumps(want))  # tuples -> lists, as stored
    keys = POLICY_KEYS if item == "policy" else STATE_KEYS
    diff = [k for k in keys if k in have and have[k] != want.get(k)]
    if diff:
        got = ", ".join(f"{k}={have[k]}" for k in diff)
        now = ", ".join(f"{k}={want.get(k)}" for k in diff)
        raise CheckpointError(f"checkpoint {mngr.directory}/{step} was written for {got}; this run's config has "
                              f"{now}: refusing to restore it (restore with the config it was trained with)")


def _quiet_closed_loop(unraisable) -> None:
    """Drop the 'Event loop is closed' errors that tensorstore's reader threads report after orbax's
    event loop has closed on a failed read (dozens of tracebacks, seconds after the one error that matters)."""
    if isinstance(unraisable.exc_value, RuntimeError) and str(unraisable.exc_value) == "Event loop is closed":
        return
    _quiet_closed_loop.previous(unraisable)


def _install_quiet_hook() -> None:
    if sys.unraisablehook is not _quiet_closed_loop:
        _quiet_closed_loop.previous = sys.unraisablehook
        sys.unraisablehook = _quiet_closed_loop


def policy_of(state) -> dict:
    """What evaluation and export need: small, independent of the number of worlds."""
    return {"params": state.params, "obs_norm": state.obs_norm, "update": state.update}


def _pack(tree) -> dict:
    """Flat ``{path: array}`` of the non-empty leaves: orbax refuses zero-size arrays, which ``mjx.Data`` has."""
    leaves = jax.tree_util.tree_flatten_with_path(tree)[0]
    return {jax.tree_util.keystr(p): x for p, x in leaves if np.prod(np.shape(x)) > 0}


def _unpack(like, flat: dict):
    paths, treedef = jax.tree_util.tree_flatten_with_path(like)
    leaves = [flat[jax.tree_util.keystr(p)] if jax.tree_util.keystr(p) in flat else x for p, x in paths]
    return jax.tree_util.tree_unflatten(treedef, leaves)


def save(mngr: ocp.CheckpointManager, step: int, state) -> None:
    """Save the whole train state (for resuming) and the policy alone (for evaluation and export)."""
    fp = getattr(mngr, "fingerprint", None)
    mngr.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(_pack(state)),
                                            policy=ocp.args.StandardSave(_pack(policy_of(state)))),
              custom_metadata={"fingerprint": fp} if fp is not None else None)
    mngr.wait_until_finished()


def restore(mngr: ocp.CheckpointManager, like, step: int | None = None, item: str = "state"):
    """Restore ``item`` into the structure of ``like`` (concrete arrays; zero-size leaves are taken from it)."""
    step = mngr.latest_step() if step is None else step
    if step is None:
        raise CheckpointError(f"no checkpoint in {mngr.directory}")
    check_fingerprint(mngr, step, item)
    abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(np.shape(x), jnp.asarray(x).dtype), _pack(like))
    _install_quiet_hook()
    try:
        flat = mngr.restore(step, args=ocp.args.Composite(**{item: ocp.args.StandardRestore(abstract)}))[item]
    except Exception as e:  # orbax raises many types for unreadable or mismatched trees
        raise CheckpointError(f"checkpoint {mngr.directory}/{step} cannot be restored into this configuration "
                              f"(damaged, or written for another one): {type(e).__name__}: "
                              f"{str(e).splitlines()[0][:200]}") from e
    return _unpack(like, flat)


def restore_newest(mngr: ocp.CheckpointManager, like, item: str = "state", log=None):
    """Restore the newest step that restores, for resuming.

    Steps that cannot be read (a truncated file) are moved to ``checkpoints-unreadable/`` next to
    ``checkpoints/``, so the resumed run can save those step numbers again, and ``log`` (default: stderr)
    gets one line saying so. A fingerprint mismatch is refused at once: older steps of the same run would not
    fit either.
    """
    log = log or (lambda line: print(line, file=sys.stderr))
    steps = sorted(mngr.all_steps(), reverse=True)
    if not steps:
        raise CheckpointError(f"no checkpoint in {mngr.directory}")
    bad: list[tuple[int, CheckpointError]] = []
    for step in steps:
        check_fingerprint(mngr, step, item)
        try:
            out = restore(mngr, like, step, item)
        except CheckpointError as e:
            bad.append((step, e))
            continue
        if bad:
            aside = Path(mngr.directory).parent / UNREADABLE_DIR
            aside.mkdir(exist_ok=True)
            for s, _ in bad:
                shutil.rmtree(aside / str(s), ignore_errors=True)
                (Path(mngr.directory) / str(s)).rename(aside / str(s))
            mngr.reload()
            names = ", ".join(str(s) for s, _ in bad)
            log(f"checkpoint {names} in {mngr.directory} cannot be restored (moved to {aside}): "
                f"resuming from checkpoint {step}")
        return out
    raise CheckpointError(f"none of the checkpoints ({', '.join(map(str, steps))}) can be restored; the newest: "
                          f"{bad[0][1]}")


def last_good(mngr: ocp.CheckpointManager) -> str:
    """How a divergence message names the checkpoint that is kept."""
    step = mngr.latest_step()
    if step is None:
        return f"no checkpoint was written yet in {mngr.directory}"
    return f"the last good checkpoint (update {step}) in {mngr.directory} is kept"


def load_config(run_dir: Path) -> TrainConfig:
    """The run's TrainConfig, its env as stored in config.json (``run_config.read``)."""
    from aswarm.training import run_config

    return run_config.read(run_dir)


def copy_policy(run_dir: Path, dest: Path, step: int | None = None) -> Path:
    """Copy a run's config and the *policy* item of one checkpoint (no optimizer or env state) to ``dest``.

    The copy is itself a run folder that ``aswarm eval`` and ``aswarm export`` read; it is how the
    pretrained policy in ``aswarm/pretrained`` is made (kilobytes instead of the full training state).
    Written to a temporary folder and renamed when complete.
    """
    run_dir, dest = Path(run_dir), Path(dest)
    step = manager(run_dir).latest_step() if step is None else step
    if step is None:
        raise CheckpointError(f"no checkpoint in {run_dir / 'checkpoints'}")
    src = run_dir / "checkpoints" / str(step)
    tmp = dest.with_name(dest.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "checkpoints" / str(step)).mkdir(parents=True)
    shutil.copy2(run_dir / "config.json", tmp / "config.json")
    for name in ("_CHECKPOINT_METADATA", "commit_success.txt"):
        if (src / name).exists():
            shutil.copy2(src / name, tmp / "checkpoints" / str(step) / name)
    shutil.copytree(src / "policy", tmp / "checkpoints" / str(step) / "policy")
    if dest.exists():
        shutil.rmtree(dest)
    tmp.rename(dest)
    return dest

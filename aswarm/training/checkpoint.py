"""Orbax checkpoints of a training run.

Orbax writes each step to a temporary directory and renames it only when the
save is complete, so a crash while saving never leaves a broken latest step.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

from aswarm.agents.config import TrainConfig


class CheckpointError(ValueError):
    """A checkpoint that cannot be read or does not fit the configuration."""


def manager(run_dir: Path, max_to_keep: int = 3) -> ocp.CheckpointManager:
    opts = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, enable_async_checkpointing=False,
                                        cleanup_tmp_directories=True)
    return ocp.CheckpointManager(Path(run_dir).absolute() / "checkpoints", options=opts,
                                 item_names=("state", "policy"))


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
    mngr.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(_pack(state)),
                                            policy=ocp.args.StandardSave(_pack(policy_of(state)))))
    mngr.wait_until_finished()


def restore(mngr: ocp.CheckpointManager, like, step: int | None = None, item: str = "state"):
    """Restore ``item`` into the structure of ``like`` (concrete arrays; zero-size leaves are taken from it)."""
    step = mngr.latest_step() if step is None else step
    if step is None:
        raise CheckpointError(f"no checkpoint in {mngr.directory}")
    abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(np.shape(x), jnp.asarray(x).dtype), _pack(like))
    try:
        flat = mngr.restore(step, args=ocp.args.Composite(**{item: ocp.args.StandardRestore(abstract)}))[item]
    except Exception as e:  # orbax raises many types for unreadable or mismatched trees
        raise CheckpointError(f"checkpoint {mngr.directory}/{step} cannot be restored into this configuration: "
                              f"{type(e).__name__}: {str(e).splitlines()[0][:300]}") from e
    return _unpack(like, flat)


def load_config(run_dir: Path) -> TrainConfig:
    path = Path(run_dir) / "config.json"
    if not path.exists():
        raise CheckpointError(f"{run_dir} is not a run folder: {path.name} is missing")
    try:
        raw = json.loads(path.read_text())["train"]
        raw["env_overrides"] = tuple((k, tuple(v) if isinstance(v, list) else v) for k, v in raw["env_overrides"])
        for k, v in list(raw.items()):
            if isinstance(v, list):
                raw[k] = tuple(v)
        return TrainConfig(**raw)
    except (KeyError, TypeError, json.JSONDecodeError) as e:
        raise CheckpointError(f"{path} is not a valid aswarm run config: {e}") from e


def copy_policy(run_dir: Path, dest: Path, step: int | None = None) -> Path:
    """Copy a run's config and the *policy* item of one checkpoint (no optimizer or env state) to ``dest``.

    The copy is itself a run folder that ``aswarm eval`` and ``aswarm export`` read; it is how the
    pretrained policy in ``aswarm/pretrained`` is made (kilobytes instead of the full training state).
    Written to a temporary folder and renamed when complete.
    """
    import shutil

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

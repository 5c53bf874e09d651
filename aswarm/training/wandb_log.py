"""Weights & Biases logging of a run (``aswarm train --wandb``): the scalars TensorBoard gets, the run's config.

``wandb`` is an optional dependency (``pip install 'aswarm[wandb]'``), imported only when a run asks for it. The
run logs into the run folder (``RUN/wandb/``, or ``WANDB_DIR``). Without an API key it logs offline rather than
stopping to ask for one: a training job is often unattended, and ``wandb sync`` uploads the folder later.
"""

from __future__ import annotations

import dataclasses
import netrc
import os
import sys
from pathlib import Path
from urllib.parse import urlsplit

MODES = ("online", "offline")
INSTALL = "pip install 'aswarm[wandb]'"


@dataclasses.dataclass(frozen=True)
class WandbOptions:
    project: str = "aswarm"
    entity: str | None = None  # None: the account's default entity
    name: str | None = None  # None: the run folder's name
    mode: str | None = None  # None: see resolve_mode


def _import():
    try:
        import wandb
    except ImportError:
        raise ValueError(f"--wandb needs the wandb package: {INSTALL}") from None
    return wandb


def require() -> None:
    """A one-line ValueError, before anything compiles, where the wandb package is missing."""
    _import()


def has_api_key() -> bool:
    """Whether W&B credentials are configured: ``WANDB_API_KEY``, or ``wandb login``'s entry in the netrc file."""
    if os.environ.get("WANDB_API_KEY"):
        return True
    host = urlsplit(os.environ.get("WANDB_BASE_URL", "https://api.wandb.ai")).netloc
    try:
        return netrc.netrc(os.environ.get("NETRC")).authenticators(host) is not None
    except (OSError, netrc.NetrcParseError):
        return False


def resolve_mode(mode: str | None) -> str:
    """The mode given, else ``WANDB_MODE``, else online where an API key is configured and offline where not."""
    if mode is not None:
        if mode not in MODES:
            raise ValueError(f"invalid --wandb-mode {mode!r}: allowed: {', '.join(MODES)}")
        return mode
    return os.environ.get("WANDB_MODE") or ("online" if has_api_key() else "offline")


class WandbLog:
    """One W&B run: :meth:`log` takes the rows the TensorBoard writer gets."""

    def __init__(self, run) -> None:
        self.run = run

    def log(self, row: dict) -> None:
        """One metrics row (as ``metrics.jsonl`` holds it) at its update."""
        self.run.log({k: v for k, v in row.items() if k != "update"}, step=int(row["update"]))

    def close(self, ok: bool = True) -> None:
        self.run.finish(exit_code=0 if ok else 1)


def start(options: WandbOptions, config, run_dir: Path, resumed: bool = False) -> WandbLog:
    """Start the W&B run of ``run_dir``, with ``config`` (a TrainConfig) as its config, as config.json holds it."""
    import json

    from aswarm.training import run_config

    wandb = _import()
    mode = resolve_mode(options.mode)
    if mode == "offline" and options.mode is None and not os.environ.get("WANDB_MODE"):
        print("wandb: no API key (WANDB_API_KEY or `wandb login`): logging offline; upload with `wandb sync`",
              file=sys.stderr)
    run = wandb.init(project=options.project, entity=options.entity, name=options.name or Path(run_dir).name,
                     group=Path(run_dir).name, job_type="resume" if resumed else "train", mode=mode,
                     dir=os.environ.get("WANDB_DIR") or str(run_dir), config=json.loads(run_config.dumps(config)),
                     # The console is the progress bar's: captured, it would fill the W&B log with bar redraws.
                     settings=wandb.Settings(console="off"))
    return WandbLog(run)

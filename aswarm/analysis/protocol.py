"""The evaluation protocol's constants, free of JAX (the command line reads them to build its flags), and the
flags of the experiments that replay a policy under its filter."""

import argparse
import json

# Evaluation draws its layouts from this seed on; training seeds are small integers, so every evaluated
# episode is unseen in training. eval, sitl, plot, render, the MPC and the experiments all start here.
EVAL_SEED = 10_000


def add_replay_arguments(p: argparse.ArgumentParser, episodes: int) -> None:
    """The flags of the experiments that replay a policy under its filter (``experiments/collision_trace.py``,
    ``filter_binding.py``): --checkpoint, --scenario, --env, --filter, --episodes (default ``episodes``), --seed;
    :func:`filter_argument` reads --filter."""
    p.add_argument("--checkpoint", required=True, help="run folder, or 'pretrained[:NAME]'")
    p.add_argument("--scenario", default=None, help="default: the one it was trained on")
    p.add_argument("--env", action="append", default=[], metavar="FIELD=VALUE", help="env override, repeatable")
    p.add_argument("--filter", default="{}", metavar="JSON", help="safety-filter fields to replace")
    p.add_argument("--episodes", type=int, default=episodes)
    p.add_argument("--seed", type=int, default=None, help="default: the evaluation seed")


def filter_argument(p: argparse.ArgumentParser, text: str) -> dict:
    """--filter's JSON object of safety-filter fields; anything else is ``p.error`` (one line, exit 2)."""
    try:
        fields = json.loads(text)
    except json.JSONDecodeError as e:
        p.error(f"invalid --filter: {e}; allowed: a JSON object of safety-filter fields")
    if not isinstance(fields, dict):
        p.error(f"invalid --filter={text!r}: allowed: a JSON object of safety-filter fields")
    return fields

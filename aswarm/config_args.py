"""Command-line flags from frozen config dataclasses: every field, typed, with a clear error on bad values."""

from __future__ import annotations

import argparse
import dataclasses
import math
import typing


def _parse(field: str, kind, text: str):
    def fail(allowed):
        raise argparse.ArgumentTypeError(f"invalid {field}={text!r}: allowed: {allowed}")

    origin = typing.get_origin(kind)
    if kind is bool:
        if text.lower() in ("1", "true", "yes", "on"):
            return True
        if text.lower() in ("0", "false", "no", "off"):
            return False
        fail("true or false")
    if kind is int:
        try:
            return int(text)
        except ValueError:
            fail("an integer")
    if kind is float:
        try:
            v = float(text)
        except ValueError:
            fail("a number")
        if not math.isfinite(v):
            fail("a finite number")
        return v
    if kind is str:
        return text
    if origin is tuple:
        args = typing.get_args(kind)
        inner = args[0]
        try:
            return tuple(inner(x) for x in text.split(",") if x)
        except ValueError:
            fail(f"comma-separated {inner.__name__}s")
    fail(f"a value of type {kind}")


def field_types(cls) -> dict:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def add_fields(parser: argparse.ArgumentParser, cls, skip: tuple[str, ...] = ()) -> None:
    """Add ``--field-name VALUE`` for every simple field of ``cls`` (defaults None = keep the config's)."""
    defaults = cls()
    for name, kind in field_types(cls).items():
        if name in skip or not (kind in (bool, int, float, str) or typing.get_origin(kind) is tuple):
            continue
        default = getattr(defaults, name)
        parser.add_argument(f"--{name.replace('_', '-')}", dest=name, default=None, metavar=kind_name(kind),
                            type=lambda t, n=name, k=kind: _parse(n, k, t), help=f"default {default!r}")


def kind_name(kind) -> str:
    return getattr(kind, "__name__", "LIST").upper()


def overrides(args: argparse.Namespace, cls) -> dict:
    return {k: getattr(args, k) for k in field_types(cls) if getattr(args, k, None) is not None}


def parse_assignments(items: list[str], cls) -> dict:
    """``["num_agents=8", "reward=paper"]`` -> typed dict for ``cls``; unknown fields are an error."""
    types = field_types(cls)
    out = {}
    for item in items:
        if "=" not in item:
            raise ValueError(f"invalid --env {item!r}: allowed form: FIELD=VALUE")
        key, text = item.split("=", 1)
        if key not in types:
            raise ValueError(f"unknown env config field {key!r}: allowed: {', '.join(sorted(types))}")
        try:
            out[key] = _parse(key, types[key], text)
        except argparse.ArgumentTypeError as e:
            raise ValueError(str(e)) from None
    return out

"""Command-line flags and config-file tables from frozen config dataclasses: every field, typed, with a clear
error on bad values."""

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
        if name in skip or not is_flag(kind):
            continue
        default = getattr(defaults, name)
        parser.add_argument(f"--{name.replace('_', '-')}", dest=name, default=None, metavar=kind_name(kind),
                            type=lambda t, n=name, k=kind: _parse(n, k, t), help=f"default {default!r}")


def kind_name(kind) -> str:
    return getattr(kind, "__name__", "LIST").upper()


def is_flag(kind) -> bool:
    """Whether a field of this type is a ``--flag`` (plain values and tuples; not nested configs)."""
    return kind in (bool, int, float, str) or typing.get_origin(kind) is tuple


def overrides(args: argparse.Namespace, cls) -> dict:
    """The ``--field`` flags of ``cls`` given on the command line (those left at None are not)."""
    return {k: getattr(args, k) for k, kind in field_types(cls).items()
            if is_flag(kind) and getattr(args, k, None) is not None}


def leaf_types(cls, prefix: str = "") -> dict:
    """``{dotted name: type}`` of every field of ``cls``, nested dataclasses flattened (``cf.mass``)."""
    out = {}
    for name, kind in field_types(cls).items():
        if dataclasses.is_dataclass(kind):
            out.update(leaf_types(kind, f"{prefix}{name}."))
        else:
            out[prefix + name] = kind
    return out


def _allowed(cls, prefix: str) -> str:
    """The names allowed at ``prefix`` (a nested dataclass as ``cf.FIELD``)."""
    return ", ".join(sorted(f"{prefix}{k}.FIELD" if dataclasses.is_dataclass(t) else prefix + k
                            for k, t in field_types(cls).items()))


def _field_type(key: str, cls, what: str):
    """The type of dotted field ``key`` of ``cls``; a one-line ValueError naming the allowed names."""
    kind, prefix = cls, ""
    for part in key.split("."):
        if not dataclasses.is_dataclass(kind):
            raise ValueError(f"unknown {what} field {key!r}: {prefix[:-1]} has no fields; allowed: {prefix[:-1]}")
        types = field_types(kind)
        if part not in types:
            raise ValueError(f"unknown {what} field {key!r}: allowed: {_allowed(kind, prefix)}")
        kind, prefix = types[part], f"{prefix}{part}."
    if dataclasses.is_dataclass(kind):
        raise ValueError(f"invalid {key}: a group of fields; allowed: {_allowed(kind, prefix)}")
    return kind


def parse_assignments(items: list[str], cls, what: str = "env config") -> dict:
    """``["num_agents=8", "cf.mass=0.03"]`` -> ``{dotted name: typed value}`` for ``cls``; nested dataclass
    fields by dotted name. Unknown fields and bad values are one-line ValueErrors naming what is allowed."""
    out = {}
    for item in items:
        if "=" not in item:
            raise ValueError(f"invalid --env {item!r}: allowed form: FIELD=VALUE (FIELD may be nested: cf.mass)")
        key, text = item.split("=", 1)
        kind = _field_type(key, cls, what)
        try:
            out[key] = _parse(key, kind, text)
        except argparse.ArgumentTypeError as e:
            raise ValueError(str(e)) from None
    return out


def replace_fields(obj, assignments: typing.Mapping[str, object]):
    """``obj`` (a frozen dataclass) with dotted ``assignments`` applied: ``{"cf.mass": 0.03}`` replaces
    ``obj.cf.mass``. Validation is the dataclasses' own (``__post_init__``); unknown names are a ValueError."""
    top, nested = {}, {}
    for key, value in assignments.items():
        head, _, rest = key.partition(".")
        if rest:
            nested.setdefault(head, {})[rest] = value
        else:
            top[key] = value
    names = field_types(type(obj))
    for key in [*top, *nested]:
        if key not in names:
            raise ValueError(f"unknown {type(obj).__name__} field {key!r}: allowed: {_allowed(type(obj), '')}")
    for head, sub in nested.items():
        if head in top:
            raise ValueError(f"invalid {head}: set as a whole and field by field; allowed: one of the two")
        inner = getattr(obj, head)
        if not dataclasses.is_dataclass(inner):
            raise ValueError(f"unknown {type(obj).__name__} field {head}.{next(iter(sub))!r}: {head} has no fields")
        top[head] = replace_fields(inner, sub)
    return dataclasses.replace(obj, **top) if top else obj


def from_dict(cls, data: typing.Mapping, where: str, require_all: bool = False):
    """A dataclass ``cls`` from its ``dataclasses.asdict`` form read back from JSON (lists -> tuples, nested
    dataclasses rebuilt). Unknown keys (and, with ``require_all``, missing ones) are a ValueError naming them."""
    types = field_types(cls)
    if not isinstance(data, typing.Mapping):
        raise ValueError(f"{where}: not a table of {cls.__name__} fields")
    unknown = sorted(set(data) - set(types))
    if unknown:
        raise ValueError(f"{where}: unknown field {unknown[0]!r}; allowed: {', '.join(types)}")
    missing = [k for k in types if k not in data]
    if require_all and missing:
        raise ValueError(f"{where}: missing field {missing[0]!r}")

    def value(kind, v, name):
        if dataclasses.is_dataclass(kind):
            return from_dict(kind, v, f"{where}.{name}", require_all)
        return as_tuples(v)

    return cls(**{k: value(types[k], v, k) for k, v in data.items()})


def as_tuples(v):
    """JSON lists (nested too) back to the tuples a frozen config holds."""
    return tuple(as_tuples(x) for x in v) if isinstance(v, list) else v


def coerce(where: str, kind, value):
    """A value read from a TOML or JSON file as a field of type ``kind`` (ints widen to floats, lists become
    tuples of the field's length); a one-line ValueError naming ``where`` and what is allowed otherwise."""
    def fail(allowed: str):
        raise ValueError(f"{where}: invalid value {value!r} ({type(value).__name__}); allowed: {allowed}")

    if kind is bool:
        return value if isinstance(value, bool) else fail("true or false")
    if kind is int:
        return value if isinstance(value, int) and not isinstance(value, bool) else fail("an integer")
    if kind is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
            return float(value)
        fail("a finite number")
    if kind is str:
        return value if isinstance(value, str) else fail("a string")
    if typing.get_origin(kind) is tuple:
        inner = typing.get_args(kind)
        if inner[-1] is Ellipsis:
            if not isinstance(value, (list, tuple)):
                fail("a list")
            return tuple(coerce(where, inner[0], v) for v in value)
        if not isinstance(value, (list, tuple)) or len(value) != len(inner):
            fail(f"a list of {len(inner)} values")
        return tuple(coerce(where, k, v) for k, v in zip(inner, value))
    fail(f"nothing: a field of type {kind} is not set from a file")


def flatten(table: typing.Mapping, leaves: typing.Collection[str], prefix: str = "") -> dict:
    """Nested tables (TOML ``[cf]`` or ``cf.mass = ...``, JSON objects) -> ``{dotted name: value}``, walking every
    table whose dotted name is not one of ``leaves`` (a table at a leaf stays whole: a sweep's ``{low, high}``)."""
    out = {}
    for key, value in table.items():
        name = prefix + key
        if isinstance(value, typing.Mapping) and name not in leaves:
            out.update(flatten(value, leaves, name + "."))
        else:
            out[name] = value
    return out


def table_fields(table: typing.Mapping, cls, where: str, what: str) -> dict:
    """A TOML or JSON table of ``cls`` fields (nested configs as tables or dotted keys) -> ``{dotted name: typed
    value}``. Unknown names and values of the wrong type are one-line ValueErrors that start with ``where``."""
    out = {}
    for key, value in flatten(table, leaf_types(cls)).items():
        try:
            kind = _field_type(key, cls, what)
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from None
        out[key] = coerce(f"{where}: {key}", kind, value)
    return out


def add_nested_fields(parser: argparse.ArgumentParser, name: str, cls,
                      aliases: typing.Mapping[str, str] | None = None) -> None:
    """``--name.field-name VALUE`` (dest ``name.field_name``) for every simple field of the nested config ``cls``;
    ``aliases`` {old flat flag name: field} keep older spellings (``--gain-min``) working as the same flag."""
    old = {v: k for k, v in (aliases or {}).items()}
    for field, kind in field_types(cls).items():
        if not is_flag(kind):
            continue
        flags = [f"--{name.replace('_', '-')}.{field.replace('_', '-')}"]
        if field in old:
            flags.append(f"--{old[field].replace('_', '-')}")
        dest = f"{name}.{field}"
        parser.add_argument(*flags, dest=dest, default=None, metavar=kind_name(kind),
                            type=lambda t, n=dest, k=kind: _parse(n, k, t), help=f"default {getattr(cls(), field)!r}")


def nested_overrides(args: argparse.Namespace, name: str, cls) -> dict:
    """The ``--name.field`` flags of :func:`add_nested_fields` given on the command line: ``{field: value}``."""
    return {f: getattr(args, f"{name}.{f}") for f in field_types(cls)
            if getattr(args, f"{name}.{f}", None) is not None}

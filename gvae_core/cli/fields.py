"""Command-line flags made from a configuration dataclass's fields: each field's metadata gives
its help (`help`; `flag`, `metavar`, `choices`, `zero_is_none`, `advanced` where it needs them), its
type gives the parsing, and the default said in the help is the dataclass's and each profile's, so
no help text restates a value."""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from collections.abc import Iterable, Mapping


def flag_of(f: dataclasses.Field) -> str:
    return f.metadata.get("flag", "--" + f.name.replace("_", "-"))


def _shown(value) -> str:
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, (tuple, list)):
        return " ".join(_shown(v) for v in value)
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def default_text(f: dataclasses.Field, profiles: Mapping[str, Mapping] | None = None) -> str:
    """"(default: X; tiny: Y, ...)": the field's default and each profile that changes it."""
    base = f.default
    parts = [f"default: {_shown(base)}"]
    for name, changes in (profiles or {}).items():
        if f.name in changes and changes[f.name] != base:
            parts.append(f"{name}: {_shown(changes[f.name])}")
    return "(" + "; ".join(parts) + ")"


def _parsing(f: dataclasses.Field, hint) -> dict:
    """argparse keywords for a field of type `hint`."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):  # X | None
        hint = next(a for a in args if a is not type(None))
        origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is bool:
        return {"action": argparse.BooleanOptionalAction}
    if origin is tuple:
        nargs = "+" if len(args) == 2 and args[1] is Ellipsis else len(args)
        return {"type": args[0], "nargs": nargs}
    return {"type": hint}


def add_fields(parser, cls, names: Iterable[str] | None = None, *, profiles: Mapping[str, Mapping] | None = None,
               groups: Mapping[str, object] | None = None) -> None:
    """Add a flag for each field of dataclass `cls` named in `names` (default: all) to `parser`
    (or to `groups[name]`, an argument group, where given). Every flag's default is None: a flag
    not given leaves the field to the profile."""
    hints = typing.get_type_hints(cls)
    wanted = None if names is None else set(names)
    for f in dataclasses.fields(cls):
        if wanted is not None and f.name not in wanted:
            continue
        meta = f.metadata
        help_text = f"{meta['help']} {default_text(f, profiles)}".replace("%", "%%")
        kwargs = {"dest": f.name, "default": None, "help": help_text, **_parsing(f, hints[f.name])}
        for key in ("metavar", "choices"):
            if key in meta:
                kwargs[key] = meta[key]
        if "choices" in kwargs and kwargs.get("type") is not None:
            kwargs.pop("metavar", None)
        (groups or {}).get(f.name, parser).add_argument(flag_of(f), **kwargs)


def field_values(args: argparse.Namespace, cls) -> tuple[dict, tuple[str, ...]]:
    """(the fields given on the command line, the fields set to none: 0 for a `zero_is_none` one)."""
    values, none = {}, []
    for f in dataclasses.fields(cls):
        value = getattr(args, f.name, None)
        if value is None:
            continue
        if f.metadata.get("zero_is_none") and value == 0:
            none.append(f.name)
        else:
            values[f.name] = tuple(value) if isinstance(value, list) else value
    return values, tuple(none)

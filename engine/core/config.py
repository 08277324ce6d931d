"""Typed dataclass configs and the one bridge between them and text: command lines, JSON and ``k=v`` lists.

A config is a (frozen) dataclass whose fields are made with :func:`option`: a default and a one-line help
text that doubles as command-line help. Nested dataclass fields are sub-configs. Every command of
Interleave turns its configs into options, and options back into configs, through this module only:

- :func:`add_options` adds one ``--name`` per field to an ``argparse`` parser (a nested field's fields
  as ``--sub.name``); :func:`config_from_args` builds the config from the parsed options that were given,
  on top of a base config (the defaults, or a config file);
- :func:`config_from_dict` / :func:`config_to_dict`: the JSON form (the config that produced a run is saved
  beside it);
- :func:`config_from_text`: ``"key=value,sub.key=value"``, the options of a method name in brackets
  (``decomp[flow_width=240,gate.tile=16]``).

One syntax for values everywhere text is parsed (:func:`parse_value`): booleans are ``true`` / ``false``
(``1`` / ``0`` also read) and on a command line ``--name`` / ``--no-name``; tuples are comma-separated
(``--fov-range 45,75``); a ``Literal`` takes one of its values. Bad values raise ``InputError`` naming the
option.

>>> from dataclasses import dataclass
>>> @dataclass(frozen=True)
... class Demo:
...     width: int = option(640, "frame width")
...     fast: bool = option(False, "skip the slow part")
>>> config_from_text(Demo, "width=320,fast=true")
Demo(width=320, fast=True)
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import types
import typing
from pathlib import Path
from typing import Any, Iterable, Literal, Optional, Union

from engine.core.errors import InputError

__all__ = ["option", "add_options", "config_from_args", "config_from_dict", "config_from_file", "config_to_dict",
           "config_from_text", "parse_value", "option_names", "option_kinds"]

_TRUE, _FALSE = ("true", "1"), ("false", "0")


def option(default: Any, help_text: str, **kwargs: Any) -> Any:
    """A dataclass field with a default and ``metadata['help']`` (its documentation and CLI help)."""
    return dataclasses.field(default=default, metadata={"help": help_text}, **kwargs)


def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        return f.default_factory()  # type: ignore[misc]
    return None


def _optional_inner(kind: Any) -> Any:
    """X for ``Optional[X]`` / ``X | None``, else None."""
    if typing.get_origin(kind) in (Union, types.UnionType):
        args = [a for a in typing.get_args(kind) if a is not type(None)]
        if len(args) == 1 and len(typing.get_args(kind)) == 2:
            return args[0]
    return None


def _text_kind(kind: Any) -> bool:
    """Whether a field of this type can be written as text (``parse_value`` reads it)."""
    inner = _optional_inner(kind)
    if inner is not None:
        return _text_kind(inner)
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if kind in (bool, int, float, str) or origin is Literal:
        return True
    if origin is tuple and args:
        return all(a in (int, float, str) for a in args if a is not Ellipsis)
    return False


def parse_value(kind: Any, text: str, name: str = "value") -> Any:
    """The value of type ``kind`` written as ``text`` (see the module docstring for the syntax); InputError
    naming ``name`` when it does not parse."""
    raw = str(text).strip()
    inner = _optional_inner(kind)
    if inner is not None:
        return None if raw.lower() == "none" else parse_value(inner, raw, name)
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    try:
        if kind is bool:
            if raw.lower() in _TRUE:
                return True
            if raw.lower() in _FALSE:
                return False
            raise ValueError(raw)
        if origin is Literal:
            for choice in args:
                if str(choice) == raw:
                    return choice
            raise InputError(f"must be one of {', '.join(map(str, args))}, got {raw!r}", field=name)
        if origin is tuple:
            parts = [p.strip() for p in raw.split(",") if p.strip()]
            if len(args) == 2 and args[1] is Ellipsis:
                return tuple(args[0](p) for p in parts)
            if len(parts) != len(args):
                raise InputError(f"must be {len(args)} comma-separated values, got {raw!r}", field=name)
            return tuple(a(p) for a, p in zip(args, parts))
        if kind in (int, float, str):
            return kind(raw)
    except InputError:  # a Literal's own message (InputError is a ValueError)
        raise
    except ValueError:
        what = "true or false" if kind is bool else f"a valid {getattr(kind, '__name__', kind)}"
        raise InputError(f"must be {what}, got {raw!r}", field=name) from None
    raise InputError(f"cannot be given as text (type {kind})", field=name)


def _show(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, tuple):
        return ",".join(map(str, value))
    return str(value)


def option_names(cls: type, prefix: str = "") -> list[str]:
    """The dotted names of every text-writable field of ``cls`` (nested configs as ``sub.name``)."""
    out = []
    hints = _hints(cls)
    for f in dataclasses.fields(cls):
        kind = hints[f.name]
        if dataclasses.is_dataclass(kind):
            out.extend(option_names(kind, f"{prefix}{f.name}."))
        elif _text_kind(kind):
            out.append(prefix + f.name)
    return out


def option_kinds(cls: type) -> dict[str, Any]:
    """Each of :func:`option_names`' dotted names -> the type :func:`parse_value` reads it as."""
    return {name: _field_kind(cls, name) for name in option_names(cls)}


def add_options(parser: argparse.ArgumentParser, cls: type, *, prefix: str = "",
                skip: Iterable[str] = ()) -> None:
    """One ``--name`` per field of the dataclass ``cls`` (underscores as dashes; a nested dataclass field's
    fields as ``--field.name``), its ``metadata['help']`` and default as the help. Options not given are
    left out of the parsed namespace, so :func:`config_from_args` changes only what the user wrote.
    Fields named in ``skip`` and fields no text can hold are left out."""
    skip = set(skip)
    hints = _hints(cls)
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        kind, dest = hints[f.name], prefix + f.name
        if dataclasses.is_dataclass(kind):
            add_options(parser, kind, prefix=dest + ".")
            continue
        if not _text_kind(kind):
            continue
        default = _default(f)
        help_text = f"{f.metadata.get('help', f.name.replace('_', ' '))} (default: {_show(default)})"
        flag = "--" + dest.replace("_", "-")
        if kind is bool:
            parser.add_argument(flag, dest=dest, action=argparse.BooleanOptionalAction, default=argparse.SUPPRESS,
                                help=help_text)
        else:
            parser.add_argument(flag, dest=dest, default=argparse.SUPPRESS,
                                type=lambda text, k=kind, d=dest: _argparse_value(k, text, d), help=help_text)


def _argparse_value(kind: Any, text: str, name: str) -> Any:
    try:
        return parse_value(kind, text, name)
    except InputError as exc:
        raise argparse.ArgumentTypeError(exc.problem) from None


def _replace(config: Any, values: dict[str, Any], where: str) -> Any:
    """``config`` with the dotted ``values`` (``name`` or ``sub.name``) set; unknown names raise."""
    hints = _hints(type(config))
    names = {f.name for f in dataclasses.fields(config)}
    direct, nested = {}, {}
    for key, value in values.items():
        head, dot, rest = key.partition(".")
        if head not in names:
            raise InputError(f"unknown option '{key}'; expected one of {', '.join(option_names(type(config)))}",
                             field=where)
        if dot:
            if not dataclasses.is_dataclass(hints[head]):
                raise InputError(f"option '{head}' has no sub-option '{rest}'", field=where)
            nested.setdefault(head, {})[rest] = value
        else:
            direct[head] = value
    for head, sub in nested.items():
        direct[head] = _replace(direct.get(head, getattr(config, head)), sub, where)
    try:
        return dataclasses.replace(config, **direct)
    except (TypeError, ValueError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(str(exc), field=where) from exc


def config_from_args(cls: type, args: argparse.Namespace, base: Any = None, *, prefix: str = "") -> Any:
    """The config of type ``cls``: ``base`` (default ``cls()``) with every option that ``args`` holds (those
    :func:`add_options` added and the user gave) set; ``prefix`` selects options added with that prefix."""
    config = cls() if base is None else base
    names = {f.name for f in dataclasses.fields(cls)}
    values = {k[len(prefix):]: v for k, v in vars(args).items()
              if k.startswith(prefix) and k[len(prefix):].partition(".")[0] in names}
    return _replace(config, values, cls.__name__)


def config_from_text(cls: type, text: str, base: Any = None) -> Any:
    """The config of type ``cls`` from ``"key=value,sub.key=value"`` on top of ``base`` (default ``cls()``);
    unknown keys and bad values raise InputError naming the option."""
    config = cls() if base is None else base
    values: dict[str, Any] = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        key, sep, raw = part.partition("=")
        key = key.strip()
        kind = _field_kind(cls, key)
        if not sep or kind is None:
            raise InputError(f"option '{part}': expected key=value with key one of {', '.join(option_names(cls))}",
                             field=cls.__name__)
        values[key] = parse_value(kind, raw, key)
    return _replace(config, values, cls.__name__)


def _field_kind(cls: type, dotted: str) -> Optional[Any]:
    head, dot, rest = dotted.partition(".")
    hints = _hints(cls)
    if head not in hints or head not in {f.name for f in dataclasses.fields(cls)}:
        return None
    kind = hints[head]
    if dot:
        return _field_kind(kind, rest) if dataclasses.is_dataclass(kind) else None
    return kind if _text_kind(kind) else None


def config_from_dict(cls: type, data: Any, *, where: Optional[str] = None) -> Any:
    """A ``cls`` from its JSON form (nested dicts for nested configs, lists for tuples); missing keys keep
    their defaults, unknown keys and values of the wrong type raise InputError naming ``where``."""
    where = where or cls.__name__
    if not isinstance(data, dict):
        raise InputError(f"must be a JSON object, got {type(data).__name__}", field=where)
    hints = _hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise InputError(f"unknown keys {', '.join(unknown)}", field=where)
    values = {k: _from_json(hints[k], v, f"{where}.{k}") for k, v in data.items()}
    try:
        return cls(**values)
    except TypeError as exc:
        raise InputError(str(exc), field=where) from exc


def config_from_file(cls: type, path: Union[str, "os.PathLike[str]"], *, field: str = "--config") -> Any:
    """A ``cls`` from a JSON file in the form :func:`config_to_dict` writes; a missing file, bad JSON or a
    wrong key raise InputError naming the file and ``field``."""
    path = Path(path)
    if not path.is_file():
        raise InputError("config file not found", file=path, field=field)
    try:
        return config_from_dict(cls, json.loads(path.read_text()))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"is not a {cls.__name__} JSON: {exc}", file=path, field=field) from None
    except InputError as exc:
        raise InputError(f"is not a {cls.__name__} JSON: {exc.problem}", file=path, field=field) from None


def _from_json(kind: Any, value: Any, where: str) -> Any:
    if dataclasses.is_dataclass(kind):
        return config_from_dict(kind, value, where=where)
    inner = _optional_inner(kind)
    if inner is not None:
        return None if value is None else _from_json(inner, value, where)
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise InputError(f"must be a list, got {value!r}", field=where)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_from_json(args[0], v, where) for v in value)
        return tuple(_from_json(a, v, where) for a, v in zip(args, value))
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if kind in (bool, int, float, str) and not isinstance(value, kind):
        raise InputError(f"must be {kind.__name__}, got {value!r}", field=where)
    if kind is int and isinstance(value, bool):
        raise InputError(f"must be int, got {value!r}", field=where)
    return value


def config_to_dict(config: Any) -> dict[str, Any]:
    """The JSON form of a config (``dataclasses.asdict``, tuples as lists)."""
    def plain(value: Any) -> Any:
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        return value

    return plain(dataclasses.asdict(config))

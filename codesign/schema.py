"""Validation of plain recipe data against config dataclasses.

A config dataclass declares types with ordinary annotations and constraints in
field metadata::

    @dataclass
    class SineConfig:
        bound: float = field(default=0.3, metadata={"gt": 0, "help": "action bound"})
        device: str = field(default="cpu", metadata={"choices": ["cpu", "cuda"]})

Supported metadata: ``gt``, ``ge``, ``lt``, ``le``, ``choices`` (applied to each
element when the field is a list) and ``min_len`` (lists). Supported types:
bool, int, float, str, Any, ``Optional``/unions, ``Literal``, ``list[T]``,
``dict[str, T]`` and nested dataclasses. A field with no default (or the
OmegaConf ``"???"`` default) is required. A nested dataclass given in part keeps
its field's own default for the keys it leaves out (e.g. an environment preset's
robot stiffness when a recipe sets only the robot's size).

OmegaConf's own structured-config checks lose key paths inside lists of
dataclasses and know no ranges or choices, so validation is done here; every
problem names its full key path, the offending value and what is allowed.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from codesign.registry import suggest

_OMEGACONF_MISSING = "???"
_INVALID = object()  # marks a value that failed validation

_BOUNDS = {
    "gt": (lambda v, b: v > b, ">"),
    "ge": (lambda v, b: v >= b, ">="),
    "lt": (lambda v, b: v < b, "<"),
    "le": (lambda v, b: v <= b, "<="),
}


@dataclass(frozen=True)
class Problem:
    """One validation failure at a key path such as ``controller.frequencies[1]``."""

    path: str
    message: str

    def __str__(self) -> str:
        return f"{self.path}: {self.message}" if self.path else self.message


def join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def is_required(f: dataclasses.Field) -> bool:
    no_default = f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
    return no_default or f.default == _OMEGACONF_MISSING


def convert(schema: type, data: Any, path: str = "") -> tuple[Any, list[Problem]]:
    """Build a ``schema`` instance from plain ``data``; returns (instance or None, problems)."""
    problems: list[Problem] = []
    value = _dataclass(schema, data, path, problems)
    return (None if value is _INVALID else value), problems


def type_name(tp: Any) -> str:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is Any:
        return "any"
    if tp is type(None):
        return "null"
    if origin is typing.Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(type_name(a) for a in args)
    if origin is list:
        return f"list[{type_name(args[0])}]" if args else "list"
    if origin is dict:
        return f"mapping of {type_name(args[1])}" if args else "mapping"
    if dataclasses.is_dataclass(tp):
        return f"mapping ({tp.__name__})"
    return getattr(tp, "__name__", str(tp))


def _describe(value: Any) -> str:
    kind = "null" if value is None else type(value).__name__
    return f"{kind} {value!r}" if value is not None else "null"


def _dataclass(cls: type, data: Any, path: str, problems: list[Problem]) -> Any:
    if not isinstance(data, Mapping):
        problems.append(Problem(path, f"expected {type_name(cls)}, got {_describe(data)}"))
        return _INVALID
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    before = len(problems)
    for key in data:
        if key not in fields:
            problems.append(
                Problem(
                    join(path, str(key)),
                    f"unknown key; {suggest(str(key), fields)}allowed: {', '.join(fields) or '(none)'}",
                )
            )
    kwargs = {}
    for name, f in fields.items():
        sub = join(path, name)
        if name in data:
            value = _value(hints[name], _over_default(f, data[name]), sub, f.metadata, problems)
            if value is not _INVALID:
                kwargs[name] = value
        elif is_required(f):
            problems.append(Problem(sub, f"missing required value ({type_name(hints[name])})"))
    if len(problems) > before:
        return _INVALID
    return cls(**kwargs)


def _over_default(f: dataclasses.Field, given: Any) -> Any:
    """`given` merged over the field's default when both are mappings (the default a dataclass),
    so a partly given section changes only what it names."""
    if not isinstance(given, Mapping):
        return given
    default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
    if not dataclasses.is_dataclass(default) or isinstance(default, type):
        return given
    return deep_merge(dataclasses.asdict(default), given)


def deep_merge(base: Mapping, child: Mapping) -> dict:
    """`child` over `base`, mappings merged key by key at every depth."""
    out = dict(base)
    for key, value in child.items():
        old = out.get(key)
        out[key] = deep_merge(old, value) if isinstance(old, Mapping) and isinstance(value, Mapping) else value
    return out


def _value(tp: Any, value: Any, path: str, meta: Mapping, problems: list[Problem]) -> Any:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        return _union(tp, args, value, path, meta, problems)
    if origin is typing.Literal:
        if value in args:
            return value
        problems.append(Problem(path, f"{value!r} is not a valid choice; allowed: {', '.join(map(str, args))}"))
        return _INVALID
    if origin is list or tp is list:
        return _list(args[0] if args else Any, value, path, meta, problems)
    if origin is dict or tp is dict:
        return _dict(args[1] if args else Any, value, path, meta, problems)
    if dataclasses.is_dataclass(tp):
        return _dataclass(tp, value, path, problems)
    return _scalar(tp, value, path, meta, problems)


def _union(tp: Any, args: tuple, value: Any, path: str, meta: Mapping, problems: list[Problem]) -> Any:
    if value is None and type(None) in args:
        return None
    options = [a for a in args if a is not type(None)]
    if len(options) == 1:
        return _value(options[0], value, path, meta, problems)
    for option in options:
        scratch: list[Problem] = []
        result = _value(option, value, path, meta, scratch)
        if not scratch:
            return result
    problems.append(Problem(path, f"expected {type_name(tp)}, got {_describe(value)}"))
    return _INVALID


def _list(item_type: Any, value: Any, path: str, meta: Mapping, problems: list[Problem]) -> Any:
    if not isinstance(value, (list, tuple)):
        problems.append(Problem(path, f"expected list[{type_name(item_type)}], got {_describe(value)}"))
        return _INVALID
    min_len = meta.get("min_len")
    if min_len is not None and len(value) < min_len:
        problems.append(Problem(path, f"needs at least {min_len} item(s), got {len(value)}"))
        return _INVALID
    items = [_value(item_type, v, f"{path}[{i}]", meta, problems) for i, v in enumerate(value)]
    return _INVALID if any(i is _INVALID for i in items) else items


def _dict(item_type: Any, value: Any, path: str, meta: Mapping, problems: list[Problem]) -> Any:
    if not isinstance(value, Mapping):
        problems.append(Problem(path, f"expected mapping of {type_name(item_type)}, got {_describe(value)}"))
        return _INVALID
    items = {str(k): _value(item_type, v, join(path, str(k)), meta, problems) for k, v in value.items()}
    return _INVALID if any(i is _INVALID for i in items.values()) else items


def _scalar(tp: Any, value: Any, path: str, meta: Mapping, problems: list[Problem]) -> Any:
    if tp not in (bool, int, float, str):
        raise TypeError(f"unsupported type {tp!r} in config schema at {path}")
    if tp is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if not isinstance(value, tp) or (tp in (int, float) and isinstance(value, bool)):
        problems.append(Problem(path, f"expected {type_name(tp)}, got {_describe(value)}"))
        return _INVALID
    choices = meta.get("choices")
    if choices is not None and value not in choices:
        problems.append(
            Problem(path, f"{value!r} is not a valid choice; {suggest(str(value), map(str, choices))}"
                    f"allowed: {', '.join(map(str, choices))}")
        )
        return _INVALID
    for key, (test, symbol) in _BOUNDS.items():
        if key in meta and not test(value, meta[key]):
            limits = " and ".join(f"{_BOUNDS[k][1]} {meta[k]}" for k in _BOUNDS if k in meta)
            problems.append(Problem(path, f"{value!r} is out of range; must be {limits}"))
            return _INVALID
    return value

"""Type checking and text parsing of dataclass config fields, driven by their annotations.

Generic on purpose: a field added to a config later is checked and parsable without more
code, as long as its annotation is one of ``bool``, ``int``, ``float``, ``str``,
``tuple[T, ...]`` / ``tuple[T1, T2]``, ``Literal[...]`` or ``X | None`` of those.

Rules (why: a wrong type must not pass silently, e.g. ``cluster_loss="no"`` is truthy):
* ``bool`` fields take only ``True``/``False`` (numpy bools too);
* ``int`` fields take integers, never bools or floats (``2.0`` is refused);
* ``float`` fields take real numbers but not bools, and not NaN;
* ``tuple`` fields take a tuple or list of the right length, each item checked (a list is
  stored as a tuple so the frozen config stays hashable);
* numpy scalars are stored as the matching Python type.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import types
import typing
from functools import lru_cache

import numpy as np

__all__ = ["ConfigTypeError", "check_field_types", "parse_option_value", "field_types"]

_TRUE = {"true", "yes", "on", "1"}
_FALSE = {"false", "no", "off", "0"}
_NONE = {"none", "null"}


class ConfigTypeError(TypeError, ValueError):
    """A config field holds a value of the wrong type (a TypeError; also a ValueError, so
    callers that catch ValueError for bad settings catch it too)."""


@lru_cache(maxsize=None)
def field_types(cls) -> dict[str, object]:
    """{field name: resolved annotation} of a dataclass."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def _describe(tp) -> str:
    origin = typing.get_origin(tp)
    if tp is type(None):
        return "None"
    if origin is typing.Literal:
        return " or ".join(repr(a) for a in typing.get_args(tp))
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_describe(a) for a in typing.get_args(tp))
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a tuple of {_describe(args[0])}"
        return f"a tuple of {len(args)} ({', '.join(_describe(a) for a in args)})"
    return {bool: "a bool (True/False)", int: "an integer", float: "a number", str: "a string"}.get(
        tp, getattr(tp, "__name__", str(tp)))


class _Mismatch(Exception):
    pass


def _coerce(value, tp):
    """``value`` as type ``tp`` (normalised), or raise _Mismatch."""
    origin = typing.get_origin(tp)
    if tp is typing.Any:
        return value
    if tp is type(None):
        if value is None:
            return None
        raise _Mismatch
    if origin in (typing.Union, types.UnionType):
        for a in typing.get_args(tp):
            try:
                return _coerce(value, a)
            except _Mismatch:
                pass
        raise _Mismatch
    if origin is typing.Literal:
        if any(value == a and type(value) is type(a) for a in typing.get_args(tp)):
            return value
        raise _Mismatch
    if origin is tuple:
        if not isinstance(value, (tuple, list)):
            raise _Mismatch
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0]) for v in value)
        if len(value) != len(args):
            raise _Mismatch
        return tuple(_coerce(v, a) for v, a in zip(value, args))
    if tp is bool:
        if _is_bool(value):
            return bool(value)
        raise _Mismatch
    if tp is int:
        if isinstance(value, numbers.Integral) and not _is_bool(value):
            return int(value)
        raise _Mismatch
    if tp is float:
        if isinstance(value, numbers.Real) and not _is_bool(value):
            v = float(value)
            if math.isnan(v):
                raise _Mismatch
            return value if type(value) in (int, float) else v
        raise _Mismatch
    if tp is str:
        if isinstance(value, str):
            return value
        raise _Mismatch
    if isinstance(tp, type):
        if isinstance(value, tp):
            return value
        raise _Mismatch
    return value  # an annotation we do not understand: not checked


def _is_bool(v) -> bool:
    return isinstance(v, (bool, np.bool_))


def check_field_types(obj) -> None:
    """Check (and normalise in place, also on frozen dataclasses) every field of ``obj``
    against its annotation; ``TypeError`` naming the class, field, expected type and value."""
    cls = type(obj)
    for name, tp in field_types(cls).items():
        value = getattr(obj, name)
        try:
            fixed = _coerce(value, tp)
        except _Mismatch:
            extra = " (NaN is not allowed)" if isinstance(value, float) and math.isnan(value) else ""
            raise ConfigTypeError(f"{cls.__name__}.{name} must be {_describe(tp)}, got {value!r} "
                            f"({type(value).__name__}){extra}") from None
        if fixed is not value:
            object.__setattr__(obj, name, fixed)


def _parse(text: str, tp):
    origin = typing.get_origin(tp)
    t = text.strip()
    low = t.lower()
    if tp is type(None):
        if low in _NONE:
            return None
        raise _Mismatch
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if type(None) in args and low in _NONE:
            return None
        for a in args:
            if a is type(None):
                continue
            try:
                return _parse(text, a)
            except (_Mismatch, ValueError):
                pass
        raise _Mismatch
    if origin is typing.Literal:
        for a in typing.get_args(tp):
            try:
                if _parse(text, type(a)) == a:
                    return a
            except (_Mismatch, ValueError):
                pass
        raise _Mismatch
    if origin is tuple:
        inner = t[1:-1] if t[:1] in "([" and t[-1:] in ")]" and t else t
        parts = [p for p in inner.split(",")] if inner.strip() else []
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_parse(p, args[0]) for p in parts)
        if len(parts) != len(args):
            raise _Mismatch
        return tuple(_parse(p, a) for p, a in zip(parts, args))
    if tp is bool:
        if low in _TRUE:
            return True
        if low in _FALSE:
            return False
        raise _Mismatch
    if tp is int:
        try:
            return int(t)
        except ValueError:
            f = float(t)  # '1e3' is fine when it is a whole number
            if f.is_integer():
                return int(f)
            raise _Mismatch from None
    if tp is float:
        return float(t)
    if tp is str:
        if len(t) >= 2 and t[0] == t[-1] and t[0] in "'\"":
            return t[1:-1]
        return t
    raise _Mismatch


def parse_option_value(cls, name: str, text: str):
    """The value of field ``name`` of the dataclass ``cls`` written as ``text`` (CLI
    ``--option name=text``). Bools accept true/false, yes/no, on/off, 1/0 (any case); tuples
    ``a,b`` or ``[a, b]`` or ``(a, b)``; optional fields ``none``/``null``. ``ValueError``
    naming the field (unknown field: listing the known ones) when it does not parse."""
    types_ = field_types(cls)
    if name not in types_:
        raise ValueError(f"{cls.__name__} has no option {name!r}; known: {', '.join(sorted(types_))}")
    if not isinstance(text, str):
        raise TypeError(f"option {name}: expected the text of a value, got {type(text).__name__}")
    tp = types_[name]
    try:
        return _parse(text, tp)
    except (_Mismatch, ValueError):
        hint = " (true/false, yes/no, on/off, 1/0)" if tp is bool else ""
        raise ValueError(f"option {name}={text!r}: expected {_describe(tp)}{hint}") from None

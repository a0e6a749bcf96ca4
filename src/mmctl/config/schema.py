"""Machinery that turns YAML mappings into frozen, validated dataclasses.

A section is a frozen dataclass whose fields are declared with :func:`param`; the
type annotation says what the YAML value must be and the metadata says which range
or shape is allowed.  :func:`build` walks a mapping against such a class and raises
:class:`~mmctl.errors.ConfigError` naming the key path, the value and what is allowed.

Supported annotations: ``float``, ``int``, ``bool``, ``str``, ``Literal[...]``,
``tuple[float, ...]`` / ``tuple[int, ...]`` (with ``shape=(n,)`` or ``shape=(n, n)``
for matrices stored as tuples of tuples), nested section dataclasses and ``X | None``.

Every number has a lower and an upper bound (``ge``/``gt`` and ``le``/``lt``; for a list,
one bound for all its entries or a tuple of one bound per entry) and a ``why``: the
physical reason for the range (the hardware's own limit where there is one), which the
error message repeats.  ``tests/test_config.py`` checks that no number lacks them.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import types
import typing
from collections.abc import Mapping
from typing import Any, Literal, cast, get_args, get_origin

from mmctl.errors import ConfigError

_MISSING = dataclasses.MISSING

#: a range bound: one number, or one per list entry, or none
Bound = float | tuple[float, ...] | None


def param(
    default: Any = _MISSING,
    *,
    doc: str = "",
    unit: str = "",
    ge: Bound = None,
    gt: Bound = None,
    le: Bound = None,
    lt: Bound = None,
    shape: tuple[int | None, ...] | None = None,
    min_len: int | None = None,
    why: str = "",
) -> Any:
    """Declare a config field: default, documentation, unit, allowed range/shape and
    ``why`` that range (one short sentence; the error message quotes it).

    A bound is a number, or for a list a tuple with one bound per entry."""
    meta = {
        "doc": doc,
        "unit": unit,
        "why": why,
        "ge": ge,
        "gt": gt,
        "le": le,
        "lt": lt,
        "shape": shape,
        "min_len": min_len,
    }
    if default is _MISSING:
        return dataclasses.field(metadata=meta)
    if isinstance(default, (list, dict)):
        raise TypeError("use tuples for sequence defaults (configs are frozen)")
    return dataclasses.field(default=default, metadata=meta)


def section(cls: type) -> type:
    """Decorator: a frozen, slotted dataclass usable as a config section."""
    return dataclasses.dataclass(frozen=True)(cls)


_BOUNDS = ("gt", "ge", "lt", "le")


def _range_text(meta: Mapping[str, Any]) -> str:
    parts = []
    for key, sym in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")):
        if meta.get(key) is not None:
            parts.append(f"{sym} {meta[key]}")
    return " and ".join(parts)


def _entry_meta(meta: Mapping[str, Any], index: int) -> Mapping[str, Any]:
    """``meta`` with per-entry bounds (tuples) narrowed to entry ``index``."""
    if not any(isinstance(meta.get(k), tuple) for k in _BOUNDS):
        return meta
    return {**meta, **{k: meta[k][index] for k in _BOUNDS if isinstance(meta.get(k), tuple)}}


def _check_range(path: str, value: float, meta: Mapping[str, Any], source: str | None) -> None:
    if isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(path, value, "must be a finite number", source)
    bad = (
        (meta.get("gt") is not None and not value > meta["gt"])
        or (meta.get("ge") is not None and not value >= meta["ge"])
        or (meta.get("lt") is not None and not value < meta["lt"])
        or (meta.get("le") is not None and not value <= meta["le"])
    )
    if bad:
        unit = f" [{meta['unit']}]" if meta.get("unit") else ""
        why = f"; {meta['why']}" if meta.get("why") else ""
        raise ConfigError(path, value, f"must be {_range_text(meta)}{unit}{why}", source)


def _scalar(path: str, value: Any, typ: Any, meta: Mapping[str, Any], source: str | None) -> Any:
    if typ is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(path, value, "must be a number", source)
        try:
            value = float(value)
        except OverflowError:  # an integer beyond any double
            raise ConfigError(path, value, "must be a finite number", source) from None
        _check_range(path, value, meta, source)
        return value
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(path, value, "must be an integer", source)
        _check_range(path, value, meta, source)
        return value
    if typ is bool:
        if not isinstance(value, bool):
            raise ConfigError(path, value, "must be true or false", source)
        return value
    if typ is str:
        if not isinstance(value, str) or (meta.get("min_len") and len(value) < meta["min_len"]):
            raise ConfigError(path, value, "must be a non-empty string", source)
        return value
    raise TypeError(f"unsupported config type {typ!r} at {path}")


def _tuple(path: str, value: Any, typ: Any, meta: Mapping[str, Any], source: str | None) -> Any:
    (elem, _ellipsis) = get_args(typ)
    shape = meta.get("shape")
    kind = "numbers" if elem in (float, int) else "values"
    if elem is int:
        kind = "integers"
    if shape is not None and len(shape) == 2:
        rows, cols = shape
        if get_origin(elem) is tuple:  # tuple[tuple[float, ...], ...]: rows of numbers
            elem = get_args(elem)[0]
        if rows is None:  # any number of rows (at least min_len), each of cols entries
            ok = isinstance(value, (list, tuple)) and all(
                isinstance(r, (list, tuple)) and len(r) == cols for r in value)
            if not ok:
                raise ConfigError(path, value, f"expected a list of [{cols} numbers] rows",
                                  source)
            if meta.get("min_len") is not None and 0 < len(value) < meta["min_len"]:
                raise ConfigError(path, value, f"expected none or at least "
                                  f"{meta['min_len']} rows", source)
            rows = len(value)
        ok = isinstance(value, (list, tuple)) and len(value) == rows and all(
            isinstance(r, (list, tuple)) and len(r) == cols for r in value
        )
        if not ok:
            raise ConfigError(path, value, f"expected a {rows}x{cols} matrix (list of lists)", source)
        return tuple(
            tuple(_scalar(f"{path}[{i}][{j}]", v, elem, _entry_meta(meta, j), source)
                  for j, v in enumerate(row))
            for i, row in enumerate(value)
        )
    if not isinstance(value, (list, tuple)):
        want = f"a list of {shape[0]} {kind}" if shape else f"a list of {kind}"
        raise ConfigError(path, value, f"expected {want}", source)
    if shape is not None and len(value) != shape[0]:
        raise ConfigError(path, value, f"expected a list of {shape[0]} {kind}, got {len(value)}", source)
    if meta.get("min_len") is not None and len(value) < meta["min_len"]:
        raise ConfigError(path, value, f"expected at least {meta['min_len']} {kind}", source)
    if elem in (float, int, bool, str):
        return tuple(_scalar(f"{path}[{i}]", v, elem, _entry_meta(meta, i), source)
                     for i, v in enumerate(value))
    if dataclasses.is_dataclass(elem):
        return tuple(build(cast(type, elem), v, f"{path}[{i}]", source)
                     for i, v in enumerate(value))
    raise TypeError(f"unsupported tuple element {elem!r} at {path}")


def _convert(path: str, value: Any, typ: Any, meta: Mapping[str, Any], source: str | None) -> Any:
    origin = get_origin(typ)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in get_args(typ) if a is not type(None)]
        if value is None:
            return None
        return _convert(path, value, args[0], meta, source)
    if origin is Literal:
        choices = get_args(typ)
        if value not in choices:
            allowed = ", ".join(repr(c) for c in choices)
            raise ConfigError(path, value, f"must be one of {allowed}", source)
        return value
    if origin is tuple:
        return _tuple(path, value, typ, meta, source)
    if dataclasses.is_dataclass(typ):
        return build(cast(type, typ), value, path, source)
    return _scalar(path, value, typ, meta, source)


def build(cls: type, data: Any, path: str = "", source: str | None = None) -> Any:
    """Build the section ``cls`` from a YAML mapping, validating every key.

    After field conversion, a ``validate(self, path, source)`` method on the class
    (if any) runs the cross-field checks and raises ``ConfigError`` itself.
    """
    where = path or "<top level>"
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise ConfigError(where, data, "expected a mapping of keys to values", source)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    for key in data:
        if key not in fields:
            allowed = ", ".join(sorted(fields)) or "(none)"
            key_path = f"{path}.{key}" if path else str(key)
            close = difflib.get_close_matches(str(key), list(fields), n=1, cutoff=0.6)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise ConfigError(key_path, data[key],
                              f"unknown key; {hint}allowed keys here: {allowed}", source)
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        key_path = f"{path}.{name}" if path else name
        if name in data:
            kwargs[name] = _convert(key_path, data[name], hints[name], f.metadata, source)
        elif f.default is _MISSING and f.default_factory is _MISSING:
            if dataclasses.is_dataclass(hints[name]):
                kwargs[name] = build(hints[name], {}, key_path, source)
            else:
                raise ConfigError(key_path, None, "is required", source)
    obj = cls(**kwargs)
    validate = getattr(obj, "validate", None)
    if validate is not None:
        validate(path, source)
    return obj


def sub(cls: type) -> Any:
    """A nested section field whose default is the section's own defaults."""
    return dataclasses.field(default_factory=lambda: build(cls, {}), metadata={"doc": cls.__doc__ or ""})


def to_dict(obj: Any) -> Any:
    """The plain-data form of a section (for `mmctl check-config --dump` and logs)."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, tuple):
        return [to_dict(v) for v in obj]
    return obj


def keys(cls: type, path: str = "") -> list[tuple[str, str, str, str, str]]:
    """(key, default, allowed, unit, meaning) of every key in the section ``cls`` and its
    subsections, in declaration order (``mmctl config reference``).  ``allowed``: the
    range of a number (per entry of a list), the choices of a Literal, "true | false",
    "text"; ``meaning``: the key's doc and the reason for its range."""
    rows: list[tuple[str, str, str, str, str]] = []
    hints = typing.get_type_hints(cls)
    defaults = build(cls, {})
    for f in dataclasses.fields(cls):
        typ = hints[f.name]
        key = f"{path}.{f.name}" if path else f.name
        optional = False
        if get_origin(typ) in (typing.Union, types.UnionType):
            optional = True
            typ = next(a for a in get_args(typ) if a is not type(None))
        if dataclasses.is_dataclass(typ):
            rows.extend(keys(cast(type, typ), key))
            continue
        meta = f.metadata
        elem = get_args(typ)[0] if get_origin(typ) is tuple else typ
        if get_origin(elem) is tuple:  # rows of a matrix
            elem = get_args(elem)[0]
        if elem in (int, float):
            allowed = _range_text(meta)
        elif get_origin(elem) is Literal:
            allowed = " | ".join(repr(a) for a in get_args(elem))
        elif elem is bool:
            allowed = "true | false"
        else:
            allowed = "text"
        if optional:
            allowed += " (or null)"
        if get_origin(typ) is tuple:
            shape = meta.get("shape")
            if shape and len(shape) == 2:
                allowed = (f"{shape[0]} x {shape[1]} " if shape[0] is not None
                           else f"rows of {shape[1]}: ") + allowed
            else:
                allowed = (f"{shape[0]} x " if shape else "list of ") + allowed
        value = to_dict(getattr(defaults, f.name))
        default = "null" if value is None else repr(value)
        doc, why = meta.get("doc", ""), meta.get("why", "")
        meaning = f"{doc} (range: {why})" if doc and why else (doc or why)
        rows.append((key, default, allowed, meta.get("unit", ""), meaning))
    return rows

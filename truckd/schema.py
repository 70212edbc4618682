"""Strict loading of nested frozen dataclasses from YAML-like mappings.

Every configuration section is a frozen dataclass whose fields carry a :func:`spec`
(unit, allowed range, description).  :func:`load_dataclass` rejects unknown keys,
missing required keys, wrong types and out-of-range values with one line that names
the file, the dotted key, the value and what is allowed.  Nothing half-loads: the
object is only built once every field has passed.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import numbers
import types
import typing
from collections.abc import Mapping
from typing import Any, TypeVar, get_args, get_origin, get_type_hints

from truckd.errors import InputError
from truckd.yamlsafe import short

T = TypeVar("T")


def spec(
    doc: str,
    *,
    unit: str = "",
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    choices: tuple[str, ...] | None = None,
    default: Any = dataclasses.MISSING,
    default_factory: Any = dataclasses.MISSING,
) -> Any:
    """A dataclass field with validation metadata.

    ``lo``/``hi`` bound numbers (inclusive; ``lo_open`` makes the lower bound strict),
    ``choices`` bounds strings.  Fields without a default are required in the file.
    """
    meta = {"doc": doc, "unit": unit, "lo": lo, "hi": hi, "lo_open": lo_open, "choices": choices}
    if default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    if default is not dataclasses.MISSING:
        return dataclasses.field(default=default, metadata=meta)
    return dataclasses.field(metadata=meta)


def _fail(source: str, key: str, value: Any, expected: str) -> InputError:
    return InputError(f"{source}: key '{key}' = {short(value)}: expected {expected}")


def _allowed(meta: Mapping[str, Any]) -> str:
    lo, hi, unit = meta.get("lo"), meta.get("hi"), meta.get("unit", "")
    u = f" {unit}" if unit else ""
    if lo is not None and hi is not None:
        left = "(" if meta.get("lo_open") else "["
        return f"a number in {left}{lo}, {hi}]{u}"
    if lo is not None:
        op = ">" if meta.get("lo_open") else ">="
        return f"a number {op} {lo}{u}"
    if hi is not None:
        return f"a number <= {hi}{u}"
    return f"a number{u}"


def _check_number(source: str, key: str, value: Any, meta: Mapping[str, Any], is_int: bool) -> Any:
    if isinstance(value, bool) or not isinstance(value, int | float):
        expected = "an integer" if is_int else _allowed(meta)
        if isinstance(value, str) and _looks_numeric(value):
            expected += " (this value was read as text: remove the quotes)"
        raise _fail(source, key, value, expected)
    if is_int and not isinstance(value, int):
        raise _fail(source, key, value, "an integer")
    if not math.isfinite(float(value)):
        raise _fail(source, key, value, "a finite " + _allowed(meta).removeprefix("a "))
    lo, hi = meta.get("lo"), meta.get("hi")
    bad_lo = lo is not None and (value <= lo if meta.get("lo_open") else value < lo)
    bad_hi = hi is not None and value > hi
    if bad_lo or bad_hi:
        raise _fail(source, key, value, _allowed(meta))
    return int(value) if is_int else float(value)


def _looks_numeric(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _convert(source: str, key: str, value: Any, tp: Any, meta: Mapping[str, Any]) -> Any:
    origin = get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if value is None and len(args) < len(get_args(tp)):
            return None
        return _convert(source, key, value, args[0], meta)
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        return load_dataclass(tp, value, source, prefix=key)
    if tp is float:
        return _check_number(source, key, value, meta, is_int=False)
    if tp is int:
        return _check_number(source, key, value, meta, is_int=True)
    if tp is bool:
        if not isinstance(value, bool):
            raise _fail(source, key, value, "true or false")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise _fail(source, key, value, "a string")
        choices = meta.get("choices")
        if choices and value not in choices:
            raise _fail(source, key, value, "one of " + ", ".join(choices))
        return value
    if origin is tuple:
        (item_tp, _ellipsis) = get_args(tp)
        if not isinstance(value, list | tuple):
            raise _fail(source, key, value, "a list")
        return tuple(_convert(source, f"{key}[{n}]", v, item_tp, meta) for n, v in enumerate(value))
    raise TypeError(f"unsupported config field type {tp!r} at {key}")  # programming error


def load_dataclass(cls: type[T], data: Any, source: str, prefix: str = "") -> T:
    """Build ``cls`` from a mapping, validating every key (see module docstring).

    ``source`` names the file in error messages; ``prefix`` is the dotted key path.
    Raises :class:`InputError` on the first problem found.
    """
    where = prefix or "(top level)"
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise _fail(source, where, data, "a mapping of keys to values")
    assert dataclasses.is_dataclass(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for k in data:
        if k not in fields:
            name = short(f"{prefix}.{k}" if prefix else str(k))[1:-1]
            close = difflib.get_close_matches(str(k), fields, n=3, cutoff=0.6)
            if close:
                hint = "did you mean " + " or ".join(f"'{c}'" for c in close)
            elif len(fields) <= 12:
                hint = "allowed here: " + ", ".join(sorted(fields))
            else:  # one line: the section's keys are in the shipped configuration
                hint = f"{len(fields)} keys are allowed here (see the shipped truck.yaml)"
            raise InputError(f"{source}: unknown key '{name}'; {hint}")
    hints = get_type_hints(cls)
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        dotted = f"{prefix}.{name}" if prefix else name
        if name not in data:
            required = f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
            if required:
                meta = f.metadata
                what = meta.get("doc", "")
                unit = f" [{meta['unit']}]" if meta.get("unit") else ""
                raise InputError(f"{source}: missing key '{dotted}' ({what}{unit})")
            continue
        kwargs[name] = _convert(source, dotted, data[name], hints[name], f.metadata)
    obj = cls(**kwargs)
    check = getattr(obj, "validate", None)
    if callable(check):
        problem = check()
        if problem:
            raise InputError(f"{source}: {prefix + ': ' if prefix else ''}{problem}")
    return obj


def to_plain(obj: Any) -> Any:
    """A dataclass tree as plain dicts/lists (for JSON and YAML output)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, tuple | list):
        return [to_plain(v) for v in obj]
    if isinstance(obj, bool) or type(obj) in (int, float):
        return obj
    if isinstance(obj, numbers.Integral):
        return int(obj)  # a numpy integer: YAML's safe dumper knows only Python's
    if isinstance(obj, numbers.Real):
        return float(obj)  # a numpy float (fitted values; np.float64 is a float subclass)
    return obj

"""A faster constructor for the frozen dataclasses built every cycle.

A frozen dataclass's generated ``__init__`` sets each field through
``object.__setattr__(self, name, value)``: a call through a wrapper (an argument tuple
made and unpacked, the attribute looked up) per field, about a tenth of the daemon's
Python work per cycle with the nine or so records each cycle builds.  :func:`fast_init`
replaces it with one that writes the fields into the new instance's ``__dict__``
directly: the same instance (same fields, same order, still frozen: assigning a field
afterwards raises ``FrozenInstanceError`` as before), several times faster.

Only for what it can do exactly as the generated one: a frozen dataclass with a
``__dict__`` (not ``slots=True``), plain defaults (no ``default_factory``), no
``__post_init__``, no ``InitVar``, no field left out of ``__init__``; anything else raises
``TypeError`` at import time.  Pure: no I/O.
"""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

T = TypeVar("T")


def fast_init(cls: type[T]) -> type[T]:
    """``cls`` (a frozen dataclass, see the module docstring) with the faster
    ``__init__``; the same signature (names, order, defaults, keyword use)."""
    params = getattr(cls, "__dataclass_params__", None)
    if params is None or not params.frozen:
        raise TypeError(f"{cls.__name__}: not a frozen dataclass")
    if "__slots__" in cls.__dict__ or hasattr(cls, "__post_init__"):
        raise TypeError(f"{cls.__name__}: slots or __post_init__ (not supported)")
    fields = dataclasses.fields(cls)  # type: ignore[arg-type]
    if len(fields) != len(getattr(cls, "__dataclass_fields__", {})):
        raise TypeError(f"{cls.__name__}: has InitVar or ClassVar pseudo-fields (not supported)")
    args: list[str] = []
    defaults: dict[str, Any] = {}
    for f in fields:
        if not f.init or f.default_factory is not dataclasses.MISSING:
            raise TypeError(f"{cls.__name__}.{f.name}: init=False or a default_factory")
        if f.default is dataclasses.MISSING:
            args.append(f.name)
        else:
            defaults[f"_fi_default_{f.name}"] = f.default
            args.append(f"{f.name}=_fi_default_{f.name}")
    kw_only = [f.kw_only for f in fields]
    if any(kw_only):
        raise TypeError(f"{cls.__name__}: keyword-only fields (not supported)")
    body = "".join(f"    _fi_d[{f.name!r}] = {f.name}\n" for f in fields)
    src = f"def __init__(self, {', '.join(args)}):\n    _fi_d = self.__dict__\n{body}"
    namespace: dict[str, Any] = {}
    exec(src, dict(defaults), namespace)
    init = namespace["__init__"]
    init.__qualname__ = f"{cls.__qualname__}.__init__"
    init.__module__ = cls.__module__
    init.__doc__ = cls.__init__.__doc__
    setattr(cls, "__init__", init)  # noqa: B010 (mypy: no method assignment)
    return cls

"""Messages built on the thread that sends them, not on the control loop's.

The loop hands the publisher (Zenoh) and the recorder (MCAP) a :class:`Deferred`: the
function and this cycle's frozen outputs.  The first thread that needs the message builds
it and keeps it for the other; the loop's cycle pays only for the hand-over.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

Msg = Mapping[str, Any]

MessageSource = Msg | Callable[[], Msg]
"""A message, or a zero-argument callable that builds it (:class:`Deferred`)."""


class Deferred:
    """``Deferred(build, *args)()`` is ``build(*args)``, computed on the first call and
    kept: the publisher and the recorder threads share one message (a race builds it twice,
    alike).  ``args`` must not change afterwards (the cycle's outputs are frozen) and the
    message must not be mutated by whoever receives it."""

    __slots__ = ("_args", "_build", "_msg")

    def __init__(self, build: Callable[..., Msg], *args: Any) -> None:
        self._build = build
        self._args = args
        self._msg: Msg | None = None

    def __call__(self) -> Msg:
        msg = self._msg
        if msg is None:
            msg = self._msg = self._build(*self._args)
        return msg


def resolve(msg: MessageSource) -> Msg:
    """The message itself (built now when it is deferred)."""
    return msg() if callable(msg) else msg

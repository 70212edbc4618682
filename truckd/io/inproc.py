"""In-process link pair for simulated time: two ends poll shared queues, no threads.

``mode="frames"`` passes :class:`Frame` objects (like a CAN bus); ``mode="bytes"`` passes
the serial wire bytes through the COBS/CRC framing (so garbage and resync can be
simulated).  :meth:`Wire.disconnect` / :meth:`Wire.reconnect` simulate a device that
vanishes and comes back: both ends see :class:`LinkDownError`, bytes in flight are lost.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Literal

from firmware_protocol.codec import Frame
from truckd.io.link import FramedStreamLink, Link, LinkDownError


class Wire:
    """The shared medium of an in-process pair."""

    def __init__(self) -> None:
        self.up = True
        self.queues: tuple[deque[object], deque[object]] = (deque(), deque())

    def disconnect(self) -> None:
        """Unplug: both ends fail until :meth:`reconnect`; data in flight is lost."""
        self.up = False
        for q in self.queues:
            q.clear()

    def reconnect(self) -> None:
        """Plug back in."""
        self.up = True


def _never() -> float:
    return 0.0


class _End:
    """What both kinds of end share: the wire, its queues, and failing while unplugged."""

    wire: Wire
    _tx: deque[object]
    _rx: deque[object]

    def _attach(self, wire: Wire, side: int) -> None:
        self.wire = wire
        self._tx = wire.queues[side]
        self._rx = wire.queues[1 - side]

    def _check(self) -> None:
        if not self.wire.up:
            raise LinkDownError("in-process wire is unplugged")

    def _open(self) -> None:
        self._check()

    def _idle(self, timeout: float) -> None:
        return None  # simulated time: never sleep

    def _take(self) -> list[object]:
        self._check()
        out = list(self._rx)
        self._rx.clear()
        return out


class InprocFrameLink(_End, Link):
    """One end of a frame-mode pair."""

    def __init__(self, wire: Wire, side: int) -> None:
        super().__init__(reconnect_interval=0.0, clock=_never)
        self._attach(wire, side)
        self.open()

    def _write(self, frame: Frame) -> None:
        self._check()
        self._tx.append(frame)

    def _read(self, timeout: float) -> list[Frame]:
        out: list[Frame] = []
        for f in self._take():
            assert isinstance(f, Frame)
            out.append(f)
        return out


class InprocStreamLink(_End, FramedStreamLink):
    """One end of a bytes-mode pair (serial framing in memory)."""

    def __init__(self, wire: Wire, side: int) -> None:
        super().__init__(reconnect_interval=0.0, clock=_never)
        self._attach(wire, side)
        self.open()

    def _write_bytes(self, data: bytes) -> None:
        self._check()
        self._tx.append(bytes(data))

    def _read_bytes(self, timeout: float) -> bytes:
        chunks: list[bytes] = []
        for c in self._take():
            assert isinstance(c, bytes)
            chunks.append(c)
        return b"".join(chunks)


def inproc_pair(mode: Literal["frames", "bytes"] = "frames") -> tuple[Link, Link, Wire]:
    """Two connected link ends (companion side, firmware side) and their wire."""
    wire = Wire()
    factory: Callable[[Wire, int], Link]
    if mode == "frames":
        factory = InprocFrameLink
    elif mode == "bytes":
        factory = InprocStreamLink
    else:
        raise ValueError(f"inproc mode must be 'frames' or 'bytes', got {mode!r}")
    return factory(wire, 0), factory(wire, 1), wire

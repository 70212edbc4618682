"""The link interface: CAN frames of truck.dbc in and out, with error counters.

A thin base class (like python-can's ``BusABC``): the public :meth:`Link.send` and
:meth:`Link.recv` own error counting, disconnect detection and reconnection; a backend
implements only ``_open``, ``_close``, ``_write`` and ``_read``.  A backend raises
:class:`LinkDownError` when its device or bus is gone; the link then reports itself
disconnected and tries ``_open`` again every ``reconnect_interval`` seconds (on the
next ``send``/``recv``), so it comes back when the device does.

Sends never wait: a backend whose transmit buffer is full raises
:class:`FrameDroppedError`; the frame is counted in ``tx_dropped`` and ``tx_full`` (not
in ``tx_frames``) and :meth:`Link.send` returns False.  A device that cannot be opened is
logged once per outage (ERROR at start-up, WARNING after a disconnect), naming it, and
retried every ``reconnect_interval`` seconds; its return is logged too.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass

from firmware_protocol.codec import Frame
from firmware_protocol.framing import FramingStats

log = logging.getLogger("truckd.link")


class LinkDownError(Exception):
    """The device or bus is gone (unplugged, closed, interface down)."""


class LinkBusyError(LinkDownError):
    """The device exists but another process holds it (EBUSY, flock taken)."""


class FrameDroppedError(Exception):
    """The backend could not take this frame now (transmit buffer full); nothing waits."""


@dataclass
class LinkStats:
    """Transport error counters (counts since start)."""

    tx_frames: int = 0
    rx_frames: int = 0
    tx_dropped: int = 0
    """Frames not sent (link down, or the backend refused them)."""
    tx_full: int = 0
    """Of ``tx_dropped``: frames dropped because the transmit buffer was full."""
    bus_errors: int = 0
    """Error frames / transport errors reported by the backend."""
    bus_off: int = 0
    disconnects: int = 0
    reconnects: int = 0
    framing: FramingStats | None = None
    """Serial framing statistics (stream backends only)."""

    def as_dict(self) -> dict[str, int]:
        """Flat JSON-ready counters (framing ones prefixed ``framing_``)."""
        d = {k: v for k, v in asdict(self).items() if k != "framing"}
        if self.framing is not None:
            d.update({f"framing_{k}": v for k, v in self.framing.as_dict().items()})
        return d


class Link:
    """Base class of every backend (see module docstring).

    ``clock`` (s) only paces reconnection attempts; ``reconnect_interval`` 0 tries on
    every call.
    """

    def __init__(
        self,
        reconnect_interval: float = 0.5,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.stats = LinkStats()
        self.reconnect_interval = reconnect_interval
        self._clock = clock
        self._pending: deque[Frame] = deque()
        self._drained = False
        """Set by a backend's read that emptied the device (see :meth:`recv_all`)."""
        self._connected = False
        self._next_attempt = float("-inf")
        self._ever_connected = False
        self.last_error: str | None = None
        self.busy = False
        """The last failed open found the device held by another process."""
        self.name = type(self).__name__
        """What the logs call the device (backends set e.g. ``serial device PATH``)."""
        self._reported = False
        self._closed = False

    # -- backend hooks -------------------------------------------------------------
    def _open(self) -> None:
        """Open the device; raise LinkDownError when it is not there."""
        raise NotImplementedError

    def _close(self) -> None:
        """Release the device (must not raise)."""

    def _write(self, frame: Frame) -> None:
        """Send one frame; raise LinkDownError when the device is gone."""
        raise NotImplementedError

    def _read(self, timeout: float) -> list[Frame]:
        """Frames received within ``timeout`` s (possibly none); LinkDownError when gone."""
        raise NotImplementedError

    def _opened(self) -> None:
        """Called after every successful open (reset per-connection state)."""

    def _idle(self, timeout: float) -> None:
        """Wait while disconnected (real-time backends sleep; in-process ones do not)."""
        if timeout > 0:
            time.sleep(timeout)

    # -- public API ----------------------------------------------------------------
    @property
    def connected(self) -> bool:
        """True while the device is open and working."""
        return self._connected

    def open(self) -> bool:
        """Try to open now; True on success (failures are remembered, not raised)."""
        if self._closed:
            return False
        if self._connected:
            return True
        self._next_attempt = self._clock() + self.reconnect_interval
        try:
            self._open()
        except LinkDownError as exc:
            self.last_error = str(exc)
            self.busy = isinstance(exc, LinkBusyError)
            self._report(exc)
            return False
        self._connected = True
        self._opened()
        if self._ever_connected:
            self.stats.reconnects += 1
        if self._reported:
            log.info("%s: open%s", self.name, " again" if self._ever_connected else " (found)")
        self._ever_connected = True
        self._reported = False
        self.last_error = None
        self.busy = False
        return True

    def _report(self, exc: BaseException) -> None:
        """Say once per outage that the device cannot be opened (it is retried)."""
        if self._reported:
            return
        self._reported = True
        again = f"retrying every {self.reconnect_interval:g} s"
        if self._ever_connected:
            log.warning("%s: cannot reopen: %s; %s", self.name, exc, again)
        else:
            log.error("%s: cannot open: %s; %s", self.name, exc, again)

    def _ensure(self) -> bool:
        if self._connected:
            return True
        if self._closed or self._clock() < self._next_attempt:
            return False
        return self.open()

    def _down(self, exc: BaseException) -> None:
        log.warning("%s: link down: %s", self.name, exc)
        self._reported = False
        self._connected = False
        self.stats.disconnects += 1
        self.last_error = str(exc) or type(exc).__name__
        self._pending.clear()
        self._close()
        self._next_attempt = self._clock() + self.reconnect_interval

    def send(self, frame: Frame) -> bool:
        """Send one frame; False (counted in ``tx_dropped``) when it could not be sent."""
        if not self._ensure():
            self.stats.tx_dropped += 1
            return False
        try:
            self._write(frame)
        except FrameDroppedError:
            self.stats.tx_full += 1
            self.stats.tx_dropped += 1
            return False
        except LinkDownError as exc:
            self._down(exc)
            self.stats.tx_dropped += 1
            return False
        self.stats.tx_frames += 1
        return True

    def _read_counted(self, timeout: float) -> list[Frame] | None:
        """One read of the device: its frames (counted in ``rx_frames``), or None when
        the link went down in it."""
        try:
            frames = self._read(timeout)
        except LinkDownError as exc:
            self._down(exc)
            return None
        self.stats.rx_frames += len(frames)
        return frames

    def recv(self, timeout: float = 0.0) -> Frame | None:
        """The next received frame, waiting up to ``timeout`` s; None if none."""
        if self._pending:
            return self._pending.popleft()
        if not self._ensure():
            self._idle(timeout)
            return None
        frames = self._read_counted(timeout)
        if not frames:
            return None
        self._pending.extend(frames)
        return self._pending.popleft()

    def recv_all(self) -> list[Frame]:
        """Every frame available now, without waiting: those pending, then what the
        device holds, read until it has no more (or, where the backend can tell, until a
        read has emptied it: one read instead of a second, empty one)."""
        out = list(self._pending)
        self._pending.clear()
        if not self._ensure():
            return out
        while True:
            self._drained = False
            frames = self._read_counted(0.0)
            if not frames:
                return out
            out.extend(frames)
            if self._drained:
                return out

    def close(self) -> None:
        """Close for good (no reconnection)."""
        self._closed = True
        if self._connected:
            self._connected = False
            self._close()

    def __enter__(self) -> Link:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class FramedStreamLink(Link):
    """A link over a byte stream with COBS/CRC-16 framing (serial, in-process bytes).

    Backends implement ``_open``, ``_close``, ``_write_bytes`` and ``_read_bytes``.
    """

    def __init__(
        self,
        reconnect_interval: float = 0.5,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        from firmware_protocol.framing import Deframer

        super().__init__(reconnect_interval, clock)
        self._deframer = Deframer()
        self.stats.framing = self._deframer.stats

    def _write_bytes(self, data: bytes) -> None:
        raise NotImplementedError

    def _read_bytes(self, timeout: float) -> bytes:
        raise NotImplementedError

    def _opened(self) -> None:
        self._deframer.reset()  # a partial frame from before the outage is gone

    def _write(self, frame: Frame) -> None:
        from firmware_protocol.framing import frame_to_bytes

        self._write_bytes(frame_to_bytes(frame))

    def _read(self, timeout: float) -> list[Frame]:
        return self._deframer.feed(self._read_bytes(timeout))

    def send_raw(self, data: bytes) -> bool:
        """Write raw bytes (fault injection: garbage on the line)."""
        if not self._ensure():
            return False
        try:
            self._write_bytes(data)
        except FrameDroppedError:
            return False
        except LinkDownError as exc:
            self._down(exc)
            return False
        return True

    def recv_raw(self, timeout: float = 0.0) -> bytes:
        """Raw received bytes, unframed (for a peer that runs its own deframer, e.g. the
        C firmware core); b"" when none or while disconnected."""
        if not self._ensure():
            self._idle(timeout)
            return b""
        try:
            return self._read_bytes(timeout)
        except LinkDownError as exc:
            self._down(exc)
            return b""

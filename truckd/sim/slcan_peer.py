"""Serial-line CAN (slcan, the ASCII protocol of CANable and USBtin adapters) on a pty:
the firmware's end of a CAN bus that another process opens with python-can
``interface="slcan"``.

:class:`SlcanDevice` is a frame :class:`~truckd.io.link.Link` over a
:class:`~truckd.sim.pty_link.PtyDevice` (the symlink at ``path`` is the adapter the
daemon opens).  It plays the adapter: it answers the host's commands (``O``/``L`` open
the channel, ``C`` closes it, ``Sn`` bit rate, ``V``/``v``/``N`` version and serial
number, anything else BEL) and turns ``tIIILDD..`` lines into frames for the firmware;
the firmware's frames leave as ``tIIILDD..\\r`` while the channel is open (dropped, as an
adapter drops them, while closed).  Bus trouble: :meth:`SlcanDevice.send_garbage` writes
random frames and malformed lines; :meth:`unplug`/:meth:`replug` make the adapter vanish
and come back (a fresh pty behind the same path).

Line format (Lawicel): ``t`` + 3 hex digits id + 1 digit length + 2 hex digits per byte +
``\\r``; a command is acknowledged with ``\\r``, refused with ``\\a`` (BEL).
"""

from __future__ import annotations

import random
import time
from collections.abc import Callable

from firmware_protocol.codec import Frame
from truckd.io.link import Link, LinkDownError
from truckd.sim.pty_link import PtyDevice

MAX_LINE = 64
"""Longer lines (no terminator in sight) are discarded as garbage."""

_ACK = b"\r"
_NAK = b"\a"


def frame_line(frame: Frame) -> bytes:
    """The slcan line of a standard data frame."""
    return f"t{frame.can_id:03X}{len(frame.data):d}{frame.data.hex().upper()}\r".encode()


def parse_frame(line: bytes) -> Frame | None:
    """A ``t`` line (without terminator) as a frame; None when malformed."""
    try:
        text = line.decode("ascii")
        can_id = int(text[1:4], 16)
        n = int(text[4])
        data = bytes.fromhex(text[5:])
    except (UnicodeDecodeError, ValueError, IndexError):
        return None
    if text[0] != "t" or len(text) != 5 + 2 * n or n > 8 or can_id >= 0x800:
        return None
    return Frame(can_id, data)


class SlcanDevice(Link):
    """A simulated slcan adapter on a pty (see module docstring)."""

    def __init__(self, path: str, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(reconnect_interval=0.0, clock=clock)
        self.path = path
        self.pty = PtyDevice(path, clock=clock)
        self.channel_open = False
        """True after the host's ``O`` (or ``L``), until ``C`` or a new pty."""
        self.bitrate_cmd = ""
        self.bad_lines = 0
        """Lines from the host that were neither a command nor a valid frame."""
        self.dropped_closed = 0
        """Frames the firmware sent while the channel was closed."""
        self._buf = bytearray()
        self._reconnects = self.pty.stats.reconnects
        self.open()

    # -- Link backend --------------------------------------------------------------------
    def _open(self) -> None:
        if not self.pty.connected and not self.pty.open():
            raise LinkDownError(self.pty.last_error or f"{self.path}: unplugged")

    def _close(self) -> None:
        """The pty stays (unplug/replug/close own it)."""

    def _fresh_pty(self) -> None:
        if self.pty.stats.reconnects != self._reconnects:
            self._reconnects = self.pty.stats.reconnects
            self.channel_open = False  # a new adapter starts closed
            self._buf.clear()

    def _write(self, frame: Frame) -> None:
        self._fresh_pty()
        if not self.pty.connected:
            raise LinkDownError(self.pty.last_error or f"{self.path}: unplugged")
        if not self.channel_open:
            self.dropped_closed += 1
            return
        if not self.pty.send_raw(frame_line(frame)):
            raise LinkDownError(self.pty.last_error or f"{self.path}: write failed")

    def _read(self, timeout: float) -> list[Frame]:
        data = self.pty.recv_raw(timeout)
        self._fresh_pty()
        if not self.pty.connected:
            raise LinkDownError(self.pty.last_error or f"{self.path}: unplugged")
        out: list[Frame] = []
        for b in data:
            if b in (0x0D, 0x0A):  # CR ends a line; a stray LF is tolerated
                if self._buf:
                    f = self._line(bytes(self._buf))
                    if f is not None:
                        out.append(f)
                    self._buf.clear()
            elif len(self._buf) < MAX_LINE:
                self._buf.append(b)
            else:
                self.bad_lines += 1
                self._buf.clear()
        return out

    def _reply(self, data: bytes) -> None:
        self.pty.send_raw(data)

    def _line(self, line: bytes) -> Frame | None:
        """One line from the host: a frame for the firmware, or a command answered here."""
        c = line[:1]
        if c == b"t":
            f = parse_frame(line)
            if f is None:
                self.bad_lines += 1
                self._reply(_NAK)
            return f if self.channel_open else None
        if line in (b"O", b"L"):
            self.channel_open = True
        elif line == b"C":
            self.channel_open = False
        elif c == b"S" and len(line) == 2 and line[1:2].isdigit():
            self.bitrate_cmd = line.decode()
        elif line in (b"V", b"v"):
            self._reply(b"V1013\r" if line == b"V" else b"v1013\r")
            return None
        elif line == b"N":
            self._reply(b"NA123\r")
            return None
        elif c in (b"F", b"Z", b"M", b"m", b"s", b"Y", b"X", b"W", b"Q", b"U"):
            pass  # status, timestamps, filters, custom timing: accepted, not simulated
        else:
            self.bad_lines += 1
            self._reply(_NAK)
            return None
        self._reply(_ACK)
        return None

    # -- bus trouble -----------------------------------------------------------------------
    def send_garbage(self, rng: random.Random, n: int) -> None:
        """``n`` bad lines: random frames (random id and payload), malformed ``t`` lines,
        unknown line types and raw bytes that are not text."""
        chunks: list[bytes] = []
        for k in range(n):
            kind = k % 4
            hexish = b"0123456789ABCDEFXYZ"
            if kind == 0:
                data = bytes(rng.randrange(256) for _ in range(rng.randrange(9)))
                chunks.append(frame_line(Frame(rng.randrange(0x800), data)))
            elif kind == 1:
                chunks.append(b"tZ" + bytes(rng.choice(hexish) for _ in range(6)) + b"\r")
            elif kind == 2:
                chunks.append(
                    b"e" + bytes(rng.choice(b"0123456789ABCDEF") for _ in range(4)) + b"\r"
                )
            else:
                chunks.append(bytes(rng.randrange(128, 256) for _ in range(8)) + b"\r")
        if self.channel_open:
            self.pty.send_raw(b"".join(chunks))

    def unplug(self) -> None:
        """The adapter vanishes (the host's reads fail) until :meth:`replug`."""
        self.pty.unplug()
        if self.connected:
            self._down(LinkDownError(f"{self.path}: unplugged"))

    def replug(self) -> None:
        """A fresh adapter behind the same path (channel closed until the host opens it)."""
        self.pty.replug()
        self.open()

    def close(self) -> None:
        """Close the pty and remove the symlink."""
        super().close()
        self.pty.close()

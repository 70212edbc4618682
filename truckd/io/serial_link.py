"""Serial backend (pyserial): COBS/CRC-16 framed frames over a device path or URL.

``device`` is a path (``/dev/ttyACM0``, a pty) or a pyserial URL (``loop://``).  A
vanished device (unplugged USB, closed pty) raises inside pyserial; the link reports it
and reopens the path every ``reconnect_interval`` s until it is back.

Exclusive: the tty is opened with pyserial's ``exclusive=True`` (``flock`` on the device
node, taken before any setting is changed) and then ``TIOCEXCL`` (later opens of the tty
fail with EBUSY, except for root); a device held by another process raises
:class:`~truckd.io.link.LinkBusyError`.  ``TIOCNXCL`` is cleared again before closing.

Never blocking: bytes go out with one ``os.write`` on the non-blocking descriptor.  When
the kernel's buffer is full the frame is dropped (:class:`FrameDroppedError`, counted as
dropped, not sent); when only part of a frame fits, the rest is kept and written before
anything else, so no frame is ever cut in two on the wire.

Never waiting on a read either: the loop's poll asks the tty how many bytes it holds
(``FIONREAD``) and reads only when there are some; it never reads or selects an empty tty
(see :meth:`SerialLink._read_bytes` for why).
"""

from __future__ import annotations

import array
import contextlib
import errno
import fcntl
import os
import select
import termios
import time
from collections.abc import Callable
from typing import Any

import serial

from truckd.io.link import FrameDroppedError, FramedStreamLink, LinkBusyError, LinkDownError

DEFAULT_BAUDRATE = 115200
READ_SIZE = 4096
"""Bytes one non-blocking read of the loop's poll takes at most."""
_BUSY = {errno.EBUSY, errno.EAGAIN, errno.EWOULDBLOCK}
_NO_FIONREAD = {errno.ENOTTY, errno.EINVAL}


class SerialLink(FramedStreamLink):
    """A serial device carrying the framed protocol."""

    def __init__(
        self,
        device: str,
        baudrate: int = DEFAULT_BAUDRATE,
        reconnect_interval: float = 0.5,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(reconnect_interval, clock)
        self.device = device
        self.baudrate = baudrate
        self.name = f"serial device {device}"
        self._ser: Any = None
        self._fd: int | None = None
        self._tail = b""
        self._timeout: float | None = -1.0
        self._inq = array.array("i", [0])  # FIONREAD's answer, one buffer for every poll
        self.open()

    def _open(self) -> None:
        # a device path is written with os.write (never waits); a URL (loop://, tests and
        # debugging only) through its pyserial handler
        wt = None if "://" in self.device else 0
        try:
            ser = serial.serial_for_url(
                self.device, baudrate=self.baudrate, timeout=0, write_timeout=wt, exclusive=True
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            self._ser = None
            code = getattr(exc, "errno", None)
            if code in _BUSY:
                raise LinkBusyError(f"{self.device}: in use by another process ({exc})") from None
            raise LinkDownError(f"{self.device}: {exc}") from None
        fd = getattr(ser, "fd", None)
        self._fd = fd if isinstance(fd, int) else None
        if self._fd is not None:
            with contextlib.suppress(OSError):  # not a tty (a plain file): nothing to exclude
                fcntl.ioctl(self._fd, termios.TIOCEXCL)
        self._ser = ser
        self._tail = b""
        self._timeout = 0.0

    def _close(self) -> None:
        ser, self._ser = self._ser, None
        fd, self._fd = self._fd, None
        if fd is not None:
            with contextlib.suppress(OSError):
                fcntl.ioctl(fd, termios.TIOCNXCL)
        if ser is not None:
            with contextlib.suppress(serial.SerialException, OSError):
                ser.close()

    def _put(self, data: bytes) -> int:
        """Write what fits now; the number of bytes taken (0 when the buffer is full)."""
        if self._fd is None:  # a URL without a descriptor (loop://, socket://)
            try:
                return int(self._ser.write(data) or 0)
            except serial.SerialTimeoutException:
                return 0
            except (serial.SerialException, OSError) as exc:
                raise LinkDownError(f"{self.device}: {exc}") from None
        try:
            return os.write(self._fd, data)
        except BlockingIOError:
            return 0
        except InterruptedError:
            return 0
        except OSError as exc:
            raise LinkDownError(f"{self.device}: {exc}") from None

    def _write_bytes(self, data: bytes) -> None:
        if self._tail:  # finish the frame started earlier before anything else
            self._tail = self._tail[self._put(self._tail) :]
            if self._tail:
                raise FrameDroppedError(f"{self.device}: transmit buffer full")
        n = self._put(data)
        if n == 0:
            raise FrameDroppedError(f"{self.device}: transmit buffer full")
        self._tail = data[n:]

    def _read_now(self, fd: int, n: int = READ_SIZE) -> bytes:
        """One non-blocking read of what is there (b"" when nothing is)."""
        try:
            return os.read(fd, n)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:
            raise LinkDownError(f"{self.device}: {exc}") from None

    def _waiting(self, fd: int) -> int | None:
        """Bytes the tty holds for us now (``FIONREAD``); None where the descriptor cannot
        tell.  A hung-up tty (unplugged USB, closed pty) fails it with EIO: link down."""
        buf = self._inq
        try:
            fcntl.ioctl(fd, termios.FIONREAD, buf)
        except OSError as exc:
            if exc.errno in _NO_FIONREAD:
                return None
            raise LinkDownError(f"{self.device}: {exc}") from None
        return buf[0]

    def _read_bytes(self, timeout: float) -> bytes:
        fd = self._fd
        if timeout == 0.0 and fd is not None:
            # The loop's poll never reads or selects an empty tty.  Linux's n_tty_read (and
            # n_tty_poll, under select) on a tty with no bytes for the reader first waits,
            # even on an O_NONBLOCK descriptor, for the tty's pending input work
            # (flush_to_ldisc, run by a kworker of the unbound workqueue at normal
            # priority) to finish: ``flush_work``.  Measured (HIL, second-daemon test, load
            # 3-4 on 2 cores): the SCHED_FIFO loop thread sat in D state in
            # n_tty_read -> __flush_work for 36-627 ms while that kworker was runnable but
            # not running behind normal-priority processes, and the firmware counted
            # command timeouts.  FIONREAD reads the count without that wait; a read that
            # finds bytes there copies them and returns without waiting.
            n = self._waiting(fd)
            if n is None:  # not a tty (a plain file): as before, read and check hang-up
                return self._read_unknown(fd)
            if n == 0:
                return b""
            data = self._read_now(fd, min(n, READ_SIZE))
            # took everything the tty held: no second read needed this poll
            self._drained = n <= READ_SIZE
            return data
        ser = self._ser
        try:
            if self._timeout != timeout:
                ser.timeout = timeout
                self._timeout = timeout
            first = ser.read(1)
            if not first:
                return b""
            n = ser.in_waiting
            return bytes(first + ser.read(n)) if n else bytes(first)
        except (serial.SerialException, OSError) as exc:
            raise LinkDownError(f"{self.device}: {exc}") from None

    def _read_unknown(self, fd: int) -> bytes:
        """The poll on a descriptor that cannot count its bytes: one non-blocking read."""
        data = self._read_now(fd)
        # a short read took everything there was: no second read needed this poll
        self._drained = 0 < len(data) < READ_SIZE
        if not data and select.select([fd], [], [], 0.0)[0]:
            # A hung-up descriptor reads b"" while select says readable.  Bytes that
            # arrived between the read and the select also make it readable: read again,
            # and only a second b"" from a readable descriptor is a hang-up.
            data = self._read_now(fd)
            if not data:
                raise LinkDownError(f"{self.device}: device returned no data (hung up)")
        return data

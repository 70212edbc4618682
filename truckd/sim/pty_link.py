"""The firmware's end of a pseudo-terminal: a stand-in serial device for HIL tests.

:class:`PtyDevice` creates a pty pair, puts it in raw mode and points a symlink at the
slave (the path the daemon opens, like ``/dev/ttyACM0``).  :meth:`PtyDevice.unplug`
closes the master and removes the symlink (the daemon's reads fail, as when a USB
device is pulled); :meth:`PtyDevice.replug` creates a fresh pair behind the same path.
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import time
import tty
from collections.abc import Callable

from truckd.io.link import FramedStreamLink, LinkDownError


class PtyDevice(FramedStreamLink):
    """Framed link on a pty master, published at ``path`` (a symlink to the slave)."""

    def __init__(self, path: str, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(reconnect_interval=0.0, clock=clock)
        self.path = path
        self._master: int | None = None
        self._slave: int | None = None
        self._plugged = True
        self.write_overruns = 0
        """Bytes dropped because nobody read the device (the pty buffer was full)."""
        self.open()

    def _open(self) -> None:
        if not self._plugged:
            raise LinkDownError(f"{self.path}: unplugged")
        master, slave = os.openpty()
        tty.setraw(slave)
        tty.setraw(master)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        tmp = f"{self.path}.tmp{os.getpid()}"
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        os.symlink(os.ttyname(slave), tmp)
        os.replace(tmp, self.path)

    def _close(self) -> None:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path)
        for fd in (self._master, self._slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = None

    def unplug(self) -> None:
        """Pull the device: the daemon's end fails until :meth:`replug`."""
        self._plugged = False
        if self.connected:
            self._down(LinkDownError(f"{self.path}: unplugged"))

    def replug(self) -> None:
        """Plug a fresh device in behind the same path."""
        self._plugged = True
        self.open()

    def _write_bytes(self, data: bytes) -> None:
        if self._master is None:
            raise LinkDownError(f"{self.path}: closed")
        try:
            n = os.write(self._master, data)
        except BlockingIOError:
            n = 0
        except OSError as exc:
            raise LinkDownError(f"{self.path}: {exc}") from None
        self.write_overruns += len(data) - n

    def _read_bytes(self, timeout: float) -> bytes:
        fd = self._master
        if fd is None:
            raise LinkDownError(f"{self.path}: closed")
        if timeout > 0:
            ready, _, _ = select.select([fd], [], [], timeout)
            if not ready:
                return b""
        try:
            return os.read(fd, 4096)
        except BlockingIOError:
            return b""
        except OSError as exc:
            if exc.errno == errno.EIO:  # no reader on the slave side yet
                return b""
            raise LinkDownError(f"{self.path}: {exc}") from None

    def close(self) -> None:
        """Close the pty and remove the symlink."""
        super().close()
        self._close()

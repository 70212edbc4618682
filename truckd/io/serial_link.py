"""Serial backend (pyserial): COBS/CRC-16 framed frames over a device path or URL.

``device`` is a path (``/dev/ttyACM0``, a pty) or a pyserial URL (``loop://``).  A
vanished device (unplugged USB, closed pty) raises inside pyserial; the link reports it
and reopens the path every ``reconnect_interval`` s until it is back.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from typing import Any

import serial

from truckd.io.link import FramedStreamLink, LinkDownError

DEFAULT_BAUDRATE = 115200


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
        self._ser: Any = None
        self._timeout: float | None = -1.0
        self.open()

    def _open(self) -> None:
        try:
            self._ser = serial.serial_for_url(
                self.device, baudrate=self.baudrate, timeout=0, write_timeout=0.5
            )
            self._timeout = 0.0
        except (serial.SerialException, OSError, ValueError) as exc:
            self._ser = None
            raise LinkDownError(f"{self.device}: {exc}") from None

    def _close(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            with contextlib.suppress(serial.SerialException, OSError):
                ser.close()

    def _write_bytes(self, data: bytes) -> None:
        try:
            self._ser.write(data)
        except serial.SerialTimeoutException:
            self.stats.bus_errors += 1  # line stalled: this frame is lost, link stays up
        except (serial.SerialException, OSError) as exc:
            raise LinkDownError(f"{self.device}: {exc}") from None

    def _read_bytes(self, timeout: float) -> bytes:
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

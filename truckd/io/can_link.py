"""CAN backend (python-can): any interface python-can supports.

``virtual`` in tests (in-process), ``socketcan`` on the car.  Error frames count as
``bus_errors``; a bus-off error frame (socketcan error class 0x40) also counts as
``bus_off``.  An operation error on receive, or a network-down error on send, means
the bus is gone: the link closes it and reopens it every ``reconnect_interval`` s.

Sends never wait (``timeout=0``): a full transmit queue drops the frame, counted in
``tx_dropped`` and ``tx_full``.
"""

from __future__ import annotations

import contextlib
import errno
import time
from collections.abc import Callable
from typing import Any

import can

from firmware_protocol.codec import Frame
from truckd.io.link import FrameDroppedError, Link, LinkDownError

_CAN_ERR_BUSOFF = 0x40
_GONE = {errno.ENETDOWN, errno.ENODEV, errno.ENXIO, errno.EBADF}


class CanLink(Link):
    """A python-can bus carrying truck.dbc frames (11-bit ids)."""

    def __init__(
        self,
        interface: str,
        channel: str,
        bitrate: int = 500_000,
        reconnect_interval: float = 0.5,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(reconnect_interval, clock)
        self.interface = interface
        self.channel = channel
        self.bitrate = bitrate
        self.name = f"CAN interface {interface} channel {channel}"
        self._bus: Any = None
        self.open()

    def _open(self) -> None:
        kwargs: dict[str, Any] = {"interface": self.interface, "channel": self.channel}
        if self.interface != "virtual":
            kwargs["bitrate"] = self.bitrate
        if self.interface == "slcan":
            kwargs["sleep_after_open"] = 0.0  # CANable/USBtin do not reset when opened
        try:
            self._bus = can.Bus(**kwargs)
        except (can.CanError, OSError, ValueError) as exc:
            self._bus = None
            raise LinkDownError(f"CAN {self.interface}:{self.channel}: {exc}") from None

    def _close(self) -> None:
        bus, self._bus = self._bus, None
        if bus is not None:
            with contextlib.suppress(can.CanError, OSError):
                bus.shutdown()

    def _write(self, frame: Frame) -> None:
        msg = can.Message(arbitration_id=frame.can_id, data=frame.data, is_extended_id=False)
        try:
            self._bus.send(msg, timeout=0.0)  # never wait: the loop must not block
        except can.CanOperationError as exc:
            code = getattr(exc, "error_code", None)
            if code in _GONE or getattr(self._bus, "_is_shutdown", False):
                raise LinkDownError(f"CAN {self.channel}: {exc}") from None
            raise FrameDroppedError(str(exc)) from None  # TX queue full: this frame is lost

    def _tty_empty(self) -> bool:
        """Whether a serial-line adapter's (slcan) tty holds no bytes for us (FIONREAD).

        python-can's slcan reads such a tty with pyserial's ``select`` and ``read(1)``.  On
        a tty with no bytes both wait in the kernel for the tty's input work (a
        normal-priority kworker, ``n_tty_read``/``n_tty_poll`` -> ``flush_work``): measured
        on the serial backend, the real-time loop waited there up to 627 ms on a busy
        machine (``serial_link.SerialLink._read_bytes``).  So the loop's poll does not call
        into python-can while the tty is empty.  A hung-up tty fails FIONREAD: link down."""
        ser = getattr(self._bus, "serialPortOrig", None)
        if ser is None:  # socketcan, virtual: no tty
            return False
        try:
            return int(ser.in_waiting) == 0
        except OSError as exc:  # pyserial's SerialException is an OSError too
            raise LinkDownError(f"CAN {self.channel}: {exc}") from None

    def _read(self, timeout: float) -> list[Frame]:
        out: list[Frame] = []
        wait: float = timeout
        while True:
            if wait == 0.0 and self._tty_empty():
                return out
            try:
                msg = self._bus.recv(wait)
            except (can.CanOperationError, OSError) as exc:
                raise LinkDownError(f"CAN {self.channel}: {exc}") from None
            except (ValueError, IndexError):  # a garbled line from a serial-line adapter
                self.stats.bus_errors += 1
                wait = 0.0
                continue
            if msg is None:
                return out
            wait = 0.0
            if msg.is_error_frame:
                self.stats.bus_errors += 1
                if msg.arbitration_id & _CAN_ERR_BUSOFF:
                    self.stats.bus_off += 1
                continue
            if msg.is_extended_id or msg.is_remote_frame:
                self.stats.bus_errors += 1
                continue
            out.append(Frame(msg.arbitration_id, bytes(msg.data)))
            if len(out) >= 64:
                return out

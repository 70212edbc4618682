"""systemd's notify protocol (sd_notify) over a unix datagram socket.

``$NOTIFY_SOCKET`` names the socket: a filesystem path, or an abstract socket when it starts
with ``@``.  Without it (not started by systemd with Type=notify) every call is a no-op.
Messages: ``READY=1``, ``WATCHDOG=1``, ``STOPPING=1``, ``STATUS=...``.  Sending never
blocks and never raises: a failed send is counted.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Mapping


def _address(name: str) -> str | bytes:
    """Socket address for a $NOTIFY_SOCKET value (``@`` -> abstract namespace)."""
    if name.startswith("@"):
        return b"\0" + name[1:].encode()
    return name


class Notifier:
    """sd_notify client; ``enabled`` is False when there is no $NOTIFY_SOCKET."""

    def __init__(self, env: Mapping[str, str] | None = None) -> None:
        env = os.environ if env is None else env
        name = env.get("NOTIFY_SOCKET", "")
        self.enabled = bool(name) and (name.startswith("/") or name.startswith("@"))
        self.failures = 0
        self.sent = 0
        self._addr: str | bytes = _address(name) if self.enabled else ""
        self._sock: socket.socket | None = None
        if self.enabled:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.setblocking(False)
        wd = env.get("WATCHDOG_USEC", "")
        pid = env.get("WATCHDOG_PID", "")
        ok_pid = not pid or pid == str(os.getpid())
        self.watchdog_usec = int(wd) if wd.isdigit() and ok_pid else 0

    def send(self, message: str) -> bool:
        """Send one notify datagram; True when sent (False when disabled or failed)."""
        if self._sock is None:
            return False
        try:
            self._sock.sendto(message.encode(), self._addr)
        except OSError:
            self.failures += 1
            return False
        self.sent += 1
        return True

    def ready(self, status: str = "") -> bool:
        """Tell systemd start-up is complete (link and sensors up)."""
        return self.send("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def watchdog(self) -> bool:
        """Feed the watchdog (only while the loop is healthy)."""
        return self.send("WATCHDOG=1")

    def stopping(self, status: str = "") -> bool:
        """Tell systemd the service is shutting down."""
        return self.send("STOPPING=1" + (f"\nSTATUS={status}" if status else ""))

    def status(self, text: str) -> bool:
        """Free-form status line shown by ``systemctl status``."""
        return self.send(f"STATUS={text}")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

"""Start and steer the simulated-firmware process (:mod:`truckd.sim.firmware_main`)
from tests: the daemon's HIL tests open ``device`` as a serial port.

    with FirmwareProcess(tmp_path / "ttyTRUCK", ["--lead-gap", "3"]) as fw:
        ... run the daemon with --backend serial on fw.device ...
        fw.control({"fault": "silent", "on": True})
"""

from __future__ import annotations

import contextlib
import json
import os
import selectors
import signal
import socket
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any


class FirmwareProcess:
    """The simulated firmware as a child process on a pty (see module docstring)."""

    def __init__(self, device: str | Path, args: Sequence[str] = (), start_timeout: float = 20.0):
        self.device = str(device)
        self.args = list(args)
        self.start_timeout = start_timeout
        self.proc: subprocess.Popen[str] | None = None
        self.control_port = 0
        self._sock: socket.socket | None = None

    def start(self) -> FirmwareProcess:
        """Start the process and wait for its ready line; RuntimeError if it fails."""
        cmd = [sys.executable, "-m", "truckd.sim.firmware_main", "--pty", self.device, *self.args]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None
        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        if not sel.select(self.start_timeout):
            self.stop()
            raise RuntimeError("simulated firmware did not report ready")
        line = self.proc.stdout.readline()
        sel.close()
        try:
            ready = json.loads(line)
        except ValueError:
            err = self.proc.stderr.read() if self.proc.stderr else ""
            self.stop()
            raise RuntimeError(f"simulated firmware failed to start: {line!r} {err}") from None
        self.control_port = int(ready["control_port"])
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.settimeout(2.0)
        return self

    @property
    def pid(self) -> int:
        """Process id (0 when not started)."""
        return self.proc.pid if self.proc is not None else 0

    def control(self, cmd: dict[str, Any]) -> dict[str, Any]:
        """Send one control command (fault, lead, status) and return the reply."""
        if self._sock is None:
            raise RuntimeError("not started")
        self._sock.sendto(json.dumps(cmd).encode(), ("127.0.0.1", self.control_port))
        reply: dict[str, Any] = json.loads(self._sock.recv(65536))
        return reply

    def stop(self, timeout: float = 5.0) -> int | None:
        """Stop cleanly (control command, then SIGTERM, then SIGKILL, by pid)."""
        p = self.proc
        if p is None:
            return None
        if p.poll() is None and self._sock is not None:
            with contextlib.suppress(OSError, ValueError):
                self.control({"cmd": "stop"})
        rc: int | None = None
        for sig in (None, signal.SIGTERM, signal.SIGKILL):
            if sig is not None and p.poll() is None:
                os.kill(p.pid, sig)
            try:
                rc = p.wait(timeout)
                break
            except subprocess.TimeoutExpired:
                continue
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        for stream in (p.stdout, p.stderr):
            if stream is not None:
                stream.close()
        return rc

    def __enter__(self) -> FirmwareProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

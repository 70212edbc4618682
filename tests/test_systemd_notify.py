"""sd_notify against real unix datagram sockets (filesystem and abstract)."""

from __future__ import annotations

import os
import socket
from pathlib import Path

from truckd.runtime.notify import Notifier


def _recv_all(sock: socket.socket) -> list[str]:
    sock.settimeout(1.0)
    out = []
    try:
        while True:
            out.append(sock.recv(4096).decode())
            sock.settimeout(0.05)
    except TimeoutError:
        pass
    return out


def test_notify_over_filesystem_socket(tmp_path: Path) -> None:
    path = str(tmp_path / "notify.sock")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(path)
    try:
        n = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000"})
        assert n.enabled
        assert n.watchdog_usec == 2_000_000
        assert n.ready("link up")
        assert n.watchdog()
        assert n.stopping()
        n.close()
        msgs = _recv_all(srv)
    finally:
        srv.close()
    assert msgs == ["READY=1\nSTATUS=link up", "WATCHDOG=1", "STOPPING=1"]


def test_notify_over_abstract_socket() -> None:
    name = f"truckd-test-{os.getpid()}"
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(b"\0" + name.encode())
    try:
        n = Notifier({"NOTIFY_SOCKET": "@" + name})
        assert n.ready()
        assert n.status("ACTIVE")
        n.close()
        msgs = _recv_all(srv)
    finally:
        srv.close()
    assert msgs == ["READY=1", "STATUS=ACTIVE"]


def test_without_socket_is_noop() -> None:
    n = Notifier({})
    assert not n.enabled
    assert not n.ready()
    assert not n.watchdog()
    assert n.sent == 0 and n.failures == 0


def test_vanished_socket_counts_failure_and_does_not_raise(tmp_path: Path) -> None:
    n = Notifier({"NOTIFY_SOCKET": str(tmp_path / "missing.sock")})
    assert n.enabled
    assert not n.watchdog()
    assert n.failures == 1
    n.close()


def test_watchdog_pid_for_another_process_is_ignored() -> None:
    n = Notifier({"WATCHDOG_USEC": "500000", "WATCHDOG_PID": str(os.getpid() + 1)})
    assert n.watchdog_usec == 0

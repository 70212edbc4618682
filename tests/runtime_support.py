"""Helpers for the runtime and HIL tests: free loopback ports, Zenoh test configs."""

from __future__ import annotations

import socket


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (never 7447)."""
    while True:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind(("127.0.0.1", 0))
            port = int(s.getsockname()[1])
        if port != 7447:
            return port


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"

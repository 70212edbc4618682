"""Helpers for the runtime and HIL tests: free loopback ports, Zenoh test configs."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import yaml

from truckd.config.truck import default_config_path


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


def deep_merge(base: dict[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = (
            deep_merge(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), dict) else v
        )
    return out


def write_config(path: Path, overrides: Mapping[str, Any]) -> Path:
    """The shipped truck.yaml with ``overrides`` merged in, written to ``path``."""
    base = yaml.safe_load(default_config_path().read_text())
    path.write_text(yaml.safe_dump(deep_merge(base, overrides)))
    return path


def wait_for(pred: Callable[[], object], timeout: float) -> bool:
    """Poll ``pred`` every 10 ms until it is true or ``timeout`` s have passed; its last
    value (a condition to wait on, not a fixed sleep)."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if pred():
            return True
        time.sleep(0.01)
    return bool(pred())

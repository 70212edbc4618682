"""Helpers for the runtime and HIL tests: free loopback ports, Zenoh test configs."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
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


def group_members(pgid: int) -> list[int]:
    """The live processes (not zombies) of process group ``pgid`` (Linux /proc)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # ended meanwhile
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            out.append(int(stat.parent.name))
    return out


def wait_for(pred: Callable[[], object], timeout: float) -> bool:
    """Poll ``pred`` every 10 ms until it is true or ``timeout`` s have passed; its last
    value (a condition to wait on, not a fixed sleep)."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if pred():
            return True
        time.sleep(0.01)
    return bool(pred())


def follower_config(path: Path, vehicle_id: str, platoon: Mapping[str, Any], port: int) -> Path:
    """A ``truckd run`` configuration for a daemon run in the test's process: the shipped
    truck.yaml with ``vehicle_id``, the ``platoon`` keys, no real-time scheduling, no
    recorder, listening on a free loopback port of its own and connected to ``port``."""
    return write_config(
        path,
        {"vehicle_id": vehicle_id, "platoon": dict(platoon),
         "runtime": {"realtime": False, "recorder": {"enabled": False},
                     "telemetry": {"listen": [endpoint(free_port())],
                                   "connect": [endpoint(port)]}}},
    )  # fmt: skip


def watch_vehicle(session: Any, vehicle_id: str) -> dict[str, list[dict[str, Any]]]:
    """Every ``state``, ``plan`` and ``health`` message of ``vehicle_id`` on ``session`` (a
    Zenoh session), decoded and appended to its list as it arrives (Zenoh's thread)."""
    got: dict[str, list[dict[str, Any]]] = {"state": [], "plan": [], "health": []}
    for suffix, seen in got.items():
        session.declare_subscriber(
            f"truckd/{vehicle_id}/{suffix}",
            lambda m, seen=seen: seen.append(json.loads(m.payload.to_bytes())),
        )
    return got


def run_daemon_beside(daemon: Any, session: Any, publish: Callable[[threading.Event], None]) -> int:
    """Run ``daemon`` (a :class:`truckd.runtime.daemon.Daemon` with its duration) while
    ``publish(stop)`` runs on a thread of its own until ``stop`` is set; then the thread
    is joined and ``session`` (a Zenoh session) closed.  The daemon's exit code."""
    stop = threading.Event()
    th = threading.Thread(target=publish, args=(stop,), daemon=True)
    th.start()
    try:
        return int(daemon.run())
    finally:
        stop.set()
        th.join(5.0)
        session.close()


def run_json_script(args: list[str], out: Path, timeout: float) -> tuple[dict[str, Any], str]:
    """Run a benchmark script (``args`` after the interpreter) that writes its result to
    ``out``; past ``timeout`` s it gets SIGTERM (it ends its own children by pid).  The
    result read from ``out`` and the script's output."""
    proc = subprocess.Popen(
        [sys.executable, *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    try:
        text, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.kill(proc.pid, signal.SIGTERM)
        text, _ = proc.communicate(timeout=60)
    result: dict[str, Any] = json.loads(out.read_text())
    return result, text

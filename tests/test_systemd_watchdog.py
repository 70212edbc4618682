"""`truckd run` under a fake systemd: READY=1 once link and sensors are up, WATCHDOG=1
only while the loop meets its deadlines, STOPPING=1 on SIGTERM (real unix datagram socket)."""

from __future__ import annotations

import json
import math
import os
import queue
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh
from runtime_support import endpoint, free_port, write_config

from truckd.runtime.telemetry import zenoh_config


def _drain(sock: socket.socket, seconds: float) -> list[tuple[float, str]]:
    out = []
    t_end = time.monotonic() + seconds
    while (left := t_end - time.monotonic()) > 0:
        sock.settimeout(left)
        try:
            out.append((time.monotonic(), sock.recv(4096).decode()))
        except TimeoutError:
            break
    return out


def _health_until(
    q: queue.Queue[dict[str, Any]], pred: Callable[[dict[str, Any]], bool], timeout: float = 30.0
) -> dict[str, Any]:
    """The first health message satisfying ``pred`` (the daemon sends one every 0.5 s)."""
    t_end = time.monotonic() + timeout
    while (left := t_end - time.monotonic()) > 0:
        try:
            h = q.get(timeout=left)
        except queue.Empty:
            break
        if pred(h):
            return h
    raise AssertionError(f"no such health message within {timeout} s")


def test_ready_watchdog_gated_by_deadlines_and_stopping(tmp_path: Path) -> None:
    port = free_port()
    cfg = write_config(
        tmp_path / "truck.yaml",
        {"runtime": {"realtime": False, "fault_injection": True,
                     "telemetry": {"listen": [endpoint(port)]},
                     "recorder": {"dir": str(tmp_path / "logs")}}},
    )  # fmt: skip
    sock_path = str(tmp_path / "notify.sock")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(sock_path)
    env = {**os.environ, "NOTIFY_SOCKET": sock_path, "WATCHDOG_USEC": "400000"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "truckd.cli.main", "run", "--config", str(cfg), "--backend", "sim"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    session = None
    try:
        srv.settimeout(60.0)
        first = srv.recv(4096).decode()  # nothing before READY: not even a watchdog feed
        assert first.startswith("READY=1"), first
        feeds = [m for _, m in _drain(srv, 1.0) if m == "WATCHDOG=1"]
        assert len(feeds) >= 5  # fed every ~0.1 s (WATCHDOG_USEC / 4) while healthy
        # the loop overruns every cycle: the watchdog must starve
        session = zenoh.open(zenoh_config(listen=[], connect=[endpoint(port)]))
        health: queue.Queue[dict[str, Any]] = queue.Queue()
        session.declare_subscriber(
            "truckd/truck1/health", lambda s: health.put(json.loads(s.payload.to_bytes()))
        )
        _health_until(health, lambda h: True)  # connected to the daemon's session
        session.put("truckd/truck1/inject", json.dumps({"fault": "overrun", "extra_s": 0.02}))
        _health_until(health, lambda h: h["injected"]["overrun_s"] > 0)  # it arrived
        _drain(srv, 0.2)  # a feed sent before it took effect
        starving = _drain(srv, 1.5)
        assert not [m for _, m in starving if m == "WATCHDOG=1"], starving
        session.put("truckd/truck1/inject", json.dumps({"fault": "clear"}))
        _health_until(health, lambda h: h["injected"]["overrun_s"] == 0)
        resumed = _drain(srv, 1.5)
        assert [m for _, m in resumed if m == "WATCHDOG=1"]
        os.kill(proc.pid, signal.SIGTERM)
        assert proc.wait(timeout=20) == 0
        final = [m for _, m in _drain(srv, 0.5)]
        assert any(m.startswith("STOPPING=1") for m in final), final
    finally:
        if session is not None:
            session.close()  # type: ignore[no-untyped-call]
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()
        srv.close()


def test_watchdog_needs_ready_fresh_link_and_met_deadline(tmp_path: Path) -> None:
    from truckd.config.truck import load_config
    from truckd.runtime.daemon import Daemon

    sock_path = str(tmp_path / "notify.sock")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(sock_path)
    env = {"NOTIFY_SOCKET": sock_path, "WATCHDOG_USEC": "1000000"}
    d = Daemon(load_config(), "sim", env=env)
    try:
        now = 100.0
        timeout = d.rt.supervisor.link_timeout_s

        def fed(ready: bool, link_age: float, missed: bool) -> bool:
            d.ready_sent, d.rk.last_missed = ready, missed
            d.sensors.t_any = now - link_age
            d._last_watchdog = -math.inf
            before = d.notifier.sent
            d.feed_watchdog(now)
            return d.notifier.sent > before

        assert fed(True, 0.0, False)
        assert not fed(False, 0.0, False)  # not before READY
        assert not fed(True, timeout * 2, False)  # link stale
        assert not fed(True, 0.0, True)  # last cycle missed its deadline
        # rate: at most every WatchdogSec/4
        d.ready_sent, d.rk.last_missed, d.sensors.t_any = True, False, now
        d._last_watchdog = now - 0.1
        d.feed_watchdog(now)
        assert d.notifier.sent == 1
        assert [m for _, m in _drain(srv, 0.2)] == ["WATCHDOG=1"]
    finally:
        d.notifier.close()
        srv.close()

"""Processes of the HIL tests: the simulated firmware on a pty, `truckd run` on the
serial backend, and a Zenoh watcher.  Every process started here is ended by its pid."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh
from runtime_support import endpoint, free_port, write_config
from stall_probe import StallProbe as StallProbe
from stall_probe import daemon_stalls

from truckd.logfile import Log
from truckd.runtime.telemetry import zenoh_config
from truckd.sim.firmware_proc import FirmwareProcess

PY = sys.executable
ROOT = Path(__file__).resolve().parent.parent


def hil_config(tmp: Path, pty: str, port: int, **runtime: Any) -> Path:
    """truck.yaml for a HIL daemon: serial on the pty, Zenoh on ``port``, log in tmp."""
    rt: dict[str, Any] = {
        "backend": "serial",
        "fault_injection": True,
        "telemetry": {"listen": [endpoint(port)]},
        "recorder": {"dir": str(tmp / "logs")},
    }
    rt.update(runtime)
    return write_config(
        tmp / "truck.yaml",
        {"link": {"serial_device": pty, "reconnect_interval": 0.1},
         "control": {"on_lead_lost": "stop"}, "runtime": rt},
    )  # fmt: skip


def daemon_waits(log: Log, t_daemon0: float) -> list[tuple[float, float]]:
    """The host's stalls as the daemon's log shows them (``stall_probe.daemon_stalls``:
    late wake-ups, cycles that waited for the CPU), on ``time.monotonic``; the log's time
    base starts at ``t_daemon0`` there."""
    return [
        (a + t_daemon0, b + t_daemon0)
        for a, b in daemon_stalls(log["t"], log["lateness_us"], log["compute_us"], log["cpu_us"])
    ]


class Firmware(FirmwareProcess):
    """``python -m truckd.sim.firmware_main`` on a pty (started), whose control commands
    must succeed."""

    def __init__(self, pty: str, config: Path, *args: str) -> None:
        super().__init__(pty, ["--config", str(config), *args], start_timeout=60.0)
        self.start()

    def cmd(self, c: dict[str, Any]) -> dict[str, Any]:
        reply = self.control(c)
        assert reply.get("ok"), reply
        return reply

    def status(self) -> dict[str, Any]:
        return self.cmd({"cmd": "status"})


class Daemon:
    """``truckd run`` as systemd would start it (stderr to a file)."""

    def __init__(self, config: Path, log: Path, *args: str) -> None:
        self.log = log
        self._fh = open(log, "w")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(
            [PY, "-m", "truckd.cli.main", "run", "--config", str(config), *args],
            stdout=subprocess.DEVNULL,
            stderr=self._fh,
            cwd=ROOT,
        )

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self, sig: int = signal.SIGTERM) -> int:
        if self.proc.poll() is None:
            os.kill(self.proc.pid, sig)
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                os.kill(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10)
        self._fh.close()
        return int(self.proc.returncode)

    def stderr(self) -> str:
        return self.log.read_text()


@dataclass
class Sample:
    rx: float  # local monotonic receive time
    msg: dict[str, Any]


@dataclass
class Watch:
    """An in-process Zenoh subscriber on one vehicle's state and health."""

    port: int
    vehicle: str = "truck1"
    states: list[Sample] = field(default_factory=list)
    health: list[Sample] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._lock = threading.Lock()
        self.session = zenoh.open(zenoh_config(listen=[], connect=[endpoint(self.port)]))
        self.session.declare_subscriber(f"truckd/{self.vehicle}/state", self._on(self.states))
        self.session.declare_subscriber(f"truckd/{self.vehicle}/health", self._on(self.health))

    def _on(self, into: list[Sample]) -> Callable[[zenoh.Sample], None]:
        def cb(s: zenoh.Sample) -> None:
            smp = Sample(time.monotonic(), json.loads(s.payload.to_bytes()))
            with self._lock:
                into.append(smp)

        return cb

    def since(self, t: float) -> list[Sample]:
        with self._lock:
            return [s for s in self.states if s.rx >= t]

    def wait_state(
        self, pred: Callable[[dict[str, Any]], bool], timeout: float, after: float = 0.0
    ) -> Sample | None:
        """The first state sample received after ``after`` satisfying ``pred``."""
        t_end = time.monotonic() + timeout
        seen = 0
        while True:
            with self._lock:
                new = self.states[seen:]
                seen = len(self.states)
            for s in new:
                if s.rx >= after and pred(s.msg):
                    return s
            if time.monotonic() > t_end:
                return None
            time.sleep(0.02)

    def modes(self) -> list[tuple[float, str]]:
        """Every change of the published mode: (receive time s after the first state,
        mode), for a failing test's message."""
        with self._lock:
            states = list(self.states)
        out: list[tuple[float, str]] = []
        for s in states:
            mode = str(s.msg.get("mode"))
            if not out or out[-1][1] != mode:
                out.append((round(s.rx - states[0].rx, 2), mode))
        return out

    def last_health(self) -> dict[str, Any]:
        with self._lock:
            return self.health[-1].msg if self.health else {}

    def inject(self, cmd: dict[str, Any]) -> None:
        self.session.put(f"truckd/{self.vehicle}/inject", json.dumps(cmd))

    def close(self) -> None:
        self.session.close()  # type: ignore[no-untyped-call]


def end_process(p: subprocess.Popen[str]) -> None:
    """Kill ``p`` by its pid if it still runs, reap it, close its pipes."""
    if p.poll() is None:
        os.kill(p.pid, signal.SIGKILL)
        p.wait(10)
    for f in (p.stdin, p.stdout, p.stderr):
        if f is not None:
            f.close()


def new_port() -> int:
    return free_port()


def start_follow_rig(
    stack: contextlib.ExitStack, tmp: Path, pty: str, cfg_path: Path, port: int
) -> tuple[Firmware, Daemon, Watch, StallProbe]:
    """The simulated firmware (no lead yet), the daemon, a state watcher and a stall probe,
    each ended by ``stack`` even when a later step fails (a leaked Zenoh session keeps
    pytest from exiting)."""
    fw = Firmware(pty, cfg_path, "--no-lead")
    stack.callback(fw.stop)
    daemon = Daemon(cfg_path, tmp / "daemon.log")
    stack.callback(daemon.stop)
    watch = Watch(port)
    stack.callback(watch.close)
    probe = StallProbe()
    stack.callback(probe.stop)
    return fw, daemon, watch, probe

"""The simulated firmware as a real-time process on a pty, steered over its control
socket: the path the daemon's HIL tests use."""

from __future__ import annotations

import os
import signal
import time
from collections import Counter
from pathlib import Path

import pytest

from firmware_protocol.messages import FirmwareHeartbeat, FirmwareState, MotorCommand, RangeReading
from truckd.io.port import Port, Received, companion_port
from truckd.io.serial_link import SerialLink
from truckd.sim.firmware_proc import FirmwareProcess

pytestmark = pytest.mark.hil


def pump(port: Port, seconds: float, voltage: float | None = 2.0) -> list[Received]:
    """Command every 10 ms (None: send nothing) and collect what arrives."""
    out: list[Received] = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if voltage is not None:
            port.send(MotorCommand(voltage, True))
        r = port.recv(0.01)
        while r is not None:
            out.append(r)
            r = port.recv(0.0)
    return out


def test_hil_process_faults_and_reconnect(tmp_path: Path) -> None:
    dev = tmp_path / "ttyTRUCK"
    with FirmwareProcess(dev, ["--lead-gap", "3.0", "--lead-speed", "0.5"]) as fw:
        assert os.path.islink(dev)
        link = SerialLink(str(dev), reconnect_interval=0.05)
        port = companion_port(link)
        try:
            got = pump(port, 0.6)
            n = Counter(r.name for r in got)
            # roughly real time (loose: 2 shared cores), every message type present
            assert n["WHEEL_ENCODERS"] >= 20 and n["RANGE"] >= 10 and n["FIRMWARE_HEARTBEAT"] >= 2
            hb = [r.msg for r in got if isinstance(r.msg, FirmwareHeartbeat)]
            assert hb[-1].state == FirmwareState.ACTIVE
            rng = [r.msg for r in got if isinstance(r.msg, RangeReading)]
            assert rng[-1].valid and 2.0 < rng[-1].distance < 3.5
            st = fw.control({"cmd": "status"})
            assert st["ok"] and st["v"] > 0.0 and st["voltage"] == pytest.approx(2.0)

            # garbage on the line (between frames): resync, nothing intact lost (no counter gap)
            before = port.stats()
            assert fw.control({"fault": "garbage", "bytes": 300})["ok"]
            pump(port, 0.3)
            s = port.stats()
            assert s["framing_resyncs"] >= 1 and s["framing_bytes_discarded"] >= 200
            assert s["rx_counter_gaps"] == before["rx_counter_gaps"]

            # stop commanding: the firmware's own 100 ms timeout switches the motor off
            got = pump(port, 0.4, voltage=None)
            hb = [r.msg for r in got if isinstance(r.msg, FirmwareHeartbeat)]
            assert hb[-1].state == FirmwareState.FAILSAFE
            assert fw.control({"cmd": "status"})["voltage"] == 0.0

            # unplug for 0.4 s: the link notices and comes back by itself
            assert fw.control({"fault": "disconnect", "duration": 0.4})["ok"]
            pump(port, 1.2)
            s = port.stats()
            assert s["disconnects"] >= 1 and s["reconnects"] >= 1 and link.connected
            assert port.fresh("WHEEL_ENCODERS")

            # a new lead, and a bad command is answered, not fatal
            assert fw.control({"cmd": "lead", "gap": 1.0, "speed": 0.0})["ok"]
            bad = fw.control({"fault": "nope"})
            assert not bad["ok"] and "unknown fault" in bad["error"]
            got = pump(port, 0.2)
            rng = [r.msg for r in got if isinstance(r.msg, RangeReading)]
            assert rng and rng[-1].distance < 1.0
        finally:
            link.close()
    assert fw.proc is not None and fw.proc.returncode == 0
    assert not dev.exists()  # the device disappears with the process


def test_hil_process_bad_arguments(tmp_path: Path) -> None:
    p = FirmwareProcess(tmp_path / "tty", ["--lead", "no_such_module:f"])
    with pytest.raises(RuntimeError, match="failed to start"):
        p.start()


def test_hil_process_runs_a_scenario_lead(tmp_path: Path) -> None:
    from truckd.config.truck import load_config
    from truckd.sim.scenarios import make_scenario

    cfg = load_config()
    sc = make_scenario("lead-brake", cfg.vehicle, cfg.control)
    assert sc.gap0 is not None
    dev = tmp_path / "tty"
    with FirmwareProcess(dev, ["--scenario", "lead-brake"]) as fw:
        link = SerialLink(str(dev), reconnect_interval=0.05)
        try:
            port = companion_port(link)
            got = pump(port, 0.3, voltage=None)
            rng = [r.msg for r in got if isinstance(r.msg, RangeReading)]
            assert rng and rng[0].valid
            # the scenario's initial gap (it grows or shrinks a little while we watch)
            assert abs(rng[0].distance - sc.gap0) < 0.5
            # started at the scenario's speed, then braked to rest (no commands: 0 V):
            # it rolled a distance a truck starting from rest would not
            st = fw.control({"cmd": "status"})
            assert sc.v0 > 0.5 and st["x"] > 0.05 and st["v"] < sc.v0
        finally:
            link.close()


def test_the_rig_reports_its_own_stalls(tmp_path: Path) -> None:
    """A firmware process held still (SIGSTOP, as a busy host or a waiting pty read would)
    reports the stall in ``status`` on the shared monotonic clock, so the HIL tests can tell
    a late rig from a daemon that stopped sending."""
    with FirmwareProcess(tmp_path / "ttyTRUCK", []) as fw:
        # its loop running (simulated time advancing), so the stop lands inside it
        deadline = time.monotonic() + 30.0
        first = fw.control({"cmd": "status"})
        while first["t"] < 0.05 and time.monotonic() < deadline:
            first = fw.control({"cmd": "status"})
        assert first["ok"] and first["t"] >= 0.05, first
        before = first["rig_stalls"]
        pid = fw.pid
        t_stop = time.monotonic()
        os.kill(pid, signal.SIGSTOP)
        try:
            time.sleep(0.3)  # the stall itself (the stimulus, not a wait for a condition)
        finally:
            os.kill(pid, signal.SIGCONT)
        t_cont = time.monotonic()
        st = fw.control({"cmd": "status"})
        new = [(a, b) for a, b in st["rig_stalls"] if b >= t_stop]
        assert any(a <= t_stop + 0.02 and b >= t_cont - 0.02 for a, b in new), (new, before)

"""The hardware path's safety: sends never wait (a stalled line drops and
counts), a missing device is named once in the log and retried, the device lock."""

from __future__ import annotations

import logging
import os
import select
import threading
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from runtime_support import write_config

from firmware_protocol.codec import Frame
from firmware_protocol.framing import Deframer
from truckd.config.truck import load_config
from truckd.control.supervisor import Mode
from truckd.io import LinkConfig
from truckd.io.can_link import CanLink
from truckd.io.devlock import DeviceBusyError, claim_device, serial_keys
from truckd.io.serial_link import SerialLink
from truckd.runtime.backend import claim_backend
from truckd.runtime.daemon import Daemon
from truckd.runtime.realtime import unfreeze_gc

F1 = Frame(0x100, b"\x01\x02\x03\x04\x05\x06\x07\x08")
HANG_S = 30.0  # a send that takes this long has blocked (failure, not a timing target)


def in_thread(fn: Any) -> Any:
    """Run ``fn`` in a thread; fail if it has not returned after HANG_S."""
    out: list[Any] = []
    t = threading.Thread(target=lambda: out.append(fn()), daemon=True)
    t.start()
    t.join(HANG_S)
    assert not t.is_alive(), "send blocked"
    return out[0]


def drain_master(fd: int) -> bytes:
    got = b""
    while select.select([fd], [], [], 0.2)[0]:
        try:
            chunk = os.read(fd, 65536)
        except OSError:
            break
        if not chunk:
            break
        got += chunk
    return got


def test_stalled_serial_line_drops_and_counts_never_blocks() -> None:
    master, slave = os.openpty()
    link = SerialLink(os.ttyname(slave), reconnect_interval=0.01)
    try:
        assert link.connected

        def fill() -> list[bool]:  # nobody reads the master: the kernel buffer fills up
            res: list[bool] = []
            while link.stats.tx_full < 20 and len(res) < 200_000:
                res.append(link.send(F1))
            return res

        results = in_thread(fill)
        st = link.stats
        assert st.tx_full == 20, "the line never stalled"
        assert st.tx_frames == results.count(True) and st.tx_dropped == results.count(False)
        assert st.tx_dropped == st.tx_full and st.tx_frames + st.tx_dropped == len(results)
        assert link.connected  # a full buffer is not a disconnect
        # the reader comes back: every frame counted as sent arrives whole, in order
        wire = drain_master(master)
        assert in_thread(lambda: link.send(F1))  # also finishes a frame cut short earlier
        wire += drain_master(master)
        frames = Deframer().feed(wire)
        assert frames == [F1] * st.tx_frames
    finally:
        link.close()
        os.close(master)
        os.close(slave)


class _FullBus:
    """A python-can bus whose transmit queue is full (records the send timeouts)."""

    def __init__(self) -> None:
        self.timeouts: list[float | None] = []

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.timeouts.append(timeout)
        raise can.CanOperationError("Transmit buffer full")

    def shutdown(self) -> None:
        pass


def test_can_send_never_waits_full_queue_drops_and_counts() -> None:
    link = CanLink("virtual", "truckd-test-full")
    bus = _FullBus()
    real, link._bus = link._bus, bus
    try:
        assert not in_thread(lambda: link.send(F1))
        assert bus.timeouts == [0.0]
        assert link.stats.tx_frames == 0 and link.stats.tx_dropped == 1
        assert link.stats.tx_full == 1 and link.connected
    finally:
        real.shutdown()
        link.close()


def test_missing_serial_device_is_named_once_and_retried(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = str(tmp_path / "ttyACM9")
    caplog.set_level(logging.DEBUG, logger="truckd")
    link = SerialLink(path, reconnect_interval=0.0)
    for _ in range(5):  # five more attempts (interval 0: every call retries)
        assert not link.send(F1)
    errs = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(errs) == 1 and errs[0].levelno == logging.ERROR
    assert path in errs[0].getMessage() and "retrying" in errs[0].getMessage()
    # it comes back by itself when the device appears
    from truckd.sim.pty_link import PtyDevice

    dev = PtyDevice(path)
    try:
        assert link.send(F1) and link.connected
    finally:
        link.close()
        dev.close()


@pytest.mark.parametrize(
    ("backend", "link", "named"),
    [
        ("serial", {"serial_device": "/nonexistent/ttyACM9"}, "/nonexistent/ttyACM9"),
        ("can", {"can_interface": "socketcan", "can_channel": "truckdnone9"}, "truckdnone9"),
    ],
)
def test_daemon_without_device_names_it_and_stays_out_of_active(
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    monkeypatch: pytest.MonkeyPatch,
    backend: str,
    link: dict[str, str],
    named: str,
) -> None:
    monkeypatch.setenv("TRUCKD_LOCK_DIR", str(tmp_path / "locks"))
    cfg_path = write_config(
        tmp_path / "truck.yaml",
        {"link": {**link, "reconnect_interval": 0.05},
         "runtime": {"realtime": False, "telemetry": {"enabled": False},
                     "recorder": {"dir": str(tmp_path / "logs")}}},
    )  # fmt: skip
    caplog.set_level(logging.INFO, logger="truckd")
    d = Daemon(load_config(cfg_path), backend, duration=1.0, env={})
    try:
        assert d.run() == 0
    finally:
        unfreeze_gc()
    named_lines = [r for r in caplog.records if named in r.getMessage()]
    assert len(named_lines) == 1 and named_lines[0].levelno == logging.ERROR, caplog.text
    assert all(tr.new != Mode.ACTIVE for tr in d.supervisor.transitions)
    assert d.decision.mode != Mode.ACTIVE
    assert d.backend is not None and d.backend.link.stats.tx_frames == 0
    assert d.recorder is not None and d.recorder.path is not None
    log = np.loadtxt(d.recorder.path, delimiter=",", skiprows=1, ndmin=2)
    assert log.shape[0] > 10  # it kept cycling (and retrying) the whole second


def test_device_lock_names_the_holder_and_is_released(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("TRUCKD_LOCK_DIR", str(tmp_path))
    dev = tmp_path / "ttyUSB7"
    alias = tmp_path / "by-id"
    dev.touch()
    alias.symlink_to(dev)
    first = claim_device("serial device X", serial_keys(str(dev)))
    try:
        # another name of the same device is the same device
        with pytest.raises(DeviceBusyError, match=rf"in use by process {os.getpid()}"):
            claim_device("serial device Y", serial_keys(str(alias)))
        # CAN: one daemon per interface + channel
        cfg = LinkConfig(can_interface="socketcan", can_channel="can7")
        can_lock = claim_backend("can", cfg)
        with pytest.raises(DeviceBusyError, match="CAN interface socketcan channel can7"):
            claim_backend("can", cfg)
        can_lock.release()
        claim_backend("can", cfg).release()  # free again
        # slcan on the same tty, through its alias and at another bit rate: the same device
        for channel in (f"{dev}@115200", f"{alias}@921600", str(alias)):
            slcan = LinkConfig(can_interface="slcan", can_channel=channel)
            with pytest.raises(DeviceBusyError):
                claim_backend("can", slcan)
    finally:
        first.release()
    assert list(tmp_path.glob("*.lock")) == []
    claim_device("serial device Y", serial_keys(str(alias))).release()


def _pty_config(tmp_path: Path, dev: str, **telemetry: Any) -> Path:
    return write_config(
        tmp_path / "truck.yaml",
        {"link": {"serial_device": dev},
         "runtime": {"backend": "serial", "realtime": False,
                     "telemetry": {"enabled": bool(telemetry), **telemetry},
                     "recorder": {"dir": str(tmp_path / "logs")}}},
    )  # fmt: skip


def test_zenoh_failure_stops_start_before_the_link_opens(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A second daemon used to fail on the Zenoh port after opening the device and then
    sent motor-off into it.  Now Zenoh comes first: the device is never opened."""
    import socket

    from runtime_support import endpoint, free_port

    from truckd.errors import TruckdError
    from truckd.sim.pty_link import PtyDevice

    monkeypatch.setenv("TRUCKD_LOCK_DIR", str(tmp_path / "locks"))
    port = free_port()
    taken = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    taken.bind(("127.0.0.1", port))
    taken.listen()
    dev = PtyDevice(str(tmp_path / "ttyT"))
    try:
        cfg = load_config(_pty_config(tmp_path, dev.path, listen=[endpoint(port)]))
        d = Daemon(cfg, duration=1.0, env={})
        with pytest.raises(TruckdError, match="Zenoh"):
            d.run()
        assert d.backend is None and d.port is None  # the link was never opened
        assert dev.recv(0.2) is None and dev.stats.framing is not None
        assert dev.stats.framing.frames_ok == 0 and dev.stats.framing.bytes_discarded == 0
        assert not list((tmp_path / "locks").iterdir())  # the claim was released
    finally:
        unfreeze_gc()
        dev.close()
        taken.close()


def test_device_held_outside_the_lock_fails_start_and_sends_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Another process (here: another link) holds the tty: the first open finds it busy and
    start fails (not retried as a missing device), naming the device."""
    from truckd.sim.pty_link import PtyDevice

    monkeypatch.setenv("TRUCKD_LOCK_DIR", str(tmp_path / "locks"))
    dev = PtyDevice(str(tmp_path / "ttyT"))
    holder = SerialLink(dev.path)
    try:
        assert holder.connected
        d = Daemon(load_config(_pty_config(tmp_path, dev.path)), duration=1.0, env={})
        with pytest.raises(DeviceBusyError, match=rf"serial device {dev.path} is in use"):
            d.run()
        assert d.port is None
        assert dev.recv(0.2) is None and dev.stats.rx_frames == 0
        assert holder.connected
        assert not list((tmp_path / "logs").glob("*.csv"))  # no empty log left behind
    finally:
        unfreeze_gc()
        holder.close()
        dev.close()

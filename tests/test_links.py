"""Links: in-process pairs, serial (loop://, pty, vanishing device), CAN (virtual),
backends by name, and the typed port on top."""

from __future__ import annotations

import array
import dataclasses
import fcntl
import os
import select
import termios
import time
import uuid
from pathlib import Path

import can
import pytest

from firmware_protocol.codec import Frame, encode
from firmware_protocol.framing import frame_to_bytes
from firmware_protocol.messages import (
    CompanionHeartbeat,
    CompanionState,
    MotorCommand,
    RangeReading,
    RangeStatus,
)
from truckd.config.truck import load_config
from truckd.io import LinkConfig
from truckd.io.can_link import CanLink
from truckd.io.inproc import inproc_pair
from truckd.io.link import FramedStreamLink, Link
from truckd.io.port import companion_port, firmware_port
from truckd.io.serial_link import SerialLink
from truckd.runtime.backend import open_backend
from truckd.sim.pty_link import PtyDevice

F1 = Frame(0x100, b"\x01\x02\x03\x04")
F2 = Frame(0x220, b"\x00\x00\x00\x00\x00\x00")


def drain(link: Link, want: int, timeout: float = 2.0) -> list[Frame]:
    """Receive until ``want`` frames or the deadline (for real-time backends)."""
    out: list[Frame] = []
    end = time.monotonic() + timeout
    while len(out) < want and time.monotonic() < end:
        f = link.recv(0.05)
        if f is not None:
            out.append(f)
    return out


@pytest.mark.parametrize("mode", ["frames", "bytes"])
def test_inproc_both_directions(mode: str) -> None:
    a, b, _ = inproc_pair(mode)  # type: ignore[arg-type]
    assert a.send(F1) and b.send(F2) and a.send(F2)
    assert b.recv() == F1 and b.recv() == F2 and b.recv() is None
    assert a.recv() == F2 and a.recv() is None
    assert a.stats.tx_frames == 2 and b.stats.rx_frames == 2


def test_inproc_bytes_garbage_resync() -> None:
    a, b, _ = inproc_pair("bytes")
    assert isinstance(a, FramedStreamLink)
    a.send_raw(b"\x13\x37" * 30)
    a.send(F1)
    a.send_raw(b"\x00\xff\xfe\x00")
    a.send(F2)
    assert [b.recv(), b.recv(), b.recv()] == [F1, F2, None]
    fs = b.stats.framing
    assert fs is not None and fs.resyncs == 2 and fs.bytes_discarded == 62


def test_inproc_disconnect_and_come_back() -> None:
    a, b, wire = inproc_pair("frames")
    a.send(F1)
    wire.disconnect()
    assert b.recv() is None  # in flight: lost
    assert not b.connected and b.stats.disconnects == 1
    assert not a.send(F1) and a.stats.tx_dropped == 1 and not a.connected
    wire.reconnect()
    assert a.send(F2) and b.recv() == F2
    assert a.connected and b.connected
    assert a.stats.reconnects == 1 and b.stats.reconnects == 1


def test_serial_loopback_url() -> None:
    link = SerialLink("loop://", reconnect_interval=0.01)
    assert link.connected
    link.send(F1)
    link.send(F2)
    assert drain(link, 2) == [F1, F2]
    link.close()


def test_serial_over_pty_pair_with_garbage() -> None:
    master, slave = os.openpty()
    link = SerialLink(os.ttyname(slave), reconnect_interval=0.01)
    try:
        os.write(master, b"\x55" * 100 + frame_to_bytes(F1) + b"\x01\x02" + frame_to_bytes(F2))
        assert drain(link, 2) == [F1, F2]
        fs = link.stats.framing
        assert fs is not None and fs.resyncs == 2
        link.send(F2)
        want, got = frame_to_bytes(F2), b""
        while len(got) < len(want) and select.select([master], [], [], 5.0)[0]:
            got += os.read(master, 100)
        assert got == want
    finally:
        link.close()
        os.close(master)
        os.close(slave)


def test_serial_device_vanishes_and_comes_back(tmp_path: Path) -> None:
    path = str(tmp_path / "ttyTRUCK")
    dev = PtyDevice(path)
    link = SerialLink(path, reconnect_interval=0.02)
    try:
        assert link.connected
        dev.send(F1)
        assert drain(link, 1) == [F1]
        dev.unplug()
        assert not os.path.exists(path)
        deadline = time.monotonic() + 2.0
        while link.connected and time.monotonic() < deadline:
            link.recv(0.02)
        assert not link.connected and link.stats.disconnects == 1
        assert link.last_error
        assert not link.send(F1)  # reported, not raised
        dev.replug()
        deadline = time.monotonic() + 2.0
        got: list[Frame] = []
        while not got and time.monotonic() < deadline:
            dev.send(F2)
            f = link.recv(0.02)
            if f is not None:
                got.append(f)
        assert got == [F2]
        assert link.connected and link.stats.reconnects == 1
        # and the other direction works on the new device
        link.send(F1)
        assert drain(dev, 1) == [F1]
    finally:
        link.close()
        dev.close()


def test_serial_device_vanishing_is_seen_by_the_loops_non_blocking_poll(tmp_path: Path) -> None:
    """The daemon polls with ``recv(0.0)`` (one non-blocking read, no select): a device
    that is unplugged must still take the link down, and data must still come through."""
    path = str(tmp_path / "ttyTRUCK")
    dev = PtyDevice(path)
    link = SerialLink(path, reconnect_interval=0.02)
    try:
        assert link.recv(0.0) is None  # nothing there: None, the link stays up
        assert link.connected
        dev.send(F1)
        dev.send(F2)
        got: list[Frame] = []
        deadline = time.monotonic() + 2.0
        while len(got) < 2 and time.monotonic() < deadline:
            f = link.recv(0.0)
            if f is not None:
                got.append(f)
        assert got == [F1, F2]
        dev.unplug()
        deadline = time.monotonic() + 2.0
        while link.connected and time.monotonic() < deadline:
            link.recv(0.0)
        assert not link.connected and link.stats.disconnects == 1
    finally:
        link.close()
        dev.close()


def test_bytes_arriving_between_the_poll_and_its_hangup_check_are_data(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On a descriptor that cannot count its bytes (no FIONREAD), the poll reads (b"" when
    empty), then asks select whether an empty read means a hang-up.  A frame that arrives
    in between makes the descriptor readable too: it is data, not a hang-up (this race once
    cut the motor: FAULT on link_down while the firmware was streaming).  The race is made
    certain by writing inside select."""
    path = str(tmp_path / "ttyTRUCK")
    dev = PtyDevice(path)
    link = SerialLink(path, reconnect_interval=0.02)
    monkeypatch.setattr(SerialLink, "_waiting", lambda self, fd: None)
    real_select = select.select
    pending = [F1]

    def select_after_a_write(r: list[int], w: list[int], x: list[int], t: float) -> object:
        while pending:  # the firmware's frame lands just after the empty read
            dev.send(pending.pop())
            deadline = time.monotonic() + 2.0
            while not real_select(r, [], [], 0.0)[0] and time.monotonic() < deadline:
                time.sleep(0.001)
        return real_select(r, w, x, t)

    monkeypatch.setattr("truckd.io.serial_link.select.select", select_after_a_write)
    try:
        assert link.recv(0.0) == F1
        assert link.connected and link.stats.disconnects == 0
    finally:
        link.close()
        dev.close()


def test_the_poll_never_reads_or_selects_an_empty_tty(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A read (or select) of a tty that holds no bytes waits in the kernel for the tty's
    input work, run by a normal-priority kworker (n_tty_read -> flush_work): on a busy
    machine the real-time loop sat there up to 627 ms.  So the poll asks FIONREAD first
    and makes neither call on an empty tty; bytes that are there are read at once, and a
    hung-up tty still takes the link down."""
    path = str(tmp_path / "ttyTRUCK")
    dev = PtyDevice(path)
    link = SerialLink(path, reconnect_interval=0.02)
    calls: list[str] = []
    real_read, real_select = os.read, select.select

    def read(fd: int, n: int) -> bytes:
        calls.append("read")
        return real_read(fd, n)

    def sel(r: list[int], w: list[int], x: list[int], t: float) -> object:
        calls.append("select")
        return real_select(r, w, x, t)

    monkeypatch.setattr("truckd.io.serial_link.os.read", read)
    monkeypatch.setattr("truckd.io.serial_link.select.select", sel)
    try:
        for _ in range(3):
            assert link.recv(0.0) is None and link.recv_all() == []
        assert calls == [] and link.connected
        dev.send(F1)
        deadline = time.monotonic() + 2.0
        got: list[Frame] = []
        while not got and time.monotonic() < deadline:
            got = link.recv_all()
        assert got == [F1] and calls == ["read"]
        dev.unplug()
        assert link.recv_all() == [] and not link.connected
        assert link.stats.disconnects == 1 and "Input/output error" in (link.last_error or "")
    finally:
        link.close()
        dev.close()


def open_link(name: str, link: LinkConfig) -> Link:
    """The link of backend ``name`` opened through the registry, as the daemon does."""
    cfg = dataclasses.replace(load_config(None), link=link)
    return open_backend(name, cfg, cfg.control).link


def test_missing_serial_device_reported(tmp_path: Path) -> None:
    link = open_link("serial", LinkConfig(serial_device=str(tmp_path / "nope")))
    assert not link.connected and link.last_error
    assert not link.send(F1) and link.recv(0.0) is None
    assert link.stats.tx_dropped == 1
    link.close()


def test_unknown_backend() -> None:
    with pytest.raises(ValueError, match="unknown backend 'carrier-pigeon'"):
        open_link("carrier-pigeon", LinkConfig())


def test_can_virtual_both_directions_and_errors() -> None:
    ch = f"truckd-{uuid.uuid4().hex}"
    a = open_link("can", LinkConfig(can_interface="virtual", can_channel=ch))
    b = CanLink("virtual", ch)
    spy = can.Bus(interface="virtual", channel=ch)
    try:
        assert a.connected and b.connected
        a.send(F1)
        b.send(F2)
        assert drain(b, 1) == [F1]
        assert drain(a, 1) == [F2]
        # error frames are counted, never handed on; 0x40 = bus-off
        spy.send(can.Message(arbitration_id=0x40, is_error_frame=True, dlc=8))
        spy.send(can.Message(arbitration_id=0x04, is_error_frame=True, dlc=8))
        spy.send(can.Message(arbitration_id=0x1234567, data=b"\x01", is_extended_id=True))
        b.send(F1)
        assert drain(a, 1) == [F1]
        assert a.stats.bus_errors == 3 and a.stats.bus_off == 1
    finally:
        a.close()
        b.close()
        spy.shutdown()


def test_can_bus_gone_and_reopened() -> None:
    ch = f"truckd-{uuid.uuid4().hex}"
    a = CanLink("virtual", ch, reconnect_interval=0.0)
    b = CanLink("virtual", ch)
    try:
        a._bus.shutdown()  # the bus disappears under the link
        assert not a.send(F1)
        assert not a.connected and a.stats.disconnects == 1
        b.send(F2)  # sent while a was down: lost
        assert a.send(F1)  # reopened on the next call
        assert a.connected and a.stats.reconnects == 1
        assert drain(b, 1) == [F1]
    finally:
        a.close()
        b.close()


def test_port_counters_checks_and_stats() -> None:
    t = [0.0]
    a, b, _ = inproc_pair("frames")
    comp = companion_port(a, clock=lambda: t[0])
    mcu = firmware_port(b, clock=lambda: t[0])
    for k in range(20):
        assert comp.send(MotorCommand(0.1 * k, True))
    comp.send(CompanionHeartbeat(CompanionState.ACTIVE))
    got = mcu.poll()
    assert [r.name for r in got] == ["MOTOR_CMD"] * 20 + ["COMPANION_HEARTBEAT"]
    assert mcu.checker.stats.counter_gaps == 0  # counters advanced 0..15, 0..3
    # a corrupt frame and a repeated counter are not handed on
    f = encode(RangeReading(1.0, RangeStatus.VALID), 0)
    b.send(Frame(f.can_id, f.data[:-1] + b"\x00" if f.data[-1] else f.data[:-1] + b"\x01"))
    b.send(f)
    b.send(f)
    got2 = comp.poll()
    assert len(got2) == 1 and got2[0].msg == RangeReading(1.0, RangeStatus.VALID)
    s = comp.stats()
    assert s["rx_checksum_errors"] == 1 and s["rx_counter_errors"] == 1 and s["connected"]
    assert comp.fresh("RANGE")
    t[0] = 1.0
    assert not comp.fresh("RANGE")
    assert comp.stats()["rx_timeouts"] == 1
    with pytest.raises(ValueError, match="finite"):
        comp.send(MotorCommand(float("nan"), True))


def test_poll_reads_a_serial_device_once_when_that_read_empties_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``recv_all`` (the loop's poll): frames that are all there come back in order from
    one read, without a second, empty read and its hang-up ``select``; frames that
    arrive later come with the next poll; a device whose every read is full (a backlog)
    is read until it is not."""
    path = str(tmp_path / "ttyTRUCK")
    dev = PtyDevice(path)
    link = SerialLink(path, reconnect_interval=0.02)
    reads: list[int] = []
    real_read = os.read

    def counted(fd: int, n: int) -> bytes:
        data = real_read(fd, n)
        reads.append(len(data))
        return data

    def wait_bytes(n: int) -> None:
        """Until the tty holds ``n`` bytes for the link (FIONREAD)."""
        assert link._fd is not None
        deadline = time.monotonic() + 2.0
        buf = array.array("i", [0])
        while time.monotonic() < deadline:
            fcntl.ioctl(link._fd, termios.FIONREAD, buf)
            if buf[0] >= n:
                return
            time.sleep(0.001)
        raise AssertionError(f"the tty holds {buf[0]} of {n} bytes")

    monkeypatch.setattr("truckd.io.serial_link.os.read", counted)
    try:
        assert link.recv_all() == [] and link.connected
        wire = frame_to_bytes(F1) + frame_to_bytes(F2)
        dev.send_raw(wire)
        wait_bytes(len(wire))
        reads.clear()
        assert link.recv_all() == [F1, F2]
        assert reads == [len(wire)]  # one read; before: a second, empty one and a select
        dev.send(F2)
        wait_bytes(len(frame_to_bytes(F2)))
        assert link.recv_all() == [F2]
        # a backlog larger than one read: read until a read is short
        monkeypatch.setattr("truckd.io.serial_link.READ_SIZE", len(frame_to_bytes(F1)))
        dev.send_raw(frame_to_bytes(F1) * 3)
        wait_bytes(3 * len(frame_to_bytes(F1)))
        reads.clear()
        assert link.recv_all() == [F1, F1, F1]
        assert len(reads) >= 3
    finally:
        link.close()
        dev.close()

"""slcan on a real pty, in one process: the simulated adapter (truckd.sim.slcan_peer) with
the C firmware core behind it, and the daemon's CAN link (python-can
``interface="slcan"``) on the pty slave.  Frames both ways, garbled lines, the adapter
vanishing and coming back.  Waits are bounded conditions on wall time (the link's
reconnect pacing is wall time)."""

from __future__ import annotations

import random
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from firmware_protocol.codec import Frame
from firmware_protocol.messages import FirmwareState, MotorCommand
from truckd.io.can_link import CanLink
from truckd.io.port import Port, Received, companion_port
from truckd.model.params import VehicleParams
from truckd.sim.firmware import SimulatedFirmware, constant_speed_lead
from truckd.sim.plant import Plant
from truckd.sim.slcan_peer import SlcanDevice, frame_line, parse_frame


@dataclass
class Bench:
    dev: SlcanDevice
    fw: SimulatedFirmware
    link: CanLink
    port: Port
    got: list[Received] = field(default_factory=list)

    def cycle(self, voltage: float = 2.0) -> None:
        self.port.send(MotorCommand(voltage, True))
        self.fw.step(0.01)
        self.got += self.port.poll()

    def until(self, cond: Callable[[], bool], timeout: float = 5.0) -> bool:
        """Run 10 ms cycles (paced on wall time) until ``cond`` or ``timeout`` s."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.cycle()
            if cond():
                return True
            time.sleep(0.002)
        return False


@pytest.fixture
def bench(tmp_path: Path, params: VehicleParams) -> Iterator[Bench]:
    plant = Plant(params)
    path = str(tmp_path / "ttyCAN")
    dev = SlcanDevice(path, clock=lambda: plant.t)
    fw = SimulatedFirmware(plant, constant_speed_lead(2.0, 1.0), dev, None, dev.unplug, dev.replug)
    link = CanLink("slcan", path, 500_000, reconnect_interval=0.05)
    try:
        yield Bench(dev, fw, link, companion_port(link, clock=lambda: plant.t))
    finally:
        link.close()
        dev.close()


def test_frames_both_ways_through_the_adapter(bench: Bench) -> None:
    assert bench.link.connected
    assert bench.until(lambda: bench.dev.channel_open, 2.0)  # python-can sent C, S6, O
    assert bench.dev.bitrate_cmd == "S6"  # 500 kbit/s
    assert bench.until(lambda: len(bench.got) >= 100)
    assert bench.fw.state == FirmwareState.ACTIVE and bench.fw.core.config.link == "can"
    st = bench.port.stats()
    assert st["rx_counter_gaps"] == 0 and st["rx_checksum_errors"] == 0
    assert {r.name for r in bench.got} == {
        "WHEEL_ENCODERS",
        "MOTOR_FEEDBACK",
        "RANGE",
        "FIRMWARE_HEARTBEAT",
    }
    assert bench.fw.link_stats()["rx_frames_ok"] >= 30  # commands checked by the C core


def test_garbled_lines_are_counted_and_the_link_recovers(bench: Bench) -> None:
    assert bench.until(lambda: len(bench.got) >= 20)
    for _ in range(5):
        bench.fw.apply_fault({"fault": "garbage", "bytes": 8})
        bench.cycle()
    n0 = len(bench.got)
    # random frames reach the checks (unknown ids, bad checksums); malformed lines are bus
    # errors; a non-ASCII line makes python-can's slcan drop its bus, the link reopens it
    assert bench.until(lambda: len(bench.got) > n0 + 50 and bench.link.connected)
    st = bench.port.stats()
    assert st["rx_unknown_ids"] + st["rx_checksum_errors"] + st["rx_length_errors"] >= 1
    assert st["bus_errors"] + st["disconnects"] >= 1
    assert bench.fw.state == FirmwareState.ACTIVE
    assert bench.fw.stats.garbage_sent == 40


def test_adapter_vanishes_and_comes_back(bench: Bench) -> None:
    assert bench.until(lambda: len(bench.got) >= 20)
    bench.fw.apply_fault({"fault": "disconnect", "duration": 0.3})
    assert bench.until(lambda: not bench.link.connected, 2.0)
    # commands stop reaching the firmware: its own timeout switches the motor off
    assert bench.until(lambda: bench.fw.state == FirmwareState.FAILSAFE, 2.0)
    assert bench.until(lambda: bench.link.connected and bench.port.fresh("WHEEL_ENCODERS"), 5.0), (
        bench.link.last_error
    )
    assert bench.until(lambda: bench.fw.state == FirmwareState.ACTIVE, 2.0)
    st = bench.port.stats()
    assert st["disconnects"] >= 1 and st["reconnects"] >= 1


def test_the_poll_never_reads_an_empty_adapter_tty(
    bench: Bench, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A read or select of a tty with no bytes waits in the kernel for a normal-priority
    kworker (n_tty_read -> flush_work; up to 627 ms measured on a busy machine), so the
    loop's poll calls python-can's slcan read only while the tty holds bytes."""
    ser = bench.link._bus.serialPortOrig
    real_read = ser.read
    reads: list[int] = []  # bytes the tty held at each read

    def read(n: int = 1) -> bytes:
        reads.append(int(ser.in_waiting))
        return bytes(real_read(n))

    monkeypatch.setattr(ser, "read", read)
    assert bench.until(lambda: len(bench.got) >= 50)
    assert reads and min(reads) > 0 and bench.link.connected


def test_adapter_commands(bench: Bench) -> None:
    assert bench.until(lambda: bench.dev.channel_open, 2.0)
    ser = bench.link._bus.serialPortOrig  # raw access, as a terminal would type
    ser.reset_input_buffer()  # acknowledgements and frames so far

    def ask(line: bytes) -> bytes:
        ser.write(line)
        got = b""
        end = time.monotonic() + 2.0
        while time.monotonic() < end and not got.endswith((b"\r", b"\a")):
            bench.dev.recv(0.0)  # the adapter reads and answers
            got += ser.read(ser.in_waiting or 1)
        return got

    assert ask(b"V\r") == b"V1013\r" and ask(b"N\r") == b"NA123\r"
    assert ask(b"?\r") == b"\a" and ask(b"t10G1\r") == b"\a"  # unknown, malformed
    assert bench.dev.bad_lines == 2
    assert ask(b"C\r") == b"\r" and not bench.dev.channel_open


def test_line_format() -> None:
    f = Frame(0x100, bytes([0x12, 0xAB, 0x00, 0xFF]))
    assert frame_line(f) == b"t100412AB00FF\r"
    assert parse_frame(b"t100412AB00FF") == f
    assert parse_frame(b"t7FF0") == Frame(0x7FF, b"")
    for bad in (b"t100412AB00", b"t10G1AA", b"T1234567811", b"t800100", b"t1009" + b"00" * 9):
        assert parse_frame(bad) is None
    rng = random.Random(1)
    for _ in range(200):
        g = Frame(rng.randrange(0x800), bytes(rng.randrange(256) for _ in range(rng.randrange(9))))
        assert parse_frame(frame_line(g)[:-1]) == g

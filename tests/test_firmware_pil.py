"""Processor in the loop: the firmware's ARM image runs on QEMU's emulated STM32F405
(``netduinoplus2``, board/qemu/board.c) in place of the ctypes firmware; the simulated
plant runs on the host (:class:`truckd.sim.pil.EmulatedBoard`), and ``truckd run`` drives
it over its serial backend on a pty, relayed byte for byte to the board's USART2.

- the truck follows a lead: frames arrive both ways (the board's receive counters, the
  daemon's link counters), the daemon goes ACTIVE, no collision, the gap settles near the
  spacing policy's;
- one corrupted frame from the daemon is rejected and counted by the board, and the
  commands after it are applied;
- a stalled link: the firmware cuts the motor (0 V, driver disabled) its command timeout
  (100 ms of the board's clock, at most one command period more) after the last command
  it received, and counts the timeout; when the link flows again it drives again.

Needs qemu-system-arm and arm-none-eabi-gcc (``.ci/run`` installs both); without them the
tests are skipped naming what is missing (tests/external_tools.py).  About 20 s.

Also here (it needs the emulator): the CAN image of the STM32F4 board example runs on
without a CAN controller.
"""

from __future__ import annotations

import itertools
import math
import os
import signal
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from external_tools import arm_gcc, qemu_arm
from hil_support import Daemon, Watch, hil_config, new_port
from runtime_support import wait_for

from truckd.config.truck import TruckConfig, load_config
from truckd.sim.firmware import CuedLead
from truckd.sim.pil import EmulatedBoard, build_pil_elf
from truckd.sim.truck import emulated_board, truck_spec

pytestmark = [
    pytest.mark.hil,
    pytest.mark.needs_tool("qemu-system-arm", install="apt-get install qemu-system-arm"),
    pytest.mark.needs_tool(
        "arm-none-eabi-gcc", install="apt-get install gcc-arm-none-eabi libnewlib-arm-none-eabi"
    ),
]

LEAD_GAP, LEAD_SPEED = 1.5, 0.8  # m, m/s
FW_DIR = Path(__file__).resolve().parent.parent / "firmware_protocol" / "firmware"
CMD_TIMEOUT_MS = 100  # the core's default (truck_fw_default_config)
FAILSAFE = 3  # TRUCK_FW_STATE_FAILSAFE (truck_fw.h)


@dataclass
class Rig:
    board: EmulatedBoard
    daemon: Daemon
    watch: Watch
    cfg: TruckConfig


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    arm_gcc()
    qemu = qemu_arm()
    elf = build_pil_elf()
    tmp = tmp_path_factory.mktemp("pil")
    cfg = load_config(None)
    lead = CuedLead(LEAD_GAP, LEAD_SPEED)
    board = emulated_board(
        truck_spec(cfg),
        lead,
        tmp / "ttyPIL",
        elf=elf,
        qemu=qemu,
    )
    board.start()
    port = new_port()
    # realtime off: the daemon's SCHED_FIFO threads would compete with the emulator and
    # the plant for the 2 cores of a loaded CI machine
    config = hil_config(tmp, str(tmp / "ttyPIL"), port, realtime=False)
    daemon = Daemon(config, tmp / "daemon.err")
    watch = Watch(port)
    try:
        # the lead sets off once the daemon publishes (it is reading the board by then)
        wait_for(lambda: bool(watch.states), 60)
        lead.go(board.plant.t)
        yield Rig(board, daemon, watch, cfg)
    finally:
        watch.close()
        daemon.stop()
        board.stop()


def _errors(st: dict[str, int]) -> int:
    return sum(st[k] for k in ("checksum_errors", "crc_errors", "cobs_errors", "length_errors"))


def test_pil_truck_follows_and_frames_arrive(rig: Rig) -> None:
    b = rig.board
    assert wait_for(lambda: b.boot_s() is not None, 30), b.diagnostics()
    active = rig.watch.wait_state(lambda m: m["mode"] == "ACTIVE", timeout=40)
    assert active is not None, f"{b.diagnostics()}\n{rig.daemon.stderr()[-2000:]}"

    # frames actually arrive: the board decoded the daemon's commands and sent its own,
    # the relay moved them, the daemon received and accepted them (waited for: the daemon
    # starts seconds after the board on a loaded machine), and none was lost on the way
    def counted() -> bool:
        st = b.last_stats()
        link = rig.watch.last_health().get("link", {})
        return (
            st.get("frames_ok", 0) > 200
            and st.get("commands_applied", 0) > 200
            and st.get("frames_sent", 0) > 1000
            and b.relay.to_board_frames > 200
            and b.relay.to_daemon_frames > 1000
            and link.get("rx_frames_ok", 0) > 500
        )

    assert wait_for(counted, 60), f"{b.diagnostics()}\n{rig.watch.last_health()}"
    st = b.last_stats()
    assert st["tx_failed"] == 0 and _errors(st) == 0, st
    assert rig.watch.last_health()["link"]["framing_crc_errors"] == 0
    # the truck follows: the gap settles near d_0 + h v (mean over 2 s of plant time,
    # waited for: a host stall on this shared machine sends the daemon to SAFE_STOP for a
    # moment), at the lead's speed; never a collision
    c = rig.cfg.control

    seen: list[tuple[float, float, float]] = []  # (plant t s, mean gap error m, mean v m/s)

    def settled() -> bool:
        last = [(g, v) for t, g, v in b.gaps if t > b.gaps[-1][0] - 2.0]
        err = math.fsum(g - (c.d_0 + c.time_headway * v) for g, v in last) / len(last)
        v_mean = math.fsum(v for _, v in last) / len(last)
        seen.append((b.gaps[-1][0], err, v_mean))
        return abs(err) < 0.05 and abs(v_mean - LEAD_SPEED) < 0.15

    assert wait_for(settled, 40), (
        f"the gap never settled: {b.diagnostics()}\n"
        f"(t, gap error, v), every 50th: {[tuple(round(x, 3) for x in s) for s in seen[::50]]}\n"
        f"modes: {rig.watch.modes()}\n{rig.daemon.stderr()[-2000:]}"
    )
    assert b.min_gap > 0.0


def test_pil_corrupted_frame_is_rejected_and_counted(rig: Rig) -> None:
    b = rig.board
    assert rig.watch.wait_state(lambda m: m["mode"] == "ACTIVE", timeout=40), b.diagnostics()
    before = b.last_stats()
    assert wait_for(lambda: b.last_stats()["ms"] > before["ms"], 5)
    before = b.last_stats()
    b.corrupt_next_frame()
    assert wait_for(lambda: b.relay.corrupted == 1, 5)
    # counted once the board has read it (the frames before it may still be on their way
    # to the emulated UART on a loaded machine), and the commands after it are applied
    assert wait_for(lambda: _errors(b.last_stats()) > _errors(before), 10), b.diagnostics()
    applied = b.last_stats()["commands_applied"]
    assert wait_for(lambda: b.last_stats()["commands_applied"] > applied + 20, 10)
    after = b.last_stats()
    assert _errors(after) == _errors(before) + 1  # exactly the one frame, counted
    assert after["cmd_timeouts"] == before["cmd_timeouts"]  # the link went on


def test_pil_stalled_link_cuts_the_motor_within_the_command_timeout(rig: Rig) -> None:
    b = rig.board
    assert rig.watch.wait_state(lambda m: m["mode"] == "ACTIVE", timeout=40), b.diagnostics()
    assert wait_for(lambda: any(m.enable for m in b.motor_lines()[-5:]), 5), b.diagnostics()
    timeouts = b.last_stats()["cmd_timeouts"]
    n0 = len(b.motor_lines())
    b.stall(True)
    try:
        assert wait_for(lambda: any(not m.enable for m in b.motor_lines()[n0:]), 5)
        assert wait_for(lambda: b.last_stats()["cmd_timeouts"] == timeouts + 1, 5)
        assert b.last_stats()["state"] == FAILSAFE
    finally:
        b.stall(False)
    lines = b.motor_lines()
    cut = next(i for i in range(n0, len(lines)) if not lines[i].enable)
    last_cmd = lines[cut - 1]
    assert last_cmd.enable and lines[cut].mv == 0
    # the board's own clock (each driver line stamped with the core's time of the decision,
    # so a SysTick between the core's reading and the driver call does not move the last
    # command a millisecond later): the command timeout after the last command applied (exact on
    # the ctypes core, tests/test_firmware_c.py; here the emulated main loop can be held
    # up a few ms while QEMU waits on a host socket: at most one command period late)
    assert CMD_TIMEOUT_MS <= lines[cut].ms - last_cmd.ms <= CMD_TIMEOUT_MS + 10
    # the link flows again: the firmware drives again
    assert wait_for(lambda: any(m.enable for m in b.motor_lines()[cut + 1 :]), 10)


def test_pil_elf_is_the_built_one() -> None:
    """The image the tests boot is rebuilt from the sources (make's dependency check)."""
    arm_gcc()
    elf = build_pil_elf()
    assert elf.stat().st_mtime >= (FW_DIR / "board/qemu/board.c").stat().st_mtime


def test_can_image_without_a_can_controller_runs_on(tmp_path: Path) -> None:
    """The STM32F4 board example's CAN image on the emulator, which has no CAN controller
    (its registers read 0: no acknowledge ever comes, as on a board with a broken CAN
    clock).  The watchdog is started before the first wait on the controller; each wait
    gives up (BOARD_FAULT_CAN_INIT) and the main loop runs and feeds the watchdog between
    the attempts, instead of spinning forever on the init acknowledge."""
    arm_gcc()
    qemu = qemu_arm()
    r = subprocess.run(["make", "-s", "-C", str(FW_DIR), "arm"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    log = tmp_path / "unimp.log"
    proc = subprocess.Popen(
        [qemu, "-M", "netduinoplus2", "-nographic", "-monitor", "none", "-icount", "shift=auto",
         "-kernel", str(FW_DIR / "build/stm32f4/truck_fw_can.elf"), "-serial", "null",
         "-serial", "null", "-d", "unimp", "-D", str(log)],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    inrq = "CAN1: unimplemented device write (size 4, offset 0x000, value 0x00000001)"
    try:
        assert wait_for(lambda: log.exists() and log.read_text().count(inrq) >= 3, 30)
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    lines = log.read_text().splitlines()
    # IWDG (QEMU 7.2 names its page I2S2ext): key 0xCCCC starts it, 0xAAAA feeds it
    start = next(i for i, ln in enumerate(lines) if "value 0x0000cccc" in ln)
    first_can = next(i for i, ln in enumerate(lines) if ln.startswith("CAN1"))
    assert start < first_can  # the watchdog runs before the first wait on the hardware
    attempts = [i for i, ln in enumerate(lines) if ln == inrq]
    for a, b in itertools.pairwise(attempts):
        feeds = sum("value 0x0000aaaa" in ln for ln in lines[a:b])
        assert feeds > 0, "no watchdog feed between two CAN attempts: a wait did not end"

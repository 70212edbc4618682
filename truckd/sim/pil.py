"""Processor in the loop: the firmware's ARM image on QEMU's emulated STM32F405
(``netduinoplus2``), the simulated plant on the host (docs/firmware.md).

:class:`EmulatedBoard` starts ``qemu-system-arm`` with the image that
``make -C firmware_protocol/firmware pil`` builds (``board/qemu/board.c``).  The emulated
board has two UARTs, both on Unix sockets this process serves:

- USART1, plant I/O (text lines, see board.c): the board sends its clock (``T <ms>``,
  every 5 ms), its motor output (``M``), its boot (``B``) and its counters (``C``, every
  100 ms); the simulated :class:`~truckd.sim.plant.Plant` runs on the board's clock:
  each line first advances it to the line's instant, a motor line then commands it, and
  a clock line is answered with a sensor snapshot (encoder counts with their fraction
  of a tick and their rate, range from ``range_fn``, current, battery) at that instant,
  unless the previous snapshot is still unread (the emulated UART takes about 16 kB/s: a
  queue of snapshots would feed the firmware stale readings); between snapshots the
  board's encoder counters run on at the snapshot's rate, as hardware counters would;
- USART2, the serial link: relayed byte for byte to a pty whose slave is published at
  ``link_path`` (the device the daemon's serial backend opens).  The relay can hold
  the daemon's bytes back (:meth:`stall`) or flip one bit of the next frame to the board
  (:meth:`corrupt_next_frame`), and counts the bytes and frames it moved.

The plant runs on the board's clock, so the virtual clock's rate (``-icount
shift=auto``: deterministic, close to real time, slower while the emulator catches up)
never skews the plant against the firmware's sample times.  The daemon runs on the
host's clock.  Every process started here is
ended by its pid (:meth:`stop`).
"""

from __future__ import annotations

import contextlib
import fcntl
import math
import os
import random
import selectors
import signal
import socket
import struct
import subprocess
import tempfile
import termios
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from truckd.errors import TruckdError
from truckd.io.config import ENCODER_TICKS_PER_REV
from truckd.sim.plant import Plant

RangeFn = Callable[[float, float], float | None]

FIRMWARE_DIR = Path(__file__).resolve().parents[2] / "firmware_protocol" / "firmware"
PIL_ELF = FIRMWARE_DIR / "build" / "qemu" / "truck_fw_pil.elf"
RANGE_VALID, RANGE_NO_TARGET = 0, 1
STATS_KEYS = (
    "ms", "frames_ok", "checksum_errors", "crc_errors", "cobs_errors", "length_errors",
    "cmd_timeouts", "frames_sent", "tx_failed", "commands_applied", "state",
)  # fmt: skip
"""The fields of the board's ``C`` line (board/qemu/board.c)."""


def build_pil_elf() -> Path:
    """``make -C firmware_protocol/firmware pil`` (rebuilds when a source changed); the
    ELF.  Raises TruckdError with make's last lines when it fails."""
    r = subprocess.run(
        ["make", "-s", "-C", str(FIRMWARE_DIR), "pil"],
        capture_output=True,
        text=True,
        check=False,
    )
    if r.returncode != 0 or not PIL_ELF.exists():
        tail = " ".join((r.stderr or r.stdout).strip().splitlines()[-3:])
        raise TruckdError(f"building the emulated board's firmware failed: {tail}")
    return PIL_ELF


@dataclass(frozen=True)
class MotorLine:
    """One ``set_motor`` of the firmware: host time (s, monotonic), board time (ms)."""

    host_t: float
    ms: int
    mv: int
    enable: bool


def count_frames(data: bytes, in_frame: bool) -> tuple[int, bool]:
    """Frames that end in ``data`` (a 0x00 delimiter after at least one other byte; the
    framing puts a delimiter before and after each frame) and whether a frame is open at
    its end."""
    n = 0
    for seg in data.split(b"\x00")[:-1]:
        if seg or in_frame:
            n += 1
        in_frame = False
    if data and not data.endswith(b"\x00"):
        in_frame = True
    return n, in_frame


@dataclass
class RelayCounts:
    """What the link relay moved (bytes, whole frames)."""

    to_board_bytes: int = 0
    to_board_frames: int = 0
    to_daemon_bytes: int = 0
    to_daemon_frames: int = 0
    held_bytes: int = 0  # daemon bytes dropped while stalled
    corrupted: int = 0


@dataclass
class BoardLog:
    """What the board reported over the plant UART."""

    boot_s: float | None = None  # from the QEMU start to the board's ``B`` line (wall)
    motor: list[MotorLine] = field(default_factory=list)
    stats: list[dict[str, int]] = field(default_factory=list)
    bad_lines: int = 0


def _unsent(conn: socket.socket) -> int:
    """Bytes written to ``conn`` that the peer has not read yet (SIOCOUTQ)."""
    buf = fcntl.ioctl(conn.fileno(), termios.TIOCOUTQ, b"\0\0\0\0")
    return int(struct.unpack("i", buf)[0])


class EmulatedBoard:
    """The emulated board with its plant (see module docstring).  ``start()``, ``stop()``;
    thread-safe readers: :meth:`last_stats`, :meth:`motor_lines`."""

    def __init__(
        self,
        plant: Plant,
        range_fn: RangeFn,
        link_path: str | Path,
        *,
        ticks_per_rev: int = ENCODER_TICKS_PER_REV,
        range_max: float = 4.0,
        range_noise: float = 0.002,
        seed: int = 0,
        elf: Path | None = None,
        qemu: str = "qemu-system-arm",
    ) -> None:
        """``range_max`` (m): farther is NO_TARGET; ``range_noise`` (m, std): added to
        the range reading (a noiseless reading of a steady gap repeats to the mm, which the
        supervisor takes for a frozen sensor); ``seed``: of that noise."""
        self.plant = plant
        self.range_fn = range_fn
        self.link_path = str(link_path)
        self.range_max = range_max
        self.range_noise = range_noise
        self._rng = random.Random(seed)
        self.elf = elf or PIL_ELF
        self.qemu = qemu
        self._ticks_per_m = ticks_per_rev / (2.0 * math.pi * plant.p.r_w)
        self.log = BoardLog()
        self.relay = RelayCounts()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._stalled = False
        self._corrupt = False
        self._proc: subprocess.Popen[bytes] | None = None
        self._tmp: tempfile.TemporaryDirectory[str] | None = None
        self._threads: list[threading.Thread] = []
        self._socks: list[socket.socket] = []
        self._fds: list[int] = []
        self._t0 = 0.0
        self.min_gap = math.inf
        """Smallest true gap to the lead seen by the plant (m)."""
        self.error = ""
        """Why the plant thread ended, if it failed."""
        self.skipped_snapshots = 0
        """Sensor snapshots not sent because the previous one was still queued."""
        self.gaps: list[tuple[float, float, float]] = []
        """(plant time s, true gap m, plant speed m/s) at every snapshot with a lead."""

    # -- lifecycle ---------------------------------------------------------------------
    def start(self, timeout: float = 30.0) -> EmulatedBoard:
        """Start QEMU, connect both UARTs, start the plant and the relay; returns once
        both UARTs are connected (not waiting for the boot: see ``log.boot_s``)."""
        self._tmp = tempfile.TemporaryDirectory(prefix="truckd-pil-")
        plant_sock = os.path.join(self._tmp.name, "plant.sock")
        link_sock = os.path.join(self._tmp.name, "link.sock")
        listeners = []
        for path in (plant_sock, link_sock):
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.bind(path)
            s.listen(1)
            s.settimeout(timeout)
            listeners.append(s)
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._fds = [master, slave]
        tmp_link = f"{self.link_path}.tmp{os.getpid()}"
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_link)
        os.symlink(os.ttyname(slave), tmp_link)
        os.replace(tmp_link, self.link_path)
        cmd = [
            self.qemu, "-M", "netduinoplus2", "-nographic", "-monitor", "none",
            "-icount", "shift=auto", "-kernel", str(self.elf),
            "-serial", f"unix:{plant_sock}", "-serial", f"unix:{link_sock}",
        ]  # fmt: skip
        self._t0 = time.monotonic()
        self._proc = subprocess.Popen(
            cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
        )
        try:
            plant_conn, _ = listeners[0].accept()
            link_conn, _ = listeners[1].accept()
        except OSError as exc:
            err = self._stderr()
            self.stop()
            raise TruckdError(f"QEMU did not connect its UARTs: {exc} {err}") from None
        finally:
            for s in listeners:
                s.close()
        plant_conn.setblocking(False)
        link_conn.setblocking(True)  # read only when select says so; sends wait for QEMU
        self._socks = [plant_conn, link_conn]
        self.plant_t0 = self.plant.t
        self._threads = [
            threading.Thread(
                target=self._plant_loop, args=(plant_conn,), name="pil-plant", daemon=True
            ),
            threading.Thread(
                target=self._board_to_daemon, args=(link_conn, master), name="pil-up", daemon=True
            ),
            threading.Thread(
                target=self._daemon_to_board, args=(link_conn, master), name="pil-down", daemon=True
            ),
        ]
        for th in self._threads:
            th.start()
        return self

    def _stderr(self) -> str:
        p = self._proc
        if p is None or p.stderr is None or p.poll() is None:
            return ""
        return p.stderr.read().decode(errors="replace").strip()[-300:]

    @property
    def pid(self) -> int:
        return self._proc.pid if self._proc is not None else 0

    def alive(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def stop(self) -> None:
        """End QEMU (SIGKILL by its pid: the emulated board has no shutdown), the threads,
        the sockets and the pty (idempotent)."""
        self._stop.set()
        p = self._proc
        if p is not None:
            if p.poll() is None:
                os.kill(p.pid, signal.SIGKILL)
            p.wait(10)
            if p.stderr is not None:
                p.stderr.close()
        for th in self._threads:
            th.join(timeout=5)
        self._threads = []
        for s in self._socks:
            s.close()
        self._socks = []
        with contextlib.suppress(FileNotFoundError):
            if os.path.islink(self.link_path):
                os.unlink(self.link_path)
        for fd in self._fds:
            with contextlib.suppress(OSError):
                os.close(fd)
        self._fds = []
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def __enter__(self) -> EmulatedBoard:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- link faults -------------------------------------------------------------------
    def stall(self, on: bool) -> None:
        """Hold back (drop) every byte from the daemon to the board while on."""
        with self._lock:
            self._stalled = on

    def corrupt_next_frame(self) -> None:
        """Flip one bit in the middle of the next whole frame from the daemon."""
        with self._lock:
            self._corrupt = True

    # -- readers -----------------------------------------------------------------------
    def last_stats(self) -> dict[str, int]:
        """The board's latest counters (empty before the first ``C`` line)."""
        with self._lock:
            return dict(self.log.stats[-1]) if self.log.stats else {}

    def motor_lines(self) -> list[MotorLine]:
        with self._lock:
            return list(self.log.motor)

    def boot_s(self) -> float | None:
        with self._lock:
            return self.log.boot_s

    # -- the plant (USART1) ------------------------------------------------------------
    def _sensor_line(self) -> bytes:
        p = self.plant
        pos = p.x * self._ticks_per_m  # ticks
        ticks = math.floor(pos)
        milli = min(int((pos - ticks) * 1000.0), 999)
        rate = round(p.v * self._ticks_per_m)  # ticks/s: the counters run on at it
        ms = round((p.t - self.plant_t0) * 1000.0)
        ticks &= 0xFFFF
        m = p.measure()
        gap = self.range_fn(p.t, p.x)
        if gap is None or not math.isfinite(gap) or gap > self.range_max:
            status, mm = RANGE_NO_TARGET, 0
        else:
            self.min_gap = min(self.min_gap, gap)
            self.gaps.append((p.t, gap, p.v))
            if self.range_noise:
                gap += self._rng.gauss(0.0, self.range_noise)
            status, mm = RANGE_VALID, round(max(gap, -1e6) * 1000.0)
        return (
            f"S {ticks} {ticks} 0 {mm} {status} {round(m.i * 1000.0)} {round(m.vbat * 1000.0)} "
            f"{ms} {milli} {rate}\n"
        ).encode()

    def _advance_to(self, ms: int) -> None:
        """The plant to the board's instant ``ms`` (never backwards), bounded steps."""
        target = self.plant_t0 + ms / 1000.0
        while self.plant.t < target - 1e-9:
            self.plant.advance(min(target - self.plant.t, 0.005))

    def _on_line(self, line: str, now: float) -> bool:
        """One line from the board; True for a clock line (a snapshot is due)."""
        parts = line.split()
        try:
            vals = [int(x) for x in parts[1:]]
        except ValueError:
            vals = []
        kind = parts[0] if parts else ""
        with self._lock:
            if kind in ("T", "M", "C") and vals:
                self._advance_to(vals[0])
            if kind == "T" and len(vals) == 1:
                return True
            if kind == "M" and len(vals) == 3:
                ml = MotorLine(now, vals[0], vals[1], bool(vals[2]))
                self.log.motor.append(ml)
                self.plant.command(ml.mv / 1000.0 if ml.enable else 0.0)
            elif kind == "C" and len(vals) == len(STATS_KEYS):
                self.log.stats.append(dict(zip(STATS_KEYS, vals, strict=True)))
            elif kind == "B" and len(vals) == 1:
                self.log.boot_s = now - self._t0
            else:
                self.log.bad_lines += 1
        return False

    def _plant_loop(self, conn: socket.socket) -> None:
        try:
            self._plant_io(conn)
        except Exception as exc:  # kept for diagnostics(): the board then waits on us
            self.error = f"plant thread: {exc!r}"

    def _plant_io(self, conn: socket.socket) -> None:
        buf = b""
        sel = selectors.DefaultSelector()
        sel.register(conn, selectors.EVENT_READ)
        while not self._stop.is_set():
            if not sel.select(0.05):
                continue
            now = time.monotonic()
            try:
                data = conn.recv(65536)
            except BlockingIOError:
                continue
            except OSError:
                return
            if not data:
                return  # QEMU went
            *lines, buf = (buf + data).split(b"\n")
            due = False
            for ln in lines:
                due = self._on_line(ln.decode(errors="replace"), now) or due
            if not due:
                continue
            with self._lock:
                line = self._sensor_line()
            try:
                if _unsent(conn) == 0:  # else the board is still reading the last one
                    conn.sendall(line)
                else:
                    self.skipped_snapshots += 1
            except BlockingIOError:
                self.skipped_snapshots += 1
            except OSError:
                return
        sel.close()

    # -- the link (USART2 <-> pty) -----------------------------------------------------
    # One thread per direction: a send that waits (QEMU takes its UART's input a byte at
    # a time) never keeps the other direction from being read, which would block QEMU's
    # own writes and freeze the board.
    def _board_to_daemon(self, conn: socket.socket, master: int) -> None:
        open_frame = False
        sel = selectors.DefaultSelector()
        sel.register(conn, selectors.EVENT_READ)
        try:
            while not self._stop.is_set():
                if not sel.select(0.05):
                    continue
                try:
                    data = conn.recv(65536)
                except OSError:
                    return
                if not data:
                    return  # QEMU went
                with contextlib.suppress(BlockingIOError, OSError):
                    os.write(master, data)  # nobody reading: the pty drops it
                n, open_frame = count_frames(data, open_frame)
                with self._lock:
                    self.relay.to_daemon_bytes += len(data)
                    self.relay.to_daemon_frames += n
        finally:
            sel.close()

    def _daemon_to_board(self, conn: socket.socket, master: int) -> None:
        pending = b""  # daemon bytes of the frame being corrupted
        open_frame = False
        sel = selectors.DefaultSelector()
        sel.register(master, selectors.EVENT_READ)
        try:
            while not self._stop.is_set():
                if not sel.select(0.05):
                    continue
                try:
                    data = os.read(master, 65536)
                except (BlockingIOError, OSError):
                    continue
                with self._lock:
                    if self._stalled:
                        self.relay.held_bytes += len(data)
                        continue
                    corrupt = self._corrupt
                if corrupt:
                    data, pending = self._corrupt_frame(pending + data)
                if not data:
                    continue
                try:
                    conn.sendall(data)
                except OSError:
                    return  # QEMU went
                n, open_frame = count_frames(data, open_frame)
                with self._lock:
                    self.relay.to_board_bytes += len(data)
                    self.relay.to_board_frames += n
        finally:
            sel.close()

    def diagnostics(self) -> str:
        """One line for a failing test: QEMU, the threads, the board's last counters."""
        with self._lock:
            stats = self.log.stats[-1] if self.log.stats else {}
            relay = dict(vars(self.relay))
            bad = self.log.bad_lines
        threads = {th.name: th.is_alive() for th in self._threads}
        return (
            f"qemu alive {self.alive()}, threads {threads}, board {stats}, relay {relay}, "
            f"bad lines {bad}, skipped snapshots {self.skipped_snapshots}, "
            f"plant t {self.plant.t:.3f} s {self.error}"
        )

    def _corrupt_frame(self, data: bytes) -> tuple[bytes, bytes]:
        """Bytes to send now and bytes to keep: waits for a whole frame (between two
        delimiters) and flips the low bit of its middle byte (never making a 0x00)."""
        start = data.find(0)
        end = data.find(0, start + 1) if start >= 0 else -1
        if end < 0 or end - start < 4:
            if start >= 0 and end >= 0:  # too short to hit: pass it, try the next
                return data[:end], data[end:]
            return b"", data
        mid = (start + end) // 2
        b = data[mid] ^ 0x02
        buf = bytearray(data)
        buf[mid] = b if b else 0x04
        with self._lock:
            self._corrupt = False
            self.relay.corrupted += 1
        return bytes(buf), b""

"""The received-message log (a sidecar of the CSV log) that makes a run replayable.

The CSV log (reference section 3) holds what the daemon did; this file holds what it
heard: every cycle's inputs to :class:`~truckd.runtime.cycle.CompanionCycle` (the time,
the checked messages with their arrival times, the link state and the loop's deadline
verdict), so :mod:`truckd.runtime.replay` can feed them through the same step again and
compare the commands (as openpilot replays its logs).  JSON lines, floats in full
precision (``repr``), written on the recorder's thread (the loop only appends to a deque):

- line 1: ``{"format": "truckd-rx/2", "t0": T0, "seq0": N, "params": {...}}``: the start of
  the run on the caller's clock (s), the first cycle in this file (0 in the first file of a
  run) and the parameters in use (the daemon's ``params`` queryable: model, control,
  runtime, ticks per revolution);
- then one line per cycle: ``[now, link_up, loop_missed, [[t, name, type, [fields]], ...]]``
  and, when there is one, a fifth element with the lead forecast (m/s per period, or null),
  a sixth with the headway (s, or null) and a seventh with the car's solver failure of that
  cycle, ``[status, iterations]`` (a solve over its time budget cannot be timed again in a
  replay: the replay fails it the same way).

On by default (``runtime.recorder.messages``): a sidecar of the
:class:`~truckd.runtime.recorder.Recorder`, opened beside each CSV file (``<log>.rx.jsonl``),
rotated with it and deleted with it beyond ``runtime.recorder.keep`` files; about the CSV's
size (20 kB/s at 100 Hz).  ``truckd-rx/1`` files (one file per run, no ``seq0``, no
failures) are read as well.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from firmware_protocol.messages import (
    FirmwareFault,
    FirmwareHeartbeat,
    FirmwareState,
    Message,
    MotorFeedback,
    RangeReading,
    RangeStatus,
    WheelEncoders,
)
from truckd.errors import InputError
from truckd.io.port import Received
from truckd.runtime.cycle import CycleInputs, CycleOutputs
from truckd.runtime.mcap_log import YIELD_S

log = logging.getLogger("truckd.rxlog")

FORMAT = "truckd-rx/2"
FORMATS = ("truckd-rx/1", FORMAT)
"""The versions read (version 1: one file per run, no ``seq0``, no solver failures)."""

SUFFIX = ".rx.jsonl"
"""Beside each CSV file: ``<log>.rx.jsonl``."""

Failure = tuple[str, int]
"""A solve that failed on the car: its status and iterations."""

_TYPES: dict[str, tuple[Callable[..., Message], tuple[Callable[[Any], Any], ...]]] = {
    "WheelEncoders": (WheelEncoders, (int, int, float, int)),
    "MotorFeedback": (MotorFeedback, (float, float, float, int)),
    "RangeReading": (RangeReading, (float, RangeStatus, float)),
    "FirmwareHeartbeat": (FirmwareHeartbeat, (FirmwareState, FirmwareFault, int)),
}
"""The messages the companion receives: constructor and field conversions."""

_FIELDS: dict[str, tuple[str, ...]] = {
    "WheelEncoders": ("ticks_left", "ticks_right", "sample_time", "status"),
    "MotorFeedback": ("current", "vbat", "u_applied", "status"),
    "RangeReading": ("distance", "status", "sample_time"),
    "FirmwareHeartbeat": ("state", "faults", "cmd_errors"),
}


def solver_failure(out: CycleOutputs) -> Failure | None:
    """The cycle's solver failure (status, iterations), None when it solved or did not
    solve (hold, an external command source, the controller raised)."""
    c = out.control
    if c is None or not (c.fallback_reason or "").startswith("solver_"):
        return None
    return (c.solver_status, c.solve_iterations)


def encode_cycle(inp: CycleInputs, failure: Failure | None = None) -> str:
    """One cycle's inputs (and the car's solver failure) as a JSON line (no newline)."""
    rx = []
    for r in inp.received:
        kind = type(r.msg).__name__
        values = (getattr(r.msg, f) for f in _FIELDS[kind])
        rx.append([r.t, r.name, kind, [v if isinstance(v, float) else int(v) for v in values]])
    row: list[Any] = [inp.now, inp.link_up, inp.loop_missed, rx]
    extra: list[Any] = [
        None if inp.lead_forecast is None else list(inp.lead_forecast),
        inp.headway,
        None if failure is None else [failure[0], failure[1]],
    ]
    while extra and extra[-1] is None:
        extra.pop()
    return json.dumps(row + extra, separators=(",", ":"))


def decode_record(line: str, where: str) -> tuple[CycleInputs, Failure | None]:
    """A JSON line back into the cycle's inputs and the car's solver failure (InputError
    naming ``where``)."""
    try:
        row = json.loads(line)
        now, link_up, missed, rx = row[:4]
        received = []
        for t, name, kind, fields in rx:
            cls, conv = _TYPES[kind]
            msg = cls(*(c(v) for c, v in zip(conv, fields, strict=True)))
            received.append(Received(float(t), str(name), msg))
        forecast = [float(x) for x in row[4]] if len(row) > 4 and row[4] is not None else None
        headway = float(row[5]) if len(row) > 5 and row[5] is not None else None
        failure = (str(row[6][0]), int(row[6][1])) if len(row) > 6 and row[6] else None
        inp = CycleInputs(float(now), received, bool(link_up), bool(missed), forecast, headway)
        return inp, failure
    except (ValueError, TypeError, KeyError, IndexError) as exc:
        raise InputError(f"{where}: not a cycle of a {FORMAT} log: {exc}") from None


def decode_cycle(line: str, where: str) -> CycleInputs:
    """A JSON line back into the cycle's inputs (InputError naming ``where``)."""
    return decode_record(line, where)[0]


@dataclass(frozen=True)
class RxRecording:
    """One received-message log: its header and its cycles (inputs, the car's failure)."""

    path: Path
    t0: float
    seq0: int
    params: dict[str, Any]
    records: list[tuple[CycleInputs, Failure | None]]


def read_rx_recording(path: str | Path) -> RxRecording:
    """A received-message log, every line checked (InputError naming the line)."""
    p = Path(path)
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: cannot read: {exc}") from None
    try:
        head = json.loads(lines[0]) if lines else None
    except ValueError:
        head = None
    if not isinstance(head, dict) or head.get("format") not in FORMATS:
        raise InputError(f"{p}: line 1: expected a {FORMAT} header")
    params, t0, seq0 = head.get("params"), head.get("t0"), head.get("seq0", 0)
    if not isinstance(params, dict) or not isinstance(t0, int | float):
        raise InputError(f"{p}: line 1: expected 't0' and 'params' in the header")
    if isinstance(seq0, bool) or not isinstance(seq0, int) or seq0 < 0:
        raise InputError(f"{p}: line 1: expected 'seq0' a cycle number >= 0")
    records = [decode_record(s, f"{p}: line {k}") for k, s in enumerate(lines[1:], 2) if s]
    return RxRecording(p, float(t0), seq0, params, records)


def read_rx_log(path: str | Path) -> tuple[float, dict[str, Any], Iterator[CycleInputs]]:
    """The start time, the parameters and the cycles' inputs of a received-message log."""
    rec = read_rx_recording(path)
    return rec.t0, rec.params, (inp for inp, _ in rec.records)


class RxLog:
    """The received-message log, a sidecar of the CSV
    :class:`~truckd.runtime.recorder.Recorder` (see module docstring): the loop calls
    :meth:`record`; the recorder's thread opens (:meth:`open`, at each rotation), writes,
    flushes and closes it.  Set :attr:`t0` (the run's start) before the first record."""

    suffix = SUFFIX

    def __init__(self, params: Mapping[str, Any], keep: int = 20, maxlen: int = 100_000):
        self.params = dict(params)
        self.keep = keep
        self._q: deque[tuple[int, CycleInputs, Failure | None]] = deque(maxlen=maxlen)
        self._lock = threading.Lock()
        self._fh: TextIO | None = None
        self._header_due = False
        self.files: list[Path] = []
        self.t0 = 0.0
        self.rows = 0
        self.dropped = 0
        self.errors = 0

    @property
    def path(self) -> Path | None:
        """The file being written."""
        return self.files[-1] if self.files else None

    def record(self, inp: CycleInputs, out: CycleOutputs | None = None) -> None:
        """Queue one cycle's inputs, with the cycle number and the solver failure of its
        output (never blocks)."""
        if len(self._q) == self._q.maxlen:
            self.dropped += 1
        if out is None:
            self._q.append((self.rows + len(self._q), inp, None))
        else:
            self._q.append((out.seq, inp, solver_failure(out)))

    def _error(self, what: str, exc: OSError) -> None:
        self.errors += 1
        if self.errors <= 3:
            log.error("received-message log %s failed: %s", what, exc.strerror or exc)

    def open(self, path: Path, rows: int | None = None) -> None:
        """Finish the current file and start ``path`` (the recorder rotated its CSV after
        ``rows`` rows, one per cycle: the cycles before ``rows`` go to the current file
        first, so each file holds the cycles of its CSV)."""
        with self._lock:
            if rows is not None:
                self._write(rows)
            self._finish()
            try:
                self._fh = open(path, "w", encoding="utf-8")  # noqa: SIM115 - kept open
            except OSError as exc:
                self._error(f"open {path}", exc)
                return
            self._header_due = True
            self.files.append(path)
            while len(self.files) > self.keep:
                old = self.files.pop(0)
                try:
                    old.unlink()
                except OSError as exc:
                    log.warning("cannot delete old log %s: %s", old, exc.strerror)

    def write_pending(self, rows: int | None = None) -> None:
        """Write the queued cycles (the header first, once the run has started): those
        before cycle ``rows`` when given (the CSV's rows so far, one per cycle: this file
        never runs ahead of its CSV, so each holds its CSV's cycles), else every one."""
        with self._lock:
            self._write(rows)

    def _write(self, upto: int | None) -> None:
        """Write the queued cycles (those before cycle ``upto`` when given)."""
        fh = self._fh
        if fh is None:
            self.dropped += len(self._q)
            self._q.clear()
            return
        last_yield = time.perf_counter()
        try:
            while self._q and (upto is None or self._q[0][0] < upto):
                now = time.perf_counter()
                if now - last_yield > YIELD_S:  # let a waking loop thread take the GIL
                    time.sleep(0)
                    last_yield = time.perf_counter()
                seq, inp, failure = self._q.popleft()
                if self._header_due:
                    head = {"format": FORMAT, "t0": self.t0, "seq0": seq}
                    fh.write(json.dumps({**head, "params": self.params}) + "\n")
                    self._header_due = False
                fh.write(encode_cycle(inp, failure) + "\n")
                self.rows += 1
        except OSError as exc:
            self._error("write", exc)

    def flush(self, force: bool = False) -> None:
        """Hand what is written to the OS."""
        with self._lock:
            if self._fh is not None:
                try:
                    self._fh.flush()
                except OSError as exc:
                    self._error("flush", exc)

    def _finish(self) -> None:
        fh, self._fh = self._fh, None
        if fh is None:
            return
        try:
            fh.close()
        except OSError as exc:
            self._error("close", exc)
        if self._header_due and self.files:  # nothing was recorded: no empty file left
            self.files.pop().unlink(missing_ok=True)
        self._header_due = False

    def close(self) -> None:
        """Write what is queued and close (idempotent)."""
        self.write_pending()
        with self._lock:
            self._finish()

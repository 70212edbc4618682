"""The received-message log (a sidecar of the CSV log) that makes a run replayable.

The CSV log (reference section 3) holds what the daemon did; this file holds what it
heard: every cycle's inputs to :class:`~truckd.runtime.cycle.CompanionCycle` (the time,
the checked messages with their arrival times, the link state and the loop's deadline
verdict), so :mod:`truckd.runtime.replay` can feed them through the same step again and
compare the commands (as openpilot replays its logs).  JSON lines, floats in full
precision (``repr``), written by a background thread (the loop only appends to a deque):

- line 1: ``{"format": "truckd-rx/1", "t0": T0, "params": {...}}``: the start of the run
  on the caller's clock (s) and the parameters in use (the daemon's ``params``
  queryable: model, control, runtime, ticks per revolution);
- then one line per cycle: ``[now, link_up, loop_missed, [[t, name, type, [fields]], ...]]``
  and, when the cycle had a lead forecast or a headway (a platoon follower), a fifth
  element with the forecast (m/s per period, or null) and a sixth with the headway (s).

Off unless ``runtime.recorder.messages`` is true; not rotated (it grows by about 20 kB/s
at 100 Hz).
"""

from __future__ import annotations

import json
import logging
import threading
from collections import deque
from collections.abc import Callable, Iterator, Mapping
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
from truckd.errors import InputError, TruckdError
from truckd.io.port import Received
from truckd.runtime.cycle import CycleInputs

log = logging.getLogger("truckd.rxlog")

FORMAT = "truckd-rx/1"

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


def encode_cycle(inp: CycleInputs) -> str:
    """One cycle's inputs as a JSON line (without the newline)."""
    rx = []
    for r in inp.received:
        kind = type(r.msg).__name__
        values = (getattr(r.msg, f) for f in _FIELDS[kind])
        rx.append([r.t, r.name, kind, [v if isinstance(v, float) else int(v) for v in values]])
    row: list[Any] = [inp.now, inp.link_up, inp.loop_missed, rx]
    if inp.lead_forecast is not None or inp.headway is not None:
        row.append(None if inp.lead_forecast is None else list(inp.lead_forecast))
    if inp.headway is not None:
        row.append(inp.headway)
    return json.dumps(row, separators=(",", ":"))


def decode_cycle(line: str, where: str) -> CycleInputs:
    """A JSON line back into the cycle's inputs (InputError naming ``where``)."""
    try:
        row = json.loads(line)
        now, link_up, missed, rx = row[:4]
        received = []
        for t, name, kind, fields in rx:
            cls, conv = _TYPES[kind]
            msg = cls(*(c(v) for c, v in zip(conv, fields, strict=True)))
            received.append(Received(float(t), str(name), msg))
        forecast = [float(x) for x in row[4]] if len(row) > 4 and row[4] is not None else None
        headway = float(row[5]) if len(row) > 5 else None
        return CycleInputs(float(now), received, bool(link_up), bool(missed), forecast, headway)
    except (ValueError, TypeError, KeyError, IndexError) as exc:
        raise InputError(f"{where}: not a cycle of a {FORMAT} log: {exc}") from None


def read_rx_log(path: str | Path) -> tuple[float, dict[str, Any], Iterator[CycleInputs]]:
    """The start time, the parameters and the cycles' inputs of a received-message log."""
    p = Path(path)
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: cannot read: {exc}") from None
    try:
        head = json.loads(lines[0]) if lines else None
    except ValueError:
        head = None
    if not isinstance(head, dict) or head.get("format") != FORMAT:
        raise InputError(f"{p}: line 1: expected a {FORMAT} header")
    params, t0 = head.get("params"), head.get("t0")
    if not isinstance(params, dict) or not isinstance(t0, int | float):
        raise InputError(f"{p}: line 1: expected 't0' and 'params' in the header")
    cycles = (decode_cycle(s, f"{p}: line {k}") for k, s in enumerate(lines[1:], 2) if s)
    return float(t0), params, cycles


class RxLog:
    """Background writer of the received-message log (see module docstring).  Set
    :attr:`t0` (the run's start) before the first :meth:`record`."""

    def __init__(self, path: Path, params: Mapping[str, Any], flush_period_s: float = 1.0):
        self.path = path
        self.params = dict(params)
        self.flush_period_s = max(flush_period_s, 0.01)
        self._q: deque[CycleInputs] = deque(maxlen=100_000)
        self._event = threading.Event()
        self._stop = False
        self._thread: threading.Thread | None = None
        self._fh: TextIO | None = None
        self._header_written = False
        self.t0 = 0.0
        self.rows = 0
        self.dropped = 0
        self.errors = 0

    def start(self) -> None:
        try:
            self._fh = open(self.path, "w", encoding="utf-8")  # noqa: SIM115 - kept open
        except OSError as exc:
            raise TruckdError(f"cannot write {self.path}: {exc.strerror}") from None
        self._thread = threading.Thread(target=self._run, name="truckd-rxlog", daemon=True)
        self._thread.start()

    def record(self, inp: CycleInputs) -> None:
        """Queue one cycle's inputs (never blocks)."""
        if len(self._q) == self._q.maxlen:
            self.dropped += 1
        self._q.append(inp)
        if len(self._q) >= 64:
            self._event.set()

    def _write_pending(self) -> None:
        fh = self._fh
        if fh is not None and not self._header_written and (self._q or self._stop):
            fh.write(json.dumps({"format": FORMAT, "t0": self.t0, "params": self.params}) + "\n")
            self._header_written = True
        while fh is not None and self._q:
            fh.write(encode_cycle(self._q.popleft()) + "\n")
            self.rows += 1

    def _run(self) -> None:
        while True:
            self._event.wait(self.flush_period_s)
            self._event.clear()
            try:
                self._write_pending()
                if self._fh is not None:
                    self._fh.flush()
            except OSError as exc:
                self.errors += 1
                if self.errors <= 3:
                    log.error("received-message log write failed: %s", exc.strerror)
            if self._stop:
                return

    def stop(self) -> None:
        """Write everything queued, flush and close (idempotent)."""
        self._stop = True
        self._event.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._fh is not None:
            try:
                self._write_pending()
                self._fh.close()
            except OSError as exc:
                log.error("received-message log close failed: %s", exc.strerror)
            self._fh = None

"""``truckd monitor``: a live table of every vehicle reachable over Zenoh.

:class:`FleetView` is pure (samples in, table out); :func:`run_monitor` wires it to a Zenoh
session: subscribers on ``truckd/*/state`` and ``truckd/*/health`` and a liveliness
subscriber (with history) on ``truckd/*/alive``.  A vehicle whose token goes is shown
``offline`` until it comes back.
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, TextIO

import zenoh

from truckd.runtime.platoon_view import platoon_lines
from truckd.runtime.telemetry import open_session, zenoh_config


@dataclass
class VehicleView:
    """What the monitor knows about one vehicle."""

    vehicle_id: str
    online: bool = False
    state: dict[str, Any] = field(default_factory=dict)
    health: dict[str, Any] = field(default_factory=dict)
    state_count: int = 0
    last_state_t: float = -math.inf  # local monotonic time of the last state sample


def _vid(key: str) -> str | None:
    parts = key.split("/")
    return parts[1] if len(parts) == 3 and parts[0] == "truckd" else None


def _num(x: Any, fmt: str) -> str:
    if isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x):
        return format(x, fmt)
    return "-"


class FleetView:
    """Vehicles seen so far (thread-safe: Zenoh callbacks run on its own threads)."""

    COLUMNS = ("vehicle", "status", "mode", "v m/s", "gap m", "gap err m", "solve us",
               "late p99 us", "rate Hz", "faults")  # fmt: skip

    def __init__(self) -> None:
        self.vehicles: dict[str, VehicleView] = {}
        self._lock = threading.Lock()

    def _get(self, vid: str) -> VehicleView:
        if vid not in self.vehicles:
            self.vehicles[vid] = VehicleView(vid)
        return self.vehicles[vid]

    def on_sample(self, key: str, payload: bytes, now: float) -> None:
        """A state or health sample arrived."""
        vid = _vid(key)
        if vid is None:
            return
        try:
            msg = json.loads(payload)
        except ValueError:
            return
        if not isinstance(msg, dict):
            return
        with self._lock:
            v = self._get(vid)
            if key.endswith("/state"):
                v.state, v.last_state_t = msg, now
                v.state_count += 1
            elif key.endswith("/health"):
                v.health = msg

    def on_alive(self, key: str, alive: bool) -> None:
        """The vehicle's liveliness token appeared (True) or went (False)."""
        vid = _vid(key)
        if vid is not None:
            with self._lock:
                self._get(vid).online = alive

    def rows(self) -> list[tuple[str, ...]]:
        """One row per vehicle, sorted by id."""
        out: list[tuple[str, ...]] = []
        with self._lock:
            for vid in sorted(self.vehicles):
                v = self.vehicles[vid]
                s, h = v.state, v.health
                gap, ref = s.get("gap"), s.get("gap_ref")
                err = (
                    gap - ref
                    if isinstance(gap, int | float) and isinstance(ref, int | float)
                    else None
                )
                loop = h.get("loop", {}) if isinstance(h.get("loop"), dict) else {}
                faults = h.get("faults", s.get("faults", []))
                out.append(
                    (
                        vid,
                        "online" if v.online else "offline",
                        str(s.get("mode", "-")),
                        _num(s.get("v"), ".2f"),
                        _num(gap, ".3f"),
                        _num(err, "+.3f"),
                        _num(s.get("solve_us"), ".0f"),
                        _num(loop.get("lateness_us_p99"), ".0f"),
                        _num(h.get("state_rate_hz"), ".1f"),
                        ",".join(map(str, faults)) if isinstance(faults, list) and faults else "-",
                    )
                )
        return out

    def render(self) -> str:
        """The table as text."""
        rows = [self.COLUMNS, *self.rows()]
        widths = [max(len(r[i]) for r in rows) for i in range(len(self.COLUMNS))]
        lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) for r in rows]
        if len(rows) == 1:
            lines.append("(no vehicle seen yet)")
        with self._lock:
            lines += platoon_lines({k: (v.state, v.health) for k, v in self.vehicles.items()})
        return "\n".join(lines)


def run_monitor(
    connect: Sequence[str],
    zenoh_file: str,
    out: TextIO,
    *,
    duration: float | None,
    interval: float,
    clear: bool,
    clock: Callable[[], float] = time.monotonic,
) -> FleetView:
    """Show the fleet table every ``interval`` s until ``duration`` (None: forever)."""
    view = FleetView()
    conf = zenoh_config(zenoh_file, listen=[], connect=list(connect), names=("", "--connect"))
    session = open_session(conf, "monitor")

    def on_data(sample: zenoh.Sample) -> None:
        view.on_sample(str(sample.key_expr), sample.payload.to_bytes(), clock())

    def on_alive(sample: zenoh.Sample) -> None:
        view.on_alive(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

    subs = [
        session.declare_subscriber("truckd/*/state", on_data),
        session.declare_subscriber("truckd/*/health", on_data),
        session.liveliness().declare_subscriber("truckd/*/alive", on_alive, history=True),
    ]
    t_end = None if duration is None else clock() + duration
    try:
        while t_end is None or clock() < t_end:
            time.sleep(interval if t_end is None else max(0.0, min(interval, t_end - clock())))
            text = view.render()
            out.write(("\x1b[H\x1b[2J" if clear else "") + text + "\n\n")
            out.flush()
    finally:
        for s in subs:
            s.undeclare()  # type: ignore[no-untyped-call]
        session.close()  # type: ignore[no-untyped-call]
    return view

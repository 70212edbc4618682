r"""``truckd monitor``: a live table of every vehicle reachable over Zenoh.

:class:`FleetView` is pure (samples in, table out); :func:`run_monitor` wires it to a Zenoh
session: subscribers on ``truckd/*/state``, ``truckd/*/health`` and
``truckd/*/characterize`` (the progress of ``truckd characterize``: a line under the
table) and a liveliness subscriber (with history) on ``truckd/*/alive``.  A vehicle
whose token goes is shown ``offline`` with its mode ``unknown`` (and no live values) until
it comes back; one whose token stays but whose state stops for :data:`STALE_S` is shown
``stale`` the same way.

Everything shown comes from the network and is untrusted: :func:`safe_text` escapes
control and formatting characters (C0, DEL, C1, bidi overrides, zero-width: ``\x1b``
is shown as the four characters ``\x1b``) and bounds each field's length, and at most
:data:`MAX_VEHICLES` vehicles are tracked.  The table says when no peer is connected
(endpoint unreachable; Zenoh keeps retrying).
"""

from __future__ import annotations

import json
import math
import threading
import time
import unicodedata
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, TextIO

import zenoh

from truckd.runtime.platoon_view import platoon_lines
from truckd.runtime.stopping import stop_signals, ticks
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
    characterize: dict[str, Any] = field(default_factory=dict)
    """The last ``truckd characterize`` progress (stage, experiment, percent), if any."""


MAX_VEHICLES = 256
"""Vehicles tracked at most (samples from further ids are counted and ignored)."""

STALE_S = 2.0
"""A vehicle online (token held) whose last state sample is older than this (s) is shown
``stale``: its session lives but its loop publishes nothing (hung, or stopped)."""

FIELD_MAX = 32
"""Characters shown at most per text field (vehicle id, mode, one fault)."""


def _escape(o: int) -> str:
    return f"\\x{o:02x}" if o < 0x100 else f"\\u{o:04x}" if o < 0x10000 else f"\\U{o:08x}"


def safe_text(x: object, limit: int = FIELD_MAX) -> str:
    r"""``x`` as printable text for a terminal: control and formatting characters
    escaped (``\xNN``, ``\uNNNN``), at most ``limit`` characters (``...`` marks a cut)."""
    text = x if isinstance(x, str) else str(x)
    text = text[: limit * 4]  # bound the work before escaping
    out: list[str] = []
    for ch in text:
        cat = unicodedata.category(ch)
        if cat[0] == "C" or cat in ("Zl", "Zp"):
            out.append(_escape(ord(ch)))
        else:
            out.append(ch)
    s = "".join(out)
    return s if len(s) <= limit else s[: limit - 3] + "..."


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
        self.ignored = 0  # samples of vehicles beyond MAX_VEHICLES
        self.connected: bool | None = None  # None: unknown (no session)
        self.endpoints: tuple[str, ...] = ()
        self._lock = threading.Lock()

    def _get(self, vid: str) -> VehicleView | None:
        v = self.vehicles.get(vid)
        if v is None:
            if len(self.vehicles) >= MAX_VEHICLES:
                self.ignored += 1
                return None
            v = self.vehicles[vid] = VehicleView(vid)
        return v

    def on_sample(self, key: str, payload: bytes, now: float) -> None:
        """A state or health sample arrived."""
        vid = _vid(key)
        if vid is None:
            return
        try:
            # Integers as floats: a 400-digit one from a peer became inf, not an
            # OverflowError in every later render (it killed the monitor).
            msg = json.loads(payload, parse_int=float)
        except (ValueError, RecursionError):  # not JSON, or nested beyond the stack
            return
        if not isinstance(msg, dict):
            return
        with self._lock:
            v = self._get(vid)
            if v is None:
                return
            if key.endswith("/state"):
                v.state, v.last_state_t = msg, now
                v.state_count += 1
            elif key.endswith("/health"):
                v.health = msg
            elif key.endswith("/characterize"):
                v.characterize = msg

    def on_alive(self, key: str, alive: bool) -> None:
        """The vehicle's liveliness token appeared (True) or went (False)."""
        vid = _vid(key)
        if vid is not None:
            with self._lock:
                v = self._get(vid)
                if v is not None:
                    v.online = alive

    def rows(self, now: float | None = None) -> list[tuple[str, ...]]:
        """One row per vehicle, sorted by id; every text field made safe (see
        :func:`safe_text`).  An offline vehicle's mode is ``unknown``, its values ``-``."""
        out: list[tuple[str, ...]] = []
        with self._lock:
            for vid in sorted(self.vehicles):
                v = self.vehicles[vid]
                stale = now is not None and now - v.last_state_t > STALE_S
                if not v.online or stale:
                    status = "offline" if not v.online else "stale"
                    out.append((safe_text(vid), status, "unknown", *["-"] * 7))
                    continue
                s, h = v.state, v.health
                gap, ref = s.get("gap"), s.get("gap_ref")
                err = (
                    gap - ref
                    if isinstance(gap, int | float) and isinstance(ref, int | float)
                    else None
                )
                loop = h.get("loop", {}) if isinstance(h.get("loop"), dict) else {}
                faults = h.get("faults", s.get("faults", []))
                pl = h.get("platoon")
                if isinstance(pl, dict) and pl.get("plan_flood") is True:
                    # a peer floods the plan key: the daemon drops what it cannot use
                    faults = [*(faults if isinstance(faults, list) else []), "plan_flood"]
                fault_text = (
                    safe_text(",".join(safe_text(f) for f in faults[:8]), 4 * FIELD_MAX)
                    if isinstance(faults, list) and faults
                    else "-"
                )
                out.append(
                    (
                        safe_text(vid),
                        "online",
                        safe_text(s.get("mode", "-")),
                        _num(s.get("v"), ".2f"),
                        _num(gap, ".3f"),
                        _num(err, "+.3f"),
                        _num(s.get("solve_us"), ".0f"),
                        _num(loop.get("lateness_us_p99"), ".0f"),
                        _num(h.get("state_rate_hz"), ".1f"),
                        fault_text,
                    )
                )
        return out

    def characterize_lines(self) -> list[str]:
        """One line per vehicle running ``truckd characterize``: stage, experiment, percent."""
        out = []
        with self._lock:
            for vid in sorted(self.vehicles):
                c = self.vehicles[vid].characterize
                if c:
                    exp = c.get("experiment")
                    what = f" {safe_text(exp)}" if exp else ""
                    out.append(
                        f"{safe_text(vid)} characterize: {safe_text(c.get('stage', '-'))}{what} "
                        f"{_num(c.get('percent'), '.0f')} %"
                    )
        return out

    def render(self, now: float | None = None) -> str:
        """The table as text (``now``: local monotonic time, s, to judge staleness)."""
        rows = [self.COLUMNS, *self.rows(now)]
        widths = [max(len(r[i]) for r in rows) for i in range(len(self.COLUMNS))]
        lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) for r in rows]
        if len(rows) == 1:
            lines.append("(no vehicle seen yet)")
        with self._lock:
            chains = platoon_lines({k: (v.state, v.health) for k, v in self.vehicles.items()})
        lines += [safe_text(c, 400) for c in chains]  # ids and modes come from the network
        lines += self.characterize_lines()
        if self.ignored:
            lines.append(f"({self.ignored} samples of more than {MAX_VEHICLES} vehicles ignored)")
        if self.connected is False:
            where = ", ".join(safe_text(e, 80) for e in self.endpoints) or "any endpoint"
            lines.append(f"not connected: {where} unreachable (retrying)")
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
    """Show the fleet table every ``interval`` s until ``duration`` (None: until SIGTERM,
    which ends it normally, or Ctrl-C, which raises KeyboardInterrupt:
    :mod:`truckd.runtime.stopping`)."""
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
        session.declare_subscriber("truckd/*/characterize", on_data),
        session.liveliness().declare_subscriber("truckd/*/alive", on_alive, history=True),
    ]
    view.endpoints = tuple(connect)
    with stop_signals():
        try:
            for _ in ticks(interval, duration, clock):
                info = session.info
                view.connected = bool(info.peers_zid() or info.routers_zid())
                text = view.render(clock())
                out.write(("\x1b[H\x1b[2J" if clear else "") + text + "\n\n")
                out.flush()
        finally:
            for s in subs:
                s.undeclare()  # type: ignore[no-untyped-call]
            session.close()  # type: ignore[no-untyped-call]
    return view

"""Receive checks on decoded frames, like opendbc / panda safety: checksum, counter
continuity and freshness per message, with error statistics.

A frame that fails a check is never handed on as data.  Counter rules (per message):
a frame whose counter equals the last accepted one (a stuck sender or a replay) is
always rejected; otherwise the first frame, or the first after a timeout, is accepted
as is; a forward jump of up to :data:`MAX_DELTA` counts the missing frames in
``counter_gaps`` and adds 1 to a per-message score (capped at twice
``max_wrong_counters``), an in-sequence frame subtracts 1; frames are accepted only
while the score is at most ``max_wrong_counters`` (a broken counter is rejected until
enough in-sequence frames have arrived).  On the side that drives the motor
(``resync`` = :data:`RESYNC`, the microcontroller's receive of commands; the C firmware
does the same), a larger jump, forward or back, while the message is fresh is a replay
or a broken sender: rejected, and so is every frame after it until ``resync`` frames in
a row have run in sequence (each within :data:`MAX_DELTA` of the one before), timeouts
included.  (The companion's receive of sensor data keeps the tolerant rule: a burst of
lost frames must not blind it for 160 ms; a replayed sensor sample repeats its sample
time and goes stale there.)  The last frames replayed in a
loop (counters 6, 7, 6, 7, ...) were accepted before, every in-sequence one refreshing
the command timeout: the motor stayed driven.  A loop of 13 frames or more cannot be
told from a sender with a 4-bit counter that lost a few (its wrap is a jump of at most
:data:`MAX_DELTA`).

Time is passed in (``now``, s, any monotonic clock or simulated time): no clock here.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import asdict, dataclass, field

from firmware_protocol.codec import Decoded, DecodeError, Frame, decode, specs
from firmware_protocol.timing import timing

MAX_DELTA = timing().counter_max_delta
"""The largest forward counter jump taken as lost frames (two lost in a row; truck.dbc's
``TruckCounterMaxDelta``)."""
RESYNC = timing().counter_resync
"""In-sequence frames needed after a larger jump before frames are accepted again (more
than any replay loop a 4-bit counter can tell; truck.dbc's ``TruckCounterResync``)."""
COUNTER_MODULO = timing().counter_modulo
"""COUNTER counts 0 .. COUNTER_MODULO - 1 (the width of truck.dbc's COUNTER signals)."""


@dataclass
class RxStats:
    """Receive error statistics (counts since start)."""

    frames_ok: int = 0
    checksum_errors: int = 0
    length_errors: int = 0
    unknown_ids: int = 0
    payload_errors: int = 0
    counter_errors: int = 0
    """Frames rejected by the counter rule (repeated counter or broken counter)."""
    counter_gaps: int = 0
    """Frames known missing from counter jumps."""
    timeouts: int = 0
    """Fresh -> stale transitions of any expected message."""
    unexpected: int = 0
    """Valid frames of a message this side does not expect (e.g. its own messages)."""

    def as_dict(self) -> dict[str, int]:
        """The counters as a JSON-ready dict."""
        return asdict(self)


@dataclass
class _MsgState:
    period: float
    timeout: float
    last_counter: int | None = None
    last_rx: float | None = None
    wrong_counters: int = 0
    stale: bool = True
    count: int = 0
    resync: int = 0
    """Frames still to run in sequence before one is accepted (after a large jump)."""
    chain: int = 0
    """The counter of the last frame of that run."""


@dataclass
class RxChecker:
    """Stateful receive checks for the messages one side expects.

    ``expect``: DBC names this side receives; ``timeout_periods``: freshness timeout as a
    multiple of each message's period; ``max_wrong_counters``: see module docstring.
    """

    expect: Iterable[str]
    timeout_periods: float = float(timing().freshness_periods)
    max_wrong_counters: int = timing().counter_max_wrong
    stats: RxStats = field(default_factory=RxStats)
    resync: int = 0
    """In-sequence frames needed after a jump beyond :data:`MAX_DELTA` (0: no such rule)."""

    def __post_init__(self) -> None:
        all_specs = specs()
        self._state: dict[str, _MsgState] = {}
        for name in self.expect:
            if name not in all_specs:
                raise ValueError(f"unknown message {name!r}; truck.dbc has {sorted(all_specs)}")
            period = all_specs[name].period
            self._state[name] = _MsgState(period, self.timeout_periods * period)

    def accept(self, frame: Frame, now: float) -> Decoded | None:
        """The decoded message if the frame passes every check, else None (counted)."""
        st = self.stats
        try:
            dec = decode(frame)
        except DecodeError as exc:
            if exc.reason == "checksum":
                st.checksum_errors += 1
            elif exc.reason == "length":
                st.length_errors += 1
            elif exc.reason == "unknown_id":
                st.unknown_ids += 1
            else:
                st.payload_errors += 1
            return None
        ms = self._state.get(dec.name)
        if ms is None:
            st.unexpected += 1
            return None
        self._expire(ms, now)
        if ms.last_counter is not None and dec.counter == ms.last_counter:
            st.counter_errors += 1  # stuck sender or replay, even after a timeout
            return None
        if ms.resync > 0:  # after a large jump: a run of in-sequence frames first
            step = (dec.counter - ms.chain) % COUNTER_MODULO
            ms.resync = ms.resync - 1 if 1 <= step <= MAX_DELTA else self.resync
            ms.chain = dec.counter
            if ms.resync > 0:
                st.counter_errors += 1
                return None
            # the run restarts the sequence, as after a timeout: accepted below, unscored
        elif ms.last_counter is not None and not ms.stale:
            jump = (dec.counter - ms.last_counter) % COUNTER_MODULO
            if self.resync and jump > MAX_DELTA:
                ms.resync, ms.chain = self.resync, dec.counter
                st.counter_errors += 1
                return None
            ms.last_counter = dec.counter
            if jump != 1:
                st.counter_gaps += jump - 1
                ms.wrong_counters = min(ms.wrong_counters + 1, 2 * self.max_wrong_counters)
            elif ms.wrong_counters > 0:
                ms.wrong_counters -= 1
            if ms.wrong_counters > self.max_wrong_counters:
                st.counter_errors += 1
                return None
        ms.last_counter = dec.counter
        ms.last_rx = now
        ms.stale = False
        ms.count += 1
        st.frames_ok += 1
        return dec

    def _expire(self, ms: _MsgState, now: float) -> None:
        if not ms.stale and ms.last_rx is not None and now - ms.last_rx > ms.timeout:
            ms.stale = True
            ms.wrong_counters = 0
            self.stats.timeouts += 1

    def poll_timeouts(self, now: float) -> None:
        """Update freshness of every expected message (counts timeouts)."""
        for ms in self._state.values():
            self._expire(ms, now)

    def fresh(self, name: str, now: float) -> bool:
        """True when ``name`` was accepted within its timeout before ``now``."""
        ms = self._state[name]
        self._expire(ms, now)
        return not ms.stale

    def age(self, name: str, now: float) -> float | None:
        """Seconds since ``name`` was last accepted (None if never)."""
        ms = self._state[name]
        return None if ms.last_rx is None else now - ms.last_rx

    def freshness(self, now: float) -> dict[str, bool]:
        """Freshness of every expected message by name."""
        return {name: self.fresh(name, now) for name in self._state}

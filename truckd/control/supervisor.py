"""The supervisor: the daemon's operating mode from sensor freshness, link health, solver
status and loop timing.  Pure: plain inputs each cycle (times in seconds from the caller's
clock), a :class:`Decision` out; no clock, no I/O.

Modes (the daemon maps them to commands):

- ``INIT``: start-up, until the link is up and encoder and range data are fresh; motor off.
  Also after a loop stall (:meth:`Supervisor.restart`: ``loop_stall`` for ``recovery_s``).
- ``ACTIVE``: everything fresh and healthy; the controller drives.
- ``DEGRADED``: still driving, with something wrong that the controller can cover: the
  solver failed ``solver_degrade_after`` cycles in a row (the controller's fallback is in
  use), the loop missed ``overrun_degrade_after`` deadlines in a row, or the lead is lost
  and the lead-lost action is ``cruise``.  Single failures and misses are only counted
  (the controller's held plan covers one failed solve).
- ``SAFE_STOP``: a controlled stop (voltage ramped to zero): encoder or link stale, no own
  speed from the encoder data arriving for twice the encoder timeout (the estimator
  refused it, e.g. the wheels failing in turn or the counters jumping: ``speed_stale``), range
  sensor stale, frozen or reporting a fault, the solver failing ``solver_fail_limit`` cycles
  in a row, the loop overrunning ``overrun_limit`` cycles in a row, the lead lost with
  action ``stop``, or the motor stalled (``motor_stalled``: commanded at least
  ``stall_command_v`` for ``stall_s`` while the truck stands; held ``stall_cooldown_s``,
  a stalled RS-540 draws some 80 A).
- ``FAULT``: the link is down (device gone, bus off): motor off, nothing to command
  through.  (The firmware's own fault bits are published in health, not acted on here:
  the firmware already switches the motor off on its command timeout.)

The mode is decided on every call, so a stop starts on the cycle the staleness is detected.
Leaving a degraded mode for ``ACTIVE`` needs every cause clear for ``recovery_s``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import astuple, dataclass, field
from enum import StrEnum

from truckd.control.frozen import fast_init
from truckd.schema import spec


class Mode(StrEnum):
    """Operating modes, ordered by severity (see module docstring)."""

    INIT = "INIT"
    ACTIVE = "ACTIVE"
    DEGRADED = "DEGRADED"
    SAFE_STOP = "SAFE_STOP"
    FAULT = "FAULT"


def time_in_modes(modes: Sequence[str], dt: float) -> dict[str, float]:
    """Seconds spent in each supervisor mode (every mode named) of a run whose cycle
    ``k`` (period ``dt`` s) was in ``modes[k]``."""
    return {m.value: round(list(modes).count(m.value) * dt, 9) for m in Mode}


_SEVERITY = {Mode.ACTIVE: 0, Mode.DEGRADED: 1, Mode.SAFE_STOP: 2, Mode.FAULT: 3, Mode.INIT: 4}

_INIT, _ACTIVE, _DEGRADED, _SAFE_STOP, _FAULT = (
    Mode.INIT, Mode.ACTIVE, Mode.DEGRADED, Mode.SAFE_STOP, Mode.FAULT
)  # fmt: skip
"""The modes as module constants (an attribute of the enum class goes through its
metaclass's ``__getattr__`` hook: several times a global's cost, every cycle)."""

_BLOCKING = (_SAFE_STOP, _FAULT)
_NOT_BLOCKING_INIT = frozenset({"solver_failed", "loop_overrun", "lead_lost"})
_RANGE_CAUSES = frozenset({"range_stale", "range_frozen", "range_fault"})


@dataclass(frozen=True)
class SupervisorConfig:
    """Thresholds of the supervisor."""

    encoder_timeout_s: float = spec(
        "encoder data older than this is stale",
        unit="s",
        lo=0.0,
        lo_open=True,
        hi=10.0,
        default=0.05,
    )
    range_timeout_s: float = spec(
        "range data older than this is stale",
        unit="s",
        lo=0.0,
        lo_open=True,
        hi=10.0,
        default=0.15,
    )
    link_timeout_s: float = spec(
        "no valid message for this long: link stale",
        unit="s",
        lo=0.0,
        lo_open=True,
        hi=10.0,
        default=0.05,
    )
    range_frozen_s: float = spec(
        "range value bit-identical for this much driving time: frozen sensor (a stuck "
        "sensor whose firmware still stamps new sample times); 0 = off (only for a "
        "noise-free sensor, which holds one value while following steadily)",
        unit="s",
        lo=0.0,
        hi=60.0,
        default=1.0,
    )
    frozen_min_speed: float = spec(
        "frozen-range check only while faster than this", unit="m/s", lo=0.0, default=0.05
    )
    solver_degrade_after: int = spec(
        "consecutive solver failures before DEGRADED (one is covered by the held plan)",
        lo=1,
        hi=1000,
        default=2,
    )
    solver_fail_limit: int = spec(
        "consecutive solver failures before a controlled stop", lo=1, hi=1000, default=10
    )
    overrun_degrade_after: int = spec(
        "consecutive deadline misses before DEGRADED (single misses are only counted)",
        lo=1,
        hi=1000,
        default=2,
    )
    overrun_limit: int = spec(
        "consecutive deadline misses before a controlled stop", lo=1, hi=1000, default=5
    )
    recovery_s: float = spec(
        "every cause clear this long before returning to ACTIVE",
        unit="s",
        lo=0.0,
        hi=60.0,
        default=0.5,
    )
    stall_command_v: float = spec(
        "a motor commanded at least this (|V|) while the truck stands (|speed| below "
        "frozen_min_speed) for stall_s is stalled: SAFE_STOP (motor_stalled); 0 = off",
        unit="V",
        lo=0.0,
        hi=100.0,
        default=3.0,
    )
    stall_s: float = spec(
        "how long a commanded motor may stand before it is stalled",
        unit="s",
        lo=0.0,
        lo_open=True,
        hi=60.0,
        default=1.5,
    )
    stall_cooldown_s: float = spec(
        "a stall holds SAFE_STOP this long before the motor may be commanded again (the "
        "winding cools; a truck held by a wall or a wrong model is not retried at once)",
        unit="s",
        lo=0.0,
        hi=600.0,
        default=5.0,
    )

    def validate(self) -> str | None:
        return None


@fast_init
@dataclass(frozen=True)
class SupervisorInputs:
    """What the supervisor sees each cycle.  Ages in seconds (``inf`` = never received)."""

    t: float
    link_up: bool
    link_age: float
    encoder_age: float
    range_age: float
    range_value: float | None = None
    range_fault: bool = False
    """The range sensor reports a fault (not the same as no target in range)."""
    speed: float = 0.0
    speed_age: float = 0.0
    """Time since the estimator last took an encoder measurement (s; ``inf`` never)."""
    lead_valid: bool = True
    solver_ok: bool = True
    loop_missed: bool = False
    command: float = 0.0
    """The motor command sent last cycle (V): with the truck standing, a stall."""


@dataclass(frozen=True)
class Transition:
    """A mode change: when, from, to, and the causes active at that moment."""

    t: float
    old: Mode
    new: Mode
    causes: tuple[str, ...]

    def as_dict(self) -> dict[str, object]:
        return {
            "t": self.t,
            "from": self.old.value,
            "to": self.new.value,
            "causes": list(self.causes),
        }


@fast_init
@dataclass(frozen=True)
class Decision:
    """The supervisor's output for one cycle."""

    mode: Mode
    causes: tuple[str, ...]
    transition: Transition | None = None


@dataclass
class _Counters:
    solver_fails: int = 0
    overruns: int = 0
    frozen_time: float = 0.0
    frozen_last_t: float | None = None
    frozen_value: float | None = None
    clear_since: float | None = None
    ever_ready: bool = False
    stall_time: float = 0.0
    stall_last_t: float | None = None
    stall_until: float = -math.inf


def _stale(age: float, timeout: float) -> bool:
    return not (math.isfinite(age) and age <= timeout)


@dataclass
class Supervisor:
    """Mode state machine (see module docstring)."""

    config: SupervisorConfig = field(default_factory=SupervisorConfig)
    lead_lost_action: str = "stop"  # "stop" or "cruise" (the controller's on_lead_lost)
    mode: Mode = Mode.INIT
    transitions: list[Transition] = field(default_factory=list)
    _c: _Counters = field(default_factory=_Counters)
    _restart_until: float = -math.inf
    _last: Decision | None = field(default=None, repr=False, compare=False)
    """The decision returned last (given again while nothing in it changes)."""

    def restart(self, t: float) -> None:
        """Back to ``INIT`` after a loop stall at time ``t`` (s): the cause ``loop_stall``
        holds it for ``recovery_s`` (the restarted estimator sees fresh data), then INIT
        ends as at start-up, once everything is fresh.  A stall's cool-down carries over
        (the winding has not cooled because the loop stalled)."""
        self._c = _Counters(stall_until=self._c.stall_until)
        self._restart_until = t + self.config.recovery_s

    def _frozen(self, t: float, v: float | None, speed: float) -> bool:
        """Range value bit-identical for ``range_frozen_s`` of driving time; latched until
        the value changes (stopping does not clear it)."""
        c, cfg = self._c, self.config
        if cfg.range_frozen_s <= 0.0 or v is None or v != c.frozen_value:
            c.frozen_value, c.frozen_time, c.frozen_last_t = v, 0.0, t
            return False
        moving = math.isfinite(speed) and abs(speed) > cfg.frozen_min_speed
        if moving and c.frozen_last_t is not None:
            c.frozen_time += max(0.0, t - c.frozen_last_t)
        c.frozen_last_t = t
        return c.frozen_time >= cfg.range_frozen_s

    def _causes(
        self,
        t: float,
        link_up: bool,
        link_age: float,
        encoder_age: float,
        range_age: float,
        range_value: float | None,
        range_fault: bool,
        speed: float,
        speed_age: float,
        lead_valid: bool,
        solver_ok: bool,
        loop_missed: bool,
        command: float = 0.0,
    ) -> dict[str, Mode]:
        """Every active cause with the mode it calls for (updates the counters)."""
        cfg, c = self.config, self._c
        c.solver_fails = 0 if solver_ok else c.solver_fails + 1
        c.overruns = c.overruns + 1 if loop_missed else 0
        out: dict[str, Mode] = {}
        isfinite = math.isfinite  # stale: not (isfinite(age) and age <= timeout), inline
        if t <= self._restart_until:
            out["loop_stall"] = _SAFE_STOP
        if not link_up:
            out["link_down"] = _FAULT
        age = link_age
        if not (isfinite(age) and age <= cfg.link_timeout_s):
            out["link_stale"] = _SAFE_STOP
        age = encoder_age
        if not (isfinite(age) and age <= cfg.encoder_timeout_s):
            out["encoder_stale"] = _SAFE_STOP
        elif _stale(speed_age, 2.0 * cfg.encoder_timeout_s):
            # Messages arrive, but no speed from them.  Twice the timeout: the estimator's
            # clock is the cycle's, a little before the messages' receipt stamps, so on
            # silence the root cause, encoder_stale, is named first.
            out["speed_stale"] = _SAFE_STOP
        age = range_age
        if not (isfinite(age) and age <= cfg.range_timeout_s):
            out["range_stale"] = _SAFE_STOP
        if self._frozen(t, range_value, speed):
            out["range_frozen"] = _SAFE_STOP
        if range_fault:
            out["range_fault"] = _SAFE_STOP
        if not lead_valid and not (out and _RANGE_CAUSES & out.keys()):
            out["lead_lost"] = _SAFE_STOP if self.lead_lost_action == "stop" else _DEGRADED
        if c.solver_fails >= cfg.solver_fail_limit:
            out["solver_failed"] = _SAFE_STOP
        elif c.solver_fails >= cfg.solver_degrade_after:
            out["solver_failing"] = _DEGRADED
        if c.overruns >= cfg.overrun_limit:
            out["loop_overrun"] = _SAFE_STOP
        elif c.overruns >= cfg.overrun_degrade_after:
            out["loop_late"] = _DEGRADED
        if self._stalled(t, command, speed, "encoder_stale" in out or "speed_stale" in out):
            out["motor_stalled"] = _SAFE_STOP
        return out

    def _stalled(self, t: float, command: float, speed: float, blind: bool) -> bool:
        """A motor commanded at least ``stall_command_v`` while the truck stands, for
        ``stall_s``; latched for ``stall_cooldown_s`` (the motor is off meanwhile, so the
        condition itself clears at once).  Without a speed (``blind``) nothing is known."""
        c, cfg = self._c, self.config
        if t < c.stall_until:
            c.stall_last_t = t  # the cool-down is no standing time
            return True
        standing = not blind and math.isfinite(speed) and abs(speed) < cfg.frozen_min_speed
        pushing = cfg.stall_command_v > 0.0 and abs(command) >= cfg.stall_command_v
        if not (standing and pushing):
            c.stall_time = 0.0
        elif c.stall_last_t is not None:
            c.stall_time += max(0.0, t - c.stall_last_t)
        c.stall_last_t = t
        if c.stall_time >= cfg.stall_s:
            c.stall_time, c.stall_until = 0.0, t + cfg.stall_cooldown_s
            return True
        return False

    def update(self, x: SupervisorInputs) -> Decision:
        """Decide this cycle's mode (:meth:`decide` of the record's fields, in order)."""
        return self.decide(*astuple(x))

    def decide(
        self,
        t: float,
        link_up: bool,
        link_age: float,
        encoder_age: float,
        range_age: float,
        range_value: float | None = None,
        range_fault: bool = False,
        speed: float = 0.0,
        speed_age: float = 0.0,
        lead_valid: bool = True,
        solver_ok: bool = True,
        loop_missed: bool = False,
        command: float = 0.0,
    ) -> Decision:
        """:meth:`update` of :class:`SupervisorInputs`' fields, in their order and with
        their defaults (the cycle's call: no record built every cycle)."""
        causes = self._causes(
            t,
            link_up,
            link_age,
            encoder_age,
            range_age,
            range_value,
            range_fault,
            speed,
            speed_age,
            lead_valid,
            solver_ok,
            loop_missed,
            command,
        )
        c = self._c
        worst = max(causes.values(), key=_SEVERITY.__getitem__) if causes else _ACTIVE
        if not c.ever_ready:
            # INIT until the first time everything is fresh and the link is up
            blocking = {k for k, m in causes.items() if m in _BLOCKING}
            blocking -= _NOT_BLOCKING_INIT
            if blocking:
                return self._set(t, _INIT, causes)
            c.ever_ready = True
        if worst is _ACTIVE:
            if self.mode is _ACTIVE or (c.ever_ready and self.mode is _INIT):
                c.clear_since = t
                return self._set(t, _ACTIVE, causes)
            if c.clear_since is None:
                c.clear_since = t
            if t - c.clear_since >= self.config.recovery_s:
                return self._set(t, _ACTIVE, causes)
            # hold a driving mode while recovering; a stop/fault holds its stop (as DEGRADED
            # would drive again before the recovery time)
            return self._set(t, self.mode, causes)
        c.clear_since = None
        return self._set(t, worst, causes)

    def _set(self, t: float, mode: Mode, causes: dict[str, Mode]) -> Decision:
        names = tuple(sorted(causes)) if causes else ()
        last = self._last
        if mode is self.mode:
            # The same mode and causes as last time: the same (frozen) decision again, not
            # a new record every cycle.
            if (
                last is not None
                and last.mode is mode
                and last.transition is None
                and last.causes == names
            ):
                return last
            self._last = last = Decision(mode, names)
            return last
        tr = Transition(t, self.mode, mode, names)
        self.transitions.append(tr)
        self.mode = mode
        self._last = last = Decision(mode, names, tr)
        return last

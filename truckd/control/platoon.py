"""Platooning (cooperative adaptive cruise), pure numerics: no I/O, no clock.

Each truck publishes its plan every cycle (reference section 5, ``truckd/<id>/plan``):
the speeds its MPC predicts over the horizon, sampled every ``dt`` from the sender's time
``t``.  A follower turns its predecessor's latest plan into the lead-speed forecast of its
own MPC (:func:`lead_forecast`: shifted by the plan's age, the last speed held past the
plan's end, a braking plan extrapolated to standstill) and drives the CACC headway while
the plan is fresh (and on the last plan, shifted in time, while it is held: a burst of
lost plans); when the plan is older than ``plan_hold_s``, missing, or at odds
with the lead speed the range sensor measures (by more than ``plan_speed_tolerance``) it
falls back to ACC on the range sensor alone, ramping the headway up to the ACC headway
(the gap opens smoothly, no hard braking), and back to CACC once plans have been fresh
for ``cacc_return_s`` (:class:`PlatoonMode`).

Clocks: a plan's ``t`` is the sender's time on the sender's own clock (its truck's clock
in ``truckd sim``, drawn with an offset and drift; the system clock in ``truckd run``).
No clock is assumed to agree with another: with ``clock_sync`` (default) the receiver
estimates the sender's offset and drift from the plans' stamps and arrival times
(:mod:`truckd.control.clocksync`) and restamps each plan on its own clock before it is
aged here.  A plan stamped in the receiver's future by more than ``max_clock_skew_s``
(on the receiver's clock) is refused.
"""

from __future__ import annotations

import itertools
import json
import math
import operator
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from truckd.control.config import ControlConfig
from truckd.control.frozen import fast_init
from truckd.schema import spec

CACC = "CACC"
ACC = "ACC"


@dataclass(frozen=True)
class PlatoonConfig:
    """The ``platoon:`` section: which truck is ahead and the CACC/ACC spacing policies."""

    predecessor: str = spec(
        "vehicle_id of the truck ahead, whose plan this truck follows; empty: no platoon "
        "(leading truck or single truck)",
        default="",
    )
    order: str = spec(
        "whom to follow: fixed (the predecessor above, always; empty: none) or auto (start "
        "behind the predecessor above, or with it empty find the platoon's tail ahead from "
        "the range sensor and the plans heard; then follow the truck that joins in front "
        "and the predecessor's predecessor when the predecessor leaves: docs/platoon.md)",
        choices=("fixed", "auto"),
        default="fixed",
    )
    cacc_headway: float = spec(
        "time headway while the predecessor's plan is fresh (CACC)",
        unit="s",
        lo=0.05,
        hi=5.0,
        default=0.3,
    )
    acc_headway: float = spec(
        "time headway on the range sensor alone (ACC fallback)",
        unit="s",
        lo=0.05,
        hi=5.0,
        default=1.1,
    )
    plan_timeout_s: float = spec(
        "a plan older than this is stale: it no longer counts towards the return to CACC "
        "(cacc_return_s); ACC once it is older than plan_hold_s too",
        unit="s",
        lo=0.0,
        lo_open=True,
        hi=10.0,
        default=0.1,
    )
    plan_hold_s: float = spec(
        "a plan older than plan_timeout_s is still followed until it is this old (CACC on "
        "the plan shifted in time on this truck's clock; past the plan's end on the lead "
        "speed the range sensor measures, when lower): lost plans in bursts are ridden "
        "out; older: ACC.  At most plan_timeout_s (e.g. 0): ACC at plan_timeout_s",
        unit="s",
        lo=0.0,
        hi=10.0,
        default=0.8,
    )
    cacc_return_s: float = spec(
        "plans fresh this long before CACC again (hysteresis)",
        unit="s",
        lo=0.0,
        hi=60.0,
        default=0.5,
    )
    headway_rate: float = spec(
        "headway ramp rate between the two policies (gap opens/closes smoothly)",
        unit="s/s",
        lo=0.0,
        lo_open=True,
        hi=100.0,
        default=0.15,
    )
    max_clock_skew_s: float = spec(
        "plans stamped this far in the receiver's future are refused",
        unit="s",
        lo=0.0,
        hi=10.0,
        default=0.05,
    )
    plan_speed_tolerance: float = spec(
        "a plan whose speed now differs more than this from the lead speed the range "
        "sensor measures is not followed (ACC): it is wrong, or describes another vehicle "
        "than the one ahead (a cut-in)",
        unit="m/s",
        lo=0.0,
        lo_open=True,
        hi=100.0,
        default=0.7,
    )

    clock_sync: bool = spec(
        "estimate the predecessor's clock offset and drift from its plans' stamps and "
        "arrival times, and age plans on this truck's own clock (false: the clocks are "
        "assumed synchronised)",
        default=True,
    )
    q_rel_speed: float = spec(
        "a follower's MPC weight on (v - v_lead)^2 (control.q_rel_speed of a truck in a "
        "platoon, the lead's included in truckd sim): higher than a single truck's, so a "
        "follower's speed follows the predecessor's plan and the headway is regained by "
        "the gap term; the spacing error a speed change leaves is then set by the headway, "
        "alike for every truck, rather than by each truck's own dynamics and model",
        unit="s^2/m^2",
        lo=0.0,
        hi=1e9,
        default=15.0,
    )
    spacing_rate: bool = spec(
        "a follower's q_rel_speed term weighs the rate of its spacing error, "
        "(v + h a - v_lead)^2 with h the CACC headway (control.rel_speed_lookahead), "
        "instead of the relative speed: the gap follows d_0 + h v through the "
        "predecessor's speed changes, spacing errors several times smaller, down to "
        "each link's own noise (where spacing-error string ratios no longer mean "
        "anything: docs/platoon.md)",
        default=False,
    )
    comfort_decel: float = spec(
        "the hardest braking allowed while a gap opens (ACC fallback, room for a "
        "joining truck, a new predecessor); the headway ramp (headway_rate) stays "
        "within it (checked by the join and leave scenarios)",
        unit="m/s^2",
        lo=0.0,
        lo_open=True,
        hi=20.0,
        default=0.5,
    )

    def validate(self) -> str | None:
        """Cross-field check (called by the config loader)."""
        if self.acc_headway < self.cacc_headway:
            return (
                f"acc_headway ({self.acc_headway}) must be at least cacc_headway "
                f"({self.cacc_headway})"
            )
        return None


def follower_control(control: ControlConfig, cfg: PlatoonConfig) -> ControlConfig:
    """The controller configuration of a truck that follows another in a platoon: its MPC
    is built for the CACC headway (the ACC headway is driven by the controller's gap
    shift, see :meth:`~truckd.control.controller.Controller.control`) and with the
    platoon's weight on the relative speed (``q_rel_speed``), or on the spacing error's
    rate (``spacing_rate``)."""
    return replace(
        control,
        time_headway=cfg.cacc_headway,
        q_rel_speed=cfg.q_rel_speed,
        rel_speed_lookahead=cfg.cacc_headway if cfg.spacing_rate else 0.0,
    )


def platoon_control(control: ControlConfig, cfg: PlatoonConfig) -> ControlConfig:
    """The controller configuration of a truck in a platoon: a follower's (a predecessor
    configured, or the order found by the truck itself) is :func:`follower_control`'s;
    others keep theirs."""
    if not cfg.predecessor and cfg.order != "auto":
        return control
    return follower_control(control, cfg)


@fast_init
@dataclass(frozen=True)
class Plan:
    """A truck's plan: ``v[k]`` (m/s) the predicted speed at ``t + k dt`` (s) and ``a[k]``
    (m/s^2) the acceleration over step k (the last one repeated, so both have the same
    length); ``seq`` the sender's cycle counter; ``vehicle_id`` the sender."""

    t: float
    seq: int
    dt: float
    v: tuple[float, ...]
    a: tuple[float, ...]
    vehicle_id: str = ""
    predecessor: str = ""
    """The truck the sender follows (optional key: the platoon's order as the trucks see
    it; "" for a lead, or when not sent)."""

    @property
    def t_end(self) -> float:
        """Time of the plan's last speed (s)."""
        return self.t + (len(self.v) - 1) * self.dt

    def as_dict(self) -> dict[str, Any]:
        """The JSON object of the contract (reference section 5); ``predecessor`` only
        when set."""
        d: dict[str, Any] = {
            "t": self.t,
            "seq": self.seq,
            "dt": self.dt,
            "v": list(self.v),
            "a": list(self.a),
            "vehicle_id": self.vehicle_id,
        }
        if self.predecessor:
            d["predecessor"] = self.predecessor
        return d


def make_plan(t: float, seq: int, dt: float, speeds: Sequence[float], vehicle_id: str = "") -> Plan:
    """A plan from predicted speeds (m/s) at ``t + k dt``; accelerations by differences.
    Negative speeds (a reversing prediction) are clipped to 0."""
    # The element loops run in C (map over operator's functions; no bytecode per
    # element): the plan is made every cycle.
    return plan_of_floats(t, seq, dt, list(map(float, speeds)), vehicle_id)


def plan_of_floats(t: float, seq: int, dt: float, vs: list[float], vehicle_id: str = "") -> Plan:
    """:func:`make_plan` of speeds that are Python floats already (a list the plan may keep
    or change, e.g. an array's ``tolist()``: no conversion of each)."""
    if not vs:
        raise ValueError("a plan needs at least one speed")
    # Clipped only when some speed is negative, as ``0.0 if x < 0.0 else x`` (NaN kept).
    # ``min`` finds a negative speed in one C loop unless a NaN hides it (min's
    # comparisons with a NaN are false): then each is tested.
    lowest = min(vs)
    if lowest < 0.0 or (lowest != lowest and any(map(_ZERO_GT, vs))):
        vs = [0.0 if x < 0.0 else x for x in vs]
    v = tuple(vs)
    a = list(map(operator.truediv, map(operator.sub, v[1:], v), itertools.repeat(dt)))
    a.append(a[-1] if a else 0.0)
    return Plan(t, seq, dt, v, tuple(a), vehicle_id)


def plan_of_array(
    t: float, seq: int, dt: float, speeds: NDArray[np.float64], vehicle_id: str = ""
) -> Plan:
    """:func:`plan_of_floats` of speeds in a float64 array (m/s; not changed): the same
    plan, bit for bit (numpy's subtraction and division are the IEEE ones Python's are),
    with each element loop one numpy call (the MPC's plan is made every cycle: a
    ``map`` over 40 speeds costs several times more)."""
    if speeds.size == 0:
        raise ValueError("a plan needs at least one speed")
    # argmin stops at a NaN: a negative speed or a NaN found in one C loop, then clipped
    # as ``0.0 if x < 0.0 else x`` (NaN and -0.0 kept; with a NaN alone, no change).
    lowest = speeds[speeds.argmin()]
    if lowest < 0.0 or lowest != lowest:
        speeds = np.where(speeds < 0.0, 0.0, speeds)
    a: list[float] = ((speeds[1:] - speeds[:-1]) / dt).tolist()
    a.append(a[-1] if a else 0.0)
    return Plan(t, seq, dt, tuple(speeds.tolist()), tuple(a), vehicle_id)


_ZERO_GT = (0.0).__gt__
"""``x -> 0.0 > x`` (a negative speed) as a C function."""


def kinematic_plan(
    t: float, seq: int, dt: float, v: float, a: float, n: int, vehicle_id: str = ""
) -> Plan:
    """The plan of a truck without an MPC plan (a driven lead, a fallback): constant
    acceleration ``a`` (m/s^2) from speed ``v`` (m/s) over ``n`` steps, never below 0."""
    return make_plan(t, seq, dt, [max(v + a * k * dt, 0.0) for k in range(n + 1)], vehicle_id)


def encode_plan(plan: Plan) -> bytes:
    """The plan as JSON bytes (NaN never appears: speeds are checked when built)."""
    return json.dumps(plan.as_dict(), allow_nan=False).encode()


MIN_PLAN_DT = 1e-4
"""s: a plan's step is at least this (a 10 kHz loop); a tiny ``dt`` would overflow the
sample index of any time after the plan's start."""

MAX_PLAN_T = 1e12
"""s: a plan's stamp lies within this of 0 (about 31 700 years of any clock)."""

_NUMBERS = frozenset((float, int))
"""The JSON numbers' Python types (not bool: ``type(True)`` is bool)."""


def _floats(x: Any, name: str) -> tuple[float, ...]:
    """A JSON list of finite numbers as floats (one pass of C loops: the types' set, the
    conversion, and a sum that is finite only when every value is, and not huge)."""
    if not isinstance(x, list) or not x:
        raise ValueError(f"'{name}' must be a non-empty list")
    if not _NUMBERS.issuperset(map(type, x)):
        raise ValueError(f"'{name}' must hold finite numbers")
    out = tuple(map(float, x))
    if not math.isfinite(sum(out)):
        raise ValueError(f"'{name}' must hold finite numbers")
    return out


def decode_plan(payload: bytes | str) -> Plan:
    """Parse and check a plan message; ValueError naming what is wrong."""
    try:
        d = json.loads(payload)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"not JSON: {exc}") from None
    if not isinstance(d, dict):
        raise ValueError("a plan is a JSON object")
    t, seq, dt = d.get("t"), d.get("seq"), d.get("dt")
    if isinstance(t, bool) or not isinstance(t, int | float) or not abs(t) < MAX_PLAN_T:
        raise ValueError(f"'t' must be a number within +-{MAX_PLAN_T:g} s")
    if isinstance(seq, bool) or not isinstance(seq, int):
        raise ValueError("'seq' must be an integer")
    if isinstance(dt, bool) or not isinstance(dt, int | float) or not (MIN_PLAN_DT <= dt < 10.0):
        raise ValueError(f"'dt' must be a number in [{MIN_PLAN_DT:g}, 10) s")
    v, a = _floats(d.get("v"), "v"), _floats(d.get("a"), "a")
    if len(a) != len(v):
        raise ValueError("'v' and 'a' must have the same length")
    if min(v) < 0.0:
        raise ValueError("'v' must not be negative")
    vid = d.get("vehicle_id", "")
    pre = d.get("predecessor", "")
    return Plan(
        float(t),
        seq,
        float(dt),
        v,
        a,
        vid if isinstance(vid, str) else "",
        pre if isinstance(pre, str) else "",
    )


def plan_speed(plan: Plan, t: float) -> float:
    """The plan's speed (m/s) at time t (s): linear between samples; before the plan its
    first speed; after its end the last speed held, or, when the plan ends braking,
    extrapolated with that deceleration down to standstill (conservative)."""
    if t <= plan.t:
        return plan.v[0]
    x = (t - plan.t) / plan.dt
    k = int(x)
    if k >= len(plan.v) - 1:
        last, a_end = plan.v[-1], plan.a[-1]
        if a_end < 0.0:
            return max(last + a_end * (t - plan.t_end), 0.0)
        return last
    f = x - k
    return plan.v[k] + f * (plan.v[k + 1] - plan.v[k])


def lead_forecast(plan: Plan, t: float, dt: float, n: int) -> list[float]:
    """The lead speed over the follower's horizon: ``n`` values at ``t + k dt`` (s), taken
    from the predecessor's plan aligned in time (see :func:`plan_speed`, whose arithmetic
    this repeats inline: a call per value cost more than the value)."""
    v, t0, pdt = plan.v, plan.t, plan.dt
    last = len(v) - 1
    out: list[float] = []
    for k in range(n):
        tk = t + k * dt
        if tk <= t0:
            out.append(v[0])
            continue
        x = (tk - t0) / pdt
        j = int(x)
        if j >= last:
            out.append(plan_speed(plan, tk))  # past the plan's end: held or braking
            continue
        out.append(v[j] + (x - j) * (v[j + 1] - v[j]))
    return out


def plan_age(plan: Plan, t: float) -> float:
    """Age (s) of a plan at the receiver's time t (negative: stamped in the future)."""
    return t - plan.t


@dataclass(frozen=True)
class PlatoonDecision:
    """One cycle's decision: ``mode`` CACC or ACC; ``headway`` (s) to drive now;
    ``forecast`` the lead speed over the horizon (m/s) in CACC, None in ACC;
    ``plan_age_s`` age of the plan in use (NaN when none)."""

    mode: str
    headway: float
    forecast: list[float] | None
    plan_age_s: float


class PlatoonMode:
    """CACC/ACC switching and the headway ramp of one follower (see module docstring).

    ``update(t, plan, ...)`` once per cycle with the latest plan received from the
    predecessor (None when none yet).  Starts in ACC at the ACC headway by default: a
    follower joins with the larger gap and closes it once its predecessor's plans arrive;
    ``initial=CACC`` starts in CACC at the CACC headway (a platoon already formed).
    """

    def __init__(self, cfg: PlatoonConfig, period: float, horizon: int, initial: str = ACC) -> None:
        if initial not in (ACC, CACC):
            raise ValueError(f"initial mode must be {ACC} or {CACC}, got {initial!r}")
        self.cfg = cfg
        self.period = period
        self.horizon = horizon
        self.mode = initial
        self.headway = cfg.acc_headway if initial == ACC else cfg.cacc_headway
        self._fresh_since = math.inf
        self._t_start = math.nan
        self.switches = 0
        self.disagreements = 0
        """Cycles whose fresh plan was not followed: at odds with the range sensor."""
        self.extra_headway = 0.0
        """Added to the headway target (s): room for a joining truck, opened and closed
        at ``headway_rate`` like every headway change."""
        self._fresh_key: tuple[str, int] | None = None
        """``(vehicle_id, seq)`` of the last plan seen fresh (see :meth:`held`)."""

    def retarget(self, headway: float) -> None:
        """Another truck ahead (a join, a leave): start the headway ramp from the time gap
        now driven to it (``headway``, s; not below the CACC headway), so the reference
        gap does not jump; at most the ACC headway, the largest the controller's gap shift
        is made for)."""
        if math.isfinite(headway):
            self.headway = min(max(headway, self.cfg.cacc_headway), self.cfg.acc_headway)

    def fall_back(self, gap: float, v: float, d_0: float) -> None:
        """To ACC now (no plan to follow, or none trusted): the headway ramp starts from the
        time gap driven (``(gap - d_0) / v``: gap and ``d_0`` in m, ``v`` in m/s; within
        the two headways) so the reference gap does not jump."""
        if self.mode == ACC:
            return
        self.mode = ACC
        self.switches += 1
        self._fresh_since = math.inf
        if math.isfinite(gap) and math.isfinite(v) and v > 0.1:
            actual = (gap - d_0) / v
            self.headway = min(max(actual, self.headway), self.cfg.acc_headway)

    def fresh(self, plan: Plan | None, t: float) -> bool:
        """Whether ``plan`` is fresh at time t (s): not older than the timeout, not from
        the future beyond the allowed clock skew."""
        if plan is None:
            return False
        age = plan_age(plan, t)
        return -self.cfg.max_clock_skew_s <= age <= self.cfg.plan_timeout_s

    def held(self, plan: Plan | None, t: float) -> bool:
        """Whether ``plan``, no longer fresh, is still followed at time t (s): not older
        than ``plan_hold_s`` and from the sender of the last fresh plan, not older than
        that one (a burst of lost plans ridden out on the last plan; a plan that was
        never fresh, e.g. from a clock that disagrees, is not held)."""
        key = self._fresh_key
        if plan is None or key is None or plan.vehicle_id != key[0] or plan.seq < key[1]:
            return False
        age = plan_age(plan, t)
        return self.cfg.plan_timeout_s < age <= self.cfg.plan_hold_s

    def update(
        self,
        t: float,
        plan: Plan | None,
        v: float = math.nan,
        gap: float = math.nan,
        d_0: float = 0.0,
        v_lead: float = math.nan,
        v_lead_std: float = 0.0,
    ) -> PlatoonDecision:
        """Decide this cycle's mode, headway and forecast at time t (s).

        ``v`` own speed (m/s), ``gap`` measured gap (m) and ``d_0`` the standstill gap (m):
        when falling back to ACC the ramp starts from the time gap actually driven
        (``(gap - d_0) / v``, within the two headways), so the reference does not jump.
        ``v_lead`` (m/s) the lead speed the range sensor measures (NaN: no lead in range)
        and its standard deviation ``v_lead_std`` (m/s): a plan whose speed now differs
        from it by more than ``plan_speed_tolerance`` plus three of those is not followed
        (counted in :attr:`disagreements`; the filter is uncertain when it has just found
        its target).
        """
        cfg = self.cfg
        if math.isnan(self._t_start):
            self._t_start = t
        fresh = self.fresh(plan, t)
        if fresh and plan is not None:
            self._fresh_key = (plan.vehicle_id, plan.seq)
        # In CACC an older plan is still followed while held (a burst of lost plans);
        # it does not count towards the return to CACC.
        usable = fresh or (self.mode == CACC and self.held(plan, t))
        if (
            usable
            and plan is not None
            and math.isfinite(v_lead)
            and abs(plan_speed(plan, t) - v_lead)
            > cfg.plan_speed_tolerance + 3.0 * (v_lead_std if math.isfinite(v_lead_std) else 0.0)
        ):
            fresh = usable = False
            self.disagreements += 1
        if plan is None and t - self._t_start <= max(cfg.plan_timeout_s, cfg.plan_hold_s):
            # Just started: the first plan may still be on its way, or lost in a burst
            # (no forecast yet; waited for as long as a plan would be held).
            fresh = usable = self.mode == CACC
        if fresh:
            if self._fresh_since == math.inf:
                self._fresh_since = t
        else:
            self._fresh_since = math.inf
        if self.mode == CACC and not usable:
            self.fall_back(gap, v, d_0)
        elif self.mode == ACC and fresh and t - self._fresh_since >= cfg.cacc_return_s:
            self.mode = CACC
            self.switches += 1
        target = (cfg.cacc_headway if self.mode == CACC else cfg.acc_headway) + self.extra_headway
        step = cfg.headway_rate * self.period
        self.headway = min(max(target, self.headway - step), self.headway + step)
        if self.mode == CACC and plan is not None:
            forecast = lead_forecast(plan, t, self.period, self.horizon)
            if not fresh and math.isfinite(v_lead):
                # a held plan: past its end the lead speed the range sensor measures when
                # lower (the plan's last speed says nothing of what came after it)
                k_end = max(0, math.ceil((plan.t_end - t) / self.period))
                forecast[k_end:] = [min(f, v_lead) for f in forecast[k_end:]]
            return PlatoonDecision(CACC, self.headway, forecast, plan_age(plan, t))
        age = plan_age(plan, t) if plan is not None else math.nan
        return PlatoonDecision(self.mode, self.headway, None, age)

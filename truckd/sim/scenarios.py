"""Closed-loop scenarios: lead trajectories and what the range sensor sees.

A lead drives a piecewise-linear speed profile (:class:`SpeedProfile`); the true gap is
``x_lead(t) - x_ego``.  A :class:`World` turns a scenario into the simulated firmware's
``range_fn(t, ego_x)`` (with sensor dropouts and the cut-in's sudden jump) and the truth
the metrics need.  Pure numerics: time is passed in.

=============== ==========================================================================
``cruise``       no lead: accelerate from rest to the set speed and hold it
``follow``       lead at constant speed, start from rest: settle at ``d_ref = d_0 + h v``
``lead-brake``   steady following, then the lead brakes as hard as the truck can, to a stop
``stop-and-go``  the lead stops, waits, goes, twice
``cut-in``       steady following, then a vehicle cuts in: the gap halves suddenly
``lead-lost``    a sensor dropout while following, then the lead drives away out of range:
                 lead lost, the truck cruises at the set speed
=============== ==========================================================================
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

from truckd.control.config import ControlConfig
from truckd.model.params import VehicleParams

SCENARIO_NAMES: tuple[str, ...] = (
    "cruise",
    "follow",
    "lead-brake",
    "stop-and-go",
    "cut-in",
    "lead-lost",
)


@dataclass(frozen=True)
class SpeedProfile:
    """Piecewise-linear speed (m/s) through ``(times[k], speeds[k])``, constant outside."""

    times: tuple[float, ...]
    speeds: tuple[float, ...]

    def __post_init__(self) -> None:
        if len(self.times) != len(self.speeds) or not self.times:
            raise ValueError("a speed profile needs as many times as speeds, at least one")
        if any(b <= a for a, b in zip(self.times, self.times[1:], strict=False)):
            raise ValueError("speed profile times must increase strictly")

    def speed(self, t: float) -> float:
        """Speed at t (s)."""
        ts, vs = self.times, self.speeds
        if t <= ts[0]:
            return vs[0]
        if t >= ts[-1]:
            return vs[-1]
        k = bisect.bisect_right(ts, t) - 1
        f = (t - ts[k]) / (ts[k + 1] - ts[k])
        return vs[k] + f * (vs[k + 1] - vs[k])

    def distance(self, t: float) -> float:
        """Distance travelled from t = 0 to t (s), exact for the piecewise-linear speed."""
        ts, vs = self.times, self.speeds
        total, prev_t, prev_v = 0.0, 0.0, self.speed(0.0)
        for tk, vk in zip(ts, vs, strict=True):
            if tk <= prev_t:
                continue
            if tk >= t:
                break
            total += 0.5 * (prev_v + vk) * (tk - prev_t)
            prev_t, prev_v = tk, vk
        return total + 0.5 * (prev_v + self.speed(t)) * (t - prev_t)


@dataclass(frozen=True)
class Scenario:
    """One closed-loop test: the ego starts at ``v0`` (m/s); the lead ``gap0`` (m) ahead.

    ``dropouts``: windows ``(t0, t1)`` (s) in which the range sensor reports no target;
    ``cut_in_time`` (s): the gap is multiplied by ``cut_in_fraction`` then (a vehicle cuts
    in at the lead's speed).
    """

    name: str
    description: str
    duration: float
    v0: float
    gap0: float | None
    lead: SpeedProfile | None
    dropouts: tuple[tuple[float, float], ...] = ()
    cut_in_time: float | None = None
    cut_in_fraction: float = 0.5


def max_decel(p: VehicleParams, v: float) -> float:
    """The truck's hardest deceleration (m/s^2) at speed v: full reverse battery voltage,
    back-EMF and Coulomb friction all braking (stalled current, no tyre limit)."""
    torque = p.K_T / p.R_m * (p.V_batt + p.K_v * p.omega(v)) + p.K_coulomb
    inertia_mass = p.J_S / (p.ratio * p.ratio)
    return torque / p.ratio / inertia_mass


def d_ref(cfg: ControlConfig, v: float) -> float:
    """The spacing policy's reference gap (m) at speed v (m/s)."""
    return cfg.d_0 + cfg.time_headway * v


def make_scenario(name: str, p: VehicleParams, cfg: ControlConfig) -> Scenario:
    """The scenario ``name`` (see the module docstring) for this truck and controller."""
    if name == "cruise":
        return Scenario(name, "no lead: from rest to the set speed", 15.0, 0.0, None, None)
    if name == "follow":
        v = 0.7 * cfg.v_set
        return Scenario(
            name,
            "lead at constant speed, start from rest",
            20.0,
            0.0,
            1.5,
            SpeedProfile((0.0,), (v,)),
        )
    if name == "lead-brake":
        v = 0.9 * cfg.v_set
        t_b = 8.0
        t_stop = t_b + v / max_decel(p, v)
        return Scenario(
            name,
            "lead brakes as hard as the truck can, to a stop",
            15.0,
            v,
            d_ref(cfg, v),
            SpeedProfile((0.0, t_b, t_stop), (v, v, 0.0)),
        )
    if name == "stop-and-go":
        v = 0.7 * cfg.v_set
        a = 2.0
        knots = [(0.0, v), (4.0, v), (4.0 + v / a, 0.0), (7.0 + v / a, 0.0)]
        t = knots[-1][0]
        knots += [(t + v / a, v), (t + v / a + 4.0, v)]
        t = knots[-1][0]
        knots += [(t + v / a, 0.0), (t + v / a + 3.0, 0.0), (t + 2 * v / a + 3.0, v)]
        return Scenario(
            name,
            "the lead stops and goes, twice",
            28.0,
            v,
            d_ref(cfg, v),
            SpeedProfile(tuple(k[0] for k in knots), tuple(k[1] for k in knots)),
        )
    if name == "cut-in":
        v = 0.8 * cfg.v_set
        return Scenario(
            name,
            "a vehicle cuts in: the gap halves suddenly",
            20.0,
            v,
            d_ref(cfg, v),
            SpeedProfile((0.0,), (v,)),
            cut_in_time=8.0,
        )
    if name == "lead-lost":
        v = 0.7 * cfg.v_set
        fast = min(cfg.v_set + 0.6, 1.5 * cfg.v_set + 0.3)
        return Scenario(
            name,
            "sensor dropout, then the lead drives out of range",
            25.0,
            v,
            d_ref(cfg, v),
            SpeedProfile((0.0, 10.0, 11.5), (v, v, fast)),
            dropouts=((6.0, 6.2),),
        )
    raise ValueError(f"unknown scenario {name!r}; expected one of {', '.join(SCENARIO_NAMES)}")


class World:
    """The truth of a scenario and the range sensor's view of it."""

    def __init__(self, sc: Scenario) -> None:
        self.sc = sc
        self._shift = 0.0
        self._cut_done = sc.cut_in_time is None

    def lead_x(self, t: float) -> float | None:
        """Lead position (m) at t (s), the ego starting at x = 0; None without lead."""
        if self.sc.lead is None or self.sc.gap0 is None:
            return None
        return self.sc.gap0 + self.sc.lead.distance(t) - self._shift

    def v_lead(self, t: float) -> float | None:
        """Lead speed (m/s) at t (s); None without lead."""
        return None if self.sc.lead is None else self.sc.lead.speed(t)

    def gap(self, t: float, ego_x: float) -> float | None:
        """True gap (m) at t (s) for the ego at ego_x (m); applies the cut-in when due."""
        x = self.lead_x(t)
        if x is None:
            return None
        if not self._cut_done and self.sc.cut_in_time is not None and t >= self.sc.cut_in_time:
            self._cut_done = True
            self._shift = (1.0 - self.sc.cut_in_fraction) * (x - ego_x)
            x -= self._shift
        return x - ego_x

    def range_fn(self, t: float, ego_x: float) -> float | None:
        """What the range sensor sees (the firmware applies its own maximum range)."""
        g = self.gap(t, ego_x)
        if g is None or any(a <= t < b for a, b in self.sc.dropouts):
            return None
        return max(g, 0.0) if math.isfinite(g) else None

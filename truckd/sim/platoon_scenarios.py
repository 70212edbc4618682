"""The platoon scenarios of ``truckd sim --platoon N``: the lead's driver (a speed
profile), the plan loss windows, the trucks' dead time, and joins and leaves."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

PLATOON_SCENARIOS: tuple[str, ...] = (
    "platoon-brake",
    "platoon-sine",
    "platoon-comm-loss",
    "platoon-join",
    "platoon-leave",
)
ACTUATION_DELAY_S = 0.15
"""Dead time (s) between command and actuation in the platoon scenarios' trucks, known to
their controllers (as ``diagnose`` identifies it): a delay is what makes ACC need a
larger headway than CACC (see docs/platoon.md); without it the MPC's ACC is string
stable at these headways already."""
SETTLE_S = 3.0
"""The spacing errors are taken from this time on: without ``steady_start`` every truck
starts at the lead's speed and gap, but its dead time holds the first commands at 0 V, a
transient of its own (not passed down the platoon); every scenario's disturbance starts
later."""
PREROLL_S = 1.2
"""With ``steady_start`` (``run_platoon``) a scenario that starts at speed starts in the
steady state of that speed: before 0 s the platoon runs this long at the lead's starting
speed, not recorded (no trace, no metrics; the link, mode-switch and solver-failure
counters start at 0 s), so each truck's supervisor is
ACTIVE, its estimator converged, its dead time's pipeline filled with its own commands
and its motor current at their value when the scenario starts.  Without it each truck
would start with its controller off at speed: the supervisor in INIT and the dead time
holding 0 V, a dip from 1.5 to about 0.8 m/s in the first 0.25 s.  Not for
``platoon-join``: its joining trucks start off the platoon's steady state (one in the next
lane, one 3 m behind the tail without a predecessor), their approach from 0 s is the
scenario, so it starts as the trucks are built (the dip included)."""
PREROLL_HOLD_S = 0.3
"""The first part of the pre-roll, each truck held at the starting speed and at its place
(:meth:`~truckd.sim.plant.Plant.hold`, as on a roller stand) while its controller comes
up and fills the dead time's pipeline (more than the 0.15 s dead time); then the trucks
run free under their controllers for the rest of :data:`PREROLL_S`."""


@dataclass(frozen=True)
class PlatoonScenario:
    """Lead speed ``lead_v(t)`` (m/s) and acceleration ``lead_a(t)`` (m/s^2); plan loss
    windows ``(t0, t1, p)``: between t0 and t1 (s) each plan is lost with probability p."""

    name: str
    description: str
    duration: float
    v0: float
    lead_v: Callable[[float], float]
    lead_a: Callable[[float], float]
    loss_windows: tuple[tuple[float, float, float], ...] = ()
    input_delay: float = ACTUATION_DELAY_S
    kind: str = ""
    """"join" or "leave": trucks change places at ``event_s``."""
    event_s: float = math.inf


def _brake_v(t: float) -> float:
    return 1.5 - 2.0 * min(max(t - 4.0, 0.0), 0.5)


def _brake_a(t: float) -> float:
    return -2.0 if 4.0 <= t < 4.5 else 0.0


_W = 2.0 * math.pi / 3.0


def _sine_v(t: float) -> float:
    return 1.2 + 0.4 * math.sin(_W * (t - 3.0)) if t >= 3.0 else 1.2


def _sine_a(t: float) -> float:
    return 0.4 * _W * math.cos(_W * (t - 3.0)) if t >= 3.0 else 0.0


def _dip_v(t: float) -> float:
    """1.2 m/s; at 12 s down to 0.8 m/s at 1 m/s^2, at 16 s back up."""
    if t < 12.0:
        return 1.2
    if t < 16.0:
        return max(1.2 - (t - 12.0), 0.8)
    return min(0.8 + (t - 16.0), 1.2)


def _dip_a(t: float) -> float:
    if 12.0 <= t < 12.4:
        return -1.0
    if 16.0 <= t < 16.4:
        return 1.0
    return 0.0


def _steady_v(t: float) -> float:
    return 1.2


def _steady_a(t: float) -> float:
    return 0.0


def make_platoon_scenario(name: str) -> PlatoonScenario:
    """The scenario ``name`` (see the module docstring)."""
    if name == "platoon-brake":
        return PlatoonScenario(
            name, "lead brakes 1.5 -> 0.5 m/s at 2 m/s^2", 12.0, 1.5, _brake_v, _brake_a
        )
    if name == "platoon-sine":
        return PlatoonScenario(
            name, "lead speed 1.2 + 0.4 sin(2 pi (t - 3 s) / 3 s)", 15.0, 1.2, _sine_v, _sine_a
        )
    if name == "platoon-comm-loss":
        return PlatoonScenario(
            name,
            "plans lost for 2 s, then 30 % loss",
            25.0,
            1.2,
            _dip_v,
            _dip_a,
            loss_windows=((5.0, 7.0, 1.0), (7.0, math.inf, 0.3)),
        )
    if name == "platoon-join":
        return PlatoonScenario(
            name,
            "1.2 m/s; a truck in the next lane announces at 4 s and moves in once room is "
            "open; another drives up from behind and joins at the tail",
            20.0,
            1.2,
            _steady_v,
            _steady_a,
            kind="join",
            event_s=4.0,
        )
    if name == "platoon-leave":
        return PlatoonScenario(
            name,
            "1.2 m/s; at 5 s the middle truck leaves, its follower takes the truck ahead",
            15.0,
            1.2,
            _steady_v,
            _steady_a,
            kind="leave",
            event_s=5.0,
        )
    raise ValueError(
        f"unknown platoon scenario {name!r}; expected one of {', '.join(PLATOON_SCENARIOS)}"
    )

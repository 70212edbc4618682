"""The ``characterize:`` section of truck.yaml: what ``truckd characterize`` checks before
the truck moves, the experiments it drives, and the limits it keeps.

The defaults suit a 1:14 truck on a 7.2 V battery (docs/characterize.md): a routine of
about 40 s that drives about 2 m either way from the start."""

from __future__ import annotations

from dataclasses import dataclass

from truckd.schema import spec

CLOSED_LOOP_SCENARIOS = ("cruise", "follow", "lead-brake", "stop-and-go", "cut-in", "lead-lost")
"""The single-truck scenarios of ``truckd sim`` (truckd.sim.scenarios, which the car does not
load)."""


@dataclass(frozen=True)
class CharacterizeConfig:
    """Bring-up limits, experiments and the distance budget of ``truckd characterize``."""

    track_length_m: float = spec(
        "free track in each direction from the start (ahead, the range sensor's free "
        "space limits it further)",
        unit="m",
        lo=0.1,
        hi=1000.0,
        default=3.0,
    )
    wall_margin_m: float = spec(
        "distance kept from what the range sensor sees ahead", unit="m", lo=0.0, hi=10.0,
        default=0.3,
    )  # fmt: skip
    min_budget_m: float = spec(
        "an experiment needs at least this much free distance; with less the routine "
        "refuses to start",
        unit="m",
        lo=0.05,
        hi=100.0,
        default=0.8,
    )
    brake_decel_m_s2: float = spec(
        "deceleration assumed at 0 V (dynamic braking) for the stopping distance",
        unit="m/s^2", lo=0.1, hi=50.0, default=2.0,
    )  # fmt: skip
    speed_limit_m_s: float = spec(
        "an experiment ends when the truck is faster", unit="m/s", lo=0.05, hi=20.0, default=1.5
    )
    battery_min_v: float = spec("lowest battery voltage at rest", unit="V", lo=0.0, default=6.0)
    battery_max_v: float = spec("highest battery voltage at rest", unit="V", lo=0.0, default=9.0)
    range_steady_std_m: float = spec(
        "largest spread (std) of the range reading at rest", unit="m", lo=0.0, default=0.02
    )
    range_dwell_s: float = spec(
        "time at rest over which the range and battery are judged", unit="s", lo=0.1, hi=10.0,
        default=0.5,
    )  # fmt: skip
    check_max_v: float = spec(
        "largest voltage of the polarity check (it ramps up until the truck moves)",
        unit="V", lo=0.1, hi=100.0, default=4.0,
    )  # fmt: skip
    check_ramp_v_per_s: float = spec(
        "ramp rate of the polarity check", unit="V/s", lo=0.1, hi=100.0, default=3.0
    )
    check_distance_m: float = spec(
        "the polarity check stops after this distance", unit="m", lo=0.01, hi=1.0, default=0.12
    )
    counts_tolerance: float = spec(
        "encoder distance / range-sensor distance must lie within 1 -/+ this",
        lo=0.01, hi=0.9, default=0.3,
    )  # fmt: skip
    ready_timeout_s: float = spec(
        "link and sensors must be up within this time", unit="s", lo=0.1, hi=60.0, default=3.0
    )
    min_encoder_rate: float = spec(
        "encoder messages per control cycle at least this fraction of one per period of "
        "the firmware's (link check)",
        lo=0.0, hi=1.0, default=0.8,
    )  # fmt: skip
    quasistatic_ramp_v_per_s: float = spec(
        "quasistatic ramp rate (up, then down)", unit="V/s", lo=0.01, hi=20.0, default=1.0
    )
    quasistatic_duration_s: float = spec(
        "quasistatic ramp length, up and down (each direction)", unit="s", lo=0.2, hi=60.0,
        default=5.0,
    )  # fmt: skip
    step_voltages: tuple[float, ...] = spec(
        "dynamic step levels (each direction)", unit="V", lo=0.1, hi=100.0, default=(1.5, 3.0)
    )
    step_duration_s: float = spec("dynamic step length", unit="s", lo=0.2, hi=60.0, default=1.5)
    validation_v: float = spec(
        "validation chirp amplitude; 0: the highest of step_voltages (the chirp must reach "
        "the voltages the fit saw: effects that act at a high duty, a battery's sag or a "
        "current limit, are told apart only there)",
        unit="V",
        lo=0.0,
        hi=100.0,
        default=0.0,
    )
    validation_duration_s: float = spec(
        "validation chirp length", unit="s", lo=0.2, hi=60.0, default=4.0
    )
    validation_f0_hz: float = spec(
        "chirp start frequency", unit="Hz", lo=0.01, hi=20.0, default=0.4
    )
    validation_f1_hz: float = spec("chirp end frequency", unit="Hz", lo=0.01, hi=20.0, default=2.0)
    rest_speed_m_s: float = spec(
        "at rest below this speed", unit="m/s", lo=0.001, hi=1.0, default=0.02
    )
    rest_timeout_s: float = spec(
        "longest wait for the truck to come to rest", unit="s", lo=0.1, hi=60.0, default=4.0
    )
    closed_loop_scenarios: tuple[str, ...] = spec(
        "truckd sim scenarios of the closed-loop comparison",
        choices=CLOSED_LOOP_SCENARIOS,
        default=("follow", "stop-and-go"),
    )

    def validate(self) -> str | None:
        if self.battery_max_v <= self.battery_min_v:
            return (
                f"battery_max_v ({self.battery_max_v}) must be above battery_min_v "
                f"({self.battery_min_v})"
            )
        if not self.step_voltages:
            return "step_voltages must list at least one voltage"
        if 0.0 < self.validation_v < 0.1:
            return f"validation_v ({self.validation_v}) must be 0 (the highest step) or >= 0.1"
        if self.min_budget_m > self.track_length_m:
            return (
                f"min_budget_m ({self.min_budget_m}) must not exceed track_length_m "
                f"({self.track_length_m})"
            )
        return None

    @property
    def chirp_v(self) -> float:
        """The validation chirp's amplitude (V): ``validation_v``, or the highest step."""
        return self.validation_v if self.validation_v > 0.0 else max(self.step_voltages)

"""``truckd characterize``: the bring-up checks, before anything moves far (each failure
one line saying what to fix): link and sensors up, encoder message rate and receive
errors, battery within limits, range reading sane and steady, free space ahead, then a
short pulse (a small positive voltage, ramped until the truck has moved
``check_distance_m``): motor polarity, encoder direction and counts per metre, judged
against the range sensor's view of a target ahead.  Also the motion limits the routine
keeps (free space ahead and behind, waiting at rest).

Generators over the cycle's :class:`Obs` (they yield the voltage): no I/O and no clock.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable, Generator
from typing import Any

from truckd.config.characterize import CharacterizeConfig
from truckd.control.supervisor import Mode
from truckd.runtime.characterize_plan import Check, CheckFailedError, Obs, TruckFacts


class BringUp:
    """The bring-up checks of one routine, in order: :meth:`wait_ready`,
    :meth:`dwell_checks`, :meth:`pulse`.  Each passed check is appended to ``checks``; a
    failed one raises :class:`CheckFailedError`.  ``stage(stage, t, experiment)`` reports
    progress, ``link_stats()`` the companion port's counters."""

    def __init__(
        self,
        cfg: CharacterizeConfig,
        truck: TruckFacts,
        *,
        link_stats: Callable[[], dict[str, Any]],
        checks: list[Check],
        stage: Callable[[str, float, str], None],
    ) -> None:
        self.cfg = cfg
        self.period = truck.period
        self.range_max = truck.range_max
        self.encoder_period = truck.encoder_period
        self.ticks_per_rev = truck.ticks_per_rev
        self.r_w = truck.r_w
        self.link_stats = link_stats
        self.checks = checks
        self.stage = stage
        self._range0: float | None = None  # the range at rest before the polarity pulse

    def _fail(self, name: str, detail: str) -> CheckFailedError:
        return CheckFailedError(Check(name, False, detail))

    def _pass(self, name: str, detail: str) -> None:
        self.checks.append(Check(name, True, detail))

    def wait_ready(self, obs: Obs) -> Generator[float, Obs, Obs]:
        """At 0 V until the supervisor leaves INIT: link and sensors up."""
        cfg = self.cfg
        t0 = obs.t
        while obs.decision.mode not in (Mode.ACTIVE, Mode.DEGRADED):
            if obs.t - t0 > cfg.ready_timeout_s:
                raise self._not_ready(obs)
            obs = yield 0.0
        self._pass("link", f"link and sensors up after {obs.t - t0:.2f} s")
        return obs

    def _not_ready(self, obs: Obs) -> CheckFailedError:
        causes = set(obs.decision.causes)
        waited = f"{self.cfg.ready_timeout_s:g} s"
        if causes & {"link_down", "link_stale"} or not causes:
            return self._fail(
                "link",
                f"no messages from the firmware for {waited}: check the cable, the device "
                "(link: section) and that the firmware runs",
            )
        if "encoder_stale" in causes or "speed_stale" in causes:
            return self._fail(
                "encoder", f"no encoder data for {waited}: check the encoder's cable and power"
            )
        if "range_stale" in causes:
            return self._fail(
                "range",
                f"no range reading for {waited}: check the range sensor's cable and power",
            )
        if "range_fault" in causes:
            return self._fail(
                "range", "the range sensor reports a fault: check its mounting and power"
            )
        return self._fail("link", f"not ready after {waited}: {', '.join(sorted(causes))}")

    def dwell_checks(self, obs: Obs) -> Generator[float, Obs, Obs]:
        """At rest for ``range_dwell_s``: link rate and errors, battery, range, free space.

        Long because one generator dwells at rest and then judges every check from the same
        samples; split, the samples would travel between generators."""
        cfg = self.cfg
        self.stage("checks", obs.t, "sensors")
        stats0 = self.link_stats()
        t0, msgs = obs.t, 0
        vbat: list[float] = []
        ranges: list[float | None] = []
        last_rt = obs.range_t
        cycles = 0
        while obs.t - t0 < cfg.range_dwell_s:
            obs = yield 0.0
            cycles += 1
            msgs += obs.encoder_msgs
            vbat.append(obs.vbat)
            if obs.range_t != last_rt:
                last_rt = obs.range_t
                ranges.append(obs.range_m)
        stats1 = self.link_stats()
        # link: encoder messages at the firmware's rate, no receive errors
        span = max(obs.t - t0, self.period)
        rate = msgs * self.encoder_period / span
        errors = {
            k: int(stats1.get(k, 0)) - int(stats0.get(k, 0))
            for k in stats1
            if k.startswith("rx_") and k != "rx_ok" and isinstance(stats1[k], int)
            and not isinstance(stats1[k], bool) and ("error" in k or "bad" in k or "invalid" in k)
        }  # fmt: skip
        bad = {k: n for k, n in errors.items() if n > 0}
        if rate < cfg.min_encoder_rate:
            raise self._fail(
                "link_rate",
                f"encoder messages arrive at {100 * rate:.0f} % of the firmware's rate "
                f"(1 per {self.encoder_period * 1e3:.0f} ms): check the link's baud rate and "
                "load",
            )
        if bad:
            listed = ", ".join(f"{k} {n}" for k, n in sorted(bad.items()))
            raise self._fail(
                "link_rate",
                f"receive errors at rest ({listed}): check the cable, its shielding and the "
                "baud rate",
            )
        self._pass("link_rate", f"encoder messages at {100 * rate:.0f} % of the firmware's rate")
        # battery
        vb = statistics.median(vbat) if vbat else 0.0
        if vb < cfg.battery_min_v:
            raise self._fail(
                "battery",
                f"battery {vb:.2f} V is below {cfg.battery_min_v:g} V "
                "(characterize.battery_min_v): charge or swap the battery",
            )
        if vb > cfg.battery_max_v:
            raise self._fail(
                "battery",
                f"battery {vb:.2f} V is above {cfg.battery_max_v:g} V "
                "(characterize.battery_max_v): check the battery type and the voltage sense",
            )
        self._pass("battery", f"{vb:.2f} V at rest")
        # range: sane and steady
        valid = [r for r in ranges if r is not None]
        if not ranges:
            raise self._fail(
                "range",
                f"no range reading in {cfg.range_dwell_s:g} s at rest: check the range "
                "sensor's cable and power",
            )
        if valid and len(valid) < len(ranges):
            raise self._fail(
                "range",
                f"the range sensor loses its target at rest ({len(ranges) - len(valid)} of "
                f"{len(ranges)} readings): check its mounting and what is ahead",
            )
        spread = statistics.pstdev(valid) if len(valid) > 1 else 0.0
        if spread > cfg.range_steady_std_m:
            raise self._fail(
                "range",
                f"the range reading spreads {spread:.3f} m at rest (limit "
                f"{cfg.range_steady_std_m:g} m, characterize.range_steady_std_m): check the "
                "sensor's mounting and that nothing moves ahead",
            )
        ahead = statistics.median(valid) if valid else None
        self._range0 = ahead
        self._pass(
            "range",
            f"{ahead:.3f} m ahead, spread {spread:.4f} m"
            if ahead is not None
            else f"no target within {self.range_max:g} m",
        )
        free = free_ahead(obs, self.cfg, self.range_max)
        if free < cfg.min_budget_m:
            what = f"a target {ahead:.2f} m ahead" if ahead is not None else "the track"
            raise self._fail(
                "free_space",
                f"{what} leaves {max(free, 0.0):.2f} m to drive, less than the "
                f"{cfg.min_budget_m:g} m an experiment needs (characterize.min_budget_m, "
                f"wall_margin_m {cfg.wall_margin_m:g} m): move the truck back or clear the "
                "track",
            )
        self._pass("free_space", f"{free:.2f} m to drive ahead")
        return obs

    def _settled_range(
        self, obs: Obs, dwell: float
    ) -> Generator[float, Obs, tuple[Obs, float | None]]:
        """At rest for ``dwell`` s: the median range reading (None: no target)."""
        t0, vals = obs.t, []
        last = obs.range_t
        while obs.t - t0 < dwell:
            obs = yield 0.0
            if obs.range_t != last:
                last = obs.range_t
                vals.append(obs.range_m)
        got = [r for r in vals if r is not None]
        return obs, (statistics.median(got) if got and len(got) == len(vals) else None)

    def pulse(self, obs: Obs) -> Generator[float, Obs, Obs]:
        """A small positive voltage, ramped until the truck moved: polarity, encoder
        direction, counts per metre."""
        cfg = self.cfg
        self.stage("checks", obs.t, "polarity")
        r0, x0, t0 = self._range0, obs.x, obs.t
        u = 0.0
        held = 0.0
        while True:
            moved = abs(obs.x - x0)
            seen = abs(obs.range_m - r0) if (r0 is not None and obs.range_m is not None) else 0.0
            if max(moved, seen) >= cfg.check_distance_m:
                break
            if abs(obs.v) > cfg.speed_limit_m_s:
                break
            if u >= cfg.check_max_v:
                held += self.period
                if held > 0.5:
                    break
            u = min(cfg.check_max_v, cfg.check_ramp_v_per_s * (obs.t - t0))
            obs = yield u
        obs = yield from rest(obs, self.cfg, self.period)
        obs, r1 = yield from self._settled_range(obs, 0.3)
        dx = obs.x - x0
        dr = (r0 - r1) if (r0 is not None and r1 is not None) else None  # > 0: forward
        small = 0.25 * cfg.check_distance_m
        if abs(dx) < small and (dr is None or abs(dr) < small):
            raise self._fail(
                "motor_polarity",
                f"the truck did not move with up to {cfg.check_max_v:g} V: check the motor's "
                "cable, the driver and that the wheels are free",
            )
        if dr is not None and abs(dr) >= small:
            if dr < 0:
                raise self._fail(
                    "motor_polarity",
                    f"a positive voltage drove the truck backwards (the target ahead moved "
                    f"{-dr:.3f} m away): swap the motor leads",
                )
            self._pass("motor_polarity", f"forward under +V ({dr:.3f} m by the range sensor)")
            if abs(dx) < small:
                raise self._fail(
                    "encoder_direction",
                    f"the truck drove {dr:.3f} m but the encoder counted {dx:.3f} m: check "
                    "the encoder's cable and power",
                )
            if dx < 0:
                raise self._fail(
                    "encoder_direction",
                    f"the encoder counts down while the truck drives forward ({dx:.3f} m by "
                    f"the encoder, {dr:.3f} m by the range sensor): swap the encoder's A and B "
                    "channels",
                )
            self._pass("encoder_direction", f"counts up going forward ({dx:.3f} m)")
            ratio = dx / dr
            tol = cfg.counts_tolerance
            per_m = self.ticks_per_rev / (2.0 * math.pi * self.r_w)
            if not 1.0 - tol <= ratio <= 1.0 + tol:
                raise self._fail(
                    "counts_per_metre",
                    f"the encoder says {dx:.3f} m where the range sensor says {dr:.3f} m "
                    f"({ratio:.2f}x): the configured {per_m:.0f} counts/m (link."
                    f"encoder_ticks_per_rev {self.ticks_per_rev}, vehicle.r_w {self.r_w:g} m) "
                    f"are off: configure {per_m * ratio:.0f} counts/m",
                )
            self._pass("counts_per_metre", f"encoder/range distance ratio {ratio:.3f}")
            return obs
        if dx < 0:
            raise self._fail(
                "motor_polarity",
                "the encoder counts down under a positive voltage: the motor leads or the "
                f"encoder channels are swapped; put a target within {self.range_max:g} m "
                "ahead so the range sensor can tell which, and rerun",
            )
        self._pass("motor_polarity", f"encoder counts up under +V ({dx:.3f} m)")
        self._pass("encoder_direction", "not checked apart from the motor: no target ahead")
        self._pass("counts_per_metre", "not checked: no target ahead of the range sensor")
        return obs


def free_ahead(obs: Obs, cfg: CharacterizeConfig, range_max: float) -> float:
    """Distance the truck may still drive forward (m): the track, and what the range
    sensor sees ahead less the margin (nothing seen: free up to its maximum)."""
    track = cfg.track_length_m - obs.x
    seen = (obs.range_m if obs.range_m is not None else range_max) - cfg.wall_margin_m
    return min(track, seen)


def free_behind(obs: Obs, cfg: CharacterizeConfig) -> float:
    """Distance the truck may still drive back (m): the track behind the start."""
    return cfg.track_length_m + obs.x


def rest(
    obs: Obs, cfg: CharacterizeConfig, period: float, fail: bool = True
) -> Generator[float, Obs, Obs]:
    """0 V until at rest (slower than ``rest_speed_m_s`` for 0.2 s)."""
    t0, calm = obs.t, 0.0
    while calm < 0.2:
        obs = yield 0.0
        calm = calm + period if abs(obs.v) < cfg.rest_speed_m_s else 0.0
        if obs.t - t0 > cfg.rest_timeout_s:
            if fail:
                raise CheckFailedError(
                    Check(
                        "rest",
                        False,
                        f"the truck still moves at {obs.v:.2f} m/s {cfg.rest_timeout_s:g} s "
                        "after 0 V: check the driver and the brake",
                    )
                )
            break
    return obs

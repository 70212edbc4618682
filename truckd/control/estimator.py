"""State estimation: own speed from wheel encoders, gap and lead speed from the range sensor.

Own speed: both wheels' 16-bit tick counters are unwrapped (modular difference), the
travelled distance is the mean of the healthy wheels, and a position/velocity Kalman
filter (white-acceleration model, measurement noise = one tick's quantisation,
``tick^2 / 12``) turns the quantised distance into a speed.  Time steps come from the
firmware's sample clock (which wraps), staleness from the caller's clock.  A
discontinuity restarts the filter from the next difference (the speed is stale until
then): two steps in a row faster than ``speed_max`` or farther from the filter's speed
than ``accel_max`` allows (the counters reset or jumped), the firmware's clock running ahead of
the caller's by more than :data:`CLOCK_SLACK_S`, or two samples in a row behind the last
one and in order among themselves (the firmware's clock restarted, e.g. a microcontroller
reset).  A single sample behind the last one is dropped (out of order).  A single step
out of bounds whose next sample lies within them again, measured from the sample before
it, is a glitch (a count read before it was updated, then caught up): dropped and counted
(``speed_glitches``), the speed stays valid (and so, for one sample, does the old speed
of a truck that really stopped dead).  Before the filter has its first difference, an
out-of-bounds step restarts it at once.  After a restart the speed is valid from the
second difference on, once the next step has confirmed the first (a first difference
taken from a stale count would be a spike).

Lead: a Kalman filter on ``[gap, v_lead]`` with ``gap' = v_lead - v_own`` and the lead's
acceleration as white noise.  Readings outside the sensor's range or flagged invalid are
"no target".  A reading whose innovation exceeds ``gate_sigma`` standard deviations is an
outlier and rejected, unless ``reinit_count`` consecutive outliers agree with each other
(a new target, e.g. a cut-in): then the filter restarts on them.  The lead is lost when no
reading has been accepted for ``lead_timeout_s``.  Pure numerics: times are passed in.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

from truckd.control.config import EstimatorConfig
from truckd.control.frozen import fast_init
from truckd.model.params import VehicleParams


@fast_init
@dataclass(frozen=True)
class EncoderSample:
    """One encoder message: raw wrapping counters, the firmware's sample time (s, wraps),
    and whether each wheel's encoder is healthy."""

    ticks_left: int
    ticks_right: int
    sample_time: float
    left_ok: bool = True
    right_ok: bool = True


@fast_init
@dataclass(frozen=True)
class RangeSample:
    """One range message: distance (m) or None when the sensor reports no valid target;
    the firmware's sample time (s, wraps)."""

    distance: float | None
    sample_time: float


@fast_init
@dataclass(frozen=True)
class Estimate:
    """Estimated state at the latest sample.

    ``v`` own speed (m/s), ``speed_valid``; ``gap`` (m) and ``v_lead`` (m/s) predicted to
    the latest encoder sample, ``lead_valid``, ``lead_status`` (``tracking``,
    ``no_target``, ``timeout``, ``none``); ``gap_std`` (m); counters
    (``speed_restarts``: own-speed filter restarts on a discontinuity).
    """

    v: float
    speed_valid: bool
    gap: float
    v_lead: float
    lead_valid: bool
    lead_status: str
    gap_std: float
    outliers: int
    reinits: int
    encoder_samples: int
    range_samples: int
    speed_restarts: int = 0
    speed_glitches: int = 0
    speed_age: float = math.inf
    """Caller time since the own-speed filter last took a measurement (s; inf: never)."""
    v_lead_std: float = math.nan
    """The lead-speed estimate's standard deviation (m/s; NaN without a lead)."""
    x: float = 0.0
    """Distance travelled since start (m, the encoders' mean; road position for terrain)."""


CLOCK_SLACK_S = 0.25
"""How far the firmware's sample clock may run ahead of the caller's between two encoder
samples (s: the caller stamps a batch of samples with one time, late after a stall); more
is a restart or a jump of that clock, not time that passed."""


def wrap_delta(new: int, old: int, modulo: int) -> int:
    """Signed difference of two wrapping counters (result in ``[-modulo/2, modulo/2)``)."""
    half = modulo // 2
    return (new - old + half) % modulo - half


def wrap_dt(new: float, old: float, modulo: float) -> float:
    """Elapsed time between two stamps of a clock that wraps at ``modulo`` (s)."""
    return (new - old) % modulo


@dataclass
class _Kf2:
    """A 2-state Kalman filter ``[position-like, rate]`` (plain floats, no numpy)."""

    x0: float = 0.0
    x1: float = 0.0
    p00: float = 1.0
    p01: float = 0.0
    p11: float = 1.0

    def predict(self, dt: float, accel_std: float, u0: float = 0.0) -> None:
        """``x0 += dt (x1 + u0)``; white acceleration noise of std accel_std."""
        self.x0 += dt * (self.x1 + u0)
        q = accel_std * accel_std
        p00 = self.p00 + dt * (2.0 * self.p01 + dt * self.p11) + q * dt**4 / 4.0
        p01 = self.p01 + dt * self.p11 + q * dt**3 / 2.0
        self.p00, self.p01, self.p11 = p00, p01, self.p11 + q * dt * dt

    def innovation(self, z: float, r: float) -> tuple[float, float]:
        """Innovation and its variance for a measurement of x0 with variance r."""
        return z - self.x0, self.p00 + r

    def update(self, z: float, r: float) -> None:
        """Measurement of x0 with variance r."""
        y, s = z - self.x0, self.p00 + r  # innovation(z, r)
        k0, k1 = self.p00 / s, self.p01 / s
        self.x0 += k0 * y
        self.x1 += k1 * y
        p00 = (1.0 - k0) * self.p00
        p01 = (1.0 - k0) * self.p01
        p11 = self.p11 - k1 * self.p01
        self.p00, self.p01, self.p11 = p00, p01, p11


@dataclass
class _SpeedState:
    kf: _Kf2 = field(default_factory=_Kf2)
    last: EncoderSample | None = None
    """The reference of the next difference."""
    t_ref: float = -math.inf
    """Caller time at which ``last`` arrived (s)."""
    behind: EncoderSample | None = None
    """The last sample dropped as behind ``last`` (None after one that was not)."""
    t_last: float = -math.inf
    """Caller time of the last measurement the filter took (s)."""
    distance: float = 0.0
    samples: int = 0
    run: int = 0
    """Samples since the filter (re)started: a speed from ``valid_from`` on."""
    restarts: int = 0
    suspect: bool = False
    """The last sample's step was out of bounds and dropped (a glitch if the next one
    agrees with ``last``, a discontinuity if it does not either)."""
    glitches: int = 0
    valid_from: int = 2
    """``run`` from which the speed is valid: 2 (the first difference) at the start, 3
    after a restart (the first difference confirmed by the next: one taken from a stale
    count would otherwise be a valid spike)."""


@dataclass
class _LeadState:
    kf: _Kf2 = field(default_factory=_Kf2)
    active: bool = False
    t_mcu: float = 0.0
    t_accept: float = -math.inf
    status: str = "none"
    candidates: list[tuple[float, float]] = field(default_factory=list)
    outliers: int = 0
    reinits: int = 0
    samples: int = 0


def for_truck(cfg: EstimatorConfig, p: VehicleParams, u_max: float) -> EstimatorConfig:
    """``cfg`` for a truck whose model is ``p`` driven up to ``u_max`` V: ``accel_max`` at
    least the model's stall acceleration (:meth:`VehicleParams.stall_acceleration`), so
    that a light or strong truck's own acceleration is motion, not a discontinuity (a
    tenth of the default's inertia, 234 m/s^2, crawled at 0.67 m/s of 1.8 under the
    default 30)."""
    stall = p.stall_acceleration(u_max)
    if not math.isfinite(stall) or stall <= cfg.accel_max:
        return cfg
    return dataclasses.replace(cfg, accel_max=stall)


class Estimator:
    """Own speed and lead state from raw encoder and range samples (see module docstring)."""

    def __init__(self, cfg: EstimatorConfig, wheel_radius: float, ticks_per_rev: int) -> None:
        """``wheel_radius`` (m); ``ticks_per_rev`` the firmware's (``link:`` section)."""
        if ticks_per_rev < 1:
            raise ValueError(f"ticks_per_rev must be >= 1, got {ticks_per_rev}")
        self.cfg = cfg
        self.tick_len = 2.0 * math.pi * wheel_radius / ticks_per_rev
        self._r_tick = self.tick_len * self.tick_len / 12.0
        self._s = _SpeedState()
        self._l = _LeadState()

    # -- own speed ------------------------------------------------------------------
    def update_encoders(self, t: float, s: EncoderSample) -> None:
        """A new encoder sample received at caller time t (s)."""
        st = self._s
        if not (math.isfinite(t) and math.isfinite(s.sample_time)):
            return  # no time to place it at: a NaN would poison the filter for good
        st.samples += 1
        if st.last is None:
            st.last, st.t_ref, st.run = s, t, 1
            return
        modulo = self.cfg.sample_time_modulo
        dt = wrap_dt(s.sample_time, st.last.sample_time, modulo)
        if dt <= 0.0:
            return  # the same sample again
        if dt > 0.5 * modulo:  # behind the last one
            prev, st.behind = st.behind, s
            if prev is None:
                return  # out of order: dropped
            dt = wrap_dt(s.sample_time, prev.sample_time, modulo)
            if not 0.0 < dt < 0.5 * modulo:
                return  # out of order: dropped
            # Two in a row, in order: the firmware's clock restarted.  Difference from the
            # first of them.
            self._restart(prev, t)
        elif dt > (t - st.t_ref) + CLOCK_SLACK_S:
            # The firmware's clock ran ahead of the caller's: it restarted (or jumped).
            self._restart(s, t)
            return
        st.behind = None
        m = self.cfg.ticks_modulo
        half = m // 2
        last = st.last
        assert last is not None
        # The healthy wheels' count differences (wrap_delta, written out): their sum and
        # how many.
        total = wheels = 0
        if s.left_ok and last.left_ok:
            total, wheels = (s.ticks_left - last.ticks_left + half) % m - half, 1
        if s.right_ok and last.right_ok:
            total += (s.ticks_right - last.ticks_right + half) % m - half
            wheels += 1
        if not wheels:
            st.last, st.t_ref, st.suspect = s, t, False
            return  # no healthy wheel: the speed goes stale
        step = self.tick_len * total / wheels
        if abs(step) > self.cfg.speed_max * dt + 2.0 * self.tick_len or (
            st.run >= 2 and abs(step - st.kf.x1 * dt) > self._speed_room(dt)
        ):
            if st.run >= 2 and not st.suspect:
                st.suspect = True  # dropped: the next sample tells a glitch from a jump
                return
            self._restart(s, t)  # no motion: the counters reset or jumped
            return
        if st.suspect:
            st.suspect = False
            st.glitches += 1
        st.last, st.t_ref = s, t
        st.distance += step
        st.run += 1
        if st.run == 2:
            # Start from the first finite difference, not from 0 (the truck may be moving).
            var_v = 2.0 * self._r_tick / (dt * dt)
            st.kf = _Kf2(st.distance, step / dt, self._r_tick, 0.0, var_v)
        else:
            st.kf.predict(dt, self.cfg.speed_accel_std)
            st.kf.update(st.distance, self._r_tick / wheels)
        st.t_last = t

    def _speed_room(self, dt: float) -> float:
        """How far (m) a step over ``dt`` (s) may lie from the filter's speed: what
        ``accel_max`` allows, two ticks of quantisation and four standard deviations of the
        speed estimate.  A counter reset that looked like an ordinary step under the speed
        bound (0.1 s, 2000 ticks back: -19 m/s) lies far outside it."""
        p11 = self._s.kf.p11
        sd = math.sqrt(0.0 if 0.0 > p11 else p11)  # max(p11, 0.0)
        return (self.cfg.accel_max * dt + 4.0 * sd) * dt + 2.0 * self.tick_len

    def _restart(self, s: EncoderSample, t: float) -> None:
        """The own-speed filter starts again from ``s`` (a speed once the next two
        differences agree)."""
        st = self._s
        st.last, st.t_ref, st.run, st.behind, st.suspect = s, t, 1, None, False
        st.valid_from = 3
        st.restarts += 1

    def speed(self, t: float) -> tuple[float, bool]:
        """Own speed (m/s) and whether it is fresh at caller time t (s)."""
        st = self._s
        fresh = st.run >= st.valid_from and (t - st.t_last) <= self.cfg.encoder_timeout_s
        return st.kf.x1, fresh

    # -- lead -------------------------------------------------------------------------
    def update_range(self, t: float, r: RangeSample, v_own: float) -> None:
        """A new range sample received at caller time t (s); v_own the own speed (m/s)."""
        cfg, ld = self.cfg, self._l
        if not (math.isfinite(t) and math.isfinite(r.sample_time) and math.isfinite(v_own)):
            return  # no time (or own speed) to place it at: not a sample
        ld.samples += 1
        d = r.distance
        if d is not None and 0.0 <= d < cfg.range_min:
            d = cfg.range_min  # closer than the sensor resolves: as close as it can say
        if d is None or not math.isfinite(d) or not (cfg.range_min <= d <= cfg.range_max):
            if ld.active:
                self._predict_lead(r.sample_time, v_own)
            ld.status = "no_target"
            ld.candidates.clear()
            return
        var_r = cfg.range_noise_std**2
        if not ld.active:
            self._start(t, r.sample_time, d, v_own)
            return
        self._predict_lead(r.sample_time, v_own)
        y, s = ld.kf.innovation(d, var_r)
        if y * y <= cfg.gate_sigma**2 * s:
            ld.kf.update(d, var_r)
            ld.t_accept, ld.status = t, "tracking"
            ld.candidates.clear()
            return
        ld.outliers += 1
        self._consider_new_target(t, r.sample_time, d, v_own)

    def _start(self, t: float, t_mcu: float, d: float, v_own: float) -> None:
        ld = self._l
        ld.kf = _Kf2(d, v_own, self.cfg.range_noise_std**2, 0.0, 1.0)
        ld.active, ld.t_mcu, ld.t_accept, ld.status = True, t_mcu, t, "tracking"
        ld.candidates.clear()

    def _consider_new_target(self, t: float, t_mcu: float, d: float, v_own: float) -> None:
        """Outliers that agree with each other for ``reinit_count`` samples: a new target."""
        ld, cfg = self._l, self.cfg
        tol = 3.0 * cfg.range_noise_std + 0.05
        if ld.candidates:
            t_prev, d_prev = ld.candidates[-1]
            dt = wrap_dt(t_mcu, t_prev, cfg.sample_time_modulo)
            # Consistent if it moved as a target at most 3 m/s faster or slower would.
            if abs(d - d_prev) > tol + 3.0 * dt:
                ld.candidates.clear()
        ld.candidates.append((t_mcu, d))
        if len(ld.candidates) >= cfg.reinit_count:
            (t0, d0), (t1, d1) = ld.candidates[0], ld.candidates[-1]
            span = wrap_dt(t1, t0, cfg.sample_time_modulo)
            closing = (d1 - d0) / span if span > 0.0 else 0.0
            self._start(t, t_mcu, d1, v_own + closing)
            ld.kf.p11 = 0.5**2
            ld.reinits += 1

    def _predict_lead(self, t_mcu: float, v_own: float) -> None:
        ld = self._l
        dt = wrap_dt(t_mcu, ld.t_mcu, self.cfg.sample_time_modulo)
        if 0.0 < dt < 0.5 * self.cfg.sample_time_modulo:
            ld.kf.predict(dt, self.cfg.lead_accel_std, -v_own)
            ld.kf.x1 = max(ld.kf.x1, 0.0)  # the lead does not reverse
            ld.t_mcu = t_mcu
        elif dt > 0.0:
            # Behind the last one: the firmware's clock restarted (or one sample came out
            # of order): predict from here on, not never again.
            ld.t_mcu = t_mcu

    def cycle(
        self, t: float, encoders: Sequence[EncoderSample], ranges: Sequence[RangeSample]
    ) -> Estimate:
        """A cycle's samples (oldest first) received at caller time t (s): the encoders,
        then the ranges (each with the own speed as it stands), then :meth:`estimate`.
        The reference of the compiled update (:mod:`truckd.control.cestimator`)."""
        for e in encoders:
            self.update_encoders(t, e)
        for r in ranges:
            self.update_range(t, r, self._s.kf.x1)  # v_own: speed(t)'s
        return self.estimate(t)

    def estimate(self, t: float) -> Estimate:
        """The state at caller time t (s): gap predicted to the latest encoder sample."""
        v, speed_ok = self.speed(t)
        ld = self._l
        lost = (t - ld.t_accept) > self.cfg.lead_timeout_s
        valid = ld.active and not lost
        if ld.active and lost:
            ld.active = False
        status = ld.status if valid else ("timeout" if ld.status == "tracking" else ld.status)
        gap, v_lead, std, v_lead_std = math.nan, math.nan, math.nan, math.nan
        if valid:
            gap, v_lead = ld.kf.x0, ld.kf.x1
            last = self._s.last
            if last is not None:
                dt = wrap_dt(last.sample_time, ld.t_mcu, self.cfg.sample_time_modulo)
                if dt < 0.5:
                    gap += dt * (v_lead - v)
            p00, p11 = ld.kf.p00, ld.kf.p11  # sqrt(max(p, 0.0)), the max written out
            std = math.sqrt(0.0 if 0.0 > p00 else p00)
            v_lead_std = math.sqrt(0.0 if 0.0 > p11 else p11)
        sp = self._s
        # Positional, in the fields' order (a keyword call to a class builds a dict of
        # them, every cycle).
        return Estimate(
            v,
            speed_ok,  # speed_valid
            gap,
            v_lead,
            valid,  # lead_valid
            status if status != "tracking" or valid else "timeout",  # lead_status
            std,  # gap_std
            ld.outliers,
            ld.reinits,
            sp.samples,  # encoder_samples
            ld.samples,  # range_samples
            sp.restarts,  # speed_restarts
            sp.glitches,  # speed_glitches
            t - sp.t_last,  # speed_age
            v_lead_std,
            sp.distance,  # x
        )

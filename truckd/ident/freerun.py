"""The free-run engine of the fast simulator: a first-order mechanical model, exact per
segment.

The electrical time constant ``L_m/R_m`` (< 1 ms) is far below a 10 ms sample, so the
current is quasi-static, ``i = (V - K_v omega) / R_tot``, and the drivetrain is first
order in the speed ``w`` (motor rad/s, or m/s for a force-input rig):

    dw/dt = a - b w - s c - d        (sliding, s = sign of w)
    w = 0 while |a - d| <= sigma     (held by stiction)

``a`` input acceleration, ``b`` damping (1/s), ``c`` Coulomb, ``sigma`` stiction and ``d``
load, all per unit inertia.  Each segment (constant inputs) is solved exactly: speed
reaching zero and breakaway are found in closed form, aero drag is linearised at each
segment's start exactly as :class:`truckd.sim.plant.Plant` does.  What the coefficients
are for a voltage-input log (driver, battery, winding, terrain: the effects of
:mod:`truckd.model.effects`) is worked out in :mod:`truckd.ident.fastsim`; the loop
itself runs in C (:mod:`truckd.ident.ckernel`) when built.  Pure numerics, no I/O.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from truckd.ident import ckernel
from truckd.model.effects import (
    BACKLASH_STEP,
    Effects,
    current_limited,
    gap_at_start,
    gap_free_motion,
    gap_opens,
    limited_torque,
    stribeck_torque,
    terrain_force,
)
from truckd.model.params import VehicleParams

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Timeline:
    """Sub-intervals between sample instants and delayed-command switches.

    ``dt[j]`` duration (s) of sub-interval j, ``cmd[j]`` index of the command active
    over it (-1 = none yet), ``sample_end[j]`` index of the sample taken at its end
    (-1 when it does not end on a sample instant).
    """

    dt: Array
    cmd: NDArray[np.int64]
    sample_end: NDArray[np.int64]


def timeline(t: Array, delay: float, hist: int = 0, t_cmd: Array | None = None) -> Timeline:
    """Sub-intervals for commands issued at ``t_cmd`` acting ``delay`` s later.

    ``t`` are the sample instants; ``t_cmd`` (default ``t``) the command instants, which
    are ``hist`` earlier commands followed by ``t`` itself (a log's history before a
    chunk).  Mirrors the plant: a command whose action time falls exactly on a sample
    instant acts from that instant on.
    """
    n = len(t)
    tc = t if t_cmd is None else t_cmd
    if delay <= 0.0:
        return Timeline(
            dt=np.diff(t),
            cmd=np.arange(hist, hist + n - 1, dtype=np.int64),
            sample_end=np.arange(1, n, dtype=np.int64),
        )
    eps = 1e-12 * max(1.0, abs(float(t[-1])))
    act = tc + delay
    act = act[(act > t[0]) & (act < t[-1])]
    # Merge sample instants and action instants; ties resolved as in the plant.
    bounds = np.concatenate([t, act])
    is_sample = np.concatenate([np.ones(n, bool), np.zeros(len(act), bool)])
    order = np.argsort(bounds, kind="stable")
    bounds, is_sample = bounds[order], is_sample[order]
    # Drop action instants that coincide with a sample instant.
    keep = np.ones(len(bounds), bool)
    close = np.flatnonzero(np.diff(bounds) <= eps)
    for j in close:
        if is_sample[j] and not is_sample[j + 1]:
            keep[j + 1] = False
        elif not is_sample[j] and is_sample[j + 1]:
            keep[j] = False
    bounds, is_sample = bounds[keep], is_sample[keep]
    starts = bounds[:-1]
    # Command active over [start, next): the last one with action time <= start.
    cmd = np.searchsorted(tc + delay, starts + eps, "right") - 1
    sample_idx = np.cumsum(is_sample) - 1
    sample_end = np.where(is_sample[1:], sample_idx[1:], -1)
    return Timeline(
        dt=np.diff(bounds), cmd=cmd.astype(np.int64), sample_end=sample_end.astype(np.int64)
    )


@dataclass(frozen=True)
class Kinetics:
    """Per-command coefficients of the first-order model (see module docstring).

    ``a[k]`` input acceleration under command k, ``b[k]`` damping (1/s, without drag),
    ``a_idle``/``b_idle`` before the first command acts; ``c`` Coulomb, ``sigma``
    stiction, ``d`` constant load (all per unit inertia, speed units per s);
    ``drag`` coefficient of ``w |w|`` per unit inertia.
    """

    a: Array
    b: Array
    a_idle: float
    b_idle: float
    c: float
    sigma: float
    d: float
    drag: float = 0.0
    scale: Array | None = None
    """Per-command factor on ``c``, ``sigma``, ``d`` and ``drag`` (None = 1)."""
    lag: float = 0.0
    """Electrical lag (s) for the breakaway test when the speed reaches zero."""
    terrain: Callable[[float], float] | None = None
    """Extra load per unit inertia at position ``x`` (integral of speed from the start),
    evaluated at the start of each sub-interval as the plant does (None = none)."""
    a_max: float = math.inf
    """Largest drive acceleration (per unit inertia) a current limit allows."""
    b_mech: float = 0.0
    """The part of ``b`` that is mechanical (viscous), kept while the current limit binds
    (the back-EMF part of ``b`` then no longer acts: the current is held)."""
    stribeck: Callable[[float], float] | None = None
    """Sliding friction above ``c`` per unit inertia at speed ``w`` (None = none),
    evaluated at the start of each sub-interval as the plant does."""
    gap: GapRun | None = None
    """The backlash gap (None = no backlash)."""
    heat: ckernel.HeatArrays | None = None
    """A resistance drift stepped beside the speed (by the kernel only; None = none)."""


def _limited(
    w: float,
    a: float,
    b: float,
    b_mech: float,
    kin: Kinetics,
    c: float,
    sigma: float,
    d: float,
    h: float,
) -> tuple[float, float] | None:
    """A sub-interval that starts with the current limit binding: ``(end speed, integral
    of speed)``, or None when the limit does not bind at its start.

    While it binds the drive is the constant ``+-a_max`` (damping ``b_mech`` only); when
    the speed reaches where the unlimited drive ``a - (b - b_mech) w`` falls within the
    limit, the rest is solved unlimited (the driver's drive only shrinks in magnitude
    under a constant command: the speed approaches its steady value)."""
    b_emf = b - b_mech
    drive = a - b_emf * w
    if abs(drive) <= kin.a_max:
        return None
    s_l = 1.0 if drive > 0.0 else -1.0
    a_l = s_l * kin.a_max
    w_end, dist = _segment(w, a_l, b_mech, c, sigma, d, h, kin.lag)
    if b_emf <= 0.0 or abs(a - b_emf * w_end) >= kin.a_max:
        return w_end, dist
    # The limit releases inside: at w* where a - b_emf w* = a_l.  Find when (bisection on
    # the exact limited solution; it is monotone in time up to w*).
    w_star = (a - a_l) / b_emf
    t_rel = _time_to(w, w_star, a_l, b_mech, c, d)
    if t_rel is not None and 0.0 <= t_rel <= h:
        w1, d1 = _segment(w, a_l, b_mech, c, sigma, d, t_rel, kin.lag)
        w2, d2 = _segment(w1, a, b, c, sigma, d, h - t_rel, kin.lag)
        return w2, d1 + d2
    lo, hi = 0.0, h
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        wm, _ = _segment(w, a_l, b_mech, c, sigma, d, mid, kin.lag)
        if (wm - w_star) * s_l < 0.0:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-9 * h:
            break
    w1, d1 = _segment(w, a_l, b_mech, c, sigma, d, hi, kin.lag)
    w2, d2 = _segment(w1, a, b, c, sigma, d, h - hi, kin.lag)
    return w2, d1 + d2


def _time_to(w: float, target: float, a: float, b: float, c: float, d: float) -> float | None:
    """When the speed, sliding from ``w`` (not 0) under ``dw/dt = a - b w - s c - d``,
    reaches ``target`` of the same sign (closed form); None when it does not."""
    if w == 0.0 or w * target <= 0.0:
        return None
    s = 1.0 if w > 0.0 else -1.0
    g = a - s * c - d
    if b * abs(target - w) < 1e-9 * max(abs(g), 1e-300):
        t = (target - w) / g if g != 0.0 else -1.0
        return t if t >= 0.0 else None
    ratio = (target - g / b) / (w - g / b)
    if not ratio > 0.0:
        return None
    t = -math.log(ratio) / b
    return t if t >= 0.0 else None


def _phi(b: float, h: float) -> tuple[float, float, float]:
    """``(exp(-b h), (1 - exp(-b h))/b, (h - phi1)/b)``, accurate for small ``b h``."""
    bh = b * h
    if bh < 1e-5:
        phi1 = h * (1.0 - 0.5 * bh + bh * bh / 6.0)
        phi2 = h * h * (0.5 - bh / 6.0 + bh * bh / 24.0)
        return 1.0 - bh + 0.5 * bh * bh, phi1, phi2
    em1 = -math.expm1(-bh)
    phi1 = em1 / b
    return 1.0 - em1, phi1, (h - phi1) / b


def _segment(
    w: float,
    a: float,
    b: float,
    c: float,
    sigma: float,
    d: float,
    h: float,
    lag: float = 0.0,
) -> tuple[float, float]:
    """Exact segment of length h (s): returns (end speed, integral of speed).

    ``lag`` (s): the electrical lag; when the speed reaches zero the current still
    carries the back-EMF of ``lag`` earlier, which the breakaway test includes.
    """
    dist = 0.0
    extra = 0.0
    for _ in range(4):
        if h <= 0.0:
            break
        if w == 0.0:
            net = a - d + extra
            extra = 0.0
            if abs(net) <= sigma:
                return 0.0, dist
            s = 1.0 if net > 0.0 else -1.0
        else:
            s = 1.0 if w > 0.0 else -1.0
        g = a - s * c - d  # acceleration at zero speed in the sliding direction
        e, phi1, phi2 = _phi(b, h)
        w1 = w * e + g * phi1
        if w1 * s > 0.0:
            return w1, dist + w * phi1 + g * phi2
        if w == 0.0 or g * s >= 0.0:
            return 0.0, dist  # breakaway torque but no motion possible
        # Speed reaches zero inside the segment: w e^{-bt} + g phi1(t) = 0.
        x = -b * w / g
        tz = math.log1p(x) / b if b * h > 1e-9 else -w / g
        tz = min(max(tz, 0.0), h)
        _, p1, p2 = _phi(b, tz)
        dist += w * p1 + g * p2
        h -= tz
        w = 0.0
        extra = b * g * lag
    return w, dist


KERNEL_FIELDS = frozenset(
    (
        "a", "b", "a_idle", "b_idle", "c", "sigma", "d", "drag", "scale", "lag", "terrain",
        "a_max", "b_mech", "stribeck", "gap", "heat",
    )
)  # fmt: skip
"""The :class:`Kinetics` fields the C kernel (:mod:`truckd.ident.ckernel`) models."""


_UNKNOWN_TO_KERNEL = tuple(f for f in dataclasses.fields(Kinetics) if f.name not in KERNEL_FIELDS)
"""The :class:`Kinetics` fields outside :data:`KERNEL_FIELDS` (checked per run)."""


def kernel_handles(kin: Kinetics) -> bool:
    """Whether the C kernel models ``kin``: a position-dependent load only as a
    :class:`Terrain`, a Stribeck friction only as a :class:`Stribeck`, and every field
    it does not know at its default (a newer model feature runs the Python loop)."""
    if kin.terrain is not None and not isinstance(kin.terrain, Terrain):
        return False
    if kin.stribeck is not None and not isinstance(kin.stribeck, Stribeck):
        return False
    for f in _UNKNOWN_TO_KERNEL:
        if f.default is dataclasses.MISSING or getattr(kin, f.name) != f.default:
            return False
    return True


def run(
    kin: Kinetics,
    tl: Timeline,
    n: int,
    w0: float,
    sensor_lag: float = 0.0,
    use_kernel: bool = True,
    band: Array | None = None,
) -> tuple[Array, Array, Array]:
    """Free run from speed w0; returns per-sample (speed, mean speed, position).

    The C kernel runs it when built and it models ``kin`` (:func:`kernel_handles`;
    ``use_kernel=False``: always the Python loop, the reference).  ``band``: two floats
    the kernel fills with the run's band of breakaway thresholds (see
    :func:`truckd.ident.ckernel.run`); the Python loop leaves them as they are.

    ``speed[k]`` at ``t[k]`` as the sensor reports it (low-pass ``sensor_lag`` s applied
    to the mean speed over each sample step, as the plant does), ``mean`` the raw
    instantaneous speed, ``pos`` the integral of speed.
    """
    if use_kernel and kernel_handles(kin):
        done = _run_in_c(kin, tl, n, w0, sensor_lag, band)
        if done is not None:
            return done
    if kin.heat is not None:
        raise RuntimeError("a heated run needs the C kernel (make firmware) and a run it models")
    return _run_in_python(kin, tl, n, w0, sensor_lag)


def _run_in_c(
    kin: Kinetics, tl: Timeline, n: int, w0: float, sensor_lag: float, band: Array | None = None
) -> tuple[Array, Array, Array] | None:
    """:func:`run` by the C kernel (None: it is not built)."""
    tr = kin.terrain
    ter = None
    if isinstance(tr, Terrain):
        e = tr.eff
        ter = (
            tr.per_newton, tr.ratio, tr.x0, e.load_force_amplitude,
            e.load_force_wavelength, e.load_force_phase, e.hill_force, e.hill_start,
            e.hill_length,
        )  # fmt: skip
    sb = kin.stribeck
    stb = sb.kernel_args() if isinstance(sb, Stribeck) else None
    lim = (kin.a_max, kin.b_mech) if kin.a_max < math.inf else None
    g = kin.gap
    gap = None
    if g is not None:
        gap = (g.constants, g.volts_arr, g.r_arr, g.state(), g.rotor_out)
    return ckernel.run(
        kin.a, kin.b, kin.a_idle, kin.b_idle, kin.c, kin.sigma, kin.d, kin.drag,
        kin.scale, kin.lag, tl.dt, tl.cmd, tl.sample_end, n, w0, sensor_lag, ter, stb, lim, gap,
        band, kin.heat,
    )  # fmt: skip


def _run_in_python(
    kin: Kinetics, tl: Timeline, n: int, w0: float, sensor_lag: float
) -> tuple[Array, Array, Array]:
    """:func:`run` as a Python loop over the sub-intervals: the reference the C kernel
    (``kernel/fastrun.c``) follows step by step (every effect: current limit, Stribeck
    friction and backlash included), and the runner when the kernel is not built or a
    newer :class:`Kinetics` field is set.

    Long because it is one loop kept whole on purpose: it mirrors the C kernel's loop
    line for line (``tests/test_ident_kernel.py`` compares them), and its fast path is
    inlined (it saves a function call per sub-interval).
    """
    out = np.empty(n)
    raw = np.empty(n)
    pos = np.empty(n)
    out[0] = raw[0] = w0
    pos[0] = 0.0
    w = w0
    v_lag = w0
    x = 0.0
    x_step0 = 0.0
    h_step = 0.0
    a_list = kin.a.tolist()
    b_list = kin.b.tolist()
    c, sigma, d, drag = kin.c, kin.sigma, kin.d, kin.drag
    lag = kin.lag
    terrain = kin.terrain
    sc_list = kin.scale.tolist() if kin.scale is not None else None
    lag_alpha_cache: dict[float, float] = {}
    limit = kin.a_max < math.inf
    stribeck = kin.stribeck
    gap = kin.gap
    for dt, k, se in zip(tl.dt.tolist(), tl.cmd.tolist(), tl.sample_end.tolist(), strict=True):
        f = 1.0
        if k >= 0:
            a, b = a_list[k], b_list[k]
            if sc_list is not None:
                f = sc_list[k]
                c, sigma, d, drag = kin.c * f, kin.sigma * f, kin.d * f, kin.drag * f
        else:
            a, b = kin.a_idle, kin.b_idle
        if terrain is not None:
            d = (kin.d + terrain(x)) * f
        if stribeck is not None:
            # Breakaway takes at least the sliding friction at zero speed.
            sigma = max(kin.sigma, kin.c + stribeck(0.0)) * f
            c = (kin.c + stribeck(w)) * f
            if dt > 0.0:
                # Midpoint: the friction at the speed halfway through the sub-interval
                # (predicted with the friction at its start).
                w_half, _ = _segment(w, a, b, c, sigma, d, 0.5 * dt, lag)
                c = (kin.c + stribeck(0.5 * (w + w_half) if w != 0.0 else w_half)) * f
        if drag != 0.0:
            aw = abs(w)
            b_eff = b + 2.0 * drag * aw
            d_eff = d - drag * w * aw
        else:
            b_eff, d_eff = b, d
        rigid = dt
        if gap is not None:
            b_m = kin.b_mech * f + (b_eff - b)
            w, dx, used = gap.step(k, w, dt, c / f, d_eff / f, b_m / f)
            x += dx
            rigid = dt - used
        if limit or gap is not None:
            if rigid > 0.0:
                w, x = _rigid(w, x, a, b, b_eff, c, sigma, d_eff, f, rigid, kin, limit, lag)
        # Fast path (inlined): sliding on, no zero crossing, not a tiny b*dt.
        elif w != 0.0 and b_eff * dt >= 1e-5:
            s = 1.0 if w > 0.0 else -1.0
            g = a - s * c - d_eff
            em1 = -math.expm1(-b_eff * dt)
            phi1 = em1 / b_eff
            w1 = w * (1.0 - em1) + g * phi1
            if w1 * s > 0.0:
                x += w * phi1 + g * (dt - phi1) / b_eff
                w = w1
            else:
                w, dx = _segment(w, a, b_eff, c, sigma, d_eff, dt, lag)
                x += dx
        else:
            w, dx = _segment(w, a, b_eff, c, sigma, d_eff, dt, lag)
            x += dx
        if gap is not None and se >= 0:
            gap.rotor_out[se] = gap.gap.rotor if gap.gap.side == 0 else w
        h_step += dt
        if se >= 0:
            raw[se] = w
            pos[se] = x
            if sensor_lag > 0.0:
                alpha = lag_alpha_cache.get(h_step)
                if alpha is None:
                    alpha = 1.0 - math.exp(-h_step / sensor_lag)
                    lag_alpha_cache[h_step] = alpha
                v_lag += alpha * ((x - x_step0) / h_step - v_lag)
                out[se] = v_lag
            else:
                out[se] = w
            x_step0 = x
            h_step = 0.0
    return out, raw, pos


def _rigid(
    w: float,
    x: float,
    a: float,
    b: float,
    b_eff: float,
    c: float,
    sigma: float,
    d_eff: float,
    f: float,
    dt: float,
    kin: Kinetics,
    limit: bool,
    lag: float,
) -> tuple[float, float]:
    """One sub-interval of the drivetrain moving as one body: ``(speed, position)``."""
    if limit:
        b_m = kin.b_mech * f + (b_eff - b)
        done = _limited(w, a, b_eff, b_m, kin, c, sigma, d_eff, dt)
        if done is not None:
            return done[0], x + done[1]
    # Fast path (inlined): sliding on, no zero crossing, not a tiny b*dt.
    bh = b_eff * dt
    if w != 0.0 and bh >= 1e-5:
        s = 1.0 if w > 0.0 else -1.0
        g = a - s * c - d_eff
        em1 = -math.expm1(-bh)
        phi1 = em1 / b_eff
        w1 = w * (1.0 - em1) + g * phi1
        if w1 * s > 0.0:
            return w1, x + w * phi1 + g * (dt - phi1) / b_eff
    w, dx = _segment(w, a, b_eff, c, sigma, d_eff, dt, lag)
    return w, x + dx


class GapRun:
    """The backlash gap during a fast run (:func:`truckd.model.effects.gap_free_motion`,
    the plant's physics), with per-command driver voltage and circuit resistance."""

    def __init__(
        self,
        p: VehicleParams,
        eff: Effects,
        volts: Array,
        r: Array,
        v_idle: float,
        kappa: float,
        n: int,
        w0: float,
    ) -> None:
        self.p, self.eff = p, eff
        self.volts, self.r = volts.tolist(), r.tolist()
        self.volts_arr = np.ascontiguousarray(volts, dtype=np.float64)
        self.r_arr = np.ascontiguousarray(np.broadcast_to(r, volts.shape), dtype=np.float64)
        self.v_idle = v_idle
        self.per = p.J_S / kappa
        """Torque (N m) per unit of the run's per-inertia coefficients."""
        self.gap = gap_at_start(eff, w0)
        self.rotor_out = np.full(n, w0)
        """Rotor speed (rad/s) at each sample (the load's while the gap is closed)."""
        self.constants = (
            p.K_T, p.K_v, p.J_S, p.K_stiction, p.R_m, eff.rotor_inertia_fraction,
            eff.backlash, limited_torque(p, eff), self.per, v_idle, BACKLASH_STEP,
            eff.current_limit,
        )  # fmt: skip
        """What the C kernel's gap needs (``kernel/fastrun.c``, ``gap_opens``)."""

    def state(self) -> Array:
        """The gap's state as the C kernel keeps it: ``[side, angle, rotor]``."""
        g = self.gap
        return np.array([float(g.side), g.angle, g.rotor])

    def step(
        self, k: int, w: float, dt: float, c: float, d: float, visc: float
    ) -> tuple[float, float, float]:
        """Open the gap when the gear torque reverses, move across it: ``(load speed,
        angle, time used)`` (no time used while the gap stays closed)."""
        p, eff, g = self.p, self.eff, self.gap
        volts = self.volts[k] if k >= 0 else self.v_idle
        r = self.r[k] if k >= 0 else p.R_m
        coulomb, load, viscous = c * self.per, d * self.per, visc * self.per
        # The driver limits the current as the plant's does: at the load's speed, before
        # the gap opens and while the rotor crosses it.
        volts = current_limited(p, eff, volts, w, r)
        if g.side != 0:
            if not gap_opens(p, eff, g, w, volts, r, coulomb, load, viscous):
                return w, 0.0, 0.0
            g.side, g.rotor = 0, w
        return gap_free_motion(p, eff, g, w, volts, r, coulomb, load, viscous, dt)


def merge_equal(tl: Timeline, a: Array, b: Array) -> Timeline:
    """Join a split sub-interval to the next when the inputs on both sides are equal.

    Exact (the inputs do not change at the split); it halves the work of a delay for
    inputs held over several samples.
    """
    if len(tl.dt) == len(tl.sample_end) and np.all(tl.sample_end >= 0):
        return tl
    k = tl.cmd
    ak = np.where(k >= 0, a[np.maximum(k, 0)], np.nan)
    bk = np.where(k >= 0, b[np.maximum(k, 0)], np.nan)
    same = (ak[:-1] == ak[1:]) & (bk[:-1] == bk[1:])
    drop = np.flatnonzero((tl.sample_end[:-1] < 0) & same)
    if drop.size == 0:
        return tl
    keep = np.ones(len(tl.dt), bool)
    keep[drop] = False
    # Each kept sub-interval absorbs the run of dropped ones just before it.
    starts = np.concatenate([[0], np.flatnonzero(keep)[:-1] + 1])
    dt = np.add.reduceat(tl.dt, starts)
    return Timeline(dt=dt, cmd=tl.cmd[keep], sample_end=tl.sample_end[keep])


@dataclass(frozen=True)
class Terrain:
    """The position-dependent load per unit inertia as a function of the motor angle
    travelled (rad) from ``x0`` (m): ``per_newton * terrain_force(eff, x0 + angle *
    ratio)``; the C kernel computes the same from these fields."""

    eff: Effects
    per_newton: float
    ratio: float
    x0: float

    def __call__(self, angle: float) -> float:
        return self.per_newton * terrain_force(self.eff, self.x0 + angle * self.ratio)


@dataclass(frozen=True)
class Stribeck:
    """The Stribeck friction above Coulomb per unit inertia at motor speed ``w`` (rad/s):
    ``per_nm * stribeck_torque(p, eff, w)``; the C kernel computes the same from
    :meth:`kernel_args`."""

    p: VehicleParams
    eff: Effects
    per_nm: float

    def __call__(self, w: float) -> float:
        return self.per_nm * stribeck_torque(self.p, self.eff, w)

    def kernel_args(self) -> tuple[float, float, float, float]:
        """``(per_nm, amplitude N m, ratio m/rad, speed m/s)`` for ``kernel/fastrun.c``."""
        return (self.per_nm, self.eff.stribeck, self.p.ratio, self.eff.stribeck_speed)

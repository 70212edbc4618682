"""Fast free-run simulator for the fitting loop: a first-order mechanical model.

The electrical time constant ``L_m/R_m`` (< 1 ms) is far below a 10 ms sample, so the
current is quasi-static, ``i = (V - K_v omega) / R_tot``, and the drivetrain is first
order in the speed ``w`` (motor rad/s, or m/s for a force-input rig):

    dw/dt = a - b w - s c - d        (sliding, s = sign of w)
    w = 0 while |a - d| <= sigma     (held by stiction)

``a`` input acceleration, ``b`` damping (1/s), ``c`` Coulomb, ``sigma`` stiction and ``d``
load, all per unit inertia.  Each segment (constant inputs) is solved exactly: speed
reaching zero and breakaway are found in closed form, aero drag is linearised at each
segment's start exactly as :class:`truckd.sim.plant.Plant` does, and the neglected
electrical pole is kept as a pure lag of ``L_m/R_tot``.  Pure numerics, no I/O.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from truckd.ident import ckernel
from truckd.model.effects import Effects, position_dependent, terrain_force
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
    ("a", "b", "a_idle", "b_idle", "c", "sigma", "d", "drag", "scale", "lag", "terrain")
)
"""The :class:`Kinetics` fields the C kernel (:mod:`truckd.ident.ckernel`) models."""


def kernel_handles(kin: Kinetics) -> bool:
    """Whether the C kernel models ``kin``: a position-dependent load only as a
    :class:`Terrain`, and every field it does not know at its default (a newer model
    feature runs the Python loop)."""
    if kin.terrain is not None and not isinstance(kin.terrain, Terrain):
        return False
    for f in dataclasses.fields(kin):
        if f.name in KERNEL_FIELDS:
            continue
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
) -> tuple[Array, Array, Array]:
    """Free run from speed w0; returns per-sample (speed, mean speed, position).

    The C kernel runs it when built and it models ``kin`` (:func:`kernel_handles`;
    ``use_kernel=False``: always the Python loop, the reference).

    ``speed[k]`` at ``t[k]`` as the sensor reports it (low-pass ``sensor_lag`` s applied
    to the mean speed over each sample step, as the plant does), ``mean`` the raw
    instantaneous speed, ``pos`` the integral of speed.
    """
    if use_kernel and kernel_handles(kin):
        tr = kin.terrain
        ter = None
        if isinstance(tr, Terrain):
            e = tr.eff
            ter = (
                tr.per_newton, tr.ratio, tr.x0, e.load_force_amplitude,
                e.load_force_wavelength, e.load_force_phase, e.hill_force, e.hill_start,
                e.hill_length,
            )  # fmt: skip
        done = ckernel.run(
            kin.a, kin.b, kin.a_idle, kin.b_idle, kin.c, kin.sigma, kin.d, kin.drag,
            kin.scale, kin.lag, tl.dt, tl.cmd, tl.sample_end, n, w0, sensor_lag, ter,
        )  # fmt: skip
        if done is not None:
            return done
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
        if drag != 0.0:
            aw = abs(w)
            b_eff = b + 2.0 * drag * aw
            d_eff = d - drag * w * aw
        else:
            b_eff, d_eff = b, d
        # Fast path (inlined): sliding on, no zero crossing, not a tiny b*dt.
        bh = b_eff * dt
        if w != 0.0 and bh >= 1e-5:
            s = 1.0 if w > 0.0 else -1.0
            g = a - s * c - d_eff
            em1 = -math.expm1(-bh)
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


def driver_volts(u: Array, eff: Effects, v_batt: float) -> Array:
    """Vectorised :func:`truckd.model.effects.driver_output` voltage (V)."""
    out = np.where(np.abs(u) >= eff.dead_zone, u, 0.0)
    if eff.dead_zone_offset != 0.0:
        out = np.sign(out) * np.maximum(np.abs(out) - eff.dead_zone_offset, 0.0)
    limit = v_batt if eff.voltage_saturation == 0.0 else min(v_batt, eff.voltage_saturation)
    return np.clip(out, -limit, limit)


@dataclass(frozen=True)
class VoltagePrediction:
    """Free-run prediction of a voltage-input log (SI)."""

    v: Array
    """Speed as the sensor reports it (m/s)."""
    v_true: Array
    """True speed (m/s)."""
    i: Array
    """Quasi-static motor current at each sample (A)."""
    x: Array
    """Position (m)."""
    volts: Array
    """Open-circuit driver voltage active at each sample (V)."""


def _merge_equal(tl: Timeline, a: Array, b: Array) -> Timeline:
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


def electrical_correction(
    p: VehicleParams, viscous: float = 0.0, resistance: Array | float | None = None
) -> tuple[Array, Array]:
    """What the neglected electrical pole does to the first-order model.

    Returns ``(kappa, lag)`` for the armature circuit resistance ``resistance`` (ohm,
    default ``R_m``; an array gives arrays): the exact slow eigenvalue of the two-state
    model over the quasi-static one (time runs ``kappa`` times faster, steady states
    unchanged) and the fast pole's time constant (s), kept as a pure lag of the input.
    """
    r = np.asarray(p.R_m if resistance is None else resistance, float)
    tr = -(r / p.L_m + viscous / p.J_S)
    det = (r * viscous + p.K_v * p.K_T) / (p.L_m * p.J_S)
    disc = np.sqrt(np.maximum(tr * tr / 4.0 - det, 0.0))
    lam_s, lam_f = tr / 2.0 + disc, tr / 2.0 - disc
    beta = (p.K_T * p.K_v / r + viscous) / p.J_S
    return -lam_s / beta, -1.0 / lam_f


def prelog_voltage(p: VehicleParams, eff: Effects, w0: float, i0: float | None) -> float:
    """Motor voltage (V) acting at the start of a log, before its first command does.

    A log that starts mid-motion leaves the commands issued before it unknown; with an
    input delay they still drive the motor for ``input_delay`` s (0 V there would brake
    a moving truck and mis-simulate the next second).  With the current ``i0`` (A)
    measured at the start the voltage is the quasi-static ``R_m i0 + K_v w0``; without
    it, the voltage that holds the start speed ``w0`` (motor rad/s) steady (0 at rest).
    """
    if i0 is not None and np.isfinite(i0):
        return p.R_m * float(i0) + p.K_v * w0
    if w0 == 0.0:
        return 0.0
    s = 1.0 if w0 > 0.0 else -1.0
    torque = (
        s * p.K_coulomb
        + eff.viscous_friction * w0
        + p.force_to_torque(eff.load_force)
        + eff.aero_drag * p.ratio**3 * w0 * abs(w0)
    )
    return p.R_m * torque / p.K_T + p.K_v * w0


HANDLED = (
    "viscous_friction",
    "aero_drag",
    "load_force",
    "input_delay",
    "dead_zone",
    "dead_zone_offset",
    "voltage_saturation",
    "battery_sag",
    "sensor_lag",
    "load_force_amplitude",
    "load_force_wavelength",
    "load_force_phase",
    "hill_force",
    "hill_start",
    "hill_length",
)
"""Effects fields :func:`simulate_voltage` models; any other active field is refused."""


def unsupported_effects(eff: Effects) -> list[str]:
    """Active fields of ``eff`` the fast simulator does not model (empty: all handled)."""
    out = []
    for f in dataclasses.fields(eff):
        if f.name in HANDLED:
            continue
        if float(getattr(eff, f.name)) != 0.0:
            out.append(f.name)
    return out


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


def _terrain(
    p: VehicleParams, eff: Effects, kappa: float, x0: float
) -> Callable[[float], float] | None:
    """The position-dependent load per unit inertia (:class:`Terrain`); None when the
    load does not depend on position."""
    if not position_dependent(eff):
        return None
    return Terrain(eff, kappa * p.force_to_torque(1.0) / p.J_S, p.ratio, x0)


PREP_CACHE = 64
"""Series whose input-side preparation (driver voltage, coefficients, timeline) is kept:
a stiction scan or a friction fit changes only what acts after it."""
_PREP: dict[tuple[object, ...], tuple[Any, ...]] = {}
_UNPREPARED = (
    "load_force",
    "aero_drag",
    "sensor_lag",
    "load_force_amplitude",
    "load_force_wavelength",
    "load_force_phase",
    "hill_force",
    "hill_start",
    "hill_length",
)
"""Effects fields that do not enter the preparation (loads, drag, lag, terrain)."""


def _prep_key(
    p: VehicleParams, eff: Effects, t: Array, u: Array, t_hist: Array | None, u_hist: Array | None
) -> tuple[object, ...]:
    """Cache key of the preparation: the arrays' identities (the cache holds them, so an
    identity cannot be reused while cached) and every parameter that enters it (the whole
    vehicle but its friction, the whole effects but loads, drag, lag and terrain; a new
    effect field is part of the key by construction)."""
    q = p.replace(K_coulomb=0.0, K_stiction=0.0)
    e = dataclasses.replace(eff, **dict.fromkeys(_UNPREPARED, 0.0))
    return (id(t), id(u), id(t_hist), id(u_hist), q, e)


def simulate_voltage(
    p: VehicleParams,
    eff: Effects,
    t: Array,
    u: Array,
    v0: float = 0.0,
    t_hist: Array | None = None,
    u_hist: Array | None = None,
    v_pre: float = 0.0,
    x0: float = 0.0,
) -> VoltagePrediction:
    """Fast free run of the plant model on a log's input (``u[k]`` from ``t[k]``).

    ``x0``: position (m) at ``t[0]``, where a position-dependent load is evaluated from.

    ``t_hist``/``u_hist``: commands issued before ``t[0]`` (a chunk's history), which
    still act after ``t[0]`` when there is an input delay.  ``v_pre``: the motor
    voltage (V) until the first known command acts; 0 as in a plant started by
    :func:`truckd.sim.plant.simulate_open_loop`, see :func:`prelog_voltage` for a log.
    """
    unsupported = unsupported_effects(eff)
    if unsupported:
        raise ValueError(
            f"the fast simulator does not model {', '.join(unsupported)} ; use truckd.sim.plant"
        )
    n = len(t)
    hist = 0 if t_hist is None or u_hist is None else len(t_hist)
    t = np.asarray(t, float)
    u_all = np.asarray(u, float) if not hist else np.concatenate([u_hist, u])
    t_cmd = t if not hist else np.concatenate([t_hist, t])
    key = _prep_key(p, eff, t, u, t_hist, u_hist)
    hit = _PREP.get(key)
    if hit is not None and hit[0] is t and hit[1] is u and hit[2] is t_hist and hit[3] is u_hist:
        volts, r_tot, k_arr, kappa, lag_e, a, b, tl = hit[4]
    else:
        volts = driver_volts(u_all, eff, p.V_batt)
        duty = volts / p.V_batt
        r_tot = p.R_m + eff.battery_sag * duty * duty
        k_arr, _ = electrical_correction(p, eff.viscous_friction, r_tot)
        k0, l0 = electrical_correction(p, eff.viscous_friction)
        kappa, lag_e = float(k0), float(l0)
        a = k_arr * p.K_T / p.J_S * volts / r_tot
        b = k_arr * (p.K_T * p.K_v / r_tot + eff.viscous_friction) / p.J_S
        tl = _merge_equal(timeline(t, eff.input_delay + lag_e, hist, t_cmd), a, b)
        if len(_PREP) >= PREP_CACHE:
            del _PREP[next(iter(_PREP))]
        _PREP[key] = (t, u, t_hist, u_hist, (volts, r_tot, k_arr, kappa, lag_e, a, b, tl))
    load = p.force_to_torque(eff.load_force)
    kin = Kinetics(
        a=a,
        b=b,
        a_idle=kappa * p.K_T / p.J_S * v_pre / p.R_m,
        b_idle=kappa * (p.K_T * p.K_v / p.R_m + eff.viscous_friction) / p.J_S,
        c=kappa * p.K_coulomb / p.J_S,
        sigma=kappa * p.K_stiction / p.J_S,
        d=kappa * load / p.J_S,
        drag=kappa * eff.aero_drag * p.ratio**3 / p.J_S,
        scale=k_arr / kappa if eff.battery_sag != 0.0 else None,
        lag=lag_e,
        terrain=_terrain(p, eff, kappa, x0),
    )
    w0 = p.omega(v0)
    meas, raw, pos = run(kin, tl, n, w0, eff.sensor_lag)
    # Active command at each sample instant (for the quasi-static current).
    act = t_cmd + eff.input_delay
    idx = np.searchsorted(act, t, "left") - 1
    v_at = np.where(idx >= 0, volts[np.maximum(idx, 0)], v_pre)
    r_at = np.where(idx >= 0, r_tot[np.maximum(idx, 0)], p.R_m)
    cur = (v_at - p.K_v * raw) / r_at
    # A command that acted just before the sample: the current is still settling.
    prev = idx - 1
    since = np.where(idx >= 0, t - act[np.maximum(idx, 0)], np.inf)
    v_old = np.where(prev >= 0, volts[np.maximum(prev, 0)], v_pre)
    r_old = np.where(prev >= 0, r_tot[np.maximum(prev, 0)], p.R_m)
    cur_old = (v_old - p.K_v * raw) / r_old
    cur = cur + (cur_old - cur) * np.exp(-since * r_at / p.L_m)
    return VoltagePrediction(
        v=meas * p.ratio, v_true=raw * p.ratio, i=cur, x=pos * p.ratio, volts=v_at
    )


@dataclass(frozen=True)
class ForceModel:
    """Rigid body with friction under a force input (SI, load side).

    ``M dv/dt = F - F_v v - F_c sign(v) - offset - c_drag v|v|``; held at rest while
    ``|F - offset| <= F_s`` (``F_s`` defaults to ``F_c``).
    """

    M: float
    F_c: float
    F_v: float = 0.0
    offset: float = 0.0
    F_s: float | None = None
    c_drag: float = 0.0


def simulate_force(m: ForceModel, t: Array, f: Array, v0: float = 0.0) -> tuple[Array, Array]:
    """Free run of a force-input model: per-sample (speed m/s, position m from 0)."""
    n = len(t)
    fs = m.F_c if m.F_s is None else m.F_s
    b = m.F_v / m.M
    kin = Kinetics(
        a=np.asarray(f, float) / m.M,
        b=np.full(n, b),
        a_idle=0.0,
        b_idle=b,
        c=m.F_c / m.M,
        sigma=fs / m.M,
        d=m.offset / m.M,
        drag=m.c_drag / m.M,
    )
    tl = timeline(np.asarray(t, float), 0.0)
    _, raw, pos = run(kin, tl, n, v0)
    return raw, pos

"""Fast free-run simulator for the fitting loop, built from :mod:`truckd.model`.

What the model's effects (:mod:`truckd.model.effects`: the driver, the battery, the
winding, the Stribeck friction, the terrain, the backlash gap) make of a voltage-input
log, as the coefficients of the first-order model that :mod:`truckd.ident.freerun`
solves exactly per segment.  The effect functions are the plant's own, called on a
whole log at once (:data:`truckd.model.effects.ARRAYS`) or per sub-interval; the
neglected electrical pole is kept as a pure lag of ``L_m/R_tot``.  Pure numerics, no I/O.
"""

from __future__ import annotations

import dataclasses
import operator
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray

from truckd.ident import ckernel
from truckd.ident.data import Series
from truckd.ident.electrical import electrical_correction as electrical_correction
from truckd.ident.freerun import GapRun, Stribeck, merge_equal
from truckd.ident.freerun import Kinetics as Kinetics  # re-exported: the run's inputs
from truckd.ident.freerun import Terrain as Terrain
from truckd.ident.freerun import Timeline as Timeline
from truckd.ident.freerun import run as run
from truckd.ident.freerun import timeline as timeline
from truckd.ident.heating import heat_arrays
from truckd.ident.heating import winding_rises as winding_rises
from truckd.ident.prediction import StictionBand as StictionBand  # re-exported: the result
from truckd.ident.prediction import VoltagePrediction as VoltagePrediction
from truckd.ident.timing import Layout, layout_of, merged, shifted
from truckd.model.effects import (
    ARRAYS,
    COPPER_TEMPCO,
    EFFECT_FIELDS,
    TERRAIN_FIELDS,
    Effects,
    driver_output,
    limited_torque,
    position_dependent,
    winding_resistance,
)
from truckd.model.params import VehicleParams

Array = NDArray[np.float64]


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


HANDLED = EFFECT_FIELDS
"""Effects fields :func:`simulate_voltage` models: every effect the model names
(:data:`truckd.model.effects.EFFECT_FIELDS`); any other active field is refused."""


_OTHERS = tuple(f.name for f in dataclasses.fields(Effects) if f.name not in HANDLED)
"""The effects' fields outside :data:`HANDLED` (each call checks only these)."""


def unsupported_effects(eff: Effects) -> list[str]:
    """Active fields of ``eff`` the fast simulator does not model (empty: all handled)."""
    return [n for n in _OTHERS if float(getattr(eff, n)) != 0.0]


def _terrain(
    p: VehicleParams, eff: Effects, kappa: float, x0: float
) -> Callable[[float], float] | None:
    """The position-dependent load per unit inertia (:class:`Terrain`); None when the
    load does not depend on position."""
    if not position_dependent(eff):
        return None
    return Terrain(eff, kappa * p.force_to_torque(1.0) / p.J_S, p.ratio, x0)


def _put(
    cache: dict[tuple[object, ...], Any], key: tuple[object, ...], value: Any, most: int
) -> Any:
    """Store ``value`` under ``key`` in one of this module's caches, dropping the oldest
    entry once ``most`` are kept; returns ``value``."""
    if len(cache) >= most:
        del cache[next(iter(cache))]
    cache[key] = value
    return value


def forget() -> None:
    """Empty this module's caches (the next simulation of a series rebuilds what it
    needs): a diagnosis calls it when the candidates' fits are done, before the report's
    free runs of the whole log."""
    for cache in (_PREP, _DRIVER, _TIMING, _LAYOUT, _SAMPLED, _RISES):
        cache.clear()


PREP_CACHE = 64
"""Series whose input-side preparation (driver voltage, coefficients, timeline) is kept:
a stiction scan or a friction fit changes only what acts after it."""
_PREP: dict[tuple[object, ...], tuple[Any, ...]] = {}
_UNPREPARED = ("load_force", "aero_drag", "sensor_lag", *TERRAIN_FIELDS)
"""Effects fields that do not enter the preparation (loads, drag, lag, terrain)."""


_PREP_VEHICLE = tuple(
    f.name for f in dataclasses.fields(VehicleParams) if f.name not in ("K_coulomb", "K_stiction")
)
"""The vehicle's fields that enter the preparation (all but its friction)."""
_PREP_EFFECTS = tuple(f.name for f in dataclasses.fields(Effects) if f.name not in _UNPREPARED)
"""The effects' fields that enter it (all but loads, drag, lag and terrain)."""
_vehicle_key = operator.attrgetter(*_PREP_VEHICLE)
_effects_key = operator.attrgetter(*_PREP_EFFECTS)


def _prep_key(
    p: VehicleParams, eff: Effects, t: Array, u: Array, t_hist: Array | None, u_hist: Array | None
) -> tuple[object, ...]:
    """Cache key of the preparation: the arrays' identities (the cache holds them, so an
    identity cannot be reused while cached) and the value of every parameter that enters
    it (the whole vehicle but its friction, the whole effects but loads, drag, lag and
    terrain; a new field is part of the key by construction)."""
    return (id(t), id(u), id(t_hist), id(u_hist), *_vehicle_key(p), *_effects_key(eff))


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
    rise0: float = 0.0,
) -> VoltagePrediction:
    """Fast free run of the plant model on a log's input (``u[k]`` from ``t[k]``).

    ``x0``: position (m) at ``t[0]``, where a position-dependent load is evaluated from.

    ``t_hist``/``u_hist``: commands issued before ``t[0]`` (a chunk's history), which
    still act after ``t[0]`` when there is an input delay.  ``v_pre``: the motor
    voltage (V) until the first known command acts; 0 as in a plant started by
    :func:`truckd.sim.plant.simulate_open_loop`, see :func:`prelog_voltage` for a log.
    ``rise0``: the winding's temperature rise (K) at ``t[0]`` (``resistance_drift``).

    A resistance drift: the C kernel steps the winding beside the speed, in one run
    (:mod:`truckd.ident.heating`); without the kernel the run is simulated cold, then
    again with each command's resistance from the pass before's current until that
    heating converges (:data:`DRIFT_TOLERANCE`: 200 K in about 14 simulations).
    """
    unsupported = unsupported_effects(eff)
    if unsupported:
        raise ValueError(
            f"the fast simulator does not model {', '.join(unsupported)} ; use truckd.sim.plant"
        )
    hist = 0 if t_hist is None or u_hist is None else len(t_hist)
    t = np.asarray(t, float)
    # A fit's trial parameters can be absurd (a winding heated without bound): the run
    # then overflows to inf or NaN, which the residuals score as a miss; no warning.
    with np.errstate(over="ignore", invalid="ignore"):
        if eff.resistance_drift != 0.0 and ckernel.available():
            return _simulate(p, eff, t, u, v0, t_hist, u_hist, v_pre, x0, None, rise0)
        out = _simulate(p, eff, t, u, v0, t_hist, u_hist, v_pre, x0, None)
        if eff.resistance_drift == 0.0:
            return out
        # Each command sees the winding as it was when the command was issued.
        t_cmd = t if not hist else np.concatenate([np.asarray(t_hist, float), t])
        k = np.clip(np.searchsorted(t, t_cmd, "right") - 1, 0, len(t) - 1)
        rise = winding_rises(p, eff, t, out.i, rise0)
        for _ in range(DRIFT_PASSES_MAX):
            r_at = p.R_m * (1.0 + COPPER_TEMPCO * rise)  # winding_resistance, elementwise
            r_cmd = np.where(t_cmd < t[0], winding_resistance(p, eff, rise0), r_at[k])
            out = _simulate(p, eff, t, u, v0, t_hist, u_hist, v_pre, x0, r_cmd - p.R_m)
            used, rise = rise, winding_rises(p, eff, t, out.i, rise0)
            if not np.max(np.abs(rise - used)) > DRIFT_TOLERANCE * (1 + np.max(np.abs(used))):
                break  # converged, or a trial that overflowed (NaN): no pass mends it
        return out


DRIFT_TOLERANCE = 1e-4
"""Largest change of the rise between two passes, relative to 1 K plus the largest rise
(0.01 K in 100 K: the resistance right to 3e-5; 1e-9 found the same drifts, 1.4x slower)."""
DRIFT_PASSES_MAX = 60


DRIVER_FIELDS = ("dead_zone", "dead_zone_offset", "voltage_saturation", "battery_sag")
"""The effects' fields :func:`truckd.model.effects.driver_output` reads (with the
battery voltage; ``tests/test_ident_fastsim.py`` checks no other field changes it)."""
_DRIVER: dict[tuple[object, ...], tuple[object, object, tuple[Array, Array]]] = {}


def _driver(
    p: VehicleParams, eff: Effects, u: Array, u_hist: Array | None, hist: int
) -> tuple[Array, Array]:
    """:func:`driver_output` of the ``hist`` commands ``u_hist`` then ``u`` (V), kept per
    series (the cache holds the arrays: an identity is not reused while cached), battery
    voltage and driver effects (:data:`DRIVER_FIELDS`): a fit that moves the motor's
    constants reuses it."""
    key = (id(u), id(u_hist), hist, p.V_batt, *[getattr(eff, n) for n in DRIVER_FIELDS])
    hit: tuple[Array, Array] | None = _timed(key, u, u_hist, _DRIVER)
    if hit is not None:
        return hit
    u_all = np.asarray(u, float) if not hist else np.concatenate([u_hist, u])
    out = driver_output(u_all, eff, p.V_batt, ARRAYS)
    for arr in out:
        arr.flags.writeable = False  # shared by the runs that hit the cache
    _keep(key, u, u_hist, out, _DRIVER, PREP_CACHE)
    return out


def _prepare(
    p: VehicleParams,
    eff: Effects,
    t: Array,
    u: Array,
    t_hist: Array | None,
    u_hist: Array | None,
    hist: int,
    r_drift: Array | None,
    same_r: bool,
    merge: bool = True,
) -> tuple[Array, Array, Array | float, float, float, Array, Array, Timeline]:
    """A free run's input side, kept per series and model: driver voltage (V), resistance
    (ohm), electrical correction (per command; the scalar when ``same_r``: every command
    sees ``R_m``, so it is theirs), the scalar, its lag (s), input terms, timeline (no
    two commands' sub-intervals merged when not ``merge``: a heated run's differ)."""
    volts, r_sag = _driver(p, eff, u, u_hist, hist)
    t_cmd = t if not hist else np.concatenate([t_hist, t])
    r_tot = p.R_m + r_sag
    if r_drift is not None:
        r_tot = r_tot + r_drift
    k0, l0 = electrical_correction(p, eff.viscous_friction)
    kappa, lag_e = float(k0), float(l0)
    # a scalar gives a and b the numbers an array of it would, in fewer operations
    k: Array | float = kappa if same_r else electrical_correction(p, eff.viscous_friction, r_tot)[0]
    a = k * p.K_T / p.J_S * volts / r_tot
    b = k * (p.K_T * p.K_v / r_tot + eff.viscous_friction) / p.J_S
    lag_cmd = lag_e if eff.backlash == 0.0 else 0.0
    ma, mb = a, b
    if not merge:  # distinct values: no two commands' sub-intervals merged
        ma = mb = np.arange(len(t_cmd), dtype=float)
    tl = _merged_timeline(t, t_hist, eff.input_delay + lag_cmd, hist, t_cmd, ma, mb)
    return volts, r_tot, k, kappa, lag_e, a, b, tl


def _simulate(
    p: VehicleParams,
    eff: Effects,
    t: Array,
    u: Array,
    v0: float,
    t_hist: Array | None,
    u_hist: Array | None,
    v_pre: float,
    x0: float,
    r_drift: Array | None,
    heated: float | None = None,
) -> VoltagePrediction:
    """:func:`simulate_voltage` with each command's extra winding resistance ``r_drift``
    (ohm, over the history and the log's commands; None = cold), or (``heated``: the
    rise at ``t[0]``, K) the winding stepped beside the speed by the kernel."""
    n = len(t)
    hist = 0 if t_hist is None or u_hist is None else len(t_hist)
    # The gap opens on the command itself (the plant decides it on the quasi-static
    # current): no electrical lag before the command acts.  A winding's resistance
    # changes per pass: neither is cached.
    cached = r_drift is None and eff.backlash == 0.0 and heated is None
    # No battery sag and no winding drift: every command sees R_m (fewer arrays).
    same_r = eff.battery_sag == 0.0 and r_drift is None and heated is None
    key = _prep_key(p, eff, t, u, t_hist, u_hist)
    hit = _PREP.get(key) if cached else None
    if hit is not None and hit[0] is t and hit[1] is u and hit[2] is t_hist and hit[3] is u_hist:
        volts, r_tot, k, kappa, lag_e, a, b, tl = hit[4]
    else:
        prepared = _prepare(p, eff, t, u, t_hist, u_hist, hist, r_drift, same_r, heated is None)
        volts, r_tot, k, kappa, lag_e, a, b, tl = prepared
        if cached:
            _put(_PREP, key, (t, u, t_hist, u_hist, prepared), PREP_CACHE)
    load = p.force_to_torque(eff.load_force)
    stribeck = None
    if eff.stribeck != 0.0:
        stribeck = Stribeck(p, eff, kappa / p.J_S)
    kin = Kinetics(
        a=a,
        b=b,
        a_idle=kappa * p.K_T / p.J_S * v_pre / p.R_m,
        b_idle=kappa * (p.K_T * p.K_v / p.R_m + eff.viscous_friction) / p.J_S,
        c=kappa * p.K_coulomb / p.J_S,
        sigma=kappa * p.K_stiction / p.J_S,
        d=kappa * load / p.J_S,
        drag=kappa * eff.aero_drag * p.ratio**3 / p.J_S,
        scale=np.asarray(k) / kappa if not same_r else None,
        lag=lag_e,
        terrain=_terrain(p, eff, kappa, x0),
        # While the limit binds the current is held: no electrical pole slows the drive.
        a_max=limited_torque(p, eff) / p.J_S,
        b_mech=kappa * eff.viscous_friction / p.J_S if eff.current_limit != 0.0 else 0.0,
        stribeck=stribeck,
        gap=None
        if eff.backlash == 0.0
        else GapRun(p, eff, volts, r_tot, v_pre, kappa, n, p.omega(v0)),
    )
    w0 = p.omega(v0)
    if heated is not None:  # the kernel writes each command's a, b, scale and resistance
        heat = _heat(p, eff, t, t_hist, hist, volts, r_tot, v_pre, heated, kin, kappa)
        kin, r_tot = dataclasses.replace(kin, heat=heat), heat.r
    # The threshold is kin.sigma throughout only without a per-command scale or a Stribeck
    # friction; the backlash gap reads K_stiction itself.
    banded = kin.scale is None and kin.stribeck is None and kin.gap is None
    # the run's own (ctypes lets other threads run during the call); NaN where Python runs
    band = _NO_BAND.copy() if banded else None
    meas, raw, pos = run(kin, tl, n, w0, eff.sensor_lag, band=band)
    rotor = raw if kin.gap is None else kin.gap.rotor_out
    idx = _active(t, t_hist, hist, eff.input_delay)
    sampled = partial(_sample_currents, p, eff, idx, volts, None if same_r else r_tot, v_pre)
    stiction = None
    if band is not None:
        stuck, moved = band.tolist()
        if stuck == stuck and moved == moved:  # not NaN: the kernel ran
            stiction = StictionBand(stuck, moved, kappa, p.J_S)
    # v; the true speed, the position, the current and the driver voltage when read
    return VoltagePrediction(
        meas * p.ratio, raw, pos, p.ratio, partial(sampled, raw, rotor), stiction
    )


def _heat(
    p: VehicleParams,
    eff: Effects,
    t: Array,
    t_hist: Array | None,
    hist: int,
    volts: Array,
    r_tot: Array,
    v_pre: float,
    rise0: float,
    kin: Kinetics,
    kappa: float,
) -> ckernel.HeatArrays:
    """The kernel's arrays for a run heated from ``rise0`` (K), ``r_tot`` the commands'
    cold resistance (ohm), ``kappa`` the electrical correction at ``R_m``; ``kin.scale``
    set to NaN (the kernel writes it as each command first acts)."""
    assert isinstance(kin.scale, np.ndarray)
    kin.scale[:] = np.nan
    idx = _active(t, t_hist, hist, eff.input_delay)
    active = np.where(idx.on, idx.at, -1), np.where(idx.prev_on, idx.prev, -1), idx.neg_since
    t_cmd = t if not hist else np.concatenate([np.asarray(t_hist, float), t])
    return heat_arrays(p, eff, t, t_cmd, volts, r_tot - p.R_m, active, v_pre, rise0, kappa)


_NO_BAND = np.array([np.nan, np.nan])
"""What a band reads before the kernel writes it (copied per run)."""


TIMING_CACHE = 64
"""Series whose timing (the timeline of a delay, the command active at each sample) is
kept: it depends only on the instants and the delay, not on any other parameter."""
_TIMING: dict[tuple[object, ...], tuple[object, object, Any]] = {}


def _timed(
    key: tuple[object, ...], t: object, t_hist: object, cache: dict[Any, Any] = _TIMING
) -> Any:
    """The value ``cache`` (default :data:`_TIMING`) holds under ``key`` for the objects
    ``t``, ``t_hist`` (arrays, a timing; the cache holds them, so an identity is not
    reused while cached), None when not cached."""
    hit = cache.get(key)
    if hit is not None and hit[0] is t and hit[1] is t_hist:
        return hit[2]
    return None


def _keep(
    key: tuple[object, ...],
    t: object,
    t_hist: object,
    value: Any,
    cache: dict[Any, Any] = _TIMING,
    most: int = TIMING_CACHE,
) -> None:
    _put(cache, key, (t, t_hist, value), most)


def _timeline(t: Array, t_hist: Array | None, delay: float, hist: int, t_cmd: Array) -> Timeline:
    """:func:`timeline` of the commands at ``t_cmd`` (``t_hist`` then ``t``) acting
    ``delay`` s later, kept per series and delay."""
    key = ("timeline", id(t), id(t_hist), delay, hist)
    tl = _timed(key, t, t_hist)
    if tl is None:
        tl = timeline(t, delay, hist, t_cmd)
        _keep(key, t, t_hist, tl)
    return tl  # type: ignore[no-any-return]


LAYOUT_CACHE = 64
"""Series whose timeline layout (the order of its instants under a delay) is kept."""
_LAYOUT: dict[tuple[object, ...], tuple[Array, Array | None, Layout]] = {}


def _merged_timeline(
    t: Array, t_hist: Array | None, delay: float, hist: int, t_cmd: Array, a: Array, b: Array
) -> Timeline:
    """``merge_equal(timeline(...), a, b)`` of the commands at ``t_cmd`` acting ``delay``
    s later: for a delay in the order of the series' kept layout, from that layout
    (:mod:`truckd.ident.timing`, the same arrays; in one pass of the C kernel when it is
    built, :func:`truckd.ident.ckernel.shift_merge`); else computed, and its layout kept."""
    if delay > 0.0:
        key = ("layout", id(t), id(t_hist), hist)
        lay: Layout | None = _timed(key, t, t_hist, _LAYOUT)
        if lay is not None and ckernel.available():
            done = ckernel.shift_merge(
                t, t_cmd, delay, lay.first, lay.stop, lay.order, lay.eps, lay.cmd,
                lay.sample_end, a, b,
            )  # fmt: skip
            if done is not None:
                return Timeline(*done)
        tl = None if lay is None else shifted(lay, t, delay, t_cmd)
        if tl is None:
            made = layout_of(t, delay, t_cmd)
            if made is not None:
                tl, lay = made
                _keep(key, t, t_hist, lay, _LAYOUT, LAYOUT_CACHE)
        if tl is not None and lay is not None:
            return merged(tl, lay, a, b)
    return merge_equal(_timeline(t, t_hist, delay, hist, t_cmd), a, b)


@dataclass(frozen=True)
class Active:
    """Which command is active at each sample instant (the timing of
    :func:`_sample_currents`, kept per series and delay)."""

    on: NDArray[np.bool_]
    """A command is active (not: before the first one acts)."""
    at: NDArray[np.int64]
    """Index of the active command in the commands (0 where none is)."""
    prev_on: NDArray[np.bool_]
    """A command was active before it."""
    prev: NDArray[np.int64]
    """Index of that command (0 where none was)."""
    neg_since: Array
    """Minus the time (s) since the active command acted (-inf where none is)."""


def _active(t: Array, t_hist: Array | None, hist: int, delay: float) -> Active:
    """The command (of the ``hist`` ones at ``t_hist``, then those at ``t``) active at
    each sample instant under the input delay ``delay`` (s), kept per series and delay."""
    key = ("active", id(t), id(t_hist), delay, len(t) + hist)
    out = _timed(key, t, t_hist)
    if out is None:
        t_cmd = t if not hist else np.concatenate([t_hist, t])
        act = t_cmd + delay
        idx = np.searchsorted(act, t, "left") - 1
        on, at = idx >= 0, np.maximum(idx, 0)
        prev = idx - 1
        since = np.where(on, t - act[at], np.inf)
        out = Active(on, at, prev >= 0, np.maximum(prev, 0), -since)
        _keep(key, t, t_hist, out)
    return out  # type: ignore[no-any-return]


SAMPLED_CACHE = 16
"""Runs whose per-sample command voltages and settling factors are kept: a fit's runs
that change only friction, loads or lag share them."""
_SAMPLED: dict[tuple[object, ...], tuple[object, object, Any]] = {}


def _sample_volts(idx: Active, volts: Array, v_pre: float) -> tuple[Array, Array]:
    """The driver voltage (V) of the command active at each sample and of the one before
    it (``v_pre`` where none is), kept per timing, command voltages and ``v_pre`` (the
    cache holds ``idx`` and ``volts``: an identity is not reused while cached)."""
    key = ("volts", id(idx), id(volts), v_pre)
    hit: tuple[Array, Array] | None = _timed(key, idx, volts, _SAMPLED)
    if hit is not None:
        return hit
    v_at = np.where(idx.on, volts[idx.at], v_pre)
    v_old = np.where(idx.prev_on, volts[idx.prev], v_pre)
    for arr in (v_at, v_old):
        arr.flags.writeable = False  # shared by the runs that hit the cache
    _keep(key, idx, volts, (v_at, v_old), _SAMPLED, SAMPLED_CACHE)
    return v_at, v_old


def _settling(idx: Active, r: float, inductance: float) -> Array:
    """``exp(-since r / L)``: what is left at each sample of the current's step at the
    last command (``r`` ohm, ``inductance`` H), kept per timing, ``r`` and ``L``."""
    key = ("settle", id(idx), r, inductance)
    hit: Array | None = _timed(key, idx, None, _SAMPLED)
    if hit is not None:
        return hit
    settle = np.exp(idx.neg_since * r / inductance)
    settle.flags.writeable = False
    _keep(key, idx, None, settle, _SAMPLED, SAMPLED_CACHE)
    return settle


def _sample_currents(
    p: VehicleParams,
    eff: Effects,
    idx: Active,
    volts: Array,
    r_tot: Array | None,
    v_pre: float,
    raw: Array,
    rotor: Array,
) -> tuple[Array, Array]:
    """Motor current (A) and driver voltage (V) at each sample of a run: quasi-static
    under the command active at the sample (``volts`` through ``r_tot`` per command,
    ``v_pre`` before the first), still settling from the previous command when one
    acted just before, within the current limit; ``raw`` the load's speed, ``rotor``
    the rotor's (rad/s); ``idx`` the command active at each sample (:func:`_active`).
    ``r_tot`` None: ``R_m`` for every command (the same numbers, fewer arrays)."""
    v_at, v_old = _sample_volts(idx, volts, v_pre)
    back_emf = p.K_v * rotor
    r_at: Array | float = p.R_m
    r_old: Array | float = p.R_m
    if r_tot is not None:
        r_at = np.where(idx.on, r_tot[idx.at], p.R_m)
        r_old = np.where(idx.prev_on, r_tot[idx.prev], p.R_m)
        settle = np.exp(idx.neg_since * r_at / p.L_m)
    else:
        settle = _settling(idx, p.R_m, p.L_m)
    cur = (v_at - back_emf) / r_at
    # A command that acted just before the sample: the current is still settling.
    cur_old = (v_old - back_emf) / r_old
    cur = cur + (cur_old - cur) * settle
    if eff.current_limit != 0.0:
        cur = np.clip(cur, -eff.current_limit, eff.current_limit)
        room = r_at * eff.current_limit
        v_at = np.clip(v_at, p.K_v * raw - room, p.K_v * raw + room)
    return cur, v_at


def predict(p: VehicleParams, e: Effects, s: Series) -> VoltagePrediction:
    """Free run of the model over ``s`` from its measured start (speed, and current when
    logged: it tells which voltage acts before the log's first command does)."""
    v0 = s.start_speed
    i0 = None if s.i is None else float(s.i[0])
    v_pre = prelog_voltage(p, e, p.omega(v0), i0)
    x0 = 0.0 if s.x is None else float(s.x[0])
    rise0 = _winding_rise_before(p, e, s)
    return simulate_voltage(p, e, s.t, s.inp, v0, s.hist_t, s.hist_inp, v_pre, x0, rise0)


RISE_CACHE = 8
"""Runs whose winding heating (under one model) is kept for the stretches cut from them."""
_RISES: dict[tuple[object, ...], tuple[Series, Array]] = {}


def _winding_rise_before(p: VehicleParams, e: Effects, s: Series) -> float:
    """The winding's temperature rise (K) at the start of ``s`` (``resistance_drift``):
    the run it was cut from simulated (0 when ``s`` starts the run).  The run's heating
    is kept per run and model: every stretch cut from it (the chunks of a fit) reads its
    start there, one free run of the run instead of one of its head per stretch (the
    free run is causal: the head's is the run's up to there)."""
    if e.resistance_drift == 0.0 or s.origin is None or s.offset < 1:
        return 0.0
    o = s.origin
    key = (id(o), p, e)
    hit = _RISES.get(key)
    if hit is None or hit[0] is not o:
        rises = winding_rises(p, e, o.t, predict(p, e, o).i, 0.0)
        hit = _put(_RISES, key, (o, rises), RISE_CACHE)
    return float(hit[1][s.offset])

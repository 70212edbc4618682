"""The winding's heating in a free run (``resistance_drift``): its rise from a current, and
what the C kernel needs to step it beside the speed.

A resistance drift couples the run to itself: each command's resistance depends on the
winding's rise when it was issued, the rise on the current drawn before.  The kernel steps
that rise sample by sample inside the run (:class:`truckd.ident.ckernel.HeatArrays`): one
run, exactly causal.  Without the kernel, :func:`truckd.ident.fastsim.simulate_voltage`
runs passes until the heating converges.  Pure numerics, no I/O.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from truckd.ident import ckernel
from truckd.model.effects import (
    COPPER_TEMPCO,
    Effects,
    winding_resistance,
    winding_rise_step,
)
from truckd.model.params import VehicleParams

Array = NDArray[np.float64]


def winding_rises(p: VehicleParams, eff: Effects, t: Array, i: Array, rise0: float) -> Array:
    """The winding's temperature rise (K) at each sample under the current ``i`` (A),
    from ``rise0`` at ``t[0]`` (copper loss over a step: the mean of the squared currents
    at its ends, as the plant counts it).  The C kernel runs the loop when built (the
    same arithmetic as :func:`winding_resistance` and :func:`winding_rise_step`)."""
    sq_arr = np.asarray(i, float) ** 2
    if eff.resistance_drift != 0.0 and len(t) > 0:
        done = ckernel.winding_rises(
            np.diff(t), sq_arr, rise0, p.R_m, COPPER_TEMPCO, eff.resistance_drift,
            eff.winding_time_constant,
        )  # fmt: skip
        if done is not None:
            return done
    out = np.empty(len(t))
    rise = rise0
    out[0] = rise
    sq = sq_arr.tolist()
    dts = np.diff(t).tolist()
    for k, h in enumerate(dts):
        r = winding_resistance(p, eff, rise)
        rise = winding_rise_step(eff, rise, 0.5 * (sq[k] + sq[k + 1]) * r, h)
        out[k + 1] = rise
    return out


def heat_arrays(
    p: VehicleParams,
    eff: Effects,
    t: Array,
    t_cmd: Array,
    volts: Array,
    sag: Array,
    active: tuple[NDArray[np.int64], NDArray[np.int64], Array],
    v_pre: float,
    rise0: float,
    kappa: float,
) -> ckernel.HeatArrays:
    """The kernel's inputs for a run heated from ``rise0`` (K) at ``t[0]``: the commands
    at ``t_cmd`` (s; those before ``t[0]`` see the winding at ``rise0``), their driver
    voltages ``volts`` (V) and battery resistance ``sag`` (ohm); ``active``: per sample
    the active command and the one before it (-1: none) and minus the time since the
    active one acted (s); ``kappa`` the electrical correction at ``R_m``."""
    n = len(t)
    kk = np.clip(np.searchsorted(t, t_cmd, "right") - 1, 0, max(n - 1, 0))
    kk = np.where(t_cmd < t[0], -1, kk).astype(np.int64)
    constants = np.array([
        p.R_m, COPPER_TEMPCO, eff.resistance_drift, eff.winding_time_constant, rise0, p.L_m,
        p.J_S, p.K_T, p.K_v, eff.viscous_friction, kappa, eff.current_limit, v_pre,
        winding_resistance(p, eff, rise0) - p.R_m,
    ])  # fmt: skip
    at, prev, since = active
    return ckernel.HeatArrays(
        constants,
        np.ascontiguousarray(volts, dtype=np.float64),
        np.ascontiguousarray(np.broadcast_to(sag, volts.shape), dtype=np.float64),
        kk,
        np.ascontiguousarray(at, dtype=np.int64),
        np.ascontiguousarray(prev, dtype=np.int64),
        np.ascontiguousarray(since, dtype=np.float64),
        np.ascontiguousarray(np.diff(t), dtype=np.float64),
        np.full(len(volts), np.nan),
        np.empty(n),
    )

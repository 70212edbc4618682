"""Exact stepping of the motor/drivetrain with Coulomb friction and stiction.

Friction (thesis eq. 6.26-6.29, the general two-direction form 6.28):

* moving (``omega != 0``): ``T_f = K_coulomb * sign(omega)``;
* at rest: friction opposes the net generated torque ``T = K_T i - T_load`` and never
  exceeds it, so while ``|T| <= K_stiction`` the shaft stays *exactly* at rest (no
  creeping, no chattering); when ``|T|`` exceeds ``K_stiction`` it breaks away in the
  direction of ``T``.

Between events the dynamics are linear with constant inputs, so each segment is solved
in closed form (exact zero-order hold).  Events, found inside a step, split it:
breakaway (closed form, the current is a first-order exponential while stuck) and
the speed reaching zero (bisection on the closed-form speed).  Pure numerics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from truckd.model.linear import Mat2, expm2, system_matrix
from truckd.model.params import VehicleParams

_MAX_EVENTS = 16
"""Events handled inside one step before the rest of it keeps the current mode."""


@dataclass
class MotorState:
    """Electromechanical state.

    ``i`` armature current (A), ``omega`` motor speed (rad/s), ``direction`` +1/-1 while
    sliding, 0 while held by stiction (then ``omega`` is exactly 0).
    """

    i: float = 0.0
    omega: float = 0.0
    direction: int = 0


@dataclass(slots=True)
class SegmentInputs:
    """What acts on the motor during one step (held constant over it).

    ``voltage`` applied armature voltage (V); ``load_torque`` torque at the motor shaft
    opposing forward motion (N m), independent of speed; ``viscous`` torque per motor
    speed (N m s/rad); ``extra_resistance`` series resistance (ohm), e.g. the battery's;
    ``coulomb_extra`` sliding friction (N m) on top of ``K_coulomb`` (Stribeck).
    """

    voltage: float
    load_torque: float = 0.0
    viscous: float = 0.0
    extra_resistance: float = 0.0
    coulomb_extra: float = 0.0


def _slide(
    p: VehicleParams, a: Mat2, i0: float, w0: float, s: int, u: SegmentInputs, t: float
) -> tuple[float, float, float]:
    """Closed-form sliding segment of length t (s): ``(i, omega, integral of omega dt)``.

    The two solves with ``A`` (:func:`truckd.model.linear.solve2`) are written out,
    sharing its determinant: the plant calls this twice a step."""
    a00, a01, a10, a11 = a
    det = a00 * a11 - a01 * a10
    b0 = -(u.voltage / p.L_m)
    b1 = -((-s * (p.K_coulomb + u.coulomb_extra) - u.load_torque) / p.J_S)
    iss, wss = (a11 * b0 - a01 * b1) / det, (a00 * b1 - a10 * b0) / det
    d0, d1 = i0 - iss, w0 - wss
    e0, e1, e2, e3 = expm2(a, t)
    i = iss + e0 * d0 + e1 * d1
    w = wss + e2 * d0 + e3 * d1
    c0, c1 = (e0 - 1.0) * d0 + e1 * d1, e2 * d0 + (e3 - 1.0) * d1
    y1 = (a00 * c1 - a10 * c0) / det
    return i, w, wss * t + y1


def _stuck_current(p: VehicleParams, u: SegmentInputs, i0: float, t: float) -> float:
    """Current (A) after t (s) with the shaft held: ``L di/dt = V - R i``."""
    r = p.R_m + u.extra_resistance
    iss = u.voltage / r
    return iss + (i0 - iss) * math.exp(-t * r / p.L_m)


def advance(p: VehicleParams, x: MotorState, u: SegmentInputs, h: float) -> float:
    """Advance ``x`` in place by h seconds under constant inputs ``u``, exactly.

    Returns the motor shaft angle travelled (rad), for the vehicle position.
    """
    a = system_matrix(p, u.viscous, u.extra_resistance)
    # Breakaway takes at least the sliding friction at zero speed (Stribeck's peak).
    k_st = max(p.K_stiction, p.K_coulomb + u.coulomb_extra)
    remaining = h
    angle = 0.0
    for _ in range(_MAX_EVENTS):
        if remaining <= 0.0:
            return angle
        if x.direction == 0:
            i_end = _stuck_current(p, u, x.i, remaining)
            torque = p.K_T * i_end - u.load_torque
            if abs(torque) <= k_st:
                x.i, x.omega = i_end, 0.0
                return angle
            # Breakaway: the current is monotone while stuck, so the crossing is closed form.
            target = math.copysign(k_st, torque)
            i_t = (target + u.load_torque) / p.K_T
            r = p.R_m + u.extra_resistance
            iss = u.voltage / r
            ratio = (i_t - iss) / (x.i - iss) if x.i != iss else 1.0
            t_b = -p.L_m / r * math.log(ratio) if 0.0 < ratio <= 1.0 else 0.0
            t_b = min(max(t_b, 0.0), remaining)
            x.i, x.omega, x.direction = i_t, 0.0, (1 if torque > 0 else -1)
            remaining -= t_b
            continue
        s = x.direction
        i1, w1, ang = _slide(p, a, x.i, x.omega, s, u, remaining)
        if w1 * s > 0.0:
            x.i, x.omega = i1, w1
            return angle + ang
        # The speed reaches zero inside the step: find when, by bisection.
        lo, hi = 0.0, remaining
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            _, wm, _ = _slide(p, a, x.i, x.omega, s, u, mid)
            if wm * s > 0.0:
                lo = mid
            else:
                hi = mid
            if hi - lo <= 1e-12 * max(1.0, remaining):
                break
        i_z, _, ang_z = _slide(p, a, x.i, x.omega, s, u, hi)
        angle += ang_z
        remaining -= hi
        torque = p.K_T * i_z - u.load_torque
        x.i, x.omega = i_z, 0.0
        x.direction = 0 if abs(torque) <= k_st else (1 if torque > 0 else -1)
    # Too many events in one step (a pathological chatter): hold the mode for the rest.
    if x.direction == 0:
        x.i = _stuck_current(p, u, x.i, remaining)
        return angle
    i1, w1, ang = _slide(p, a, x.i, x.omega, x.direction, u, remaining)
    x.i, x.omega = i1, w1 if w1 * x.direction > 0 else 0.0
    if x.omega == 0.0:
        x.direction = 0
    return angle + ang


def steady_speed(p: VehicleParams, voltage: float, viscous: float = 0.0) -> float:
    """Closed-form steady motor speed (rad/s) under constant voltage, Coulomb friction.

    ``0 = V - R i - K_v w`` and ``0 = K_T i - b w - K_c sign(w)``; zero when the voltage
    cannot hold motion against Coulomb friction.
    """
    s = 1.0 if voltage >= 0 else -1.0
    w = (voltage - s * p.R_m * p.K_coulomb / p.K_T) / (p.K_v + p.R_m * viscous / p.K_T)
    return w if w * s > 0 else 0.0

"""Friction feedforward: the voltage that cancels what the friction-free MPC model lacks.

The MPC plans on the linear model without Coulomb friction and stiction.  This adds, to
its command, the armature voltage whose steady current produces the missing torque:
``u_ff = R_m / K_T * T`` with

* moving (``|v| > moving_speed``): ``T = K_coulomb sign(v)`` plus the load torques the
  controller's model knows (the feedforward terms of
  :data:`truckd.control.effect_use.EFFECT_USES`: ``load_force``, aero drag at the current
  speed, the terrain at the position ``x`` where the command acts);
* at rest with a start commanded: ``T = margin * K_stiction`` (breaks stiction; the
  Stribeck peak ``K_coulomb + stribeck`` when larger) plus the known load at ``x``;
* otherwise 0.

A known driver dead zone is not an offset: the driver (``truckd.model.effects.driver_output``)
outputs 0 for ``|u| < dead_zone`` and passes larger commands unchanged, so
:func:`dead_zone_command` only moves a wanted voltage that falls inside the zone to the nearest
voltage the driver can produce.  The textbook form ``dead_zone_offset`` is an offset: the
driver outputs ``u - sign(u) u_dz`` above it, so the command is the wanted voltage plus
``sign(u) u_dz``.  Pure numerics.
"""

from __future__ import annotations

import math

from truckd.control.effect_use import Torque, breakaway_torque, feedforward_torque
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams


def torque_to_voltage(p: VehicleParams, torque: float) -> float:
    """Armature voltage (V) whose stalled current gives ``torque`` (N m): ``R/K_T T``."""
    return p.R_m / p.K_T * torque


def load_torque_known(p: VehicleParams, eff: Effects, v: float) -> float:
    """Speed-independent load and aero drag torque at the motor shaft (N m) at speed v."""
    force = eff.load_force + eff.aero_drag * v * abs(v)
    return p.force_to_torque(force)


def moving_feedforward(
    p: VehicleParams,
    eff: Effects,
    v: float,
    moving_speed: float,
    x: float = 0.0,
    terms: tuple[Torque, ...] | None = None,
) -> float:
    """Feedforward voltage (V) while moving at v (m/s), the command acting at road
    position x (m); 0 at rest.  ``terms``: see :func:`feedforward_torque`."""
    if abs(v) <= moving_speed:
        return 0.0
    s = math.copysign(1.0, v)
    # (no terms: their sum is 0.0, added without calling for it)
    known = feedforward_torque(p, eff, v, x, terms) if terms is None or terms else 0.0
    return p.R_m / p.K_T * (s * p.K_coulomb + known)  # torque_to_voltage


def breakaway_feedforward(p: VehicleParams, eff: Effects, margin: float, x: float = 0.0) -> float:
    """Forward start voltage (V) that breaks stiction (and holds the known load at road
    position x, m): ``margin`` times the static friction (``K_stiction``, or the Stribeck
    curve's peak at zero speed when the model knows a larger one)."""
    torque = margin * breakaway_torque(p, eff) + feedforward_torque(p, eff, 0.0, x)
    return torque_to_voltage(p, torque)


def dead_zone_command(u: float, dead_zone: float, offset: float = 0.0) -> float:
    """The command (V) that makes a driver with a dead zone apply as close to ``u`` as it can.

    ``dead_zone`` (V) is the threshold form: outside the zone the driver passes the command
    unchanged, so it is sent as is; inside, the driver can only make 0 V or the threshold:
    the nearer of the two is sent.  ``offset`` (V) is the textbook form (output
    ``c - sign(c) offset`` for a command ``c`` beyond it): ``u + sign(u) offset`` is sent.
    With both, the smallest non-zero output is ``dead_zone - offset``.
    """
    if not math.isfinite(u) or u == 0.0:
        return u
    if offset <= 0.0:
        if dead_zone <= 0.0 or abs(u) >= dead_zone:
            return u
        return math.copysign(dead_zone, u) if abs(u) >= 0.5 * dead_zone else 0.0
    smallest = max(dead_zone - offset, 0.0)  # smallest non-zero output (V)
    if abs(u) >= smallest:
        return math.copysign(abs(u) + offset, u)
    return math.copysign(max(dead_zone, offset), u) if abs(u) >= 0.5 * smallest else 0.0

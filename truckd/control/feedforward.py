"""Friction feedforward: the voltage that cancels what the friction-free MPC model lacks.

The MPC plans on the linear model without Coulomb friction and stiction.  This adds, to
its command, the armature voltage whose steady current produces the missing torque:
``u_ff = R_m / K_T * T`` with

* moving (``|v| > moving_speed``): ``T = K_coulomb sign(v)`` plus the load torques the
  controller's model knows (``load_force``, aero drag at the current speed);
* at rest with a start commanded: ``T = margin * K_stiction`` (breaks stiction);
* otherwise 0.

A known driver dead zone adds ``dead_zone * sign`` whenever a direction is defined.
Pure numerics.
"""

from __future__ import annotations

import math

from truckd.model.effects import Effects
from truckd.model.params import VehicleParams


def torque_to_voltage(p: VehicleParams, torque: float) -> float:
    """Armature voltage (V) whose stalled current gives ``torque`` (N m): ``R/K_T T``."""
    return p.R_m / p.K_T * torque


def load_torque_known(p: VehicleParams, eff: Effects, v: float) -> float:
    """Speed-independent load and aero drag torque at the motor shaft (N m) at speed v."""
    force = eff.load_force + eff.aero_drag * v * abs(v)
    return p.force_to_torque(force)


def moving_feedforward(p: VehicleParams, eff: Effects, v: float, moving_speed: float) -> float:
    """Feedforward voltage (V) while moving at v (m/s); 0 at rest."""
    if abs(v) <= moving_speed:
        return 0.0
    s = math.copysign(1.0, v)
    torque = s * p.K_coulomb + load_torque_known(p, eff, v)
    return torque_to_voltage(p, torque) + s * eff.dead_zone


def breakaway_feedforward(p: VehicleParams, eff: Effects, margin: float) -> float:
    """Forward start voltage (V) that breaks stiction (and holds the known load)."""
    torque = margin * p.K_stiction + p.force_to_torque(eff.load_force)
    return torque_to_voltage(p, torque) + eff.dead_zone

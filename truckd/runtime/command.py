"""From the supervisor's mode and the controller's output to the motor command.  Pure.

Whatever arrives, the command is finite and within ``[-u_max, u_max]``:

- ``ACTIVE``/``DEGRADED``: the controller's voltage (its fallback law when degraded);
- ``SAFE_STOP``: the previous command ramped towards 0 V by ``ramp_step`` per cycle (0 V
  is dynamic braking on a DC motor), driver enabled;
- ``INIT``/``FAULT``: 0 V, driver disabled (motor off).
"""

from __future__ import annotations

import math

from truckd.control.supervisor import Mode

_DRIVING = (Mode.ACTIVE, Mode.DEGRADED)
_RAMPING = (Mode.ACTIVE, Mode.DEGRADED, Mode.SAFE_STOP)
"""The modes that drive with the controller's voltage, and those that ramp to 0 V without
one (module constants: the enum's attributes cost a hook each, every cycle)."""


def motor_command(
    mode: Mode, u_ctrl: float | None, u_prev: float, ramp_step: float, u_max: float
) -> tuple[float, bool]:
    """(voltage V, enable) for this cycle."""
    if not (math.isfinite(u_max) and u_max >= 0.0):
        return 0.0, False
    prev = u_prev if math.isfinite(u_prev) else 0.0
    if mode in _DRIVING and u_ctrl is not None and math.isfinite(u_ctrl):
        u, enable = u_ctrl, True
    elif mode in _RAMPING:
        step = ramp_step if math.isfinite(ramp_step) and ramp_step > 0 else u_max
        u, enable = math.copysign(max(abs(prev) - step, 0.0), prev), True
    else:
        u, enable = 0.0, False
    u = -u_max if -u_max > u else u  # min(max(u, -u_max), u_max) written out
    return (u_max if u_max < u else u), enable

"""An independent fine-step reference for the seed model: scipy LSODA with events.

Written from the equations, not from truckd.model.motor: slide phases integrate the
ODE with friction -K_c sign(omega) until omega reaches 0 (event); stuck phases integrate
the current with omega held at 0 until |K_T i - T_load| reaches K_stiction (event).
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp

from truckd.model.params import VehicleParams


def reference_run(
    p: VehicleParams, t: np.ndarray, u: np.ndarray, load_torque: float = 0.0
) -> np.ndarray:
    """Vehicle speed at the sample times t under u held over each interval (ZOH)."""
    i, w, direction = 0.0, 0.0, 0
    out = np.zeros(len(t))
    for k in range(len(t) - 1):
        out[k] = p.speed(w)
        t0, t1, volts = float(t[k]), float(t[k + 1]), float(u[k])
        while t1 - t0 > 1e-13:
            if direction == 0:
                torque = p.K_T * i - load_torque
                if abs(torque) > p.K_stiction:
                    direction = 1 if torque > 0 else -1
                    continue

                def stuck(_t: float, y: np.ndarray, v: float = volts) -> list[float]:
                    return [(v - p.R_m * y[0]) / p.L_m]

                def breakaway(_t: float, y: np.ndarray) -> float:
                    return abs(p.K_T * y[0] - load_torque) - p.K_stiction

                breakaway.terminal = True  # type: ignore[attr-defined]
                sol = solve_ivp(
                    stuck, (t0, t1), [i], method="LSODA", rtol=1e-10, atol=1e-12, events=breakaway
                )
                i = float(sol.y[0, -1])
                if sol.status == 1:
                    t0 = float(sol.t_events[0][0])
                    torque = p.K_T * i - load_torque
                    direction = 1 if torque > 0 else -1
                else:
                    t0 = t1
            else:
                s = direction

                def slide(_t: float, y: np.ndarray, v: float = volts, s: int = s) -> list[float]:
                    di = (v - p.R_m * y[0] - p.K_v * y[1]) / p.L_m
                    dw = (p.K_T * y[0] - s * p.K_coulomb - load_torque) / p.J_S
                    return [di, dw]

                def stop(_t: float, y: np.ndarray, s: int = s) -> float:
                    return float(y[1] * s) + 1e-300 * 0.0

                stop.terminal = True  # type: ignore[attr-defined]
                stop.direction = -1  # type: ignore[attr-defined]
                sol = solve_ivp(
                    slide,
                    (t0, t1),
                    [i, w],
                    method="LSODA",
                    rtol=1e-10,
                    atol=[1e-10, 1e-9],
                    events=stop,
                )
                i, w = float(sol.y[0, -1]), float(sol.y[1, -1])
                if sol.status == 1 and sol.t_events[0][0] > t0 + 1e-12:
                    t0 = float(sol.t_events[0][0])
                    w = 0.0
                    torque = p.K_T * i - load_torque
                    direction = 0 if abs(torque) <= p.K_stiction else (1 if torque > 0 else -1)
                else:
                    t0 = t1
    out[-1] = p.speed(w)
    return out

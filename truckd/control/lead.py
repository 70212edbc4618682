"""The lead's speed as the MPC is given it (m/s, one value per period from now): over the
commands sent but not yet acting (an input delay), then over the QP's horizon.

A forecast (a plan received from the truck ahead) when given and finite, else the lead's
estimate held constant, capped in ``[0, cap]``; over an input delay without a forecast a
braking lead keeps braking.  Pure numerics: no I/O, no clock.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from truckd.control.config import ControlConfig
from truckd.control.estimator import Estimate

LEAD_ACCEL_TAU_S = 0.1
"""Time constant (s) of the lead acceleration's filter (used over an input delay only)."""


def lead_horizon(
    est: Estimate, forecast: Sequence[float] | None, n: int, cap: float
) -> list[float]:
    """Lead speed (m/s) from now over the pipeline and the QP's horizon (``n`` values),
    in [0, ``cap``]: the forecast when given and finite (its last value held past its
    end), else the estimate held constant.  Python floats, no numpy: the QP gathers them
    with its other inputs."""
    if forecast is not None and len(forecast) > 0:
        f = [float(x) for x in forecast[:n]]
        f += [f[-1]] * (n - len(f))
        if math.isfinite(sum(f)):  # any NaN or infinity makes the sum non-finite
            return [min(max(x, 0.0), cap) for x in f]
    x = est.v_lead  # min(max(x, 0.0), cap), written out (the builtins cost a keyword call)
    x = 0.0 if 0.0 > x else x
    return [cap if cap < x else x] * n


class LeadSpeeds:
    """The lead's speeds a controller gives its MPC, with the lead acceleration's filter."""

    def __init__(self, cfg: ControlConfig, horizon: int) -> None:
        self.cfg = cfg
        self._horizon = horizon
        self.reset()

    def reset(self) -> None:
        """Forget the lead's last speed and acceleration."""
        self._v_lead_prev = math.nan
        self._a_lead = 0.0

    def reset_speed(self) -> None:
        """Forget the lead's last speed (as :meth:`speeds` does without a lead)."""
        self._v_lead_prev = math.nan

    def speeds(
        self,
        est: Estimate,
        forecast: Sequence[float] | None,
        mode: str,
        lead: bool,
        n_pipe: int,
    ) -> list[float]:
        """The lead's speed (m/s) over the ``n_pipe`` commands in the pipeline, then the
        QP's horizon (0 without a lead)."""
        cfg = self.cfg
        n_all = n_pipe + self._horizon
        if not lead:
            self._v_lead_prev = math.nan
            return [0.0] * n_all
        # Never follow faster than the set speed: a faster lead is taken as driving at
        # v_set (conservative, the predicted gap is smaller than the real one).
        # Cruising, a lead faster than v_max is taken as driving at v_max (a forecast
        # of a wrong plan can say anything: it never reaches the QP beyond that).
        cap = cfg.v_set if mode == "follow" else cfg.v_max
        v_lead_all = lead_horizon(est, forecast, n_all, cap)
        if n_pipe and not forecast:
            # Over the input delay a braking lead keeps braking (what happens before
            # the first planned command acts; held constant after).  An accelerating
            # lead is not assumed to go on (conservative: measured, it made
            # stop-and-go's starts 2-3 % worse than the seed model's).
            a_lead = min(self._accel(est.v_lead), 0.0)
            v_end = min(max(est.v_lead + a_lead * n_pipe * cfg.period, 0.0), cap)
            for k in range(n_all):
                vk = est.v_lead + a_lead * min(k, n_pipe) * cfg.period
                v_lead_all[k] = min(max(vk, 0.0), cap) if k < n_pipe else v_end
        return v_lead_all

    def _accel(self, v_lead: float) -> float:
        """The lead's acceleration (m/s^2): its speed estimate's difference from the last
        cycle, low-pass filtered (time constant :data:`LEAD_ACCEL_TAU_S`)."""
        prev, self._v_lead_prev = self._v_lead_prev, v_lead
        if math.isfinite(prev):
            dt = self.cfg.period
            alpha = dt / (LEAD_ACCEL_TAU_S + dt)
            self._a_lead += alpha * ((v_lead - prev) / dt - self._a_lead)
        else:
            self._a_lead = 0.0
        return self._a_lead

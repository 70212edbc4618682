"""The estimator's per-cycle update compiled (truckd/control/kernel/estimator.c, in the
library :mod:`truckd.control.ccycle` loads), in the same call as the controller's numerics
(``truckd_cycle_run``, :mod:`truckd.control.cnumerics`).

:class:`CompiledEstimator` computes what :class:`~truckd.control.estimator.Estimator`
computes from a cycle's samples (:meth:`Estimator.cycle`): the same own speed, lead, counters
and :class:`~truckd.control.estimator.Estimate`.  Its state lives in the library, in the
instance of the MPC solver's compiled cycle it is bound to; the Python estimator is the
reference and the fallback (the library missing, stale or without a free instance: the
MPC then runs its Python path too).  tests/test_estimator_compiled.py compares both on
the recorded replay and on hostile samples.  Loading is :mod:`truckd.control.ccycle`'s;
this module computes nothing itself.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence

import numpy as np

from truckd.control import ccycle
from truckd.control.config import EstimatorConfig
from truckd.control.estimator import CLOCK_SLACK_S, EncoderSample, Estimate, RangeSample

CONSTANTS = (
    "tick_len",
    "r_tick",
    "ticks_modulo",
    "sample_time_modulo",
    "speed_accel_std",
    "encoder_timeout_s",
    "speed_max",
    "accel_max",
    "range_min",
    "range_max",
    "range_noise_std",
    "lead_accel_std",
    "gate_sigma",
    "reinit_count",
    "lead_timeout_s",
    "clock_slack_s",
)
"""The constants ``truckd_estimator_bind`` takes, in its order."""

FIELDS = 16
"""Values of the estimate the library writes: :class:`Estimate`'s fields in their order
(``lead_status`` as an index into :data:`STATUS`)."""

STATUS = ("none", "tracking", "no_target", "timeout")
"""The lead's status by the library's code."""

_HEAD = 3
"""Inputs before the samples: the caller's time (s), the numbers of encoder and range
samples."""

_PUT_HEAD = struct.Struct(f"={_HEAD}d").pack_into
_ENC = struct.Struct("=5d").pack_into
_RNG = struct.Struct("=2d").pack_into
_NAN = math.nan
_TRUNC = math.trunc


def constants(cfg: EstimatorConfig, tick_len: float) -> list[float]:
    """:data:`CONSTANTS`' values (``tick_len`` m, the estimator's)."""
    named = {
        "tick_len": tick_len,
        "r_tick": tick_len * tick_len / 12.0,
        "clock_slack_s": CLOCK_SLACK_S,
    }
    return [float(named[k] if k in named else getattr(cfg, k)) for k in CONSTANTS]


class CompiledEstimator:
    """The estimator in the library's instance of one compiled cycle (see module doc)."""

    def __init__(self, cc: ccycle.CompiledCycle, cfg: EstimatorConfig, tick_len: float) -> None:
        self.cfg = cfg
        self.tick_len = tick_len
        """m per encoder tick (the Python estimator's)."""
        self._cc = cc
        self._lib = cc.lib
        self._instance = cc.instance
        self._run = cc.lib.truckd_cycle_run
        self._consts = np.array(constants(cfg, tick_len))
        self._m = cfg.ticks_modulo
        self.est = np.zeros(FIELDS)
        """The estimate the library wrote last (:data:`FIELDS`)."""
        self._bind(64, True)

    def _bind(self, size: int, reset: bool) -> None:
        """Inputs of ``size`` values bound (``reset``: the state starts again)."""
        self.inputs = np.zeros(size)
        self._in_mv = self.inputs.data
        flag = self._lib.truckd_estimator_bind(
            self._instance, int(self._consts.ctypes.data), len(self._consts),
            int(self.inputs.ctypes.data), int(self.est.ctypes.data), size, int(reset),
        )  # fmt: skip
        if flag != 0:
            raise RuntimeError(f"truckd_estimator_bind refused ({flag})")

    def reset(self) -> None:
        """The state starts again (a new estimator)."""
        self._bind(self.inputs.size, True)

    def fresh(self) -> CompiledEstimator:
        """A new estimator in the same instance, its state started again (this one no
        longer bound: not to be used)."""
        return CompiledEstimator(self._cc, self.cfg, self.tick_len)

    def put(
        self, t: float, encoders: Sequence[EncoderSample], ranges: Sequence[RangeSample]
    ) -> None:
        """A cycle's samples into :attr:`inputs` (a ``struct`` call per sample: no list
        of them built): the counters modulo ``ticks_modulo`` (Python's exact integers: the
        same differences), a range without a target as NaN (as None: no target either
        way)."""
        ne, nr = len(encoders), len(ranges)
        if _HEAD + 5 * ne + 2 * nr > self.inputs.size:
            self._bind(2 * (_HEAD + 5 * ne + 2 * nr), False)
        m, mv, enc, rng = self._m, self._in_mv, _ENC, _RNG
        _PUT_HEAD(mv, 0, t, ne, nr)
        at = 8 * _HEAD
        for e in encoders:
            enc(mv, at, e.ticks_left % m, e.ticks_right % m, e.sample_time, e.left_ok, e.right_ok)
            at += 40
        for r in ranges:
            d = r.distance
            rng(mv, at, _NAN if d is None else d, r.sample_time)
            at += 16

    def read(self) -> Estimate:
        """The estimate the library wrote (:attr:`est`) as the Python estimator's."""
        v, ok, gap, vl, lv, st, std, outl, rein, ne, nr, rs, gl, age, vls, x = self.est.tolist()
        i = _TRUNC  # int() of a whole float, a third of int()'s cost
        return Estimate(
            v, ok == 1.0, gap, vl, lv == 1.0, STATUS[i(st)], std, i(outl), i(rein), i(ne),
            i(nr), i(rs), i(gl), age, vls, x,
        )  # fmt: skip

    def cycle(
        self, t: float, encoders: Sequence[EncoderSample], ranges: Sequence[RangeSample]
    ) -> Estimate:
        """:meth:`Estimator.cycle` in one call (the estimate only)."""
        self.put(t, encoders, ranges)
        status = int(self._run(self._instance, 0))
        if status != ccycle.ESTIMATED:
            raise RuntimeError(f"truckd_cycle_run refused the samples ({status})")
        return self.read()


def bind(
    cc: ccycle.CompiledCycle | None, cfg: EstimatorConfig, tick_len: float
) -> tuple[CompiledEstimator | None, str]:
    """The compiled estimator in a compiled cycle's instance, or None and why not (the
    MPC runs its Python path: no instance)."""
    if cc is None:
        return None, "the MPC runs its Python path"
    return CompiledEstimator(cc, cfg, tick_len), ""

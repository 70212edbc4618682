"""A log stamped with a clock's epoch (Unix time) is fitted as the same log from 0 s."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from labkit.synth import plant_log

from truckd.config.truck import load_config
from truckd.ident.api import identify_log
from truckd.logfile import Log
from truckd.model.effects import Effects

UNIX_2024 = 1.7e9
"""Seconds since 1970 in 2024: float64 keeps 0.24 us of them."""


@pytest.mark.parametrize("effects", [Effects(), Effects(input_delay=0.013)])
def test_unix_time_stamps_give_the_model_of_times_from_zero(effects: Effects) -> None:
    p = load_config().vehicle
    log = plant_log(p, effects, seed=11, n=1500)
    # Stamped as a logger with a wall clock writes them: microseconds, in text.
    t_epoch = np.round(log["t"] + UNIX_2024, 6)
    t_zero = t_epoch - UNIX_2024  # the same stamps' rounding, from 0 s
    fits = []
    for t in (t_zero, t_epoch):
        one = Log({**log.columns, "t": t}, log.source)
        fits.append(identify_log(one, p).vehicle)
    zero, epoch = (dataclasses.asdict(f) for f in fits)
    for name in ("K_v", "J_S", "K_coulomb", "K_stiction", "R_m"):
        assert epoch[name] == pytest.approx(zero[name], rel=1e-6), name

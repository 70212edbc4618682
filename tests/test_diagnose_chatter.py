"""Chatter: the measured speed swinging fast while the command holds still.

Hidden in logs of trucks drawn over a wide range (:func:`labkit.synth.draw_truck`), found
in a real robot's log (a drivetrain turning in place, ``tests/data/sysid/README.md``), never
named in logs without it, and left out of the fit so that the drivetrain's own model is
what the diagnosis reports.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from labkit.synth import EFFECT_RANGES, DrawnTruck, draw_truck, drawn_log, random_effects

from truckd.config.truck import load_config
from truckd.ident.api import diagnose_log, identify_log, read_logs, runs_from_logs
from truckd.ident.chatter import chatter_spans, without_chatter
from truckd.logfile import Log
from truckd.model.effects import Effects
from truckd.model.motor import steady_speed
from truckd.model.params import VehicleParams
from truckd.sim.plant import PlantConfig, simulate_open_loop

DATA = Path(__file__).parent / "data" / "sysid"
SEEDS = [int(s) for s in np.random.SeedSequence(20261204).generate_state(4)]
HOLD_S = 3.0
HIDDEN = (1.0, 2.5)
"""The chatter runs from 1.0 s to 2.5 s into the fourth of eight held commands."""


def _held_log(truck: DrawnTruck, rng: np.random.Generator, chatter: bool) -> tuple[Log, float]:
    """Eight commands held 3 s each through ``truck``; with ``chatter``, the speed swings
    at 6-15 Hz by 15-40 % of the truck's top speed in :data:`HIDDEN` of the fourth (and
    drops on average, as slipping wheels do).  Returns the log and that hold's start (s)."""
    h = 1.0 / truck.rate_hz
    n = int(8 * HOLD_S / h)
    dt = h * (1.0 + truck.jitter * rng.uniform(-1.0, 1.0, n - 1))
    t = np.concatenate([[0.0], np.cumsum(dt)])
    levels = rng.uniform(3.0, 7.0, 8) * rng.choice([-1.0, 1.0], 8)
    u = levels[np.minimum((t // HOLD_S).astype(int), 7)]
    cfg = PlantConfig(noise_v=truck.noise_v, seed=int(rng.integers(1 << 30)))
    v = simulate_open_loop(truck.params, t, u, cfg).v
    hold = 3 * HOLD_S
    if chatter:
        top = float(np.max(np.abs(v)))
        amp = float(rng.uniform(0.15, 0.4)) * top
        f, phase = float(rng.uniform(6.0, 15.0)), float(rng.uniform(0.0, 2 * np.pi))
        on = (t >= hold + HIDDEN[0]) & (t < hold + HIDDEN[1])
        swing = amp * np.sin(2 * np.pi * f * t + phase) - 0.3 * amp * np.sign(u)
        v = np.where(on, v + swing, v)
    if truck.speed_step > 0:
        v = np.round(v / truck.speed_step) * truck.speed_step
    return Log({"t": t, "u": u, "v": v}, "<held commands>"), hold


@pytest.mark.parametrize("seed", SEEDS)
def test_chatter_is_found_where_it_was_hidden(params: VehicleParams, seed: int) -> None:
    rng = np.random.default_rng(seed)
    truck = draw_truck(params, rng)
    log, hold = _held_log(truck, rng, chatter=True)
    spans = chatter_spans(runs_from_logs([log]))
    assert len(spans) == 1, spans
    (s,) = spans
    assert s.start == pytest.approx(hold + HIDDEN[0], abs=0.15)
    assert s.end == pytest.approx(hold + HIDDEN[1], abs=0.15)
    clean, _ = _held_log(truck, np.random.default_rng(seed), chatter=False)
    assert chatter_spans(runs_from_logs([clean])) == []


@pytest.mark.parametrize("name", [None, *EFFECT_RANGES])
def test_no_chatter_in_logs_of_drawn_trucks_with_each_effect(
    params: VehicleParams, name: str | None
) -> None:
    """Random commands held 0.2-2 s (steps, knees, reversals, backlash, delays, a
    current limit's constant acceleration): none of it is chatter."""
    for seed in SEEDS[:2]:
        rng = np.random.default_rng([seed, len(name or "")])
        truck = draw_truck(params, rng)
        eff = Effects() if name is None else random_effects(name, rng, truck.k_scale)
        log = drawn_log(truck, eff, seed, seconds=50.0)
        assert chatter_spans(runs_from_logs([log])) == [], (name, seed)


def test_chatter_is_found_in_a_real_robot_turning_in_place() -> None:
    """The steps of a drivetrain turning in place: at -7 V the speed swings by 3-5 m/s for
    about 4.6 s before it settles, at +7 V for about 0.6 s (a plot of the file shows it);
    the swerve drivetrain's log beside it has none."""
    runs = runs_from_logs(read_logs([str(DATA / "elite_angular1_steps.json")]))
    spans = chatter_spans(runs)
    assert [s.run for s in spans] == [0, 1]
    assert spans[0].start < 0.2 and 0.5 < spans[0].end < 0.9
    assert spans[1].start < 0.2 and 4.4 < spans[1].end < 5.0
    swerve = runs_from_logs(read_logs([str(DATA / "frc_swerve_12_12.json")]))
    assert chatter_spans(swerve) == []


def test_chatter_is_left_out_of_the_fit_and_named() -> None:
    """Without the chatter the diagnosis fits the drivetrain (above the least squares, as
    everywhere); with it left in, the same model fits far worse: the note says both."""
    logs = read_logs([str(DATA / "elite_angular1_steps.json")])
    d = diagnose_log(logs, load_config().vehicle, workers=1)
    out = d.to_json()
    assert [(c["data"], c["run"]) for c in out["chatter"]] == [("log", 1), ("log", 2)]
    fit, with_it = out["extended"]["fit_percent"], out["fit_percent_with_chatter"]
    assert fit > with_it + 10.0
    assert fit >= out["least_squares"]["fit_percent"]
    assert any(n.startswith("chatter:") for n in d.alerts)
    assert out["samples"] < sum(len(r) for r in runs_from_logs(logs))


def test_the_cut_keeps_every_other_sample_and_each_pieces_history(
    params: VehicleParams,
) -> None:
    rng = np.random.default_rng(SEEDS[0])
    log, _ = _held_log(draw_truck(params, rng), rng, chatter=True)
    (run,) = runs_from_logs([log])
    pieces, (span,) = without_chatter([run])
    assert len(pieces) == 2
    assert sum(len(p) for p in pieces) == len(run) - (span.stop - span.first)
    np.testing.assert_array_equal(pieces[1].t, run.t[span.stop :])
    assert pieces[1].hist_t is not None and pieces[1].hist_t[-1] < pieces[1].t[0]


def test_identify_fits_the_drivetrain_not_its_chatter() -> None:
    """``truckd identify`` on the robot turning in place: its model's steady speed at the
    steps' +-7 V is the speed the steps settle at (their last second), within 5 %."""
    logs = read_logs([str(DATA / "elite_angular1_steps.json")])
    p = identify_log(logs, load_config().vehicle).vehicle
    for run in runs_from_logs(logs):
        settled = float(np.mean(run.v[run.t > run.t[-1] - 1.0]))
        u = float(run.inp[-1])
        model = steady_speed(p, u) * p.r_w / (p.n_g * p.n_fd)
        assert model == pytest.approx(settled, rel=0.05), (u, settled, model)

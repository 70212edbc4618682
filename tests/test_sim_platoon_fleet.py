"""``truckd sim --platoon``: a fleet as it meets the real world (drawn trucks, lossy links
with drawn delays, unsynchronised clocks, trucks joining and leaving), in simulated time."""

from __future__ import annotations

import json
import random
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from truckd.cli.main import main
from truckd.config.truck import load_config
from truckd.control.platoon import ACC, CACC, PlatoonConfig
from truckd.control.qp import ControlModel
from truckd.sim import platoon
from truckd.sim.closed_loop import SimSetup
from truckd.sim.platoon import PREROLL_S, PlatoonTrace, make_platoon_scenario, run_platoon
from truckd.sim.platoon_truck import draw_platoon_truck, scaled_truck

LINK = {"loss": 0.3, "delay_s": (0.0, 0.05), "clock_offset_s": 2.0, "clock_drift_ppm": 100.0}


def _setup() -> SimSetup:
    cfg = load_config()
    return SimSetup(
        cfg.vehicle, cfg.plant, cfg.control, ControlModel(cfg.vehicle), ticks_per_rev=512
    )


def _pcfg() -> PlatoonConfig:
    """The shipped platoon settings with the timeout for a link whose delay reaches 50 ms:
    0.1 s of lost plans after the slowest delivery (docs/platoon.md)."""
    return replace(load_config().platoon, plan_timeout_s=0.15)


def _window_accel(tr: PlatoonTrace, j: int) -> tuple[np.ndarray, np.ndarray]:
    """Truck j's acceleration over 0.2 s windows (the per-cycle difference shows the
    encoder's quantisation), and the window end times."""
    t, v = np.asarray(tr.t), np.asarray(tr.v, dtype=float)[:, j]
    return (v[20:] - v[:-20]) / (t[20:] - t[:-20]), t[20:]


@pytest.mark.parametrize("name", ["platoon-brake", "platoon-sine"])
def test_ten_drawn_trucks_on_lossy_links_with_their_own_clocks(name: str) -> None:
    """Each truck drawn (mass, motor, one effect), 30 % of the plans lost, each delayed by
    a draw in 0-50 ms, each truck's clock off by up to 2 s and drifting by up to 100 ppm:
    no collision, the minimum gap kept, plans used (CACC) nearly throughout, and the
    disturbance does not grow down the platoon (acceleration ratios).  Spacing-error
    ratios from the second follower on at most 1 (brake 0.985 / 0.988, sine 0.874 /
    0.906; on the brake 1.02 / 1.00 with a single truck's relative-speed weight, before
    ``platoon.q_rel_speed``, and 1.20 / 1.19 before the input blocks were fitted to each
    truck's mechanical time constant: docs/platoon.md)."""
    pcfg = _pcfg()
    m, _ = run_platoon(make_platoon_scenario(name), _setup(), pcfg, 10, mixed=True, seed=5, **LINK)
    assert not m["collision"]
    assert m["min_gap_m"] >= load_config().control.d_min
    offsets = m["clock_offset_s"]
    assert max(offsets) - min(offsets) > 2.0  # the clocks really disagree
    assert len({round(d["m"], 3) for d in m["trucks_drawn"]}) == 10  # every truck its own
    assert min(m["cacc_fraction"]) > 0.9, m["cacc_fraction"]
    assert len(m["accel_ratio_l2"]) == 8
    assert max(m["accel_ratio_l2"] + m["accel_ratio_max"]) <= 1.0, m
    assert max(m["string_ratio_l2"] + m["string_ratio_max"]) <= 1.0, m
    assert sum(m["solver_failures"]) == 0


@pytest.mark.parametrize(("cap", "stable"), [(True, True), (False, False)])
def test_a_quick_truck_behind_the_shipped_one_makes_no_larger_spacing_error(
    monkeypatch: pytest.MonkeyPatch, cap: bool, stable: bool
) -> None:
    """Truck 2 light (0.6x the mass) with a strong motor (1.3x): its back-EMF turns a held
    voltage into an acceleration that decays with a time constant of 0.078 s, the
    configured truck's (trucks 0 and 1) 0.167 s.  With every truck's MPC input blocks at
    most 0.3 of its own time constant (``control.block_tau_fraction``, as every drawn
    truck's: 2 steps for truck 2, 4 for the others) its plan holds the brake's
    deceleration as the trucks ahead do and its spacing error is no larger than truck
    1's (l2 / max ratio 0.90 / 0.85).  With the shipped 8-step blocks for all (the
    control experiment: fraction 0) its blocked plan cannot, and its error is larger than
    truck 1's (1.24 / 1.17)."""
    kinds = iter([(1.0, 1.0), (1.0, 1.0), (0.6, 1.3)])  # (mass, motor constant) factors

    def truck(s: SimSetup, rng: object) -> SimSetup:
        t = scaled_truck(s, *next(kinds))
        return t if cap else replace(t, control=replace(t.control, block_tau_fraction=0.0))

    monkeypatch.setattr(platoon, "draw_platoon_truck", truck)
    sc = make_platoon_scenario("platoon-brake")
    m, _ = run_platoon(sc, _setup(), _pcfg(), 3, mixed=True, duration=8.0)
    assert not m["collision"] and m["min_gap_m"] >= load_config().control.d_min
    assert (max(m["string_ratio_l2"] + m["string_ratio_max"]) <= 1.0) == stable, m


@pytest.mark.parametrize(("q_rel", "bound"), [(None, 1.02), (5.0, None)])
def test_a_drawn_trucks_own_spacing_error_area_is_the_configured_trucks(
    monkeypatch: pytest.MonkeyPatch, q_rel: float | None, bound: float | None
) -> None:
    """The spacing-error area (``integral of e dt`` from 3 s, the brake's) a truck makes
    behind the configured truck sets the low-frequency ratio of its pair: a truck that
    makes more than the truck ahead gives a ratio above 1 anywhere in a long platoon
    (docs/platoon.md).  Truck 2 of seed 1's draw (viscous friction, 0.64x the mass)
    behind two configured trucks, ideal link: with the platoon's relative-speed weight
    (``platoon.q_rel_speed``, the follower's speed following its predecessor's plan)
    its area is within 2 % of truck 1's (1.018); with a single truck's weight (5, the
    control experiment) 12 % larger (1.117)."""
    kinds = iter([False, False, True])

    def truck(s: SimSetup, _rng: object) -> SimSetup:
        if not next(kinds):
            return scaled_truck(s, 1.0, 1.0)
        rng = random.Random(1)
        return [draw_platoon_truck(s, rng) for _ in range(3)][2]

    monkeypatch.setattr(platoon, "draw_platoon_truck", truck)
    pcfg = load_config().platoon
    if q_rel is not None:
        pcfg = replace(pcfg, q_rel_speed=q_rel)
    _m, tr = run_platoon(make_platoon_scenario("platoon-brake"), _setup(), pcfg, 3, mixed=True)
    t = np.asarray(tr.t)
    err = (np.asarray(tr.gap) - np.asarray(tr.gap_ref))[t >= 3.0]
    ratio = float(err[:, 2].sum() / err[:, 1].sum())
    if bound is not None:
        assert ratio <= bound, ratio
    else:
        assert ratio > 1.08, ratio


def test_identical_trucks_ride_out_bursts_of_lost_plans() -> None:
    """10 identical trucks, 30 % of the plans lost in bursts (runs of 8 on average, some
    of 30 and more), delays drawn in 0-50 ms, clocks +-2 s and 100 ppm apart: every
    follower stays in CACC throughout on its last plan shifted in time
    (``plan_hold_s``); the lead's braking is not amplified down the platoon (acceleration
    ratios, L2, at most 1) and its spacing error dies out along it (every follower's at
    most the first's, the last's at most half of it).  The spacing-error ratios of the
    last pairs are those of a floor each link makes for itself (its own bursts, delays and
    encoder): 0.98-1.08 over seeds 1-8, not at most 1 (docs/platoon.md, known gaps).
    (Without the hold, the same bursts switched followers to ACC and back many times and
    the ratios reached 11.)"""
    m, _ = run_platoon(
        make_platoon_scenario("platoon-brake"), _setup(), _pcfg(), 10, seed=1,
        burst_loss=True, **LINK,  # type: ignore[arg-type]
    )  # fmt: skip
    assert not m["collision"] and m["min_gap_m"] >= load_config().control.d_min
    assert m["plans_lost"] > 0.25 * m["plans_sent"]
    assert min(m["cacc_fraction"]) == 1.0 and max(m["mode_switches"]) == 0
    assert len(m["string_ratio_l2"]) == len(m["accel_ratio_l2"]) == 8
    assert max(m["accel_ratio_l2"]) <= 1.0, m["accel_ratio_l2"]
    e = m["spacing_error_max_m"]
    assert max(e[1:]) <= e[0] and e[-1] <= 0.5 * e[0], e
    assert max(m["string_ratio_l2"] + m["string_ratio_max"]) <= 1.15, m


def test_without_the_hold_bursts_switch_followers_to_acc() -> None:
    """The control experiment of the test above, 3 trucks: the same kind of link with
    ``plan_hold_s`` at the timeout (ACC once the newest plan is 0.15 s old): bursts
    switch the followers to ACC; with the shipped hold they do not."""
    sc = make_platoon_scenario("platoon-brake")
    kw = {"seed": 1, "burst_loss": True, "duration": 8.0, **LINK}
    off, _ = run_platoon(sc, _setup(), replace(_pcfg(), plan_hold_s=0.0), 3, **kw)  # type: ignore[arg-type]
    on, _ = run_platoon(sc, _setup(), _pcfg(), 3, **kw)  # type: ignore[arg-type]
    assert off["plans_lost"] > 0.2 * off["plans_sent"]
    assert max(off["mode_switches"]) >= 2
    assert max(on["mode_switches"]) == 0 and min(on["cacc_fraction"]) == 1.0


def test_without_the_clock_estimate_offset_clocks_lose_the_plans() -> None:
    """The same clocks with ``clock_sync`` off (clocks taken as agreeing): plans from a
    truck whose clock is behind look stale, from one ahead come from the future, and are
    not followed; with the estimate they are."""
    sc = make_platoon_scenario("platoon-sine")
    kw = {"clock_offset_s": 2.0, "clock_drift_ppm": 100.0, "seed": 3, "duration": 6.0}
    off, _ = run_platoon(sc, _setup(), replace(_pcfg(), clock_sync=False), 3, **kw)  # type: ignore[arg-type]
    on, _ = run_platoon(sc, _setup(), _pcfg(), 3, **kw)  # type: ignore[arg-type]
    assert max(off["cacc_fraction"]) < 0.1
    assert min(on["cacc_fraction"]) == 1.0


def test_a_truck_joins_in_the_middle_and_one_at_the_tail() -> None:
    """A truck in the next lane announces that it will follow truck 1; truck 2 (behind
    truck 1) opens room by its headway ramp, the joining truck moves in, and truck 2 takes
    it as its predecessor (from its range sensor and the plans, no list); a truck behind
    the tail finds the tail and closes up.  No collision, the minimum gap kept, and no
    truck brakes harder than the comfort limit while the room opens."""
    pcfg = _pcfg()
    sc = make_platoon_scenario("platoon-join")
    m, tr = run_platoon(sc, _setup(), pcfg, 6, **LINK)  # type: ignore[arg-type]
    assert not m["collision"]
    assert m["min_gap_m"] >= load_config().control.d_min
    t = np.asarray(tr.t)
    pre = np.asarray(tr.predecessor)
    lane = np.asarray(tr.lane)
    # truck 4 joined: in the platoon's lane, followed by truck 2, which followed truck 1
    assert lane[-1, 4] == 0 and lane[0, 4] == 1
    assert pre[0, 2] == "truck1" and pre[-1, 2] == "truck4" and pre[-1, 4] == "truck1"
    merged = t[np.argmax(lane[:, 4] == 0)]
    assert sc.event_s < merged < sc.duration - 3.0
    # truck 5 found the tail (truck 3) and drives CACC behind it at the end
    assert pre[0, 5] == "" and pre[-1, 5] == "truck3" and tr.mode[-1][5] == CACC
    # the gap opened smoothly: every truck from 1 on (the joining ones too), from the
    # announcement on
    for j in range(1, 6):
        a, ta = _window_accel(tr, j)
        assert np.min(a[ta > sc.event_s]) >= -pcfg.comfort_decel, (j, np.min(a[ta > sc.event_s]))
    # the room was opened by truck 2 before the merge: its gap grew by a CACC gap
    g2 = np.asarray(tr.gap, dtype=float)[:, 2]
    i = int(np.argmax(lane[:, 4] == 0)) - 1
    assert g2[i] > 1.8 * g2[round(sc.event_s / 0.01)]


def test_a_truck_leaves_and_its_follower_takes_the_truck_ahead() -> None:
    """Truck 2 leaves at 5 s: truck 3 sees the gap jump and follows truck 1 (the
    predecessor truck 2's plans named), on a plan it already listened to, so it stays in
    CACC, and closes the gap by its headway ramp: acceleration within the comfort limit
    either way, no switch to ACC."""
    pcfg = _pcfg()
    sc = make_platoon_scenario("platoon-leave")
    m, tr = run_platoon(sc, _setup(), pcfg, 5, **LINK)  # type: ignore[arg-type]
    assert not m["collision"] and m["min_gap_m"] >= load_config().control.d_min
    pre = np.asarray(tr.predecessor)
    assert pre[0, 3] == "truck2" and pre[-1, 3] == "truck1"
    t = np.asarray(tr.t)
    modes = np.asarray(tr.mode)
    assert np.all(modes[t > sc.event_s, 2] == "OUT")
    assert np.all(modes[t > sc.event_s, 3] == CACC) and not np.any(modes[:, 3:] == ACC)
    for j in (3, 4):
        a, ta = _window_accel(tr, j)
        after = a[ta > sc.event_s]
        assert np.min(after) >= -pcfg.comfort_decel and np.max(after) <= pcfg.comfort_decel
    # and the gap closed towards the CACC gap
    g3 = np.asarray(tr.gap, dtype=float)[:, 3]
    assert g3[-1] < 0.6 * g3[round((sc.event_s + 0.2) / 0.01)]


def test_cli_platoon_options(tmp_path: Path) -> None:
    out = tmp_path / "p.json"
    args = ["sim", "--platoon", "4", "--scenario", "platoon-sine", "--duration", "2"]
    args += ["--plan-delay", "0.01-0.04", "--plan-loss", "0.3", "--burst-loss"]
    args += ["--clock-offset", "1.5", "--clock-drift", "50", "--mixed", "--true-models"]
    args += ["--seed", "7"]
    assert main([*args, "--steady-start", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["trucks"] == 4 and len(doc["trucks_drawn"]) == 4
    assert doc["preroll_s"] == pytest.approx(PREROLL_S)  # the sine starts at speed
    assert all(abs(o) <= 1.5 for o in doc["clock_offset_s"])
    assert all(abs(d) <= 50.0 for d in doc["clock_drift_ppm"])
    for key in ("collision", "min_gap_m", "string_ratio_l2", "string_ratio_max",
                "cacc_fraction", "accel_ratio_l2", "accel_ratio_max", "events"):  # fmt: skip
        assert key in doc


@pytest.mark.parametrize(
    "args",
    [
        ("--platoon", "101"),
        ("--platoon", "3", "--plan-delay", "0.05-0.01"),
        ("--platoon", "3", "--plan-delay", "a-b"),
        ("--platoon", "3", "--clock-drift", "-1"),
        ("--platoon", "3", "--clock-offset", "nan"),
        ("--platoon", "3", "--scenario", "platoon-join"),  # needs 4 trucks
        ("--scenario", "cruise", "--mixed"),
        ("--scenario", "cruise", "--clock-offset", "1"),
        ("--scenario", "cruise", "--steady-start"),
    ],
)
def test_cli_bad_fleet_options_exit_2(
    args: tuple[str, ...], capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["sim", *args]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_the_spacing_rate_term_keeps_every_gap_on_its_reference() -> None:
    """``platoon.spacing_rate``: a follower weighs the rate of its spacing error
    (``v + h a - v_lead``) instead of the relative speed, so through the lead's braking
    each gap follows ``d_0 + h v`` instead of lagging it: every follower's peak spacing
    error at most a quarter of what the relative-speed term leaves (measured: a tenth),
    no collision, the minimum gap kept, and the braking not amplified down the platoon
    (acceleration ratios at most 1)."""
    sc = make_platoon_scenario("platoon-brake")
    off, _ = run_platoon(sc, _setup(), _pcfg(), 6, seed=1, **LINK)  # type: ignore[arg-type]
    on, _ = run_platoon(sc, _setup(), replace(_pcfg(), spacing_rate=True), 6, seed=1, **LINK)  # type: ignore[arg-type]
    assert not on["collision"] and on["min_gap_m"] >= load_config().control.d_min
    assert min(on["cacc_fraction"]) == 1.0
    assert max(on["accel_ratio_l2"]) <= 1.0, on["accel_ratio_l2"]
    e_on, e_off = on["spacing_error_max_m"], off["spacing_error_max_m"]
    assert len(e_on) == len(e_off) == 5
    assert all(a <= 0.25 * b for a, b in zip(e_on, e_off, strict=True)), (e_on, e_off)

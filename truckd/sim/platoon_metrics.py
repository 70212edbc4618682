"""The platoon's trace and metrics (reference section 1): spacing errors, string ratios,
minimum gaps, switches, accelerations."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from truckd.control.platoon import ACC, CACC, PlatoonConfig
from truckd.control.supervisor import time_in_modes
from truckd.sim.plan_channel import PlanChannel
from truckd.sim.platoon_scenarios import SETTLE_S
from truckd.sim.platoon_truck import PlatoonTruck

ACCEL_WINDOW_S = 0.5
"""The acceleration ratios' moving mean (s)."""


@dataclass
class PlatoonTrace:
    """Per-truck time series (SI): position, speed, gap to the vehicle the truck's range
    sensor sees (NaN: none; a truck in the next lane before it merges: to its
    predecessor), the reference gap at the headway in use, the headway, the mode
    (CACC/ACC, truck 0: LEAD, a truck that left: OUT), the voltage, the lane (0 the
    platoon's)."""

    t: list[float] = field(default_factory=list)
    x: list[list[float]] = field(default_factory=list)
    v: list[list[float]] = field(default_factory=list)
    gap: list[list[float]] = field(default_factory=list)
    gap_ref: list[list[float]] = field(default_factory=list)
    headway: list[list[float]] = field(default_factory=list)
    mode: list[list[str]] = field(default_factory=list)
    u: list[list[float]] = field(default_factory=list)
    accel: list[list[float]] = field(default_factory=list)
    lane: list[list[int]] = field(default_factory=list)
    predecessor: list[list[str]] = field(default_factory=list)
    supervisor: list[list[str]] = field(default_factory=list)
    rows: list[list[tuple[float, ...]]] = field(default_factory=list)
    """Per truck (truck 0, the lead, first): the daemon's log row each cycle with the truth
    appended, as :class:`~truckd.sim.closed_loop.Trace` rows (``--trace``)."""


def record_cycle(
    tr: PlatoonTrace,
    t: float,
    v_driver: float,
    d_0: float,
    trucks: list[PlatoonTruck],
    gaps: list[float],
) -> None:
    tr.t.append(t)
    nan = math.nan
    xs: list[float] = []
    vs: list[float] = []
    refs: list[float] = []
    hs: list[float] = []
    modes: list[str] = []
    us: list[float] = []
    acc: list[float] = []
    lanes: list[int] = []
    pres: list[str] = []
    for i, f in enumerate(trucks):
        live = f.active and f.dec is not None and f.out is not None
        xs.append(f.plant.x if live else nan)
        vs.append(f.plant.v if live else nan)
        refs.append(d_0 + f.dec.headway * f.plant.v if live and f.dec is not None else nan)
        hs.append(f.dec.headway if live and f.dec is not None else nan)
        modes.append(("LEAD" if i == 0 else f.dec.mode) if live and f.dec is not None else "OUT")
        us.append(f.out.command.voltage if live and f.out is not None else nan)
        acc.append(nan)
        lanes.append(f.lane)
        pres.append(f.predecessor)
    tr.x.append(xs)
    tr.v.append(vs)
    tr.gap.append(list(gaps))
    tr.gap_ref.append(refs)
    tr.headway.append(hs)
    tr.mode.append(modes)
    tr.u.append(us)
    tr.accel.append(acc)
    tr.lane.append(lanes)
    tr.predecessor.append(pres)
    tr.supervisor.append(
        [f.out.mode.value if f.active and f.out is not None else "OUT" for f in trucks[1:]]
    )
    if not tr.rows:
        tr.rows = [[] for _ in trucks]
    by_id = {f.vid: f for f in trucks}
    for j, f in enumerate(trucks):
        if not f.active or f.out is None:
            continue
        ahead = by_id.get(f.predecessor)
        v_ahead = v_driver if j == 0 else (ahead.plant.v if ahead is not None else nan)
        tr.rows[j].append(
            (*f.cyc.log_row(f.out), f.plant.v, gaps[j], v_ahead, f.plant.x, f.plant.motor.i)
        )


def string_ratios(
    err: np.ndarray, floor: float = 0.0
) -> tuple[list[float | None], list[float | None]]:
    """``(l2, max)`` ratios for each follower i >= 2 from spacing errors ``err`` (m; rows:
    samples; columns: followers 1..N-1). A ratio is ``None`` where the truck ahead made no
    spacing error in the window (it was not yet in the lane: a truck that joins after the
    run ends), so there is nothing to compare with.

    ``floor`` (m, 0: the plain ratios): an error below it counts as the floor, for both
    trucks of a pair: ``max(||e_i||, f) / max(||e_(i-1)||, f)`` with ``f`` the floor's
    norm over the window (``floor sqrt(samples)`` for L2, ``floor`` for the maximum).  Two
    errors within the floor give 1 (neither truck can tell its error from its range
    sensor's noise); an error that grows above the floor still gives a ratio above 1."""
    l2: list[float | None] = []
    mx: list[float | None] = []
    f2 = floor * math.sqrt(err.shape[0])
    for j in range(1, err.shape[1]):
        a, b = err[:, j - 1], err[:, j]
        defined = bool(np.any(a))
        n_a, n_b = max(float(np.linalg.norm(a)), f2), max(float(np.linalg.norm(b)), f2)
        m_a, m_b = max(float(np.max(np.abs(a))), floor), max(float(np.max(np.abs(b))), floor)
        l2.append(n_b / n_a if defined else None)
        mx.append(m_b / m_a if defined else None)
    return l2, mx


def _changes(seq: list[str]) -> int:
    """How often consecutive entries of ``seq`` differ."""
    return sum(a != b for a, b in itertools.pairwise(seq))


def _supervisor_figures(tr: PlatoonTrace, dt: float) -> dict[str, Any]:
    """Per follower: the supervisor modes it was in (``OUT`` while off the road), and as
    a single truck's run reports them, the seconds in each mode (every mode named) and
    the count of mode changes from one cycle to the next while on the road."""
    seqs = list(zip(*tr.supervisor, strict=True))
    return {
        "supervisor_modes": [sorted(set(m)) for m in seqs],
        "mode_time_s": [time_in_modes(seq, dt) for seq in seqs],
        "transitions": [_changes([m for m in seq if m != "OUT"]) for seq in seqs],
    }


def platoon_metrics(
    name: str,
    n_trucks: int,
    tr: PlatoonTrace,
    followers: list[PlatoonTruck],
    channels: list[PlanChannel],
    pcfg: PlatoonConfig,
) -> dict[str, Any]:
    """The contract keys (reference section 1) plus switch times and decelerations.
    Columns are trucks by index (with joins and leaves, the pairs of the ratios are the
    trucks' indices, not their order on the road); collision and minimum gap are over
    the platoon's lane."""
    t = np.asarray(tr.t)
    lane = np.asarray(tr.lane)[:, 1:]
    all_gaps = np.asarray(tr.gap, dtype=float)[:, 1:]
    gaps = np.where(lane == 0, all_gaps, np.nan)
    err = np.nan_to_num(gaps - np.asarray(tr.gap_ref, dtype=float)[:, 1:])
    keep = t >= SETTLE_S if len(t) and t[-1] >= 2.0 * SETTLE_S else np.ones(len(t), dtype=bool)
    l2, mx = string_ratios(err[keep])
    floor = max((f.fw.cfg.range_noise for f in followers), default=0.0)
    l2_f, mx_f = string_ratios(err[keep], floor)
    modes = np.asarray(tr.mode)[:, 1:]
    v = np.asarray(tr.v, dtype=float)
    dt = float(t[1] - t[0]) if len(t) > 1 else 1.0
    accel = np.diff(v, axis=0) / dt
    min_gap = float(np.nanmin(gaps))
    first_acc = [
        float(t[np.argmax(modes[:, j] == ACC)]) if np.any(modes[:, j] == ACC) else None
        for j in range(modes.shape[1])
    ]
    live = modes != "OUT"
    # acceleration ratios: the 0.5 s mean of each truck's true acceleration (the lead's
    # manoeuvre as it travels down the platoon; a truck's own actuation ripple, from a
    # dead zone or the encoder, averaged out), pairs as above
    # (no wider than the run: a run shorter than the window averages over all of it)
    win = max(1, min(round(ACCEL_WINDOW_S / dt), len(accel)))
    smooth = np.array(
        [
            np.convolve(np.nan_to_num(accel[:, j]), np.ones(win) / win, "same")
            for j in range(1, accel.shape[1])
        ]
    ).T.reshape(len(accel), -1)
    a_l2, a_mx = string_ratios(smooth[keep[1:]])
    return {
        "scenario": name,
        "trucks": n_trucks,
        "collision": bool(min_gap <= 0.0),
        "min_gap_m": min_gap,
        "string_ratio_l2": l2,
        "string_ratio_max": mx,
        "cacc_fraction": [
            float(np.mean(modes[live[:, j], j] == CACC)) for j in range(modes.shape[1])
        ],
        # Extensions:
        "min_gap_per_follower_m": [
            float(np.nanmin(gaps[:, j])) if np.any(np.isfinite(gaps[:, j])) else None
            for j in range(gaps.shape[1])
        ],
        "spacing_error_max_m": [float(np.max(np.abs(err[keep, j]))) for j in range(err.shape[1])],
        "first_acc_s": first_acc,
        "mode_switches": [f.mode.switches for f in followers],
        "min_accel_m_s2": [float(np.nanmin(accel[keep[1:], j])) for j in range(1, accel.shape[1])],
        "string_ratio_floor_m": floor,
        "string_ratio_l2_floored": l2_f,
        "string_ratio_max_floored": mx_f,
        "accel_ratio_l2": a_l2,
        "accel_ratio_max": a_mx,
        "cacc_headway_s": pcfg.cacc_headway,
        "acc_headway_s": pcfg.acc_headway,
        "plans_sent": sum(c.sent for c in channels),
        "plans_lost": sum(c.lost for c in channels),
        "solver_failures": [f.cyc.controller.solver_failures for f in followers],
        **_supervisor_figures(tr, dt),
        "duration_s": round(float(t[-1] + dt), 6),
    }

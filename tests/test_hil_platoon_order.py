"""HIL: whom each truck follows, found by the daemons themselves (``platoon.order: auto``)
with separate processes in real time (``benchmarks/platoon_hil.py --order auto --join
--told``): a world process with 4 trucks on 4 ptys and ``truckd run`` daemons over Zenoh on
loopback.

p2 is configured with no predecessor and finds the tail (p1) from its range sensor and the
plans heard once the trucks move.  A fourth truck is put beside the platoon behind p0 and
its daemon started with no predecessor; an operator's order on ``truckd/p3/platoon_join``
(``{"behind": "p0"}``) tells it where to join: p1 hears it announce, opens room, and
follows it once the world moves it into the lane (the same join, configured with
``platoon.predecessor: p0`` at start, is ``--join`` alone).  Then p1 leaves the lane and p2, whose
range sensor now sees p3, follows p3 and drives CACC behind it.  Pass: those
predecessors, read from each truck's published plans, each change after the event that
causes it, no collision among the trucks in the lane (true gaps from the world), every
daemon exits 0 on SIGTERM.  Staying in CACC through a join and a leave is asserted in
simulated time (``tests/test_sim_platoon_fleet.py``).  Wall-clock waits are bounds; the
times are reported, not asserted."""

from __future__ import annotations

from pathlib import Path

import pytest
from runtime_support import run_json_script

pytestmark = [pytest.mark.hil, pytest.mark.slow]

ROOT = Path(__file__).resolve().parent.parent


def test_tail_join_and_leave_with_separate_processes(tmp_path: Path) -> None:
    out = tmp_path / "hil.json"
    script = str(ROOT / "benchmarks" / "platoon_hil.py")
    args = [script, "--order", "auto", "--join", "--told", "--json", str(out)]
    r, text = run_json_script(args, out, 240.0)
    assert r["ok"], r.get("error", "") + "\n" + text[-2000:]
    assert r["exit_codes"] == [0, 0, 0, 0], r["daemon_stderr_tail"]
    assert not r["collision"] and min(g for g in r["min_true_gap_m"] if g is not None) > 0.1
    p1, p2 = r["predecessors"]["p1"], r["predecessors"]["p2"]
    # p2, configured with none ("" until the trucks move): the tail, then past the leaver
    assert [pre for _t, pre in p2] in (["p1", "p3"], ["", "p1", "p3"]), p2
    assert p2[-1][0] >= r["leave_s"], (p2, r["leave_s"])
    # p1 behind p0, then behind the truck told to join, once it moved in
    assert r["join"] == "told" and r["joiner_started_s"] < r["told_s"] < r["p1_opens_room_s"]
    assert [pre for _t, pre in p1][:2] == ["p0", "p3"], p1
    assert r["merge_s"] <= p1[1][0] < r["leave_s"], (p1, r["merge_s"])
    # p2 drives CACC behind p3 at the end (then the daemons are stopped, the lead first)
    t_end = r["leave_phase_end_s"]
    p2_modes = [pl for t, vid, pl, _m in r["events"] if vid == "p2" and t < t_end]
    assert p2_modes and p2_modes[-1] == "CACC", r["events"]

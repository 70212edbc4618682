"""HIL: the platoon with separate processes in real time (benchmarks/platoon_hil.py): a
world process with 3 trucks on 3 ptys, 3 `truckd run` daemons over Zenoh on loopback, a
lead brake and a cut link.

Pass: every phase reached (both followers in CACC; after the link to truck 2 is cut it
switches to ACC; once restored, back to CACC), no collision (true gaps from the world),
every daemon exits 0 on SIGTERM.  Wall-clock waits are bounds, not timings: the switch
times are reported, not asserted."""

from __future__ import annotations

from pathlib import Path

import pytest
from runtime_support import run_json_script

pytestmark = [pytest.mark.hil, pytest.mark.slow]

ROOT = Path(__file__).resolve().parent.parent


def test_platoon_brake_and_link_loss_with_separate_processes(tmp_path: Path) -> None:
    out = tmp_path / "hil.json"
    script = str(ROOT / "benchmarks" / "platoon_hil.py")
    r, text = run_json_script([script, "--json", str(out)], out, 180.0)
    assert r["ok"], r.get("error", "") + "\n" + text[-2000:]
    assert not r["collision"] and min(r["min_true_gap_m"]) > 0.1
    assert r["exit_codes"] == [0, 0, 0], r["daemon_stderr_tail"]
    modes = [(vid, pl) for _t, vid, pl, _mode in r["events"] if vid == "p2"]
    assert ("p2", "ACC") in modes and ("p2", "CACC") in modes
    assert r["acc_after_s"] > 0 and r["cacc_again_after_s"] > 0

"""``benchmarks/wakeup_floor.py``: the bare periodic sleeper that measures the machine's
own wake-up floor beside the loop benchmark (what it reports, what it refuses)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parent.parent / "benchmarks" / "wakeup_floor.py"


def test_a_short_run_reports_every_wakeup_and_the_late_ones_it_counted(tmp_path: Path) -> None:
    out = tmp_path / "floor.json"
    r = subprocess.run(
        [sys.executable, str(SCRIPT), "--rate", "200", "--duration", "0.5", "--compute-us", "0",
         "--json", str(out), "--key", "short_run_2026-12-02"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    got = json.loads(out.read_text())["short_run_2026-12-02"]
    assert got["wakeups"] == 100 and got["rate_hz"] == 200.0
    assert 0 <= got["lateness_us_p50"] <= got["lateness_us_p99"] <= got["lateness_us_max"]
    # a wake-up is too late when it leaves the cycle less than its compute time
    late = got["too_late"]
    assert len(late) == min(50, got["wakeups_too_late_for_the_cycle"])
    assert all(x["lateness_us"] > 5000 - 1 for x in late)
    assert (got["lateness_us_max"] > 5000) == (got["wakeups_too_late_for_the_cycle"] > 0)


@pytest.mark.parametrize(
    "args",
    [
        ["--rate", "0.5"],
        ["--duration", "0"],
        ["--rate", "500", "--compute-us", "2000"],
        ["--json", "x.json", "--key", "undated"],
    ],
)
def test_arguments_outside_their_range_are_exit_2(args: list[str]) -> None:
    r = subprocess.run(
        [sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 2 and "wakeup_floor:" in r.stderr

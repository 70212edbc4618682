"""A recorder that cannot write (a full disk, simulated with RLIMIT_FSIZE) must not stop
the daemon: it keeps controlling, counts the failures, and says the log is incomplete
instead of claiming it was flushed."""

from __future__ import annotations

import re
from pathlib import Path

from cli_support import run_limited
from runtime_support import write_config

from truckd.logfile import read_log


def test_full_disk_keeps_the_loop_running_and_says_the_log_is_incomplete(
    tmp_path: Path,
) -> None:
    cfg = write_config(
        tmp_path / "c.yaml",
        {
            "runtime": {
                "realtime": False,
                "telemetry": {"enabled": False},
                "recorder": {"dir": str(tmp_path / "logs"), "flush_period_s": 0.1},
            }
        },
    )
    p = run_limited(
        ["run", "--config", str(cfg), "--backend", "sim", "--duration", "3"],
        tmp_path,
        fsize=20_000,  # about 120 rows of the CSV, well under 3 s at 100 Hz
    )
    assert p.returncode == 0, p.stderr[-2000:]
    assert "Traceback" not in p.stderr
    m = re.search(r"stopped after (\d+) cycles", p.stderr)
    assert m is not None and int(m.group(1)) >= 200  # the loop ran on (3 s at 100 Hz)
    assert "log flushed" not in p.stderr  # not claimed
    assert re.search(r"log incomplete: \d+ write errors", p.stderr), p.stderr[-2000:]
    (csv,) = (tmp_path / "logs").glob("*.csv")
    assert csv.stat().st_size <= 20_000
    log = read_log(csv)  # what did reach the disk reads back (a cut last line skipped)
    assert 10 <= len(log["t"]) < int(m.group(1))

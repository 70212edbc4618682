"""A recorder that cannot write (a full disk, simulated with RLIMIT_FSIZE) must not stop
the daemon: it keeps controlling, counts the failures, and says the log is incomplete
instead of claiming it was flushed."""

from __future__ import annotations

import re
import time
from pathlib import Path
from typing import BinaryIO

from cli_support import run_limited
from runtime_support import write_config

from truckd.config.runtime import RecorderConfig
from truckd.logfile import read_log
from truckd.runtime.recorder import Recorder


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


def test_disk_full_at_rotation_keeps_the_writer_alive_and_resumes(tmp_path: Path) -> None:
    """A file that cannot be flushed when the recorder rotates (ENOSPC: ``/dev/full``
    stands in for a full disk) must not leave a closed file behind: the writer thread
    stays alive, stop() does not raise, and recording resumes in a new file once there is
    space again."""
    cfg = RecorderConfig(
        dir=str(tmp_path / "logs"), max_bytes=4096, keep=50, flush_period_s=0.01, mcap=False
    )
    rec = Recorder(cfg, ("t", "u", "v"))
    real = rec._create
    full = {"on": False}

    def create(base: str) -> tuple[Path, BinaryIO]:
        if full["on"]:  # a name that is never a device: keep= may unlink it
            return tmp_path / f"{base}-full.csv", open("/dev/full", "wb", buffering=0)
        return real(base)

    rec._create = create  # type: ignore[method-assign]
    rec.start()
    full["on"] = True  # the next file lands on a full disk

    def feed(n0: int, n: int) -> None:
        for i in range(n0, n0 + n):
            rec.record((i * 0.01, 1.0, 2.0))
            if i % 64 == 0:
                rec._event.set()
                deadline = time.monotonic() + 5.0
                while rec._q and time.monotonic() < deadline:  # bounded wait: drained
                    time.sleep(0.001)

    feed(0, 1500)  # several rotations onto the full disk
    assert rec.errors > 0
    assert rec._thread is not None and rec._thread.is_alive()
    full["on"] = False  # space again
    feed(1500, 1500)
    rec.stop()  # must not raise
    good = [p for p in rec.files if p.exists() and p.read_text().count("\n") > 1]
    assert good, "recording did not resume after the disk had space again"
    t_last = max(float(read_log(p)["t"][-1]) for p in good)
    assert t_last >= 29.0  # the rows fed after the disk had space are on disk

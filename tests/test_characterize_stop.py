"""`truckd characterize` stopped mid-experiment (a stop request over Zenoh, or SIGTERM),
the CLI on the ``sim`` backend in its own process: exit 4, 0 V within 2 control periods of
the stop, the truck ends at rest, the partial log is complete up to the stop (and through
the braking after it), readable, and marked (``summary.json`` ``stopped``)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from hil_support import PY, ROOT, end_process
from runtime_support import endpoint, free_port, wait_for, write_config

from truckd.logfile import read_log
from truckd.runtime.telemetry import zenoh_config

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("how", ["zenoh", "sigterm"])
def test_a_stop_mid_experiment_stops_the_truck_and_keeps_the_log(tmp_path: Path, how: str) -> None:
    port = free_port()
    cfg = write_config(
        tmp_path / "truck.yaml",
        {"runtime": {"backend": "sim", "telemetry": {"listen": [endpoint(port)]}}},
    )
    out = tmp_path / "out"
    msgs: list[dict[str, Any]] = []
    lock = threading.Lock()

    def on(s: zenoh.Sample) -> None:
        with lock:
            msgs.append(json.loads(s.payload.to_bytes()))

    session = zenoh.open(zenoh_config(listen=[], connect=[endpoint(port)]))
    session.declare_subscriber("truckd/truck1/characterize", on)
    proc = subprocess.Popen(
        [PY, "-m", "truckd.cli.main", "characterize", "--config", str(cfg), "--out", str(out)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT,
    )  # fmt: skip
    try:

        def moving() -> bool:  # well into the first ramp: the truck drives
            with lock:
                ramp = [m for m in msgs if m["experiment"] == "quasistatic-forward"]
            return len(ramp) >= 4

        assert wait_for(moving, 60.0), msgs
        if how == "zenoh":
            session.put("truckd/truck1/stop", b"{}")
        else:
            os.kill(proc.pid, signal.SIGTERM)
        _, stderr = proc.communicate(timeout=60)
        assert proc.returncode == 4, stderr[-2000:]
    finally:
        end_process(proc)
        session.close()  # type: ignore[no-untyped-call]
    summary = json.loads((out / "summary.json").read_text())
    stopped = summary["stopped"]
    assert stopped["reason"] == ("stop request over Zenoh" if how == "zenoh" else "SIGTERM")
    assert summary["experiments"][0]["ended"] == "stopped"
    assert summary["experiments"][1]["t_start"] is None  # nothing started after the stop
    assert not (out / "model.yaml").exists()
    log = read_log(out / "log.csv")
    t, u, v = log["t"], log["u"], log["v"]
    period = 0.01
    t_stop = stopped["t"]
    assert t[0] <= summary["experiments"][0]["t_start"] + period
    assert t[-1] >= t_stop
    # complete: a row for every period up to the end, but for the periods the loop skipped
    # after an overrun (counted by the loop: a lost row is told from a late host); the
    # rows' times are their cycles' wake-ups, up to a period after their periods' starts
    skipped = summary["loop"]["skipped_periods"]
    assert len(t) + skipped >= (t[-1] - t[0]) / period, (len(t), skipped, t[-1] - t[0])
    assert np.max(np.diff(t)) < (2.0 + skipped) * period
    before = t < t_stop - period
    assert np.max(np.abs(u[before])) > 0.5 and np.max(np.abs(v[before])) > 0.1  # driving
    after = t >= t_stop + 2 * period
    assert after.any() and np.all(u[after] == 0.0)
    assert np.array_equal(log["stopped"] == 1.0, t >= t_stop - 1e-6)  # the log marks the stop
    assert abs(v[-1]) < 0.02 and abs(summary["end_speed_m_s"]) < 0.02  # at rest

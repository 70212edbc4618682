"""`truckd monitor`: the fleet table, and the live CLI against a publishing vehicle."""

from __future__ import annotations

import json
import subprocess
import sys
import time

from runtime_support import endpoint, free_port

from truckd.runtime.config import TelemetryConfig
from truckd.runtime.monitor import FleetView
from truckd.runtime.telemetry import Telemetry


def test_fleet_view_rows() -> None:
    v = FleetView()
    v.on_alive("truckd/a/alive", True)
    state = {"mode": "ACTIVE", "v": 1.234, "gap": 1.5, "gap_ref": 1.25, "solve_us": 210.0}
    v.on_sample("truckd/a/state", json.dumps(state).encode(), 1.0)
    v.on_sample("truckd/a/health", b'{"loop": {"lateness_us_p99": 88.0}, "faults": ["x"]}', 1.0)
    v.on_sample("truckd/b/state", b'{"mode": "SAFE_STOP", "v": null}', 1.0)
    v.on_sample("truckd/b/state", b"not json", 1.0)  # ignored
    v.on_sample("other/b/state", b"{}", 1.0)  # not ours
    rows = v.rows()
    assert rows[0] == ("a", "online", "ACTIVE", "1.23", "1.500", "+0.250", "210", "88", "-", "x")
    assert rows[1][:4] == ("b", "offline", "SAFE_STOP", "-")
    assert len(rows) == 2
    v.on_alive("truckd/a/alive", False)
    assert v.rows()[0][1] == "offline"
    assert "vehicle" in v.render()


def test_monitor_cli_sees_vehicle_then_offline() -> None:
    port = free_port()
    tel = Telemetry("mon1", TelemetryConfig(listen=(endpoint(port),)), dict)
    tel.start()
    try:
        proc = subprocess.Popen(
            [sys.executable, "-m", "truckd.cli.main", "monitor", "--connect", endpoint(port),
             "--duration", "4", "--interval", "0.25"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        t_end = time.monotonic() + 2.0
        seq = 0
        while time.monotonic() < t_end:
            tel.publish_state({"seq": seq, "mode": "ACTIVE", "v": 0.75, "gap": 1.0, "gap_ref": 1.0})
            seq += 1
            time.sleep(0.02)
        tel.close()
        out, err = proc.communicate(timeout=20)
    finally:
        tel.close()
    assert proc.returncode == 0, err
    tables = [t for t in out.split("\n\n") if t.strip()]
    online = [t for t in tables if "mon1" in t and "online" in t and "0.75" in t]
    assert online, out
    last = tables[-1].splitlines()
    assert last[1].split()[:3] == ["mon1", "offline", "ACTIVE"]

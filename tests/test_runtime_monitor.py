"""`truckd monitor`: the fleet table, and the live CLI against a publishing vehicle."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable

import pytest
from hil_support import end_process
from runtime_support import endpoint, free_port

from truckd.config.runtime import TelemetryConfig
from truckd.runtime.monitor import MAX_VEHICLES, STALE_S, FleetView
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
    assert rows[1][:4] == ("b", "offline", "unknown", "-")  # no token: its mode is not known
    assert len(rows) == 2
    v.on_alive("truckd/a/alive", False)
    assert v.rows()[0][:4] == ("a", "offline", "unknown", "-")  # not its last ACTIVE
    assert "vehicle" in v.render()


def test_a_huge_integer_or_deep_nesting_from_a_peer_is_no_crash() -> None:
    """A 400-digit integer in a state (OverflowError in every later render: the monitor
    exited) or JSON nested beyond the stack (RecursionError out of the callback)."""
    v = FleetView()
    v.on_alive("truckd/a/alive", True)
    big = "9" * 400
    v.on_sample(
        "truckd/a/state",
        f'{{"mode": "ACTIVE", "v": {big}, "gap": {big}, "gap_ref": 1}}'.encode(),
        1.0,
    )
    v.on_sample(
        "truckd/a/health",
        f'{{"loop": {{"lateness_us_p99": {big}}}, "state_rate_hz": {big}}}'.encode(),
        1.0,
    )
    v.on_sample("truckd/b/state", b"[" * 100_000, 1.0)
    text = v.render()
    assert "a" in text
    assert v.rows()[0][3] == "-"  # not a speed


def _wait_output(lines: list[str], pred: Callable[[str], bool], timeout: float) -> bool:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if any(pred(line) for line in list(lines)):
            return True
        time.sleep(0.02)
    return False


def test_monitor_cli_sees_vehicle_then_offline() -> None:
    port = free_port()
    tel = Telemetry("mon1", TelemetryConfig(listen=(endpoint(port),)), dict)
    tel.start()
    lines: list[str] = []
    try:
        # --duration counts from the monitor's session being open (not its start-up)
        proc = subprocess.Popen(
            [sys.executable, "-m", "truckd.cli.main", "monitor", "--connect", endpoint(port),
             "--duration", "5", "--interval", "0.25"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        assert proc.stdout is not None
        stdout = proc.stdout

        def read() -> None:
            for line in stdout:
                lines.append(line)

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        assert _wait_output(lines, lambda ln: "vehicle" in ln, 60.0), "no table"
        seq = 0
        t_end = time.monotonic() + 4.0
        while not any("mon1" in ln and "online" in ln and "0.75" in ln for ln in list(lines)):
            assert time.monotonic() < t_end, "".join(lines)
            tel.publish_state({"seq": seq, "mode": "ACTIVE", "v": 0.75, "gap": 1.0, "gap_ref": 1.0})
            seq += 1
            time.sleep(0.02)
        tel.close()
        assert proc.wait(timeout=20) == 0, proc.stderr.read()  # type: ignore[union-attr]
        reader.join(timeout=5)
    finally:
        tel.close()
        end_process(proc)
    out = "".join(lines)
    tables = [t for t in out.split("\n\n") if t.strip()]
    online = [t for t in tables if "mon1" in t and "online" in t and "0.75" in t]
    assert online, out
    last = tables[-1].splitlines()
    assert last[1].split()[:3] == ["mon1", "offline", "unknown"]
    assert not any("unreachable" in t for t in online)  # connected while it was seen
    assert "unreachable" in tables[-1]  # the vehicle's session (the only peer) has gone


def test_untrusted_text_is_escaped_and_bounded() -> None:
    v = FleetView()
    evil = "\x1b[2J\x1b]0;pwned\x07\x9b31m\u202eACTIVE\u200b" + "A" * 500
    v.on_alive("truckd/\x1b[31mx/alive", True)
    v.on_sample("truckd/\x1b[31mx/state", json.dumps({"mode": evil, "v": 1.0}).encode(), 1.0)
    v.on_sample("truckd/\x1b[31mx/health", json.dumps({"faults": [evil] * 50}).encode(), 1.0)
    text = v.render()
    bad = [ch for ch in text if ch != "\n" and (ord(ch) < 0x20 or 0x7F <= ord(ch) <= 0x9F)]
    assert bad == [] and "\u202e" not in text and "\u200b" not in text
    assert "\\x1b[2J" in text  # shown, visibly, not executed
    assert max(len(line) for line in text.splitlines()) < 400
    row = v.rows()[0]
    assert row[0] == "\\x1b[31mx" and len(row[2]) <= 32 and row[2].endswith("...")


def test_vehicles_tracked_are_bounded() -> None:
    v = FleetView()
    for k in range(MAX_VEHICLES + 50):
        v.on_sample(f"truckd/v{k}/state", b'{"mode": "ACTIVE"}', 1.0)
    assert len(v.rows()) == MAX_VEHICLES and v.ignored == 50
    assert "ignored" in v.render()


def test_monitor_says_when_the_endpoint_is_unreachable() -> None:
    port = free_port()  # nothing listens there
    r = subprocess.run(
        [sys.executable, "-m", "truckd.cli.main", "monitor", "--connect", endpoint(port),
         "--duration", "1", "--interval", "0.25"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    tables = [t for t in r.stdout.split("\n\n") if t.strip()]
    assert tables and all(f"not connected: {endpoint(port)} unreachable" in t for t in tables)


def test_online_vehicle_whose_state_stops_is_stale_not_its_last_mode() -> None:
    v = FleetView()
    v.on_alive("truckd/a/alive", True)
    v.on_sample("truckd/a/state", b'{"mode": "ACTIVE", "v": 1.0}', 10.0)
    assert v.rows(now=10.0 + STALE_S / 2)[0][:4] == ("a", "online", "ACTIVE", "1.00")
    assert v.rows(now=10.0 + STALE_S * 2)[0][:4] == ("a", "stale", "unknown", "-")
    v.on_sample("truckd/a/state", b'{"mode": "ACTIVE", "v": 1.0}', 10.0 + STALE_S * 2)
    assert v.rows(now=10.0 + STALE_S * 2)[0][1] == "online"  # it came back


def test_platoon_lines_from_the_network_are_escaped() -> None:
    v = FleetView()
    evil = "\x1b]0;pwned\x07lead"
    v.on_sample("truckd/f1/state", json.dumps({"mode": "ACTIVE", "gap": 1.0}).encode(), 1.0)
    v.on_sample(
        "truckd/f1/health",
        json.dumps({"platoon": {"predecessor": evil}, "faults": []}).encode(),
        1.0,
    )
    v.on_sample(
        "truckd/f1/state",
        json.dumps({"mode": "ACTIVE", "gap": 1.0, "platoon": "\x1b[2JCACC"}).encode(),
        1.0,
    )
    text = v.render()
    platoon = [line for line in text.splitlines() if line.startswith("platoon:")]
    assert platoon, text  # the chain is listed
    bad = [ch for ch in text if ch != "\n" and (ord(ch) < 0x20 or 0x7F <= ord(ch) <= 0x9F)]
    assert bad == [] and "\\x1b]0;pwned" in platoon[0]


def test_characterize_progress_is_a_line_under_the_table() -> None:
    v = FleetView()
    v.on_alive("truckd/a/alive", True)
    v.on_sample("truckd/a/state", b'{"mode": "DEGRADED", "v": 0.4}', 1.0)
    assert "characterize" not in v.render(1.0)
    msg = {"t": 3.0, "stage": "experiments", "experiment": "dynamic-forward-3V", "percent": 41.6}
    v.on_sample("truckd/a/characterize", json.dumps(msg).encode(), 1.0)
    lines = v.render(1.0).splitlines()
    assert lines[-1] == "a characterize: experiments dynamic-forward-3V 42 %"
    evil = {"stage": "\x1b[2Jdone", "experiment": "", "percent": 100}
    v.on_sample("truckd/a/characterize", json.dumps(evil).encode(), 1.0)
    assert "\x1b" not in v.render(1.0)


@pytest.mark.parametrize(
    ("mode", "ready", "sig", "code"),
    [
        ("table", "vehicle", signal.SIGTERM, 0),
        ("table", "vehicle", signal.SIGINT, 130),
        ("foxglove", "serving on", signal.SIGTERM, 0),
    ],
)
def test_sigterm_stops_the_monitor_cleanly_and_ctrl_c_interrupts_it(
    mode: str, ready: str, sig: signal.Signals, code: int
) -> None:
    """Running until stopped (no ``--duration``): SIGTERM, as a service manager or ``kill``
    sends it, ends the table and the Foxglove relay with exit 0 (reference section 1);
    Ctrl-C is an interruption, 130."""
    argv = [sys.executable, "-m", "truckd.cli.main", "monitor", "--connect",
            endpoint(free_port()), "--interval", "0.25"]  # fmt: skip
    if mode == "foxglove":
        argv += ["--foxglove", "0"]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    try:
        assert proc.stdout is not None
        stdout = proc.stdout
        reader = threading.Thread(target=lambda: lines.extend(stdout), daemon=True)
        reader.start()
        assert _wait_output(lines, lambda ln: ready in ln, 60.0), "".join(lines)
        os.kill(proc.pid, sig)
        assert proc.wait(timeout=20) == code, proc.stderr.read()  # type: ignore[union-attr]
        reader.join(timeout=5)
    finally:
        end_process(proc)

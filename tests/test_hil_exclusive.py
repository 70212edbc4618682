"""One daemon per device: a second `truckd run` on the serial device that a
first one drives fails to start, names the device and the first one's pid, and sends
nothing: the firmware sees no counter gap, no bad frame, no motor-off, and the first
daemon keeps driving."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from hil_support import ROOT, Daemon, Firmware, StallProbe, Watch, hil_config, new_port

pytestmark = [pytest.mark.hil, pytest.mark.slow]

ERRORS = ("rx_counter_errors", "rx_counter_gaps", "rx_checksum_errors", "rx_length_errors",
          "rx_payload_errors", "framing_crc_errors", "framing_cobs_errors",
          "framing_length_errors", "framing_resyncs", "framing_bytes_discarded")  # fmt: skip


HOST_STALL_S = 0.05
"""A stall this long (half the firmware's 100 ms command timeout) of the host (the probe's
normal-priority process) or of the rig itself (the simulated firmware, also a normal
process, reports the passes of its loop that began late) excuses command timeouts at the
firmware: the daemon's commands were sent, the rig did not take them in time."""


def errors(st: dict[str, Any]) -> dict[str, int]:
    rx = st["rx"]
    return {k: int(rx[k]) for k in ERRORS}


def second_daemon(cfg: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "truckd.cli.main", "run", "--config", str(cfg), "--duration", "5"],
        capture_output=True, text=True, timeout=120, cwd=ROOT,
    )  # fmt: skip


def test_second_daemon_on_one_device_fails_and_sends_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("TRUCKD_LOCK_DIR", str(tmp_path / "locks"))  # inherited by children
    pty = str(tmp_path / "ttyTRUCK")
    port = new_port()
    cfg_a = hil_config(tmp_path, pty, port)
    with contextlib.ExitStack() as stack:
        fw = Firmware(pty, cfg_a, "--no-lead")
        stack.callback(fw.stop)
        a = Daemon(cfg_a, tmp_path / "a.log")
        stack.callback(a.stop)
        watch = Watch(port)
        stack.callback(watch.close)
        up = watch.wait_state(lambda m: m["mode"] in ("SAFE_STOP", "ACTIVE"), 60.0)
        assert up is not None, a.stderr()[-2000:]
        fw.cmd({"cmd": "lead", "gap": 1.5, "speed": 0.8})
        active = watch.wait_state(lambda m: m["mode"] == "ACTIVE" and m["enable"], 20.0)
        assert active is not None, a.stderr()[-2000:]
        # The firmware is a normal process here: starved past its 100 ms command timeout
        # by a busy host, it counts timeouts however fast the daemon sends.  A probe
        # measures the host's own stalls, independently of the code under test.
        probe = StallProbe()
        stack.callback(probe.stop)
        t_before = time.monotonic()
        before = fw.status()
        assert before["last_command"]["enable"], before

        # B1: one configuration twice, same Zenoh port too; B2: its own port (only the device
        # is shared).  Both must fail at the device lock, before Zenoh or the link.
        (tmp_path / "b2").mkdir()
        cfg_b2 = hil_config(tmp_path / "b2", pty, new_port())
        for cfg in (cfg_a, cfg_b2):
            r = second_daemon(cfg)
            assert r.returncode == 1, r.stderr
            err = [ln for ln in r.stderr.splitlines() if "error" in ln or "failed" in ln]
            assert len(err) == 1, r.stderr
            assert pty in err[0] and f"process {a.proc.pid}" in err[0], r.stderr
            assert "Traceback" not in r.stderr

        # the firmware kept receiving the first daemon's stream, untouched
        t_after = time.monotonic()
        after = fw.status()
        health = watch.last_health()
        assert errors(after) == errors(before), (errors(before), errors(after), health["link"])
        timeouts = after["firmware"]["cmd_timeouts"] - before["firmware"]["cmd_timeouts"]
        # the host's stalls (the probe) and the rig's own: the firmware process's late
        # wake-ups and slow steps, e.g. its read of the pty waiting for the kernel's
        # normal-priority tty worker (docs/daemon.md, Non-blocking read)
        stalls = [*probe.stalls, *(tuple(x) for x in after["rig_stalls"])]
        stall = max((b - a for a, b in stalls if b >= t_before and a <= t_after), default=0)
        assert timeouts == 0 or stall >= HOST_STALL_S, (
            f"{timeouts} command timeouts at the firmware and no stall of the host or the "
            f"rig of {HOST_STALL_S * 1e3:.0f} ms or more (longest {stall * 1e3:.0f} ms): the first "
            f"daemon stopped sending (its loop: {health.get('loop')}; firmware before "
            f"{before['firmware']}, after {after['firmware']})"
        )
        assert after["last_command"]["enable"], after
        assert after["firmware"]["commands_applied"] > before["firmware"]["commands_applied"]
        # and the first daemon is still driving
        still = watch.wait_state(lambda m: m["mode"] == "ACTIVE", 10.0, t_after)
        assert still is not None and a.alive(), a.stderr()[-2000:]
        assert a.stop() == 0
    assert not (tmp_path / "b2" / "logs").exists() or not any((tmp_path / "b2" / "logs").iterdir())
    assert not list((tmp_path / "locks").iterdir())  # released on exit


def test_device_is_exclusive_even_without_the_lock_file(tmp_path: Path) -> None:
    """Processes that see different lock directories are kept apart by the tty itself
    (flock on the device node; TIOCEXCL as well for non-root)."""
    from truckd.io.serial_link import SerialLink
    from truckd.sim.pty_link import PtyDevice

    path = str(tmp_path / "ttyX")
    dev = PtyDevice(path)
    first = SerialLink(path, reconnect_interval=0.01)
    try:
        assert first.connected
        code = (
            "import sys; from truckd.io.serial_link import SerialLink; "
            f"l = SerialLink({path!r}); print(l.connected, l.busy); l.close()"
        )
        r = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT,
            env={**os.environ, "TRUCKD_LOCK_DIR": str(tmp_path / "elsewhere")},
        )  # fmt: skip
        assert r.stdout.split() == ["False", "True"], r.stderr
        assert first.connected
    finally:
        first.close()
        dev.close()

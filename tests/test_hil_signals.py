"""HIL: the daemon stopped by a signal mid-run (separate processes: the simulated firmware
on a pty, `truckd run` on the serial backend), one signal per test.

SIGHUP (a hung-up terminal), SIGTERM and SIGINT: exit 0, the firmware's last command is
motor off (0 V, driver disabled), the CSV has no torn row and the MCAP is finished (it
opens in mcap's indexed reader).  SIGKILL: the firmware stops the motor on its own
(FAILSAFE), the CSV has no torn row, and the MCAP opens in the indexed reader once the
next daemon start has recovered it (a line says so).  A SIGHUP ignored at start (nohup)
stays ignored."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from hil_support import PY, ROOT, Firmware, Watch, hil_config, new_port
from mcap.reader import make_reader

from truckd.config.truck import load_config

pytestmark = [pytest.mark.hil, pytest.mark.slow]

LEAD_SPEED = 0.8


def start_daemon(
    cfg: Path, log: Path, hup: Any = signal.SIG_DFL, *args: str
) -> subprocess.Popen[bytes]:
    """`truckd run` with SIGHUP's disposition set to ``hup`` (the test runner's own may
    be anything, e.g. ignored under nohup)."""
    with open(log, "ab") as err:
        return subprocess.Popen(
            [PY, "-m", "truckd.cli.main", "run", "--config", str(cfg), *args],
            stdout=subprocess.DEVNULL, stderr=err, cwd=ROOT,
            preexec_fn=lambda: signal.signal(signal.SIGHUP, hup),
        )  # fmt: skip


def end(p: subprocess.Popen[bytes]) -> None:
    if p.poll() is None:
        os.kill(p.pid, signal.SIGKILL)
        p.wait(10)


@contextlib.contextmanager
def driving(
    tmp: Path, hup: Any = signal.SIG_DFL
) -> Iterator[tuple[Firmware, subprocess.Popen[bytes], Path]]:
    """Firmware, daemon and a lead; yields once the truck drives (ACTIVE, moving)."""
    pty = str(tmp / "ttyTRUCK")
    port = new_port()
    cfg_path = hil_config(tmp, pty, port)
    cfg = load_config(cfg_path)
    with contextlib.ExitStack() as stack:
        fw = Firmware(pty, cfg_path, "--no-lead")
        stack.callback(fw.stop)
        daemon = start_daemon(cfg_path, tmp / "daemon.log", hup)
        stack.callback(end, daemon)
        watch = Watch(port)
        stack.callback(watch.close)
        assert watch.wait_state(lambda m: True, 60.0) is not None, (tmp / "daemon.log").read_text()
        c = cfg.control
        fw.cmd({"cmd": "lead", "gap": c.d_0 + c.time_headway * LEAD_SPEED + 0.1,
                "speed": LEAD_SPEED})  # fmt: skip
        s = watch.wait_state(
            lambda m: m["mode"] == "ACTIVE" and (m["v"] or 0.0) > 0.5, 30.0, time.monotonic()
        )
        assert s is not None, watch.last_health()
        st = fw.status()
        assert st["state"] == "ACTIVE" and st["voltage"] > 0.1, st
        yield fw, daemon, cfg_path


def wait_fw(fw: Firmware, seconds: float) -> dict[str, Any]:
    """The firmware's status once ``seconds`` of its clock have passed."""
    t0 = fw.status()["t"]
    st = fw.status()
    while st["t"] - t0 < seconds:
        time.sleep(0.01)
        st = fw.status()
    return st


def check_csv(logs: Path) -> int:
    """Every CSV row has the header's fields and ends with a newline; returns the rows."""
    rows = 0
    files = sorted(logs.glob("*.csv"))
    assert files
    for f in files:
        text = f.read_text()
        assert text.endswith("\n"), f"{f}: torn last row {text[-80:]!r}"
        lines = text.splitlines()
        n = lines[0].count(",")
        torn = [i for i, line in enumerate(lines) if line.count(",") != n]
        assert not torn, f"{f}: torn rows at lines {torn[:5]}"
        rows += len(lines) - 1
    return rows


def mcap_indexed(logs: Path) -> int:
    """Messages of every MCAP in ``logs``, read through mcap's indexed reader (summary
    and chunk index; an unfinished file raises)."""
    total = 0
    files = sorted(logs.glob("*.mcap"))
    assert files
    for f in files:
        with open(f, "rb") as fh:
            r = make_reader(fh)
            summary = r.get_summary()
            assert summary is not None and summary.chunk_indexes, f
            n = sum(1 for _ in r.iter_messages())
            assert n == summary.statistics.message_count > 0  # type: ignore[union-attr]
            total += n
    return total


@pytest.mark.parametrize("sig", [signal.SIGHUP, signal.SIGTERM, signal.SIGINT])
def test_a_stop_signal_sends_motor_off_and_closes_the_logs(tmp_path: Path, sig: int) -> None:
    with driving(tmp_path) as (fw, daemon, _cfg):
        os.kill(daemon.pid, sig)
        assert daemon.wait(20) == 0, (tmp_path / "daemon.log").read_text()[-2000:]
        off = wait_fw(fw, 0.3)
        assert off["last_command"] == {"voltage": 0.0, "enable": False}, off
        assert off["voltage"] == 0.0, off
    logs = tmp_path / "logs"
    assert check_csv(logs) > 10
    assert mcap_indexed(logs) > 10
    assert "log flushed" in (tmp_path / "daemon.log").read_text()


def test_sigkill_the_firmware_stops_and_the_next_start_recovers_the_mcap(
    tmp_path: Path,
) -> None:
    with driving(tmp_path) as (fw, daemon, cfg_path):
        time.sleep(1.5)  # more than one MCAP flush period of driving
        os.kill(daemon.pid, signal.SIGKILL)
        daemon.wait(10)
        st = wait_fw(fw, 0.3)
        assert st["state"] == "FAILSAFE" and st["voltage"] == 0.0, st
    logs = tmp_path / "logs"
    rows = check_csv(logs)
    assert rows > 100
    (killed,) = logs.glob("*.mcap")
    with open(killed, "rb") as fh, pytest.raises(Exception):  # noqa: B017 - any refusal
        make_reader(fh).get_summary()
    # the next start (any backend) recovers it, and says so
    log2 = tmp_path / "daemon2.log"
    nxt = start_daemon(cfg_path, log2, signal.SIG_DFL, "--backend", "sim", "--duration", "0.5")
    try:
        assert nxt.wait(60) == 0, log2.read_text()[-2000:]
    finally:
        end(nxt)
    text = log2.read_text()
    assert f"{killed}: recovered" in text, text[-2000:]
    with open(killed, "rb") as fh:
        r = make_reader(fh)
        n = sum(1 for m in r.iter_messages())
    # at 100 Hz states plus health and plans: most of the run up to the last second
    assert n > 50, n
    assert mcap_indexed(logs) > n


def test_an_ignored_sighup_stays_ignored(tmp_path: Path) -> None:
    """nohup: SIGHUP ignored at start is not taken over by the daemon."""
    with driving(tmp_path, signal.SIG_IGN) as (fw, daemon, _cfg):
        os.kill(daemon.pid, signal.SIGHUP)
        st = wait_fw(fw, 0.5)
        assert daemon.poll() is None
        assert st["state"] == "ACTIVE" and st["voltage"] > 0.0, st
        os.kill(daemon.pid, signal.SIGTERM)
        assert daemon.wait(20) == 0

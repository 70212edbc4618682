"""Real-time set-up in a child process: the report matches what the OS reports."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys

import pytest

from truckd.runtime import realtime

CHILD = """
import gc, json, logging, os, sys
logging.basicConfig(level=logging.INFO, stream=sys.stderr)
from truckd.runtime.realtime import setup_realtime
rep = setup_realtime(sys.argv[1] == "on", 10)
out = rep.as_dict()
out["policy_is_fifo"] = os.sched_getscheduler(0) == os.SCHED_FIFO
out["freeze_count"] = gc.get_freeze_count()
print(json.dumps(out))
"""


def run_child(mode: str, user: int | None = None) -> tuple[dict[str, object], str]:
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, mode],
        capture_output=True,
        text=True,
        timeout=60,
        user=user,
        cwd="/",
        env={**os.environ, "PYTHONPATH": os.getcwd()},
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout), proc.stderr


def test_report_matches_os_state() -> None:
    rep, err = run_child("on")
    assert isinstance(rep["gc_frozen"], int) and rep["gc_frozen"] > 1000
    assert isinstance(rep["freeze_count"], int) and rep["freeze_count"] > 1000
    assert rep["sched_fifo"] == rep["policy_is_fifo"]
    if not rep["sched_fifo"]:
        assert "SCHED_FIFO 10 not permitted" in err
    if not rep["mlock"]:
        assert "mlockall" in err
    assert "gc frozen after start-up" in err


def test_disabled_leaves_normal_scheduling() -> None:
    rep, err = run_child("off")
    assert rep["sched_fifo"] is False and rep["policy_is_fifo"] is False and rep["mlock"] is False
    assert "real-time scheduling disabled" in err


def test_not_permitted_paths_log_clear_lines(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def deny(*_a: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(realtime.os, "sched_setscheduler", deny)
    monkeypatch.setattr(realtime.os, "geteuid", lambda: 1000)
    monkeypatch.setattr(realtime.resource, "getrlimit", lambda _r: (65536, 65536))
    rep = realtime.RealtimeReport()
    with caplog.at_level(logging.INFO, logger="truckd.realtime"):
        realtime._sched_fifo(20, rep)
        realtime._mlockall(rep)
    assert rep.sched_fifo is False and rep.mlock is False
    text = caplog.text
    assert "SCHED_FIFO 20 not permitted (Operation not permitted)" in text
    assert "mlockall skipped: RLIMIT_MEMLOCK is 65536 B" in text

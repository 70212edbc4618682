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


LATENCY_CHILD = """
import json, os, struct, sys
from truckd.runtime.realtime import RealtimeReport, hold_cpu_latency, release_cpu_latency
def current():
    fd = os.open(sys.argv[1], os.O_RDONLY)
    try:
        return struct.unpack("=i", os.read(fd, 4))[0]
    finally:
        os.close(fd)
before = current()
rep = RealtimeReport()
hold_cpu_latency(int(sys.argv[2]), rep)
held = current()
release_cpu_latency()
print(json.dumps({"before": before, "held": held, "after": current(), "rep": rep.cpu_latency_us}))
"""


@pytest.mark.skipif(
    not os.access(realtime.CPU_LATENCY_DEV, os.R_OK | os.W_OK),
    reason="needs read and write access to /dev/cpu_dma_latency (root)",
)
def test_cpu_latency_request_is_held_while_open_and_dropped_on_release() -> None:
    """The kernel's aggregate PM QoS target (read back from the device) is the value
    requested while it is held, and what it was before once released."""
    proc = subprocess.run(
        [sys.executable, "-c", LATENCY_CHILD, realtime.CPU_LATENCY_DEV, "7"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd="/",
        env={**os.environ, "PYTHONPATH": os.getcwd()},
    )
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["rep"] == 7
    assert out["held"] == min(7, out["before"])
    assert out["after"] == out["before"]


def test_cpu_latency_not_permitted_logs_and_runs_on(
    tmp_path: os.PathLike[str], caplog: pytest.LogCaptureFixture
) -> None:
    """A device that cannot be opened leaves the report empty and says why, once."""
    rep = realtime.RealtimeReport()
    missing = os.path.join(tmp_path, "no_such_device")
    with caplog.at_level(logging.INFO, logger="truckd.realtime"):
        realtime.hold_cpu_latency(0, rep, device=missing)
    assert rep.cpu_latency_us is None
    assert rep.as_dict()["cpu_latency_us"] is None
    assert "CPU wake-up latency 0 us not requested" in caplog.text
    assert "No such file or directory" in caplog.text


def test_helpers_and_zenoh_callback_threads_are_promoted_others_not() -> None:
    """Every thread that takes the GIL for the daemon (its own ``truckd-*`` writers and
    zenoh-python's callback threads) is raised to SCHED_FIFO; an unrelated thread is not."""
    import threading

    stop = threading.Event()
    threads = [
        threading.Thread(target=stop.wait, name=name, daemon=True)
        for name in ("truckd-test", "Thread-9 (pyo3-closure)", "unrelated")
    ]
    for th in threads:
        th.start()
    rep = realtime.RealtimeReport()
    try:
        realtime.promote_helpers(5, rep)
        policy = {th.name: os.sched_getscheduler(th.native_id or 0) for th in threads}
    finally:
        stop.set()
        for th in threads:
            th.join(5.0)
    assert policy["unrelated"] == os.SCHED_OTHER
    for name in ("truckd-test", "Thread-9 (pyo3-closure)"):
        promoted = policy[name] == os.SCHED_FIFO
        assert promoted or any(f"SCHED_FIFO for {name} failed" in n for n in rep.notes), rep.notes


DYNAMIC_NONE = "CONFIG_PREEMPT_BUILD=y\nCONFIG_PREEMPT_NONE=y\n# CONFIG_PREEMPT is not set\n"


@pytest.mark.parametrize(
    "texts,mode",
    [
        # a PREEMPT_RT kernel, by its flag file or by uname
        ({"uname_version": "#1 SMP PREEMPT_DYNAMIC", "realtime_flag": "1\n"}, "rt"),
        ({"uname_version": "#1 SMP PREEMPT_RT Thu Nov 20"}, "rt"),
        # a dynamic kernel: debugfs's choice first, then preempt=, then the build default
        ({"uname_version": "#1 SMP PREEMPT_DYNAMIC", "debugfs": "none voluntary (full) lazy\n",
          "cmdline": "preempt=none", "config": DYNAMIC_NONE}, "full"),
        ({"uname_version": "#1 SMP PREEMPT_DYNAMIC", "cmdline": "quiet preempt=voluntary",
          "config": DYNAMIC_NONE}, "voluntary"),
        ({"uname_version": "#1 SMP PREEMPT_DYNAMIC @0", "config": DYNAMIC_NONE}, "none"),
        ({"uname_version": "#1 SMP PREEMPT_DYNAMIC"}, "unknown"),
        # preempt= means nothing to a kernel built without dynamic preemption
        ({"uname_version": "#1 SMP Debian", "cmdline": "preempt=full",
          "config": "CONFIG_PREEMPT_VOLUNTARY=y\n"}, "voluntary"),
        # a Raspberry Pi OS kernel says PREEMPT; an old server kernel says nothing
        ({"uname_version": "#1 SMP PREEMPT Debian 1:6.6.51-1+rpt3"}, "full"),
        ({"uname_version": "#1 SMP Debian 5.10.0-28"}, "unknown"),
    ],
)  # fmt: skip
def test_the_kernels_preemption_model_is_read_from_what_the_kernel_says(
    texts: dict[str, str], mode: str
) -> None:
    got, how = realtime.preemption_model(**texts)
    assert got == mode, how


def test_a_kernel_that_does_not_preempt_is_a_warning_naming_the_remedy(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """The start-up's line says the model, and where the loop can wait, as a warning; a
    preemptible kernel is an info line."""
    monkeypatch.setattr(realtime, "preemption_model", lambda *_a: ("none", "build default"))
    rep = realtime.RealtimeReport()
    with caplog.at_level(logging.INFO, logger="truckd.realtime"):
        realtime._kernel_preemption(rep)
    assert rep.kernel_preemption == "none" and rep.as_dict()["kernel_preemption"] == "none"
    (record,) = caplog.records
    assert record.levelno == logging.WARNING
    assert "PREEMPT_RT" in record.getMessage() and "preempt=full" in record.getMessage()
    monkeypatch.setattr(realtime, "preemption_model", lambda *_a: ("rt", "flag"))
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="truckd.realtime"):
        realtime._kernel_preemption(rep)
    assert rep.kernel_preemption == "rt"
    assert [r.levelno for r in caplog.records] == [logging.INFO]

"""The diagnosis's independent fits on forked workers: the same diagnosis, and a map
that survives what its children do.

:class:`truckd.workers.ForkMap` runs a list of tasks on forked children and falls back
to this process when it cannot fork safely or a child dies; the diagnosis hands it the
fits of a stage that do not depend on each other (:mod:`truckd.ident.fanout`).  What needs
a process that may fork runs in a fresh interpreter (``tests/fork_checks.py``).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest
from runtime_support import group_members, wait_for

from truckd.cli.main import main
from truckd.ident.fanout import as_start
from truckd.workers import ForkMap, can_fork

FORK_CHECKS = Path(__file__).resolve().parent / "fork_checks.py"


def _fresh(check: str) -> dict[str, Any]:
    """What ``tests/fork_checks.py CHECK`` saw, in an interpreter of its own (this pytest
    worker may run other threads, and then nothing forks)."""
    r = subprocess.run(
        [sys.executable, str(FORK_CHECKS), check], capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 0, r.stderr[-2000:]
    out: dict[str, Any] = json.loads(r.stdout)
    return out


def test_tasks_run_in_children_and_come_back_in_order() -> None:
    r = _fresh("order")
    assert r["can_fork"], "the check's own process runs other threads"
    assert r["squares"] == [x * x for x in range(12)]
    assert set(r["pids"]) - {r["parent"]}, "every task ran in the parent"
    assert r["fallbacks"] == 0


def test_an_exception_in_a_child_is_raised_here() -> None:
    assert _fresh("raised")["raised"] == "ValueError: task 5 refused"


def test_a_child_killed_halfway_through_a_result_falls_back_to_this_process() -> None:
    """A torn result costs only that child's pipe: the call does not wait on it and
    runs the list here (each result then carries this process's pid)."""
    r = _fresh("torn")
    assert [sq for _, sq in r["out"]] == [x * x for x in range(6)] and r["fallbacks"] == 1
    assert len({pid for pid, _ in r["out"]}) == 1


def test_a_result_that_cannot_come_back_is_an_error_naming_it() -> None:
    raised = _fresh("unpicklable")["raised"]
    assert raised is not None and raised.startswith("RuntimeError: a task's outcome"), raised


def test_a_child_killed_falls_back_to_this_process() -> None:
    r = _fresh("killed")
    assert r["out"] == [10 * x for x in range(6)] and r["fallbacks"] == 1


def test_a_result_equal_to_its_start_comes_back_as_the_start_object() -> None:
    start = {"kS": 0.1, "kV": 2.0}
    copy = dict(start)  # what a worker hands back for a fit that kept its start
    better = {"kS": 0.1, "kV": 2.1}
    assert as_start(copy, start) is start
    assert as_start(start, start) is start
    assert as_start(better, start) is better


def _pid_and_square(x: int) -> tuple[int, int]:
    return os.getpid(), x * x


def test_ctrl_c_while_the_children_start_is_a_keyboard_interrupt_and_ends_them() -> None:
    """Ctrl-C to the group right after the children are forked, before any task is
    handed out: the call raises KeyboardInterrupt and no child is left."""
    got = _fresh("interrupted_at_start")
    assert len(got["forked"]) == 2, got
    assert got["raised"] is not None and got["raised"].startswith("KeyboardInterrupt"), got
    assert got["alive"] == [], got


def test_ctrl_c_while_the_children_run_kills_them_at_once() -> None:
    """Ctrl-C to the whole group while both children run a task that would take an
    hour: the call raises KeyboardInterrupt without waiting for the tasks (the check
    would hang until its timeout) and leaves no process of its group."""
    got = _fresh("interrupted_while_running")
    assert got["raised"] is not None and got["raised"].startswith("KeyboardInterrupt"), got
    assert got["left"] == [], got


def test_ctrl_c_right_after_a_task_is_sent_kills_that_child_too() -> None:
    """The Ctrl-C lands just after the second child's task is written, before the call
    notes it running: that child is killed with the other (it would hold the reaping
    for the hour its task takes) and no process of the group is left."""
    got = _fresh("interrupted_right_after_a_send")
    assert got["raised"] is not None and got["raised"].startswith("KeyboardInterrupt"), got
    assert got["left"] == [], got


def test_with_another_thread_running_nothing_forks() -> None:
    stop = threading.Event()
    other = threading.Thread(target=stop.wait)
    other.start()
    try:
        assert not can_fork()
        out = ForkMap(2)(_pid_and_square, range(4))
    finally:
        stop.set()
        other.join()
    assert {pid for pid, _ in out} == {os.getpid()}


def test_workers_below_one_are_refused() -> None:
    with pytest.raises(ValueError, match="at least 1"):
        ForkMap(0)


def test_diagnosis_on_workers_is_the_diagnosis_in_order() -> None:
    """Two causes hidden in a log of the default truck (the pair stage runs): the
    diagnosis with the candidates and pairs fitted on two forked workers is the plain
    loop's, to the last digit, and the progress reads the same."""
    r = _fresh("diagnosis")
    assert r["calls"] >= 2, "the candidate and pair stages did not use the workers"
    assert set(r["pids"]) - {r["parent"]}, "no fit ran on a worker"
    assert r["forked"] == r["plain"]
    assert r["said_forked"] == r["said_plain"]


def test_drawn_trucks_diagnosed_on_workers_get_the_same_controllers() -> None:
    """``truckd sim --mixed`` drives and diagnoses the drawn trucks on forked workers: the
    same controllers, summaries and progress as one after another; a repeated truck is
    diagnosed once; the trucks ran in other processes."""
    r = _fresh("mixed")
    assert r["models_2"] == r["models_1"] and r["summaries_2"] == r["summaries_1"]
    assert r["said_2"] == r["said_1"]
    assert [line.split(": model ")[1] for line in r["said_1"]] == [
        "diagnosed", "diagnosed", "diagnosed", "reused",
    ]  # fmt: skip
    assert len(r["ran_in"]) == 6  # three trucks, each way
    assert set(r["ran_in"][3:]) - {r["parent"]}, "no truck was diagnosed on a worker"


@pytest.mark.parametrize("value", ["0", "65", "two", "1.5"])
def test_jobs_outside_its_range_is_exit_2(value: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["diagnose", "any.csv", "--jobs", value]) == 2
    err = capsys.readouterr().err
    assert "--jobs" in err and value in err


SWERVE = Path(__file__).resolve().parent / "data" / "sysid" / "frc_swerve_12_12.json"


@pytest.mark.parametrize("sig,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_during_the_fits_ends_the_command_and_its_workers(
    sig: signal.Signals, code: int
) -> None:
    """``truckd diagnose --jobs 2`` stopped by Ctrl-C (the whole group) or SIGTERM (the
    command alone) while its workers fit: it ends by the signal (exit code 128 + the
    signal) within the minute and leaves no process of its group behind."""
    with subprocess.Popen(
        [sys.executable, "-m", "truckd", "diagnose", str(SWERVE), "--jobs", "2"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    ) as proc:  # fmt: skip
        try:
            # its workers are fitting: more than the command in its group (the progress
            # lines of a stage come only once its workers are done, too late to signal)
            def fitting() -> bool:
                return len(group_members(proc.pid)) > 1 or proc.poll() is not None

            if not wait_for(fitting, 60):
                pytest.fail("no worker started within 60 s")
            assert proc.poll() is None, "the diagnosis ended before a worker was seen"
            if sig == signal.SIGINT:
                os.killpg(proc.pid, sig)
            else:
                proc.send_signal(sig)
            # 128 + the signal from the command's handler; a signal that lands as the
            # interpreter exits ends it by the default action (a negative code)
            assert proc.wait(timeout=60) in (code, -sig)
            assert group_members(proc.pid) == [], "processes of the command's group left behind"
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()

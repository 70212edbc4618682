"""The diagnosis's independent fits on forked workers: the same diagnosis, and a map
that survives what its children do.

:class:`truckd.workers.ForkMap` runs a list of tasks on forked children and falls back
to this process when it cannot fork safely or a child dies; the diagnosis hands it the
fits of a stage that do not depend on each other (:mod:`truckd.ident.fanout`).
"""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import pytest
from labkit.synth import plant_log, random_effects

from truckd.cli.main import main
from truckd.ident.api import one_blas_thread
from truckd.ident.data import runs_from_logs
from truckd.ident.diagnose import diagnose_voltage
from truckd.ident.fanout import in_order
from truckd.model.effects import COMPANIONS, Effects
from truckd.model.params import VehicleParams
from truckd.workers import ForkMap, can_fork

T = TypeVar("T")
R = TypeVar("R")

PARENT = os.getpid()


def _pid_and_square(x: int) -> tuple[int, int]:
    return os.getpid(), x * x


def test_tasks_run_in_children_and_come_back_in_order() -> None:
    assert can_fork(), "the test process runs other threads: nothing would fork"
    pool = ForkMap(2)
    out = pool([*range(12)].__getitem__, range(12))
    assert out == list(range(12))
    pids_squares = pool(_pid_and_square, range(12))
    assert [sq for _, sq in pids_squares] == [x * x for x in range(12)]
    assert {pid for pid, _ in pids_squares} - {os.getpid()}, "every task ran in this process"
    assert pool.fallbacks == 0


def _raise_on_five(x: int) -> int:
    if x == 5:
        raise ValueError(f"task {x} refused")
    return x


def test_an_exception_in_a_child_is_raised_here() -> None:
    with pytest.raises(ValueError, match="task 5 refused"):
        ForkMap(2)(_raise_on_five, range(8))


def _die_in_a_child(x: int) -> int:
    if os.getpid() != PARENT and x == 3:
        os.kill(os.getpid(), signal.SIGKILL)
    return 10 * x


def test_a_child_killed_falls_back_to_this_process() -> None:
    pool = ForkMap(2)
    assert pool(_die_in_a_child, range(6)) == [10 * x for x in range(6)]
    assert pool.fallbacks == 1


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


class _Recording:
    """ForkMap(2), counting its calls and the processes the tasks ran in."""

    def __init__(self) -> None:
        self.inner = ForkMap(2)
        self.calls = 0
        self.pids: set[int] = set()

    def __call__(self, fn: Callable[[T], R], items: Sequence[T], /) -> list[R]:
        def tagged(x: T) -> tuple[int, R]:
            return os.getpid(), fn(x)

        out = self.inner(tagged, items)
        self.calls += 1
        self.pids |= {pid for pid, _ in out}
        return [r for _, r in out]


def _json(d: Any) -> Any:
    return d.to_json()


def test_diagnosis_on_workers_is_the_diagnosis_in_order(params: VehicleParams) -> None:
    """Two causes hidden in a log of the default truck (the pair stage runs): the
    diagnosis with the candidates and pairs fitted on two forked workers is the plain
    loop's, to the last digit, and the progress reads the same."""
    rng = np.random.default_rng(20261127)
    fields: dict[str, float] = {}
    for n in ("current_limit", "sensor_lag"):
        e = random_effects(n, rng)
        fields[n] = float(getattr(e, n))
        fields.update({c: float(getattr(e, c)) for c in COMPANIONS.get(n, ())})
    log = plant_log(params, dataclasses.replace(Effects(), **fields), seed=7, n=5000)
    runs = runs_from_logs([log], None)
    said_plain: list[str] = []
    said_forked: list[str] = []
    recording = _Recording()
    with one_blas_thread():
        plain = diagnose_voltage(params, runs, None, said_plain.append, in_order)
        forked = diagnose_voltage(params, runs, None, said_forked.append, recording)
    assert recording.calls >= 2, "the candidate and pair stages did not use the workers"
    assert recording.pids - {os.getpid()}, "no fit ran on a worker"
    assert _json(forked) == _json(plain)
    assert said_forked == said_plain


@pytest.mark.parametrize("value", ["0", "65", "two", "1.5"])
def test_jobs_outside_its_range_is_exit_2(value: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["diagnose", "any.csv", "--jobs", value]) == 2
    err = capsys.readouterr().err
    assert "--jobs" in err and value in err


SWERVE = Path(__file__).resolve().parent / "data" / "sysid" / "frc_swerve_12_12.json"


def _group(pgid: int) -> list[int]:
    """The live processes (not zombies) of process group ``pgid`` (Linux /proc)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # ended meanwhile
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            out.append(int(stat.parent.name))
    return out


@pytest.mark.parametrize("sig,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_during_the_fits_ends_the_command_and_its_workers(
    sig: signal.Signals, code: int
) -> None:
    """``truckd diagnose --jobs 2`` stopped by Ctrl-C (the whole group) or SIGTERM (the
    command alone) while its workers fit the candidates: it exits with 128 + the signal
    and leaves no process of its group behind."""
    with subprocess.Popen(
        [sys.executable, "-m", "truckd", "diagnose", str(SWERVE), "--jobs", "2"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    ) as proc:  # fmt: skip
        try:
            assert proc.stderr is not None
            for line in proc.stderr:  # the candidates' stage: its workers are running
                if line.startswith("candidate 1/"):
                    break
            else:
                pytest.fail("the diagnosis ended before its candidates were fitted")
            if sig == signal.SIGINT:
                os.killpg(proc.pid, sig)
            else:
                proc.send_signal(sig)
            assert proc.wait(timeout=60) == code
            assert _group(proc.pid) == [], "processes of the command's group left behind"
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()

"""Checks of :class:`truckd.workers.ForkMap` that need a process of their own.

A pytest worker may run other Python threads left by earlier tests (a Zenoh session's,
a daemon's), and then ForkMap rightly refuses to fork. ``tests/test_diagnose_workers.py``
runs each check here in a fresh interpreter: ``python tests/fork_checks.py NAME`` prints
what the check saw as one JSON object; the test asserts on it.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import sys
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import numpy as np
from labkit.synth import plant_log, random_effects
from runtime_support import group_members

from truckd.config.truck import load_config
from truckd.ident.api import one_blas_thread
from truckd.ident.data import runs_from_logs
from truckd.ident.diagnose import diagnose_voltage
from truckd.ident.fanout import in_order
from truckd.model.effects import COMPANIONS, Effects
from truckd.workers import ForkMap, can_fork

T = TypeVar("T")
R = TypeVar("R")

PARENT = os.getpid()


def _pid_and_square(x: int) -> tuple[int, int]:
    return os.getpid(), x * x


def _raise_on_five(x: int) -> int:
    if x == 5:
        raise ValueError(f"task {x} refused")
    return x


def _die_in_a_child(x: int) -> int:
    if os.getpid() != PARENT and x == 3:
        os.kill(os.getpid(), signal.SIGKILL)
    return 10 * x


def order() -> dict[str, Any]:
    """Twelve tasks on two workers: the pid each ran in and its result."""
    pool = ForkMap(2)
    out = pool(_pid_and_square, range(12))
    return {"parent": PARENT, "can_fork": can_fork(), "pids": [p for p, _ in out],
            "squares": [sq for _, sq in out], "fallbacks": pool.fallbacks}  # fmt: skip


def raised() -> dict[str, Any]:
    """A task that raises in a child: what this process sees."""
    try:
        ForkMap(2)(_raise_on_five, range(8))
    except ValueError as exc:
        return {"raised": f"ValueError: {exc}"}
    return {"raised": None}


def torn() -> dict[str, Any]:
    """A child killed halfway through writing a result (the first result a child sends
    is cut after half its bytes): the results and the fallbacks counted."""
    import truckd.workers as workers

    write_all = workers._write_all

    def half_then_die(fd: int, data: bytes) -> None:
        if os.getpid() != PARENT and len(data) > 8:
            os.write(fd, data[: len(data) // 2])
            os.kill(os.getpid(), signal.SIGKILL)
        write_all(fd, data)

    workers._write_all = half_then_die
    pool = ForkMap(2)
    return {"out": pool(_pid_and_square, range(6)), "fallbacks": pool.fallbacks}


def _unpicklable(x: int) -> Any:
    return (lambda: x) if x == 2 else x


def unpicklable() -> dict[str, Any]:
    """A task whose result cannot be pickled back: what this process raises."""
    try:
        ForkMap(2)(_unpicklable, range(5))
    except RuntimeError as exc:
        return {"raised": f"RuntimeError: {exc}"}
    return {"raised": None}


def killed() -> dict[str, Any]:
    """A child killed by SIGKILL: the results and the fallbacks counted."""
    pool = ForkMap(2)
    return {"out": pool(_die_in_a_child, range(6)), "fallbacks": pool.fallbacks}


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


def diagnosis() -> dict[str, Any]:
    """Two causes hidden in a log of the default truck, diagnosed with the plain loop
    and with the fits on two workers: both diagnoses, both progress lists, the workers'
    calls and pids."""
    params = load_config().vehicle
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
    return {
        "parent": PARENT, "calls": recording.calls, "pids": sorted(recording.pids),
        "plain": plain.to_json(), "forked": forked.to_json(),
        "said_plain": said_plain, "said_forked": said_forked,
    }  # fmt: skip


def mixed() -> dict[str, Any]:
    """``truckd sim --mixed``'s drawn trucks (the drive and diagnosis of each replaced by
    a model made from the truck, the pid it ran in noted): one after another and on two
    workers, with a repeated truck: the controllers, progress lines and pids of each."""
    from dataclasses import replace

    import truckd.cli.platoon_diagnosis as pd
    from truckd.control.qp import ControlModel
    from truckd.modelfile import ModelFile
    from truckd.sim.closed_loop import SimSetup

    ran_in: list[int] = []
    read, write = os.pipe()

    def identify(cfg: Any, truth: SimSetup) -> ModelFile:
        os.write(write, f"{os.getpid()}\n".encode())
        p = truth.plant_params
        return ModelFile(vehicle=p.replace(R_m=p.R_m * 0.9), effects=truth.plant_config.effects)

    pd.identify_truck = identify
    cfg = load_config()
    base = SimSetup(cfg.vehicle, cfg.plant, cfg.control, ControlModel(cfg.vehicle), 512)
    trucks = [replace(base, plant_params=base.plant_params.replace(m=m)) for m in (3.0, 4.0, 5.0)]
    trucks.append(trucks[0])
    got: dict[str, Any] = {"parent": PARENT}
    for workers in (1, 2):
        pd._MEMO.clear()
        said: list[str] = []
        out = pd.DiagnosedControllers(cfg, said.append, workers=workers)(base, trucks)
        got[f"models_{workers}"] = [repr(setup.model) for setup, _ in out]
        got[f"summaries_{workers}"] = [summary for _, summary in out]
        got[f"said_{workers}"] = [line.rsplit(" (", 1)[0] for line in said]  # not the time
    os.close(write)
    with os.fdopen(read) as f:
        ran_in = [int(x) for x in f.read().split()]
    got["ran_in"] = ran_in
    return got


def _slow_square(x: int) -> int:
    import time

    time.sleep(0.05)  # the tasks still running when the signal's exception is raised
    return x * x


def interrupted_at_start() -> dict[str, Any]:
    """Ctrl-C while the children start: SIGINT sent to this process and to each child (as
    a terminal's Ctrl-C reaches the whole group) right after they are forked, before any
    task is handed out. What this process raised, and which of its children are left."""
    import truckd.workers as workers

    # Python's own Ctrl-C handler, whatever this process inherited (a test runner's
    # workers may ignore SIGINT, and an ignored signal stays ignored across exec)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    fork = workers._fork
    forked: list[int] = []

    def fork_then_interrupt(n: int) -> list[Any]:
        children = fork(n)
        forked.extend(c.pid for c in children)
        for pid in [*forked, os.getpid()]:
            os.kill(pid, signal.SIGINT)
        return children

    workers._fork = fork_then_interrupt
    try:
        ForkMap(2)(_slow_square, range(8))
        raised = None
    except BaseException as exc:  # what was raised is the finding
        raised = f"{type(exc).__name__}: {exc}"
    alive = [pid for pid in forked if os.path.exists(f"/proc/{pid}")]
    for pid in alive:  # a child left waiting for work would outlive this process
        os.kill(pid, signal.SIGKILL)
    return {"raised": raised, "forked": forked, "alive": alive}


def _report_then_sleep(x: int) -> int:
    """A task that says its pid on the inherited pipe, then would run for an hour."""
    import time

    assert _PIDS_WRITE is not None
    os.write(_PIDS_WRITE, f"{os.getpid()}\n".encode())
    time.sleep(3600)
    return x


_PIDS_WRITE: int | None = None


def _end_the_group_and_fail(signum: int, frame: object) -> None:
    """SIGALRM's handler: kill every other process of this group, exit 3."""
    for pid in group_members(os.getpgid(0)):
        if pid != os.getpid():
            os.kill(pid, signal.SIGKILL)
    print(f"timed out: signal {signum}", file=sys.stderr)
    os._exit(3)


def interrupted_while_running(*, right_after_a_send: bool = False) -> dict[str, Any]:
    """Ctrl-C to the whole group (this process in a group of its own, as a terminal
    gives a command) while both children run a task that would take an hour: what this
    process raised, the seconds the call took, and the processes of the group left.

    ``right_after_a_send``: the Ctrl-C lands in this process just after the second
    child's task is written to its pipe, before anything else of the call runs (the
    write is held there until the signal comes)."""
    import time

    import truckd.workers as workers

    global _PIDS_WRITE
    signal.signal(signal.SIGINT, signal.default_int_handler)
    # a call that waits for the hour-long tasks fails this check at once (the children
    # killed: they hold its output pipe open, and the test would wait on them)
    signal.signal(signal.SIGALRM, _end_the_group_and_fail)
    signal.alarm(60)
    os.setpgid(0, 0)
    read, _PIDS_WRITE = os.pipe()
    signaller = os.fork()
    if signaller == 0:  # once both children said their pid: Ctrl-C to the group
        os.close(_PIDS_WRITE)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        seen = b""
        while seen.count(b"\n") < 2:
            seen += os.read(read, 64)
        os.killpg(0, signal.SIGINT)
        os._exit(0)
    if right_after_a_send:
        write = workers._write_all
        sent = [0]

        def write_then_wait_for_the_signal(fd: int, data: bytes) -> None:
            write(fd, data)
            sent[0] += 1
            if sent[0] == 2:
                signal.pause()  # the Ctrl-C's KeyboardInterrupt is raised here

        workers._write_all = write_then_wait_for_the_signal
    t0 = time.monotonic()
    try:
        ForkMap(2)(_report_then_sleep, range(4))
        raised = None
    except BaseException as exc:  # what was raised is the finding
        raised = f"{type(exc).__name__}: {exc}"
    took = time.monotonic() - t0
    signal.alarm(0)
    os.waitpid(signaller, 0)
    left = [p for p in group_members(os.getpgid(0)) if p != os.getpid()]
    for p in left:  # a child left running would outlive this check
        os.kill(p, signal.SIGKILL)
    return {"raised": raised, "took_s": took, "left": left}


def interrupted_right_after_a_send() -> dict[str, Any]:
    """:func:`interrupted_while_running`, the Ctrl-C landing right after a task's write."""
    return interrupted_while_running(right_after_a_send=True)


CHECKS = {
    "order": order, "raised": raised, "killed": killed, "unpicklable": unpicklable, "torn": torn,
    "diagnosis": diagnosis, "mixed": mixed,
    "interrupted_at_start": interrupted_at_start,
    "interrupted_while_running": interrupted_while_running,
    "interrupted_right_after_a_send": interrupted_right_after_a_send,
}  # fmt: skip

if __name__ == "__main__":
    print(json.dumps(CHECKS[sys.argv[1]](), default=str))

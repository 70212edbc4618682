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
    """Ctrl-C while the pool starts: SIGINT sent to this process (and to each child, as a
    terminal's Ctrl-C reaches the whole group) right after the children are forked and
    before the pool's manager thread starts. What this process raised, and which of
    its children are left."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    # Python's own Ctrl-C handler, whatever this process inherited (a test runner's
    # workers may ignore SIGINT, and an ignored signal stays ignored across exec)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    launch = ProcessPoolExecutor._launch_processes  # type: ignore[attr-defined]
    forked: list[int] = []

    def launch_then_interrupt(self: Any) -> None:
        launch(self)
        forked.extend(p.pid for p in self._processes.values())
        for pid in [*forked, os.getpid()]:
            os.kill(pid, signal.SIGINT)

    ProcessPoolExecutor._launch_processes = launch_then_interrupt  # type: ignore[attr-defined]
    try:
        ForkMap(2)(_slow_square, range(8))
        raised = None
    except BaseException as exc:  # what was raised is the finding
        raised = f"{type(exc).__name__}: {exc}"
    left = [p.pid for p in multiprocessing.active_children()]
    alive = [pid for pid in forked if os.path.exists(f"/proc/{pid}")]
    for pid in alive:  # a child left waiting for work would keep this process from exiting
        os.kill(pid, signal.SIGKILL)
    return {"raised": raised, "forked": forked, "active_children": left, "alive": alive}


CHECKS = {
    "order": order, "raised": raised, "killed": killed, "diagnosis": diagnosis, "mixed": mixed,
    "interrupted_at_start": interrupted_at_start,
}  # fmt: skip

if __name__ == "__main__":
    print(json.dumps(CHECKS[sys.argv[1]](), default=str))

"""Shared fixtures: the shipped default vehicle; device locks per test process; the compiled MPC
cycle as if not built."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from truckd.config.truck import load_config
from truckd.io.devlock import LOCK_DIR_ENV
from truckd.model.params import VehicleParams

pytest_plugins = ["tool_markers"]  # the needs_tool marker (tests/tool_markers.py)


@pytest.fixture(scope="session")
def params() -> VehicleParams:
    """The default truck's parameters (config/truck.yaml)."""
    return load_config().vehicle


@pytest.fixture(scope="session", autouse=True)
def _device_locks_of_this_worker(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """The daemons the tests start lock their devices in a directory of this test
    process's own (``$TRUCKD_LOCK_DIR``, inherited by the processes it starts; a test of
    the lock sets its own).  ``make test`` runs HIL files on two workers side by side, and
    a pty's number that one test freed while its daemon still held the lock of
    ``/dev/pts/N`` (a firmware killed or unplugged on purpose) can be the other worker's
    next pty: one directory per worker keeps their locks apart, as two machines' are."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(LOCK_DIR_ENV, str(tmp_path_factory.mktemp("locks")))
        yield


@pytest.fixture(autouse=True)
def _scheduling_left_as_found() -> Iterator[None]:
    """A test that runs a daemon in this process with real-time scheduling on leaves the
    test process (and every process it starts later) on SCHED_FIFO: that test fails."""
    before = os.sched_getscheduler(0)
    yield
    assert os.sched_getscheduler(0) == before, (
        "the test left this process on real-time scheduling: run the daemon with "
        "runtime.realtime: false in-process"
    )


@pytest.fixture
def no_library(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Iterator[None]:
    """The compiled MPC cycle's library as if it were not built (the loader's cache
    emptied before and after)."""
    from truckd.control import ccycle

    monkeypatch.setattr(ccycle, "LIBRARY", tmp_path / "libtruckd_mpc.so")
    monkeypatch.setattr(ccycle, "_state", {})
    yield
    ccycle._state.clear()

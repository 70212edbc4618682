"""Shared fixtures: the shipped default vehicle; the compiled MPC cycle as if not built."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from truckd.config.truck import load_config
from truckd.model.params import VehicleParams

pytest_plugins = ["tool_markers"]  # the needs_tool marker (tests/tool_markers.py)


@pytest.fixture(scope="session")
def params() -> VehicleParams:
    """The default truck's parameters (config/truck.yaml)."""
    return load_config().vehicle


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

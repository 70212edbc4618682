"""``benchmarks/host_steal.py``: the host's steal time read back from its samples, and the
deadline misses it can explain (the loop benchmark's ``misses_and_host_steal``)."""

from __future__ import annotations

import importlib.util
import os
import signal
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import numpy as np

SCRIPT = Path(__file__).resolve().parent.parent / "benchmarks" / "host_steal.py"


def _module() -> ModuleType:
    spec = importlib.util.spec_from_file_location("host_steal", SCRIPT)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_steal_is_the_sum_over_cpus_of_the_counters_moves_in_seconds() -> None:
    hs = _module()
    t, added = hs.steal_times(["10.0 5 7", "10.5 6 7", "", "11.25 6 10"])
    np.testing.assert_allclose(t, [10.5, 11.25])
    np.testing.assert_allclose(added, [1 / hs.USER_HZ, 3 / hs.USER_HZ])
    t, added = hs.steal_times(["10.0 5 7"])  # no move: nothing stolen
    assert t.size == 0 and added.size == 0


def test_a_miss_is_explained_only_by_a_move_inside_its_window() -> None:
    hs = _module()
    steal_t = np.array([2.0105, 7.5])  # one move 10.5 ms after a miss ends, one far away
    got = hs.misses_explained([2.0, 5.0], [2.0001, 5.0001], steal_t, 0.015, 60.0)
    assert got["misses"] == 2 and got["with_host_steal"] == 1 and got["steal_moves"] == 2
    assert 0 < got["expected_by_chance"] < 0.01
    narrow = hs.misses_explained([2.0, 5.0], [2.0001, 5.0001], steal_t, 0.005, 60.0)
    assert narrow["with_host_steal"] == 0
    none = hs.misses_explained([], [], steal_t, 0.015, 60.0)
    assert none == {"misses": 0, "with_host_steal": 0, "expected_by_chance": 0.0,
                    "steal_moves": 2}  # fmt: skip


def test_the_sampler_prints_the_machines_counters_and_ends_on_sigterm() -> None:
    with subprocess.Popen(
        [sys.executable, str(SCRIPT), "0.001"], stdout=subprocess.PIPE, text=True
    ) as proc:
        assert proc.stdout is not None
        first = proc.stdout.readline().split()
        os.kill(proc.pid, signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
    cpus = [
        ln for ln in Path("/proc/stat").read_text().splitlines() if ln[:3] == "cpu" and ln[3] != " "
    ]
    assert len(first) == 1 + len(cpus)
    assert all(x.isdigit() for x in first[1:]) and float(first[0]) > 0

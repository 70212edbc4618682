"""``vehicle_id`` becomes a Zenoh key chunk: only safe characters pass the config loader."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from runtime_support import write_config

from truckd.config.truck import load_config
from truckd.errors import InputError

BAD = ["", "*", "**", "$*", "a/b", "truck?1", "truck#1", "truck 1", "\x1b[2Jx", "é", "a" * 65,
       "truck1\n"]  # fmt: skip
GOOD = ["truck1", "T-2_b", "a" * 64, "0"]


@pytest.mark.parametrize("value", BAD)
def test_unsafe_vehicle_id_is_rejected_in_one_line(tmp_path: Path, value: str) -> None:
    f = write_config(tmp_path / "truck.yaml", {"vehicle_id": value})
    with pytest.raises(InputError) as err:
        load_config(f)
    msg = str(err.value)
    assert str(f) in msg and "'vehicle_id'" in msg and "A-Z a-z 0-9 _ -" in msg
    assert "\n" not in msg and "\x1b" not in msg


@pytest.mark.parametrize("value", GOOD)
def test_safe_vehicle_ids_load(tmp_path: Path, value: str) -> None:
    assert (
        load_config(write_config(tmp_path / "truck.yaml", {"vehicle_id": value})).vehicle_id
        == value
    )


@pytest.mark.parametrize("value", ["", "*"])
def test_run_with_unsafe_vehicle_id_is_exit_2_before_anything_starts(
    tmp_path: Path, value: str
) -> None:
    logs = str(tmp_path / "logs")
    f = write_config(
        tmp_path / "truck.yaml", {"vehicle_id": value, "runtime": {"recorder": {"dir": logs}}}
    )
    r = subprocess.run(
        [sys.executable, "-m", "truckd.cli.main", "run", "--config", str(f), "--backend", "sim",
         "--duration", "1"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode == 2, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "vehicle_id" in r.stderr
    assert not (tmp_path / "logs").exists()

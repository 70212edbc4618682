"""Recorder: contract CSV readable by read_log, size rotation, retention, nothing lost on stop."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from truckd.config.runtime import RecorderConfig
from truckd.errors import TruckdError
from truckd.logfile import read_log
from truckd.runtime.recorder import Recorder

COLS = ("t", "u", "v", "i", "gap", "mode")


def rows(n: int) -> list[tuple[float, ...]]:
    out = []
    for k in range(n):
        t = 0.01 * k
        gap = math.nan if k % 7 == 0 else 1.0 + 0.001 * k
        out.append((t, 3.0 * math.sin(t), 0.5 * t, 1.5, gap, float(k % 5)))
    return out


def test_rotates_by_size_every_file_is_a_contract_log(tmp_path: Path) -> None:
    cfg = RecorderConfig(dir=str(tmp_path / "logs"), max_bytes=4096, keep=1000, flush_period_s=0.0)
    rec = Recorder(cfg, COLS)
    rec.start()
    data = rows(2000)
    for r in data:
        rec.record(r)
    rec.stop()
    files = sorted((tmp_path / "logs").glob("truckd-*.csv"))
    assert files == rec.files
    assert len(files) > 5
    ts, gaps = [], []
    for f in files:
        assert f.stat().st_size <= 4096 + 200  # one row past the limit at most
        log = read_log(f, require=("t", "u", "v"))
        assert log.input_kind == "voltage"
        ts.append(log["t"])
        gaps.append(log["gap"])
    t = np.concatenate(ts)
    np.testing.assert_allclose(t, [r[0] for r in data], rtol=0, atol=1e-12)
    # extra columns round-trip, NaN included (an invalid range reading)
    np.testing.assert_allclose(np.concatenate(gaps), [r[4] for r in data], rtol=1e-9)
    assert rec.rows == 2000 and rec.dropped == 0 and rec.errors == 0


def test_keeps_only_the_newest_files(tmp_path: Path) -> None:
    cfg = RecorderConfig(dir=str(tmp_path), max_bytes=4096, keep=3, flush_period_s=0.0)
    rec = Recorder(cfg, COLS)
    rec.start()
    for r in rows(3000):
        rec.record(r)
    rec.stop()
    files = sorted(tmp_path.glob("truckd-*.csv"))
    assert len(files) == 3
    assert files == rec.files
    # the newest rows survive
    assert read_log(files[-1])["t"][-1] == pytest.approx(29.99)


def test_stop_flushes_rows_queued_just_before(tmp_path: Path) -> None:
    cfg = RecorderConfig(dir=str(tmp_path), flush_period_s=60.0)  # no periodic flush
    rec = Recorder(cfg, COLS)
    rec.start()
    for r in rows(10):
        rec.record(r)
    rec.stop()
    assert rec.path is not None
    assert len(read_log(rec.path)) == 10


def test_unwritable_directory_is_a_clear_error(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    rec = Recorder(RecorderConfig(dir=str(blocker / "sub")), COLS)
    with pytest.raises(TruckdError, match="cannot write logs"):
        rec.start()


def test_rejects_bad_columns() -> None:
    with pytest.raises(ValueError):
        Recorder(RecorderConfig(), ("u", "v"))
    with pytest.raises(ValueError):
        Recorder(RecorderConfig(), ("t", "u", "u"))


def test_two_recorders_in_one_directory_in_one_second_never_share_a_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Same directory, same UTC second, even the same pid: each gets its own file."""
    import truckd.runtime.recorder as recorder_mod

    monkeypatch.setattr(recorder_mod.time, "strftime", lambda fmt, t=None: "20260101T000000")
    cfg = RecorderConfig(dir=str(tmp_path), flush_period_s=0.0)
    a, b = Recorder(cfg, COLS), Recorder(cfg, COLS)
    a.start()
    b.start()
    ra, rb = rows(30), [(r[0], -1.0, *r[2:]) for r in rows(40)]
    for r in ra:
        a.record(r)
    for r in rb:
        b.record(r)
    a.stop()
    b.stop()
    assert a.path is not None and b.path is not None and a.path != b.path
    assert len(list(tmp_path.glob("*.csv"))) == 2
    la, lb = read_log(a.path), read_log(b.path)
    assert len(la) == 30 and len(lb) == 40
    assert np.all(lb["u"] == -1.0) and not np.any(la["u"] == -1.0)

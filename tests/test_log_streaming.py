"""Long logs read in blocks: the columns in memory, not the text (bounded bytes per row,
measured with tracemalloc, not time); a log longer than a row budget kept as evenly
spread stretches, every row still checked; errors name the same line and byte whether
the reader meets them inside a block or across blocks."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from truckd import logfile
from truckd.errors import InputError
from truckd.logfile import read_log, read_log_windows


def write(path: Path, n: int, extra: bool = False) -> Path:
    t = np.arange(n) * 0.01
    u = np.round(np.sin(t), 3)
    v = np.round(np.cos(t) * 0.5, 5)
    head = "t,u,v" + (",note,seq" if extra else "")
    with open(path, "w") as fh:
        fh.write(head + "\n")
        for k in range(n):
            tail = f",x{k % 3},{k}" if extra else ""
            fh.write(f"{t[k]:.2f},{u[k]:.3f},{v[k]:.5f}{tail}\n")
    return path


def test_reading_holds_the_columns_not_the_text(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The reader at a scale of 1:16: 64 KiB blocks over 20 000 rows (430 kB, about seven
    # blocks) as 1 MiB blocks over 4.4 MB; the fixed cost of a block stays a few bytes a
    # row.  Holding the lines instead measures about 115 bytes per row at either scale.
    monkeypatch.setattr(logfile, "BLOCK_BYTES", 1 << 16)
    n = 20_000
    p = write(tmp_path / "long.csv", n)
    assert p.stat().st_size > 6 * logfile.BLOCK_BYTES  # read in several blocks
    tracemalloc.start()
    try:
        log = read_log(p, require=("t", "u", "v"))
        _cur, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(log) == n
    # three float64 columns are 24 bytes per row; the text alone is 22
    assert peak / n < 100, f"{peak / n:.0f} bytes per row"


def test_a_log_beyond_the_budget_is_kept_as_spread_stretches(tmp_path: Path) -> None:
    n = 10_000
    p = write(tmp_path / "long.csv", n, extra=True)
    whole = read_log(p)
    parts = read_log_windows(p, ("t", "u", "v"), None, max_rows=2_000, windows=4)
    assert len(parts) == 4 and all(len(lg) == 500 for lg in parts)
    t = whole["t"]
    starts = [int(np.searchsorted(t, lg["t"][0])) for lg in parts]
    assert starts[0] == 0 and starts[-1] + 500 == n  # from the start to the end
    for lg, a in zip(parts, starts, strict=True):
        for c in ("t", "u", "v", "seq"):
            assert np.array_equal(lg[c], whole[c][a : a + 500])
        assert lg.text_columns == ["note"] == whole.text_columns
        assert f"lines {a + 2}-{a + 501}" in lg.source
    assert any("10000 data rows" in note for note in parts[0].notes)
    # within the budget: one log, the same as read_log
    (one,) = read_log_windows(p, ("t",), None, max_rows=n)
    assert np.array_equal(one["v"], whole["v"]) and one.source == str(p)


def test_every_row_is_checked_outside_the_stretches_too(tmp_path: Path) -> None:
    p = write(tmp_path / "long.csv", 10_000)
    lines = p.read_text().splitlines(keepends=True)
    lines[5001] = "50.00,abc,0.1\n"  # data row 5000: between the stretches
    p.write_text("".join(lines))
    with pytest.raises(InputError, match=r"line 5002: column 'u': 'abc' is not a number"):
        read_log_windows(p, ("t",), None, max_rows=1_000, windows=2)
    lines[5001] = "1.00,0.5,0.1\n"  # time going back
    p.write_text("".join(lines))
    with pytest.raises(InputError, match=r"line 5002: time t=1\.0 does not increase"):
        read_log_windows(p, ("t",), None, max_rows=1_000, windows=2)


@pytest.mark.parametrize("block", [7, 64, 1 << 20])
def test_blocks_do_not_change_what_is_read_or_the_errors(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, block: int
) -> None:
    monkeypatch.setattr(logfile, "BLOCK_BYTES", block)
    p = tmp_path / "a.csv"
    p.write_bytes(
        "\ufeff".encode() + b"t,u,v,label\n0,1,2,\xc3\xa9t\xc3\xa9\n0.01,1,2,x\n0.02,1,2,y"
    )
    log = read_log(p)
    assert list(log["t"]) == [0.0, 0.01, 0.02] and log.text_columns == ["label"]
    p.write_bytes(b"t,u,v\n0,1,2\n0.01,1,2\n0.02,1")  # cut short: skipped, with a note
    log = read_log(p)
    assert list(log["t"]) == [0.0, 0.01] and any(
        "line 4: the last line is cut" in n for n in log.notes
    )
    data = b"t,u,v\n0,1,2\n0.01,1,2\n0.02,\xff,2\n"
    p.write_bytes(data)
    at = data.index(b"\xff")
    with pytest.raises(InputError) as err:
        read_log(p)
    assert str(err.value) == (
        f"{p}: line 4: byte 0xff at offset {at} is not UTF-8; expected a UTF-8 text CSV log"
    )

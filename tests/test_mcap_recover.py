"""MCAP files a crash left unfinished: recovered (index and footer rewritten, atomically)
by ``truckd recover`` and by the daemon's next start; a crash loses at most about one
flush period; finished files and files being written are left alone."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from cli_support import cli
from mcap.reader import make_reader

from truckd.errors import InputError, TruckdError
from truckd.runtime import mcap_recover
from truckd.runtime.mcap_log import McapFile, McapLog
from truckd.runtime.mcap_recover import recover_dir, recover_file

ORIGIN = 1_700_000_000_000_000_000


def indexed(path: Path) -> list[int]:
    """Log times of every message, through mcap's indexed reader (raises on a file
    without summary or index)."""
    with open(path, "rb") as fh:
        r = make_reader(fh)
        s = r.get_summary()
        assert s is not None and s.statistics is not None
        times = [m.log_time for _s, _c, m in r.iter_messages()]
        assert len(times) == s.statistics.message_count
        assert bool(s.chunk_indexes) == bool(times)
        return times


def crashed_log(tmp: Path, seconds: float, flush_period_s: float = 1.0) -> tuple[Path, int]:
    """The daemon's MCAP log fed at 100 Hz for ``seconds`` on a fake clock, then
    abandoned as a SIGKILL leaves it (no close): the file and the cycles recorded."""
    now = [0.0]
    log = McapLog("t1", origin_ns=ORIGIN, flush_period_s=flush_period_s, monotonic=lambda: now[0])
    path = tmp / "run.mcap"
    log.open(path)
    n = round(seconds * 100)
    for k in range(n):
        now[0] = k * 0.01
        log.record_state(now[0], {"seq": k, "t": now[0], "mode": "ACTIVE"})
        if k % 5 == 4:  # the recorder's writer thread wakes every few cycles
            log.write_pending()
            log.flush()
    f = log._file
    assert f is not None and f._fh is not None
    f._fh.flush()  # what the OS has when the process dies (Python's buffer is lost)
    shutil.copy(path, tmp / "crashed.mcap")
    log.close()
    return tmp / "crashed.mcap", n


def test_a_crash_loses_at_most_a_flush_period_and_recovery_restores_the_index(
    tmp_path: Path,
) -> None:
    path, n = crashed_log(tmp_path, 5.0)
    with open(path, "rb") as fh, pytest.raises(Exception):  # noqa: B017 - any refusal
        make_reader(fh).get_summary()
    r = recover_file(path)
    assert r.status == "recovered" and r.messages > 0
    times = indexed(path)
    assert len(times) == r.messages
    last_t = (times[-1] - ORIGIN) * 1e-9
    assert last_t >= (n - 1) * 0.01 - 1.0 - 0.05  # at most ~one flush period lost
    assert times == sorted(times)
    assert "recovered" in r.line() and str(path) in r.line()
    # again: finished now, nothing to do, bytes unchanged
    before = path.read_bytes()
    assert recover_file(path).status == "complete"
    assert path.read_bytes() == before


@pytest.mark.parametrize("cut", [20, 100, 1000, 5000, -1, -9])
def test_any_cut_point_recovers_to_a_readable_file(tmp_path: Path, cut: int) -> None:
    path, _ = crashed_log(tmp_path, 3.0, flush_period_s=0.2)
    data = path.read_bytes()
    path.write_bytes(data[:cut])
    r = recover_file(path)
    assert r.status == "recovered"
    assert len(indexed(path)) == r.messages


def test_a_file_being_written_is_left_alone(tmp_path: Path) -> None:
    f = McapFile(tmp_path / "live.mcap", "t1")
    f.write("state", ORIGIN, b'{"seq": 0}')
    f.flush()
    before = (tmp_path / "live.mcap").read_bytes()
    assert recover_file(tmp_path / "live.mcap").status == "busy"
    assert [r.status for r in recover_dir(tmp_path)] == ["busy"]
    assert (tmp_path / "live.mcap").read_bytes() == before
    f.close()
    assert recover_dir(tmp_path) == []  # finished: not even looked at


def test_not_an_mcap_file_is_refused_and_untouched(tmp_path: Path) -> None:
    p = tmp_path / "x.mcap"
    p.write_bytes(b"id,t\n1,2\n")
    with pytest.raises(InputError, match="not an MCAP file"):
        recover_file(p)
    assert p.read_bytes() == b"id,t\n1,2\n"
    assert recover_dir(tmp_path) == []


def test_a_failed_write_leaves_the_original(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path, _ = crashed_log(tmp_path, 1.0)
    before = path.read_bytes()

    def full(*_a: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(mcap_recover.os, "replace", full)
    with pytest.raises(TruckdError, match="cannot write the recovered file"):
        recover_file(path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["crashed.mcap", "run.mcap"]


def test_recover_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, _ = crashed_log(tmp_path, 2.0)
    (tmp_path / "run.mcap").unlink()
    code, out, err = cli(["recover", str(tmp_path)], capsys)
    assert code == 0, err
    (line,) = out.splitlines()
    assert line.startswith(f"{path}: recovered ") and "index rewritten" in line
    assert indexed(path)
    code, out, err = cli(["recover", str(path)], capsys)
    assert (code, out.strip()) == (0, f"{path}: complete, nothing to do")
    code, out, err = cli(["recover", str(tmp_path)], capsys)
    assert (code, out.strip()) == (0, f"{tmp_path}: no unfinished MCAP file")
    code, out, err = cli(["recover", str(tmp_path / "nope.mcap")], capsys)
    assert code == 2 and "no such file" in err and len(err.strip().splitlines()) == 1
    (tmp_path / "notes.txt").write_text("hello")
    code, out, err = cli(["recover", str(tmp_path / "notes.txt")], capsys)
    assert code == 2 and "not an MCAP file" in err

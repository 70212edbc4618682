"""Outputs all or nothing: a write that fails leaves no half-written file, no
temporary file, and an existing target untouched."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cli_support import assert_one_line, run_limited

from truckd.errors import TruckdError
from truckd.logfile import write_log
from truckd.outputs import atomic_dir, atomic_text, write_set, write_text


def listing(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir())


def test_exception_while_writing_keeps_the_old_file(tmp_path: Path) -> None:
    target = tmp_path / "out.json"
    target.write_text("old\n")
    with pytest.raises(RuntimeError), atomic_text(target) as fh:
        fh.write("partial")
        raise RuntimeError("fit failed")
    assert target.read_text() == "old\n"
    assert listing(tmp_path) == ["out.json"]


def test_success_replaces_in_one_step(tmp_path: Path) -> None:
    target = tmp_path / "out.json"
    target.write_text("old\n")
    write_text(target, "new\n")
    assert target.read_text() == "new\n"
    assert listing(tmp_path) == ["out.json"]


def test_directory_target_is_an_error_and_nothing_is_left(tmp_path: Path) -> None:
    d = tmp_path / "m.yaml"
    d.mkdir()
    with pytest.raises(TruckdError, match="is a directory"):
        write_text(d, "x")
    assert listing(tmp_path) == ["m.yaml"] and listing(d) == []


def test_a_set_is_written_whole_or_not_at_all(tmp_path: Path) -> None:
    first, second = tmp_path / "m.yaml", tmp_path / "d.json"
    second.mkdir()
    with pytest.raises(TruckdError):
        write_set([(first, "model\n"), (second, "{}\n")])
    assert not first.exists()
    assert listing(tmp_path) == ["d.json"]
    second.rmdir()
    write_set([(first, "model\n"), (second, "{}\n")])
    assert first.read_text() == "model\n" and second.read_text() == "{}\n"


def test_report_directory_appears_only_when_complete(tmp_path: Path) -> None:
    rep = tmp_path / "report"
    with pytest.raises(RuntimeError), atomic_dir(rep) as tmp:
        (tmp / "index.html").write_text("<html>")
        raise RuntimeError("plot failed")
    assert listing(tmp_path) == []
    with atomic_dir(rep) as tmp:
        (tmp / "index.html").write_text("<html>")
    assert listing(rep) == ["index.html"] and listing(tmp_path) == ["report"]
    with atomic_dir(rep) as tmp:  # an existing, non-empty report is updated file by file
        (tmp / "index.html").write_text("<html>2")
        (tmp / "fit.png").write_bytes(b"png")
    assert listing(rep) == ["fit.png", "index.html"]
    assert (rep / "index.html").read_text() == "<html>2"
    assert listing(tmp_path) == ["report"]


def test_file_size_limit_leaves_nothing_half_written(tmp_path: Path) -> None:
    """RLIMIT_FSIZE in a child (SIGXFSZ ignored): the write fails with EFBIG part-way."""
    t = np.arange(2000) * 0.01
    write_log(tmp_path / "in.csv", {"t": t, "u": np.where(t > 1, 6.0, 0.0)})
    size_in = (tmp_path / "in.csv").stat().st_size
    limit = 16 * 1024
    assert size_in > limit  # the output (more columns) is larger still
    out = tmp_path / "out.csv"
    r = run_limited(["simulate", "in.csv", "--out", "out.csv"], tmp_path, fsize=limit)
    line = assert_one_line(r.stderr)
    assert r.returncode == 1, r.stderr
    assert "out.csv: cannot write: File too large" in line
    assert listing(tmp_path) == ["in.csv"]
    out.write_text("old\n")
    r = run_limited(["simulate", "in.csv", "--out", "out.csv"], tmp_path, fsize=limit)
    assert r.returncode == 1 and "File too large" in assert_one_line(r.stderr)
    assert out.read_text() == "old\n"
    assert listing(tmp_path) == ["in.csv", "out.csv"]


def test_sim_json_and_plot_are_written_as_a_set(tmp_path: Path) -> None:
    """A sim whose plot cannot be written under the size limit writes neither file."""
    (tmp_path / "s.json").write_text("old\n")
    r = run_limited(
        ["sim", "--scenario", "cruise", "--duration", "1", "--json", "s.json", "--plot", "s.png"],
        tmp_path,
        fsize=4096,
    )
    line = assert_one_line(r.stderr)
    assert r.returncode == 1 and "s.png: cannot write: File too large" in line
    assert (tmp_path / "s.json").read_text() == "old\n"
    assert listing(tmp_path) == ["s.json"]


def test_sim_json_mcap_and_traces_are_one_set(tmp_path: Path) -> None:
    """A trace too large for the size limit: no JSON, no MCAP, no trace (before: the JSON
    and every MCAP file were written, then one trace of six)."""
    (tmp_path / "s.json").write_text("old\n")
    argv = ["sim", "--scenario", "cruise", "--duration", "5", "--json", "s.json"]
    # the limit lies between the MCAP (about 83 kB with its plans) and the trace (107 kB)
    limit = 96 * 1024
    r = run_limited([*argv, "--mcap", "mc", "--trace", "tr"], tmp_path, fsize=limit)
    line = assert_one_line(r.stderr)
    assert r.returncode == 1 and "cruise.csv: cannot write: File too large" in line
    assert (tmp_path / "s.json").read_text() == "old\n"
    assert [p.name for p in tmp_path.rglob("*") if p.is_file()] == ["s.json"]
    r = run_limited([*argv, "--mcap", "mc", "--trace", "tr"], tmp_path)  # no limit: all three
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "mc" / "cruise.mcap").stat().st_size > 0
    assert (tmp_path / "mc" / "cruise.mcap").stat().st_size < limit
    assert (tmp_path / "tr" / "cruise.csv").stat().st_size > limit


def test_sigterm_while_writing_leaves_nothing_half_written(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A tool stopped by SIGTERM (systemd, `kill`) unwinds as on Ctrl-C: the file being
    written is removed, the old one kept, the exit code is 128 + 15 (before: the default
    action killed the process and left the temporary file)."""
    import os
    import signal

    import truckd.cli.params as cli_params
    from truckd.cli.main import main
    from truckd.outputs import atomic_text

    out = tmp_path / "out.json"
    out.write_text("old")

    def run(_args: object) -> int:
        with atomic_text(out) as f:
            f.write("half")
            if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:  # fail, do not die
                raise AssertionError("main installed no SIGTERM handler")
            os.kill(os.getpid(), signal.SIGTERM)  # delivered before the next bytecode
            f.write("never")
        return 0

    monkeypatch.setattr(cli_params, "run", run)
    before = signal.signal(signal.SIGTERM, signal.SIG_DFL)  # as a tool starts
    try:
        with pytest.raises(SystemExit) as exc:
            main(["params"])
        assert exc.value.code == 128 + signal.SIGTERM
        assert out.read_text() == "old"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # restored
    finally:
        signal.signal(signal.SIGTERM, before)


def test_an_ignored_sighup_stays_ignored(monkeypatch: pytest.MonkeyPatch) -> None:
    """`nohup truckd diagnose ...`: SIGHUP is ignored by nohup and must stay so (the tool
    ran on after the terminal closed; unwinding on it would end the run)."""
    import signal

    import truckd.cli.params as cli_params
    from truckd.cli.main import main

    seen: list[object] = []

    def run(_args: object) -> int:
        seen.append(signal.getsignal(signal.SIGHUP))
        return 0

    monkeypatch.setattr(cli_params, "run", run)
    before = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        assert main(["params"]) == 0
        assert seen == [signal.SIG_IGN]
    finally:
        signal.signal(signal.SIGHUP, before)

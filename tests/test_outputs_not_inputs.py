"""An output never replaces an input, for every command that writes: an output path that
resolves to one of the command's inputs (the same path, a symbolic link to it, a hard
link to it: compared by device and inode) is refused with one line, exit 2, and the input
is unchanged (nothing else written either)."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from cli_support import assert_one_line, cli

from truckd.config.truck import default_config_path
from truckd.errors import InputError
from truckd.outputs import atomic_dir, guard_inputs, write_set, write_text

Link = Callable[[Path, Path], None]


def same(src: Path, dst: Path) -> None:
    """The output given as the input's own path (dst is ignored)."""


def symlink(src: Path, dst: Path) -> None:
    dst.symlink_to(src)


def hardlink(src: Path, dst: Path) -> None:
    os.link(src, dst)


LINKS = {"same": same, "symlink": symlink, "hardlink": hardlink}


def make_log(path: Path) -> Path:
    t = np.arange(0.0, 4.0, 0.01)
    u = np.where(t < 2.0, 3.0, 0.0)
    v = np.cumsum(u) * 1e-3
    rows = "\n".join(f"{a:.2f},{b:.3f},{c:.5f}" for a, b, c in zip(t, u, v, strict=True))
    path.write_text("t,u,v\n" + rows + "\n")
    return path


def files(tmp: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(tmp)): p.read_bytes()
        for p in sorted(tmp.rglob("*"))
        if p.is_file() and not p.is_symlink()
    }


def refused(tmp: Path, argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """``truckd argv`` refuses with one line, exit 2, and no file in ``tmp`` changed,
    appeared or vanished."""
    before = files(tmp)
    code, _out, err = cli(argv, capsys)
    line = assert_one_line(err)
    assert code == 2, err
    assert "would replace the input" in line, line
    assert files(tmp) == before
    return line


@pytest.fixture
def log(tmp_path: Path) -> Path:
    return make_log(tmp_path / "run.csv")


@pytest.mark.parametrize("link", LINKS)
@pytest.mark.parametrize("option", ["--json", "--out"])
def test_diagnose_output_over_its_log(
    tmp_path: Path, log: Path, option: str, link: str, capsys: pytest.CaptureFixture[str]
) -> None:
    out = log if link == "same" else tmp_path / f"{link}.out"
    LINKS[link](log, out)
    line = refused(tmp_path, ["diagnose", str(log), option, str(out)], capsys)
    assert str(out) in line and option in line


def test_diagnose_output_over_a_validation_log_a_config_or_a_sysid_file(
    tmp_path: Path, log: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    val = make_log(tmp_path / "val.csv")
    refused(tmp_path, ["diagnose", str(log), "--validate", str(val), "--json", str(val)], capsys)
    cfg = tmp_path / "truck.yaml"
    cfg.write_bytes(default_config_path().read_bytes())
    refused(tmp_path, ["diagnose", str(log), "--config", str(cfg), "--out", str(cfg)], capsys)
    sysid = tmp_path / "sysid.json"
    sysid.write_text("{}")
    refused(tmp_path, ["diagnose", f"{sysid}:slow-forward", "--json", str(sysid)], capsys)


@pytest.mark.parametrize("link", LINKS)
def test_identify_output_over_its_log(
    tmp_path: Path, log: Path, link: str, capsys: pytest.CaptureFixture[str]
) -> None:
    out = log if link == "same" else tmp_path / f"{link}.yaml"
    LINKS[link](log, out)
    refused(tmp_path, ["identify", str(log), "--out", str(out)], capsys)


@pytest.mark.parametrize("link", ["symlink", "hardlink"])
def test_simulate_output_over_its_input_or_model(
    tmp_path: Path, log: Path, link: str, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / f"{link}.csv"
    LINKS[link](log, out)
    before = files(tmp_path)
    code, _o, err = cli(["simulate", str(log), "--out", str(out)], capsys)
    assert code == 2 and assert_one_line(err) and files(tmp_path) == before
    model = tmp_path / "model.yaml"
    model.write_text("not read: refused before\n")
    refused(tmp_path, ["simulate", str(log), "--model", str(model), "--out", str(model)], capsys)


@pytest.mark.parametrize("option", ["--json", "--mcap"])
def test_sim_output_over_its_config(
    tmp_path: Path, option: str, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = tmp_path / "truck.yaml"
    cfg.write_bytes(default_config_path().read_bytes())
    link = tmp_path / "out.json"
    hardlink(cfg, link)
    refused(
        tmp_path,
        ["sim", "--scenario", "cruise", "--duration", "1", "--config", str(cfg), option, str(link)],
        capsys,
    )
    refused(
        tmp_path,
        ["sim", "--platoon", "2", "--duration", "1", "--config", str(cfg), "--json", str(link)],
        capsys,
    )


def test_sim_trace_directory_over_its_config(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A file the trace directory would publish is the configuration (checked when the
    outputs are written, after the run): refused, nothing written."""
    d = tmp_path / "traces"
    d.mkdir()
    cfg = d / "cruise.csv"  # the configuration, under the trace's name
    cfg.write_bytes(default_config_path().read_bytes())
    refused(
        tmp_path,
        ["sim", "--scenario", "cruise", "--duration", "1", "--config", str(cfg), "--trace", str(d)],
        capsys,
    )


def test_a_report_directory_never_publishes_over_an_input(tmp_path: Path) -> None:
    d = tmp_path / "report"
    d.mkdir()
    data = make_log(d / "index.html")  # a log (oddly named) where the report's index goes
    before = data.read_bytes()
    with (
        guard_inputs([data]),
        pytest.raises(InputError, match="would replace the input"),
        atomic_dir(d) as tmp,
    ):
        (tmp / "plot.png").write_bytes(b"png")
        (tmp / "index.html").write_text("<html>")
    assert data.read_bytes() == before
    assert sorted(p.name for p in d.iterdir()) == ["index.html"]  # no plot published either
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]  # no temporary left


def test_a_set_of_outputs_is_refused_whole(tmp_path: Path) -> None:
    inp = make_log(tmp_path / "in.csv")
    first = tmp_path / "first.json"
    with guard_inputs([inp]), pytest.raises(InputError):
        write_set([(first, "{}"), (inp, "{}")])
    assert not first.exists() and inp.read_bytes().startswith(b"t,u,v")
    # outside the guard (another command's inputs are not this one's) it is written
    write_text(first, "{}")
    assert first.read_text() == "{}"

"""Bad input: every case exits 2 with one line naming the file and what was
expected; never a traceback, never a hang, never a half-written output."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from cli_support import bad_input, cli

import truckd.logfile as logfile
from truckd.config.truck import default_config_path, load_config, parse_config
from truckd.errors import InputError
from truckd.logfile import read_log, require_io
from truckd.modelfile import read_model

GOOD = "t,u,v\n0,1,0\n0.01,1,0.01\n0.02,1,0.02\n"


def write(tmp_path: Path, name: str, data: str | bytes) -> Path:
    p = tmp_path / name
    if isinstance(data, bytes):
        p.write_bytes(data)
    else:
        p.write_text(data, encoding="utf-8")
    return p


def log_error(path: Path, **kw: object) -> str:
    with pytest.raises(InputError) as err:
        log = read_log(path, **kw)  # type: ignore[arg-type]
        require_io(log)
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg
    return msg


# --- files: encoding, kind, size -------------------------------------------------------


def test_non_utf8_log_config_and_model_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    csv = write(tmp_path, "latin1.csv", "t,u,v,note\n0,1,0,café\n".encode("latin-1"))
    line = bad_input(["diagnose", str(csv)], capsys)
    assert "latin1.csv: line 2" in line and "not UTF-8" in line
    cfg = write(tmp_path, "c.yaml", b"vehicle:\n  R_m: 1 # \xe9\n")
    line = bad_input(["params", "--config", str(cfg)], capsys)
    assert "c.yaml: line 2" in line and "UTF-8" in line
    model = write(tmp_path, "m.yaml", b"\xff\xfe v\x00")
    line = bad_input(["sim", "--scenario", "follow", "--model", str(model)], capsys)
    assert "m.yaml" in line and "UTF-8" in line


def test_utf8_bom_is_accepted(tmp_path: Path) -> None:
    log = read_log(write(tmp_path, "bom.csv", "\ufeff" + GOOD))
    assert list(log.columns) == ["t", "u", "v"]
    cfg = default_config_path().read_text(encoding="utf-8")
    p = write(tmp_path, "bom.yaml", "\ufeff" + cfg)
    assert load_config(p) == load_config()


@pytest.mark.parametrize(
    ("target", "expected"),
    [("/dev/zero", "not a regular file"), (".", "is a directory"), ("absent.csv", "no such file")],
)
def test_devices_directories_and_missing_logs_exit_2(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    target: str,
    expected: str,
) -> None:
    monkeypatch.chdir(tmp_path)
    line = bad_input(["diagnose", target], capsys)
    assert target in line and expected in line


def test_a_fifo_is_refused_without_waiting_for_a_writer(tmp_path: Path) -> None:
    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    assert "not a regular file" in log_error(fifo)
    with pytest.raises(InputError, match="not a regular file"):
        load_config(fifo)


def test_byte_and_row_limits(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    p = write(tmp_path, "long.csv", GOOD + "0.03,1,0.03\n0.04,1,0.04\n")
    monkeypatch.setattr(logfile, "MAX_ROWS", 4)
    assert "line 6: more than 4 data rows" in log_error(p)
    monkeypatch.setattr(logfile, "MAX_LOG_BYTES", 20)
    assert "more than the limit of 20 bytes" in log_error(p)


# --- columns and rows ------------------------------------------------------------------


def test_extra_text_and_empty_columns_are_kept_and_ignored(tmp_path: Path) -> None:
    text = "t,note,u,,v,temp\n0,start,1,,0,20.5\n0.01,,1,,0.01,\n0.02,go on,1,,0.02,21\n"
    log = read_log(write(tmp_path, "extra.csv", text))
    require_io(log)
    assert list(log.columns) == ["t", "u", "v", "temp"]
    assert log.text_columns == ["note"]
    np.testing.assert_array_equal(log["v"], [0, 0.01, 0.02])
    assert np.isnan(log["temp"][1]) and log["temp"][2] == 21


def test_empty_known_cell_names_line_and_column(tmp_path: Path) -> None:
    msg = log_error(write(tmp_path, "hole.csv", "t,u,v\n0,1,0\n0.01,,0.01\n"))
    assert "line 3: column 'u' is empty" in msg


def test_rows_of_empty_cells(tmp_path: Path) -> None:
    """Inside the data: refused with the line (a lost sample); at the end (a spreadsheet's
    trailing rows): skipped and said."""
    inner = write(tmp_path, "inner.csv", "t,u,v\n0,1,0\n,,\n0.02,1,0.02\n")
    assert "line 3: every cell is empty" in log_error(inner)
    tail = read_log(write(tmp_path, "tail.csv", GOOD + ",,\n , ,\n"))
    assert len(tail) == 3
    assert tail.notes == [f"{tmp_path / 'tail.csv'}: skipped 2 empty row(s) at the end (lines 5-6)"]


def test_a_log_cut_by_a_crash_is_read_up_to_its_last_full_line(tmp_path: Path) -> None:
    log = read_log(write(tmp_path, "cut.csv", GOOD + "0.03,1"))
    assert len(log) == 3
    assert log.notes == [
        f"{tmp_path / 'cut.csv'}: line 5: the last line is cut short (2 of 3 cells, no newline "
        "at the end: a log whose writer stopped); skipped"
    ]
    inner = write(tmp_path, "short.csv", "t,u,v\n0,1\n0.01,1,0\n")
    assert "line 2: 2 cells, header has 3" in log_error(inner)
    no_newline = read_log(write(tmp_path, "nonl.csv", GOOD + "0.03,1,0.03"))
    assert len(no_newline) == 4 and no_newline.notes == []


def test_u_and_f_together_says_u_is_used(tmp_path: Path) -> None:
    log = read_log(write(tmp_path, "both.csv", "t,u,F,v\n0,1,2,0\n0.01,1,2,0.01\n"))
    assert log.input_kind == "voltage"
    assert len(log.notes) == 1 and "using 'u'" in log.notes[0] and "'F' ignored" in log.notes[0]


def test_u_and_f_notice_is_one_line_on_stderr(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    p = write(tmp_path, "both.csv", "t,u,F\n0,1,2\n0.01,2,2\n0.02,3,2\n")
    out = tmp_path / "out.csv"
    code, _o, err = cli(["simulate", str(p), "--out", str(out)], capsys)
    assert code == 0
    assert [ln for ln in err.splitlines() if "using 'u'" in ln] == [
        f"note: {p}: both 'u' and 'F' present; using 'u' (voltage input), 'F' ignored"
    ]


def test_duty_times_vbat_column_or_option(tmp_path: Path) -> None:
    p = write(tmp_path, "duty.csv", "t,duty,vbat,v\n0,0.5,8,0\n0.01,-0.25,7.5,0.01\n")
    np.testing.assert_allclose(read_log(p)["u"], [4.0, -1.875])
    opt = read_log(p, vbat=7.0)
    np.testing.assert_allclose(opt["u"], [3.5, -1.75])
    assert any("--vbat" in n for n in opt.notes)
    q = write(tmp_path, "duty_only.csv", "t,duty,v\n0,0.5,0\n0.01,1,0.01\n")
    np.testing.assert_allclose(read_log(q, vbat=12.0)["u"], [6.0, 12.0])
    assert "needs the supply voltage" in log_error(q)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("t,duty,vbat,v\n0,1.5,8,0\n", "line 2: column 'duty' = 1.5 is beyond +-1"),
        ("t,duty,vbat,v\n0,0.5,8,0\n0.01,0.5,0,0\n", "line 3: column 'vbat' = 0"),
        ("t,duty,vbat,v\n0,0.5,-3,0\n", "line 2: column 'vbat' = -3"),
    ],
)
def test_duty_and_vbat_are_checked(tmp_path: Path, text: str, expected: str) -> None:
    assert expected in log_error(write(tmp_path, "d.csv", text))


def test_vbat_option_is_checked(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = write(tmp_path, "duty.csv", "t,duty,v\n0,0.5,0\n")
    for bad in ("inf", "0", "-7", "nan", "1e308", "x"):
        line = bad_input(
            ["identify", str(p), "--out", str(tmp_path / "m.yaml"), "--vbat", bad], capsys
        )
        assert ("--vbat" in line and "supply voltage" in line) or "not a number" in line


@pytest.mark.parametrize(
    ("cell", "expected"),
    [
        ("1e308", "column 'v' = 1e+308 is beyond +-1000 m/s"),
        ("-1e300", "column 'v' = -1e+300 is beyond"),
        ("inf", "column 'v': 'inf' is not finite"),
        ("nan", "column 'v': 'nan' is not finite"),
        ("1,5", "3 cells, header has 3"),
    ],
)
def test_absurd_values_exit_2_before_any_fit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], cell: str, expected: str
) -> None:
    text = f"t,u,v\n0,1,0\n0.01,1,{cell}\n0.02,1,0\n"
    if cell == "1,5":
        text = 't,u,v\n0,1,0\n0.01,1,"1,5",9\n'
        expected = "4 cells, header has 3"
    p = write(tmp_path, "big.csv", text)
    line = bad_input(["diagnose", str(p)], capsys)
    assert f"big.csv: line 3: {expected}" in line


# --- YAML ------------------------------------------------------------------------------


def _config_with(tmp_path: Path, extra: str, name: str = "c.yaml") -> Path:
    return write(tmp_path, name, default_config_path().read_text(encoding="utf-8") + extra)


def test_alias_bomb_is_refused_at_the_first_alias(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bomb = 'a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n'
    for k in range(1, 9):
        prev = chr(ord("a") + k - 1)
        cur = chr(ord("a") + k)
        bomb += f"{cur}: &{cur} [" + ",".join([f"*{prev}"] * 9) + "]\n"
    p = write(tmp_path, "bomb.yaml", "vehicle_id: x\n" + bomb)
    line = bad_input(["params", "--config", str(p)], capsys)
    assert "bomb.yaml:3:" in line and "alias '*a' is not allowed" in line
    assert len(line) < 200


def test_deep_nesting_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = write(tmp_path, "deep.yaml", "vehicle: " + "[" * 50000 + "]" * 50000 + "\n")
    line = bad_input(["params", "--config", str(p)], capsys)
    assert "deep.yaml:1:" in line and "nested deeper than 32 levels" in line
    m = write(
        tmp_path, "deep_model.yaml", "vehicle:\n" + "".join(" " * k + "a:\n" for k in range(1, 200))
    )
    with pytest.raises(InputError, match="nested deeper"):
        read_model(m)


def test_duplicate_key_names_key_and_both_lines(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    p = write(tmp_path, "dup.yaml", "vehicle_id: one\nruntime: {}\nvehicle_id: two\n")
    line = bad_input(["params", "--config", str(p)], capsys)
    assert "dup.yaml:3:1: key 'vehicle_id' given twice (first at line 1)" in line


def test_syntax_error_is_one_line_with_line_and_column(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    p = write(tmp_path, "syn.yaml", "vehicle:\n  R_m: 1\n   L_m: [2,\n")
    line = bad_input(["params", "--config", str(p)], capsys)
    assert line.startswith(f"truckd params: error: {p}:3:")
    assert "invalid YAML" in line


def test_exponent_without_dot_is_a_number(tmp_path: Path) -> None:
    """YAML 1.1 (PyYAML) reads ``1e-3`` and ``1.0e308`` as text; the loader reads them as
    numbers, so the range check names the key."""
    base = default_config_path().read_text(encoding="utf-8")
    assert "R_m:" in base
    for value in ("1.0e308", "1e308"):
        with pytest.raises(InputError) as err:
            parse_config(base.replace("R_m:", f"R_m: {value} #", 1), "c.yaml")
        assert "key 'vehicle.R_m' = 1e+308: expected a number in" in str(err.value)
    ok = parse_config(base.replace("R_m:", "R_m: 12e-2 #", 1), "c.yaml")
    assert ok.vehicle.R_m == 0.12


def test_quoted_number_says_it_was_read_as_text() -> None:
    base = default_config_path().read_text(encoding="utf-8")
    with pytest.raises(InputError) as err:
        parse_config(base.replace("R_m:", "R_m: '1.0e308' #", 1), "c.yaml")
    assert "key 'vehicle.R_m' = '1.0e308'" in str(err.value)
    assert "read as text" in str(err.value)


def test_huge_values_are_not_rendered(tmp_path: Path) -> None:
    base = default_config_path().read_text(encoding="utf-8")
    with pytest.raises(InputError) as err:
        parse_config(base.replace("R_m:", f"R_m: {'x' * 100000} #", 1), "c.yaml")
    assert len(str(err.value)) < 300
    with pytest.raises(InputError) as err:
        parse_config("q" * 100000 + ": 1\n", "c.yaml")
    assert len(str(err.value)) < 600


# --- command-line arguments and output paths ------------------------------------------


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["sim", "--duration", "1e308"], "expected a number of seconds in (0, 3600] (1 h)"),
        (["sim", "--duration", "-1"], "expected a number of seconds in (0, 3600]"),
        (["sim", "--duration", "1e-9"], "shorter than one control period (0.01 s at"),
        (["sim", "--duration", "nan"], "expected a number of seconds"),
        (
            ["sim", "--platoon", "100", "--scenario", "platoon-brake", "--duration", "200"],
            "20000 truck-seconds; expected at most 10800",
        ),
        (["sim", "--platoon", "4", "--seed", "-1"], "--seed: expected 0 or more"),
        (["sim", "--platoon", "3"], "--platoon 3: platoon-join needs at least 4 trucks (or run"),
        (
            ["sim", "--platoon", "4", "--duration", "0.5"],
            "--duration: a platoon run needs at least 1 s",
        ),
        (["monitor", "--interval", "inf"], "expected a number of seconds in (0, 3600]"),
        (["monitor", "--duration", "-1"], "expected a number of seconds in [0,"),
        (["run", "--config", "x.yaml", "--duration", "inf"], "expected a number of seconds"),
        (["sim", "--plot", "x.xyz"], "plot must end in one of .png, .svg, .pdf"),
        (["sim", "--plot", "out/"], "expected a file name for the plot, not a directory"),
        (["sim", "--plot", "."], "expected a file name for the plot"),
        (["sim", "--json", "nodir/x.json"], "directory 'nodir' does not exist"),
        (["sim", "--scenario", "nope"], "invalid choice"),
    ],
)
def test_bad_arguments_exit_2_with_one_line(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    argv: list[str],
    expected: str,
) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "out").mkdir()
    line = bad_input(argv, capsys)
    assert expected in line


def test_plot_into_a_directory_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    d = tmp_path / "out.png"
    d.mkdir()
    line = bad_input(["sim", "--plot", str(d)], capsys)
    assert "is a directory" in line
    assert list(d.iterdir()) == []


def test_diagnose_checks_every_output_before_the_fit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = write(tmp_path, "log.csv", GOOD)
    model = tmp_path / "m.yaml"
    line = bad_input(["diagnose", str(log), "--out", str(model), "--json", str(tmp_path)], capsys)
    assert "--json" in line and "is a directory" in line
    assert not model.exists()
    line = bad_input(["diagnose", str(log), "--out", str(model), "--json", str(model)], capsys)
    assert "given for both --out and --json" in line
    f = write(tmp_path, "afile", "x")
    line = bad_input(["diagnose", str(log), "--report", str(f / "sub")], capsys)
    assert "report directory" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "log.csv"]


def test_an_output_file_where_an_output_directory_writes_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--json`` on a file the ``--trace`` or ``--mcap`` directory writes (one would
    replace the other), or inside the ``--report`` directory (published whole): refused
    before any work; another kind of file beside a trace is fine."""
    trace = tmp_path / "trace"
    trace.mkdir()
    run = ["sim", "--scenario", "follow", "--duration", "1", "--trace", str(trace)]
    line = bad_input([*run, "--json", str(trace / "follow.csv")], capsys)
    assert "--trace holds the --json output" in line
    line = bad_input(
        ["sim", "--scenario", "all", "--mcap", str(trace), "--json", str(trace / "p.mcap")], capsys
    )
    assert "--mcap holds the --json output" in line
    assert list(trace.iterdir()) == []
    log = write(tmp_path, "log.csv", GOOD)
    (tmp_path / "rep").mkdir()
    line = bad_input(
        ["diagnose", str(log), "--report", str(tmp_path / "rep"), "--json",
         str(tmp_path / "rep" / "d.json")], capsys,
    )  # fmt: skip
    assert "--report holds the --json output" in line
    assert cli([*run, "--json", str(trace / "metrics.json")], capsys)[0] == 0
    assert sorted(p.name for p in trace.iterdir()) == ["follow.csv", "metrics.json"]
    both = tmp_path / "both"  # a trace and MCAP in one directory: each its own suffix
    assert cli([*run[:-1], str(both), "--mcap", str(both)], capsys)[0] == 0
    assert sorted(p.name for p in both.iterdir()) == ["follow.csv", "follow.mcap"]


def test_identify_and_simulate_check_out(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = write(tmp_path, "log.csv", GOOD)
    line = bad_input(["identify", str(log), "--out", str(tmp_path)], capsys)
    assert "is a directory" in line and "model file" in line
    line = bad_input(["simulate", str(log), "--out", str(tmp_path) + "/"], capsys)
    assert "not a directory" in line


@pytest.mark.parametrize("target", ["/dev/zero", "."])
def test_zenoh_config_must_be_a_regular_file(
    capsys: pytest.CaptureFixture[str], target: str
) -> None:
    """``/dev/zero`` as the Zenoh file hung the monitor (zenoh read it forever)."""
    line = bad_input(["monitor", "--zenoh-config", target, "--duration", "0"], capsys)
    assert f"{target}: " in line and "Zenoh configuration file" in line


def test_an_unforeseen_exception_is_one_line_exit_1(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Not a traceback (a firmware core that cannot be built, a full disk on stdout, a
    bug): one line naming the command and the exception, exit 1; TRUCKD_DEBUG lets the
    traceback through."""
    import truckd.cli.params as cli_params
    from truckd.cli.main import main

    def run(_args: object) -> int:
        raise RuntimeError("gcc: not found")

    monkeypatch.setattr(cli_params, "run", run)
    monkeypatch.delenv("TRUCKD_DEBUG", raising=False)
    assert main(["params"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "truckd params: failed: RuntimeError: gcc: not found" in err
    monkeypatch.setenv("TRUCKD_DEBUG", "1")
    with pytest.raises(RuntimeError):
        main(["params"])


def test_a_closed_output_pipe_is_quiet() -> None:
    """`truckd params --json | head -c0`: the reader is gone before anything is written."""
    import os
    import subprocess
    import sys

    r, w = os.pipe()
    os.close(r)  # every write to w fails with EPIPE
    try:
        p = subprocess.run(
            [sys.executable, "-m", "truckd.cli.main", "params", "--json"],
            stdout=w,
            stderr=subprocess.PIPE,
            timeout=120,
            check=False,
        )
    finally:
        os.close(w)
    assert p.returncode == 1
    assert p.stderr == b""


@pytest.mark.parametrize(
    ("overrides", "says"),
    [
        ({"vehicle": {"J_S": 1e-300}}, "mechanical time constant"),
        ({"vehicle": {"R_m": 1e-300}}, "electrical time constant"),
        ({"vehicle": {"L_m": 1e-12}}, "electrical time constant"),
        ({"vehicle": {"n_g": 1e-300}}, "no-load speed"),
        ({"vehicle": {"r_w": 1e-300}}, "no-load speed"),
        ({"vehicle": {"K_v": 1e-300}}, "mechanical time constant"),
        ({"control": {"v_set": 0.0}}, "control.v_set"),
        ({"control": {"estimator": {"range_min": 10.0}}}, "range_min (10.0) must be below"),
    ],
)
def test_values_each_allowed_but_not_a_machine_together_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], overrides: dict[str, Any], says: str
) -> None:
    """Each value passed its own positive check; together they made the controller's
    Riccati equation overflow, the plant NaN, the scenarios refuse to build, or no range
    reading a target (a collision): the configuration is refused, naming what is wrong."""
    from runtime_support import write_config

    cfg = write_config(tmp_path / "truck.yaml", overrides)
    line = bad_input(
        ["sim", "--scenario", "follow", "--duration", "1", "--config", str(cfg)], capsys
    )
    assert "truck.yaml" in line and says in line


def test_outputs_over_an_input_or_each_other_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = write(tmp_path, "run.csv", GOOD)
    line = bad_input(["simulate", str(log), "--out", str(log)], capsys)
    assert "run.csv" in line and "--out" in line
    assert log.read_text() == GOOD  # the measured log is untouched
    same = tmp_path / "d.json"
    line = bad_input(["diagnose", str(log), "--json", str(same), "--report", str(same)], capsys)
    assert "--json" in line and "--report" in line
    assert not same.exists()


def test_an_output_where_nothing_can_be_created_is_refused_before_any_work() -> None:
    """/proc takes no new file, whoever asks (root passes a permission check there): an
    output file or directory in it is refused when the arguments are read."""
    from truckd.outputs import check_output_dir, check_output_file

    with pytest.raises(InputError, match="not writable"):
        check_output_file("/proc/truckd-out.json", "JSON output")
    with pytest.raises(InputError, match="not writable"):
        check_output_dir("/proc/truckd-report", "report directory")


def test_plan_delay_reads_exponents_and_refuses_underscores() -> None:
    """``--plan-delay``: a dash inside an exponent is no range (``1e-2`` is 10 ms), a
    range may use exponents, and ``1_0`` (which float() reads as 10) is refused."""
    from truckd.cli.sim_platoon import parse_delay

    assert parse_delay("1e-2") == (0.01, 0.01)
    assert parse_delay("1e-3-2e-2") == (0.001, 0.02)
    assert parse_delay("0-0.05") == (0.0, 0.05)
    for bad in ("1_0", "0.05-0.01", "-1", "a-b"):
        with pytest.raises(InputError, match="--plan-delay"):
            parse_delay(bad)


def test_a_run_stopped_before_its_outputs_leaves_no_trace_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The trace directory is checked when the arguments are read and created only when
    the traces are written: Ctrl-C during the run leaves nothing behind."""
    import truckd.cli.sim as cli_sim

    def interrupted(*_args: Any, **_kwargs: Any) -> Any:
        raise KeyboardInterrupt

    monkeypatch.setattr(cli_sim, "run_scenario", interrupted)
    trace = tmp_path / "new" / "trace"
    code, _out, _err = cli(["sim", "--scenario", "follow", "--trace", str(trace)], capsys)
    assert code == 130 and not (tmp_path / "new").exists()

"""Property-based fuzz of the CSV reader, the configuration and model loaders
and the command-line parsing.  Whatever the input: the result is a value or one
:class:`InputError` line (exit 2), never another exception, never a traceback.  Time is
bounded by a fixed number of examples; memory by running the bombs in a child process
under RLIMIT_AS."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import pytest
from cli_support import assert_one_line, run_limited
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import truckd.cli.main as cli_main
from truckd.config.truck import default_config_path, parse_config
from truckd.errors import InputError
from truckd.logfile import read_log, require_io
from truckd.modelfile import read_model

FUZZ = settings(
    max_examples=150,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
    derandomize=True,
)

CELLS = st.one_of(
    st.sampled_from(
        ["0", "1", "-1", "0.01", "1e308", "-1e308", "inf", "nan", "", " ", "x", '"1,2"', "1e-320"]
    ),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.text(alphabet='0123456789.,-+eE "\n\r\t\ufeffab\x00', max_size=8),
)
NAMES = st.sampled_from(["t", "u", "v", "i", "x", "F", "duty", "vbat", "gap", "note", "", " t"])


@st.composite
def csv_bytes(draw: st.DrawFn) -> bytes:
    """A CSV-like log: a header of known and unknown names, rows of odd cells, and now
    and then raw bytes or a byte-order mark."""
    names = draw(st.lists(NAMES, min_size=0, max_size=6))
    rows = draw(st.lists(st.lists(CELLS, max_size=7), max_size=8))
    text = ",".join(names) + "\n" + "".join(",".join(r) + "\n" for r in rows)
    data = text.encode("utf-8", "surrogatepass")
    if draw(st.booleans()):
        data = b"\xef\xbb\xbf" + data
    if draw(st.integers(0, 4)) == 0:
        data += draw(st.binary(max_size=16))
    return data


def one_line_error(exc: InputError) -> None:
    msg = str(exc)
    assert msg and "\n" not in msg and len(msg) < 400, msg


@pytest.fixture(scope="module")
def scratch(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


@FUZZ
@given(data=csv_bytes(), vbat=st.one_of(st.none(), st.floats(0.5, 24)))
def test_csv_reader_returns_a_log_or_one_line(
    scratch: Path, data: bytes, vbat: float | None
) -> None:
    p = scratch / "log.csv"
    p.write_bytes(data)
    try:
        log = read_log(p, vbat=vbat)
        require_io(log)
    except InputError as exc:
        one_line_error(exc)
        return
    assert len(log) >= 1
    assert all(len(c) == len(log) for c in log.columns.values())
    for name in ("t", "u", "v"):
        if name in log:
            assert all(abs(x) <= 1e10 for x in log[name])


BASE = default_config_path().read_text(encoding="utf-8").splitlines()
YAML_BITS = st.one_of(
    st.sampled_from(
        [
            "&a",
            "*a",
            "[",
            "]",
            "{",
            "}",
            ":",
            "- ",
            "!!python/object:os.system",
            "1.0e308",
            "1e308",
            "'1.0'",
            ".inf",
            "~",
            "<<: {x: 1}",
            "? a",
            "|",
            "\t",
            "%YAML 1.1",
            "---",
            "vehicle_id: x",
            "R_m: 1",
            "\ufeff",
            "\x85",
            "\\",
            '"',
            "#",
        ]
    ),
    st.text(alphabet="abc01.:-[]{}&*!|>'\"\n #,?", max_size=12),
)


@st.composite
def yaml_texts(draw: st.DrawFn) -> str:
    """The shipped configuration with a few lines cut, duplicated or spliced with YAML
    syntax, or a short text of YAML punctuation."""
    if draw(st.booleans()):
        return "".join(draw(st.lists(YAML_BITS, max_size=12)))
    lines = list(BASE)
    for _ in range(draw(st.integers(1, 4))):
        k = draw(st.integers(0, len(lines) - 1))
        op = draw(st.sampled_from(["cut", "dup", "splice", "indent"]))
        if op == "cut":
            del lines[k]
        elif op == "dup":
            lines.insert(k, lines[k])
        elif op == "indent":
            lines[k] = " " + lines[k]
        else:
            pos = draw(st.integers(0, len(lines[k])))
            lines[k] = lines[k][:pos] + draw(YAML_BITS) + lines[k][pos:]
        if not lines:
            break
    return "\n".join(lines) + "\n"


@FUZZ
@given(text=yaml_texts())
def test_config_loader_returns_a_config_or_one_line(text: str) -> None:
    try:
        parse_config(text, "fuzz.yaml")
    except InputError as exc:
        one_line_error(exc)


MODEL = (
    "vehicle: {R_m: 2.0, L_m: 0.001, K_v: 0.01, K_T: 0.01, J_S: 1.0e-6, n_g: 3.0, n_fd: 3.0, "
    "r_w: 0.04, m: 3.0, K_coulomb: 0.001, K_stiction: 0.002}\neffects: {}\nsource: fuzz\n"
)


@FUZZ
@given(
    pos=st.integers(0, len(MODEL)),
    junk=st.one_of(YAML_BITS.map(lambda s: s.encode("utf-8")), st.binary(max_size=6)),
)
def test_model_loader_returns_a_model_or_one_line(scratch: Path, pos: int, junk: bytes) -> None:
    raw = MODEL.encode()
    p = scratch / "model.yaml"
    p.write_bytes(raw[:pos] + junk + raw[pos:])
    try:
        read_model(p)
    except InputError as exc:
        one_line_error(exc)


COMMANDS = ["sim", "monitor", "run", "params", "simulate", "identify", "diagnose", "nope", ""]
OPTIONS = [
    "--duration",
    "--interval",
    "--plot",
    "--json",
    "--out",
    "--report",
    "--vbat",
    "--config",
    "--scenario",
    "--model",
    "--backend",
    "--connect",
    "--realtime",
    "--validate",
    "-h",
    "--x",
]
VALUES = st.one_of(
    st.sampled_from(
        [
            "1",
            "0",
            "-1",
            "1e308",
            "inf",
            "nan",
            "x.png",
            "x.xyz",
            "out/",
            ".",
            "",
            "/dev/null",
            "follow",
            "all",
            "sim",
            "log.csv",
            "m.yaml",
            "j.json",
            "rep",
            "1_0",
            "0x10",
        ]
    ),
    st.text(alphabet="abc0123456789./-_e", max_size=10),
)


@contextlib.contextmanager
def parse_only() -> Iterator[list[str]]:
    """Every subcommand's run() replaced by a stub: parsing alone decides the exit code."""
    called: list[str] = []
    with pytest.MonkeyPatch.context() as mp:
        for module in cli_main.SUBCOMMANDS.values():
            mod = __import__(module, fromlist=["run"])
            mp.setattr(mod, "run", lambda args, _m=module: called.append(_m) or 0)
        yield called


@settings(FUZZ, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    command=st.sampled_from(COMMANDS),
    args=st.lists(st.one_of(st.sampled_from(OPTIONS), VALUES), max_size=6),
)
def test_cli_parsing_exits_0_or_2_with_one_line(
    scratch: Path, capsys: pytest.CaptureFixture[str], command: str, args: list[str]
) -> None:
    argv = [command, *args] if command else args
    with pytest.MonkeyPatch.context() as mp, parse_only():
        mp.chdir(scratch)
        capsys.readouterr()
        code = cli_main.main(argv)
        _out, err = capsys.readouterr()
    assert code in (0, 2)
    if code == 2:
        assert_one_line(err)
    else:
        assert err == ""


BOMBS = {
    "alias.yaml": "a: &a [x, x, x, x, x, x, x, x, x]\n"
    + "".join(
        f"{chr(98 + k)}: &{chr(98 + k)} [{', '.join([f'*{chr(97 + k)}'] * 9)}]\n" for k in range(12)
    ),
    "deep.yaml": "vehicle: " + "[" * 200_000 + "]" * 200_000 + "\n",
    "deepmap.yaml": "".join(" " * k + f"k{k}:\n" for k in range(3000)),
    "wide.yaml": "vehicle_id: '" + "x" * 900_000 + "'\nvehicle_id: y\n",
}


@pytest.mark.parametrize("name", sorted(BOMBS))
def test_yaml_bombs_are_refused_in_bounded_memory(tmp_path: Path, name: str) -> None:
    (tmp_path / name).write_text(BOMBS[name])
    r = run_limited(["params", "--config", name], tmp_path, address_space=2 * 1024**3, cpu_s=60)
    line = assert_one_line(r.stderr)
    assert r.returncode == 2, r.stderr
    assert line.startswith(f"truckd params: error: {name}:") and len(line) < 300

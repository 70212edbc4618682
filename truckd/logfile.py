"""The log format (reference section 3): CSV, one header row, columns by name.

``t`` (s, strictly increasing), ``u`` (V), ``v`` (m/s); optional ``i``, ``x``, ``gap``,
``v_lead``, ``vbat``; force-input logs carry ``F`` (N) instead of ``u`` and may carry
``x`` instead of ``v``; a duty-cycle log carries ``duty`` (-1..1) instead of ``u``, with
``vbat`` or ``--vbat V``: u = duty * vbat.  Columns the reader does not know are kept
(numeric ones as arrays, text ones as strings) and ignored.  A UTF-8 byte-order mark is
accepted.  Errors name the file and line; docs/inputs.md lists every rule and limit.
"""

from __future__ import annotations

import csv
import math
import os
from array import array
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np
from numpy.typing import NDArray

from truckd.errors import InputError
from truckd.inputs import open_regular
from truckd.outputs import atomic_text

KNOWN_COLUMNS = ("t", "u", "v", "i", "x", "gap", "v_lead", "vbat", "F", "duty")
NAN_ALLOWED = ("gap", "v_lead")
"""Optional columns where NaN means "no lead tracked" (the daemon's own logs)."""

MAX_LOG_BYTES = 128 * 1024 * 1024
"""Largest log read (about 2.5 h at 100 Hz, eight full-precision columns; the daemon
rotates its logs at 20 MB)."""

MAX_ROWS = 5_000_000
"""Most data rows read (short rows); past it the reader stops with an error."""

# Largest magnitude accepted per known column, with its unit.  Far beyond a 1:14 truck
# (a few m/s, 12 V, tens of A) yet small enough that squares and products of them stay
# finite in float64: a value past these is a unit or export error, not a measurement.
BOUNDS: dict[str, tuple[float, str]] = {
    "t": (1e10, "s"),  # Unix time in seconds fits (year 2286)
    "u": (1e3, "V"),
    "v": (1e3, "m/s"),
    "i": (1e4, "A"),
    "x": (1e8, "m"),
    "gap": (1e6, "m"),
    "v_lead": (1e3, "m/s"),
    "vbat": (1e3, "V"),
    "F": (1e6, "N"),
    "duty": (1.0, "(fraction of the supply)"),
}


@dataclass
class Log:
    """A log's columns as float arrays keyed by name, in file order.

    Columns the reader does not know are in ``columns`` too when every cell is a number
    or empty (NaN); ``text_columns`` names the others (text, ignored).  ``notes`` are
    one-line remarks for the user (e.g. which of ``u`` and ``F`` is used).
    """

    columns: dict[str, NDArray[np.float64]]
    source: str = "<memory>"
    text_columns: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    position_unit: str = "m"
    """The unit of ``x`` (``m``; ``rad`` for a rotational SysId log, whose ``v`` is then
    rad/s)."""

    def __getitem__(self, name: str) -> NDArray[np.float64]:
        return self.columns[name]

    def __contains__(self, name: object) -> bool:
        return name in self.columns

    def __len__(self) -> int:
        return len(self.columns["t"]) if "t" in self.columns else 0

    @property
    def input_kind(self) -> str:
        """``"voltage"`` (has ``u``) or ``"force"`` (has ``F``)."""
        return "voltage" if "u" in self.columns else "force"


def _number(src: str, lineno: int, name: str, cell: str) -> float:
    """A known column's cell as a float within :data:`BOUNDS`."""
    text = cell.strip()
    bound, unit = BOUNDS[name]
    if not text:
        raise InputError(f"{src}: line {lineno}: column '{name}' is empty; expected a number")
    try:
        val = float(text)
    except ValueError:
        raise InputError(
            f"{src}: line {lineno}: column '{name}': {_clip(text)!r} is not a number"
        ) from None
    if math.isnan(val) and name in NAN_ALLOWED:
        return val  # no lead tracked in this sample
    if not math.isfinite(val):
        raise InputError(
            f"{src}: line {lineno}: column '{name}': {_clip(text)!r} is not finite; "
            "expected a measured value"
        )
    if abs(val) > bound:
        raise InputError(
            f"{src}: line {lineno}: column '{name}' = {val:.6g} is beyond +-{bound:g} {unit}; "
            "expected a measured value (a unit or export error?)"
        )
    return val


def _clip(text: str, limit: int = 40) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _extra(cell: str) -> float | None:
    """An unknown column's cell as a float (empty: NaN), or None if it is text."""
    c = cell.strip()
    if not c:
        return math.nan
    try:
        return float(c)
    except ValueError:
        return None


BLOCK_BYTES = 1 << 20
"""The reader decodes and parses a log this many bytes at a time (memory: the parsed
columns, not the text)."""


def read_log(path: str | Path, require: Sequence[str] = ("t",), vbat: float | None = None) -> Log:
    """Read and validate a log.

    ``require`` names the columns that must be present (``u`` is satisfied by ``duty``
    with a supply voltage).  ``vbat`` (V, the ``--vbat`` option) is the supply for a
    ``duty`` column; it takes precedence over a ``vbat`` column.  Raises
    :class:`InputError` naming the file and line of the first problem.  The file is read
    in blocks: memory holds the parsed columns (8 bytes per value), not the text.
    """
    (log,) = read_log_windows(path, require, vbat)
    return log


def read_log_windows(
    path: str | Path,
    require: Sequence[str] = ("t",),
    vbat: float | None = None,
    max_rows: int | None = None,
    windows: int = 8,
) -> list[Log]:
    """:func:`read_log`, keeping at most about ``max_rows`` rows of a longer log: then
    ``windows`` contiguous stretches of ``max_rows // windows`` rows, evenly spread over
    it, each a :class:`Log` of its own (a separate run; a note says so).  Every row is
    still read and checked (one pass, memory for the rows kept only)."""
    src = os.fspath(path)
    fd = open_regular(path, "CSV log", MAX_LOG_BYTES)
    try:
        with os.fdopen(fd, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            if size > MAX_LOG_BYTES:
                raise InputError(
                    f"{src}: more than the limit of {MAX_LOG_BYTES >> 20} MiB for a log"
                )
            ends_cut = False
            spans: list[tuple[int, int]] | None = None
            if size:
                fh.seek(size - 1)
                ends_cut = fh.read(1) not in (b"\n", b"\r")
                fh.seek(0)
            if max_rows is not None and size:
                rows = _count_lines(fh) - 1  # about the data rows (blank lines aside)
                fh.seek(0)
                if rows > max_rows:
                    spans = _spans(rows, max_rows, windows)
            return _parse(_stream_lines(fh, src), src, require, vbat, ends_cut, spans)
    except OSError as exc:
        raise InputError(f"{src}: cannot read the log: {exc.strerror}") from None


def _count_lines(fh: BinaryIO) -> int:
    n, last = 0, b""
    while block := fh.read(BLOCK_BYTES):
        n += block.count(b"\n")
        last = block[-1:]
    return n + (1 if last and last != b"\n" else 0)


def _spans(rows: int, keep: int, windows: int) -> list[tuple[int, int]]:
    """``windows`` data-row ranges ``[a, b)`` of ``keep // windows`` rows evenly spread
    over ``rows`` rows (the first at the start, the last at the end)."""
    size = max(1, keep // max(1, windows))
    starts = np.linspace(0, max(0, rows - size), max(1, windows)).astype(int)
    return [(int(a), int(a) + size) for a in starts]


def _stream_lines(fh: BinaryIO, src: str) -> Iterator[str]:
    """The lines of a UTF-8 file (a leading BOM dropped), decoded a block at a time; a
    byte that is not UTF-8 is an InputError naming its line and offset."""
    rest = b""
    offset = 0  # of rest[0] in the file
    line = 1  # of rest[0]
    first = True
    while True:
        block = fh.read(BLOCK_BYTES)
        data = rest + block
        if block:
            cut = data.rfind(b"\n") + 1  # UTF-8 never has 0x0a inside a character
            if cut == 0:
                rest = data
                continue
            part, rest = data[:cut], data[cut:]
        else:
            part, rest = data, b""
        if not part:
            return
        try:
            text = part.decode("utf-8-sig" if first else "utf-8")
        except UnicodeDecodeError as exc:
            at = line + part.count(b"\n", 0, exc.start)
            raise InputError(
                f"{src}: line {at}: byte 0x{part[exc.start]:02x} at offset {offset + exc.start} "
                "is not UTF-8; expected a UTF-8 text CSV log"
                + (
                    " (a .wpilog is a binary WPILib DataLog: give SysId's JSON export)"
                    if str(src).lower().endswith(".wpilog")
                    else ""
                )
            ) from None
        first = False
        offset += len(part)
        line += part.count(b"\n")
        yield from _lines(text)
        if not block:
            return


def _parse(
    text_lines: Iterable[str],
    src: str,
    require: Sequence[str],
    vbat: float | None,
    ends_cut: bool,
    spans: Sequence[tuple[int, int]] | None = None,
) -> list[Log]:
    """The logs of one CSV text, one per stretch of rows in ``spans`` (the whole text when
    None), columns mapped by name, every refused value named with its line
    (:class:`InputError`); ``ends_cut``: the last row may be cut short (a log still written).

    Long because the header checks, the column map and the row loop share the line
    number and the notes: one pass over the text, each refusal naming its line."""
    reader = csv.reader(text_lines)
    notes: list[str] = []
    try:
        header = next(reader, None)
        if header is None:
            raise InputError(f"{src}: empty file, expected a CSV header row")
        names = [h.strip() for h in header]
        if not any(names):
            raise InputError(f"{src}: line 1: the header row is empty; expected column names")
        known: dict[str, int] = {}
        extra: dict[str, int] = {}
        for k, n in enumerate(names):
            if n in KNOWN_COLUMNS:
                if n in known:
                    raise InputError(f"{src}: line 1: column '{n}' appears twice")
                known[n] = k
            elif n and n not in extra:
                extra[n] = k
        _check_header(src, names, known, require, vbat)
        parts = [_Part(known, extra) for _ in spans or [(0, MAX_ROWS + 1)]]
        bounds = list(spans or [(0, MAX_ROWS + 1)])
        texts: set[str] = set()  # unknown columns seen holding text
        w = 0  # the window rows go to
        rows = 0  # data rows so far
        t_prev = -math.inf
        t_col = known.get("t")
        empty_rows: list[int] = []
        cut: tuple[int, int] | None = None  # a short last line without a newline
        for row in reader:
            lineno = reader.line_num
            if cut is not None:
                raise InputError(f"{src}: line {cut[0]}: {cut[1]} cells, header has {len(names)}")
            if not row:
                continue  # a blank line
            if all(not c.strip() for c in row):
                empty_rows.append(lineno)
                continue
            if empty_rows:
                raise InputError(
                    f"{src}: line {empty_rows[0]}: every cell is empty; expected numbers "
                    "(a lost sample? delete or fill the row)"
                )
            if len(row) < len(names) and ends_cut:
                cut = (lineno, len(row))  # refused above unless it is the last line
                continue
            if len(row) != len(names):
                raise InputError(f"{src}: line {lineno}: {len(row)} cells, header has {len(names)}")
            if rows >= MAX_ROWS:
                raise InputError(
                    f"{src}: line {lineno}: more than {MAX_ROWS} data rows, the limit for a log"
                )
            values = {n: _number(src, lineno, n, row[k]) for n, k in known.items()}
            if t_col is not None:
                t = values["t"]
                if not t > t_prev:
                    raise InputError(
                        f"{src}: line {lineno}: time t={t!r} does not increase "
                        f"(previous {t_prev!r}); t must be strictly increasing"
                    )
                t_prev = t
            while w < len(bounds) - 1 and rows >= bounds[w][1]:
                w += 1
            a, b = bounds[w]
            if a <= rows < b:
                parts[w].add(values, row, lineno, texts)
            else:
                for n, k in extra.items():
                    if n not in texts and _extra(row[k]) is None:
                        texts.add(n)
            rows += 1
    except csv.Error as exc:
        raise InputError(f"{src}: line {reader.line_num}: {_clip(str(exc), 80)}") from None
    if not rows:
        raise InputError(f"{src}: no data rows after the header")
    if cut is not None:
        notes.append(
            f"{src}: line {cut[0]}: the last line is cut short ({cut[1]} of {len(names)} cells, "
            "no newline at the end: a log whose writer stopped); skipped"
        )
    if empty_rows:
        span = (
            f"line {empty_rows[0]}"
            if len(empty_rows) == 1
            else (f"lines {empty_rows[0]}-{empty_rows[-1]}")
        )
        notes.append(f"{src}: skipped {len(empty_rows)} empty row(s) at the end ({span})")
    kept = [p for p in parts if p.lines]
    if spans is not None:
        size = spans[0][1] - spans[0][0]
        notes.append(
            f"{src}: {rows} data rows; read whole, diagnosed on {len(kept)} stretches of "
            f"{size} rows evenly spread over it (each a run)"
        )
    logs = []
    for k, part in enumerate(kept):
        cols = part.columns(names, texts)
        lines = part.lines
        _derive_u(src, cols, lines, vbat, notes if k == 0 else [])
        if "u" in cols and "F" in cols and k == 0:
            notes.append(f"{src}: both 'u' and 'F' present; using 'u' (voltage input), 'F' ignored")
        name = src if spans is None else f"{src} (lines {lines[0]}-{lines[-1]})"
        text_cols = list(dict.fromkeys(n for n in names if n in texts))
        logs.append(Log(cols, name, text_cols, notes if k == 0 else []))
    return logs


class _Part:
    """The rows of one stretch of a log, as columns (array of doubles)."""

    def __init__(self, known: Mapping[str, int], extra: Mapping[str, int]) -> None:
        self.extra = extra
        self.vals = {n: array("d") for n in known}
        self.nums: dict[str, array[float]] = {n: array("d") for n in extra}
        self.lines: array[int] = array("q")

    def add(
        self, values: Mapping[str, float], row: Sequence[str], lineno: int, texts: set[str]
    ) -> None:
        for n, x in values.items():
            self.vals[n].append(x)
        for n, k in self.extra.items():
            if n in texts:
                continue
            y = _extra(row[k])
            if y is None:
                texts.add(n)  # a text column: ignored from here on
            else:
                self.nums[n].append(y)
        self.lines.append(lineno)

    def columns(self, names: Sequence[str], texts: set[str]) -> dict[str, NDArray[np.float64]]:
        cols: dict[str, NDArray[np.float64]] = {}
        for n in names:
            if n in self.vals and n not in cols:
                cols[n] = np.frombuffer(self.vals[n], dtype=float).copy()
            elif n in self.nums and n not in cols and n not in texts:
                cols[n] = np.frombuffer(self.nums[n], dtype=float).copy()
        return cols


def _lines(text: str) -> Iterator[str]:
    """The lines of ``text`` with their endings, one at a time (no copy of the whole)."""
    start, n = 0, len(text)
    while start < n:
        end = text.find("\n", start)
        if end < 0:
            yield text[start:]
            return
        yield text[start : end + 1]
        start = end + 1


def _check_header(
    src: str,
    names: list[str],
    known: Mapping[str, int],
    require: Sequence[str],
    vbat: float | None,
) -> None:
    for col in require:
        if col in known:
            continue
        if col == "u" and "duty" in known and ("vbat" in known or vbat is not None):
            continue
        if col == "u" and "duty" in known:
            raise InputError(
                f"{src}: line 1: column 'duty' needs the supply voltage: a 'vbat' column "
                "or --vbat V"
            )
        listed = _clip(", ".join(names), 80)
        raise InputError(
            f"{src}: line 1: missing column '{col}' (header has: {listed}){_hint(col, names)}"
        )


_ALIASES = {
    "t": ("time", "timestamp", "time_s"),
    "u": ("voltage", "volts", "voltage_v"),
    "v": ("velocity", "speed", "velocity_m_s"),
}
"""Names other tools give the required columns (said as a hint, never read as them)."""


def _hint(col: str, names: Sequence[str]) -> str:
    """What a header that lacks ``col`` looks like it is (a wrong separator, a name in
    another case or with its unit, a WPILib DataLog export), or ''."""
    if len(names) == 1 and (";" in names[0] or "\t" in names[0]):
        sep = "';'" if ";" in names[0] else "tabs"
        return f"; the file looks separated by {sep}: expected commas"
    if {n.lower() for n in names} >= {"timestamp", "name", "value"}:
        return (
            "; a WPILib DataLog export (one row per entry): give the SysId JSON, or a CSV "
            "with one row per sample and columns t, u, v"
        )
    alike = {col.lower(), *_ALIASES.get(col, ())}
    near = [n for n in names if n.split("[")[0].split("(")[0].strip().lower() in alike]
    if near:
        return f"; did you mean {near[0]!r}? columns are named exactly {col!r} (SI, no unit)"
    return ""


def _derive_u(
    src: str,
    cols: dict[str, NDArray[np.float64]],
    lines: Sequence[int],
    vbat: float | None,
    notes: list[str],
) -> None:
    """u = duty * vbat for a duty-cycle log (reference section 3)."""
    if vbat is not None and not (math.isfinite(vbat) and 0 < vbat <= BOUNDS["vbat"][0]):
        raise InputError(f"--vbat {vbat!r}: expected a supply voltage in (0, 1000] V")
    if "duty" not in cols:
        if vbat is not None:
            notes.append(f"{src}: the log has no 'duty' column; --vbat is not used")
        return
    if "u" in cols:
        notes.append(f"{src}: both 'u' and 'duty' present; using 'u', 'duty' ignored")
        return
    if vbat is not None:
        supply = np.full_like(cols["duty"], vbat)
        if "vbat" in cols:
            notes.append(f"{src}: u = duty * {vbat:g} V from --vbat; the 'vbat' column is not used")
    elif "vbat" in cols:
        supply = cols["vbat"]
        bad = np.flatnonzero(~(supply > 0))
        if bad.size:
            k = int(bad[0])
            raise InputError(
                f"{src}: line {lines[k]}: column 'vbat' = {float(supply[k]):g}; expected a "
                "supply voltage > 0 V to convert 'duty' (or give --vbat V)"
            )
    else:
        raise InputError(
            f"{src}: line 1: column 'duty' needs the supply voltage: a 'vbat' column or --vbat V"
        )
    cols["u"] = cols["duty"] * supply


def require_io(log: Log) -> None:
    """Check the log has an input and an output column (the contract's minimum)."""
    if "u" not in log and "F" not in log:
        raise InputError(
            f"{log.source}: line 1: missing column 'u' (or 'F' for force input, or 'duty' "
            "with 'vbat')"
        )
    if "u" in log and "v" not in log:
        raise InputError(f"{log.source}: line 1: missing column 'v' (measured speed, m/s)")
    if "F" in log and "u" not in log and "v" not in log and "x" not in log:
        raise InputError(f"{log.source}: line 1: missing column 'v' or 'x' for a force log")


def write_log(path: str | Path, columns: Mapping[str, Iterable[float]]) -> None:
    """Write columns (equal length) as CSV with full float precision, all or nothing."""
    names = list(columns)
    arrays = [
        np.asarray(
            list(columns[n]) if not isinstance(columns[n], np.ndarray) else columns[n], dtype=float
        )
        for n in names
    ]
    n = len(arrays[0]) if arrays else 0
    if any(len(a) != n for a in arrays):
        raise ValueError("columns must have equal length")
    with atomic_text(path) as fh:
        w = csv.writer(fh)
        w.writerow(names)
        for k in range(n):
            w.writerow([repr(float(a[k])) for a in arrays])

"""The log format (CONTRACTS.md section 3): CSV, one header row, columns by name.

``t`` (s, strictly increasing), ``u`` (V), ``v`` (m/s); optional ``i``, ``x``, ``gap``,
``v_lead``, ``vbat``; force-input logs carry ``F`` (N) instead of ``u`` and may carry
``x`` instead of ``v``.  Extra columns are kept.  Errors name the file and line.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from truckd.errors import InputError

KNOWN_COLUMNS = ("t", "u", "v", "i", "x", "gap", "v_lead", "vbat", "F")
NAN_ALLOWED = ("gap", "v_lead")
"""Optional columns where NaN means "no lead tracked" (the daemon's own logs)."""


@dataclass
class Log:
    """A log's columns as float arrays keyed by name, in file order."""

    columns: dict[str, NDArray[np.float64]]
    source: str = "<memory>"

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


def read_log(path: str | Path, require: Sequence[str] = ("t",)) -> Log:
    """Read and validate a log.

    Besides ``t``, a log needs an input (``u`` or ``F``) and an output (``v``, or ``x`` for
    force-input logs) unless ``require`` says otherwise.  Raises :class:`InputError`
    naming the file and line of the first problem.
    """
    src = str(path)
    try:
        fh = open(path, newline="", encoding="utf-8")  # noqa: SIM115 - closed below
    except OSError as exc:
        raise InputError(f"{src}: cannot read log: {exc.strerror}") from None
    with fh:
        reader = csv.reader(fh)
        try:
            header = next(reader)
        except StopIteration:
            raise InputError(f"{src}: empty file, expected a CSV header row") from None
        except csv.Error as exc:
            raise InputError(f"{src}: line 1: {exc}") from None
        names = [h.strip() for h in header]
        if len(set(names)) != len(names):
            dup = next(n for n in names if names.count(n) > 1)
            raise InputError(f"{src}: line 1: column '{dup}' appears twice")
        for col in require:
            if col not in names:
                raise InputError(
                    f"{src}: line 1: missing column '{col}' (header has: {', '.join(names)})"
                )
        rows: list[list[float]] = []
        lines: list[int] = []
        try:
            for row in reader:
                lineno = reader.line_num
                if not row or all(not c.strip() for c in row):
                    continue
                if len(row) != len(names):
                    raise InputError(
                        f"{src}: line {lineno}: {len(row)} cells, header has {len(names)}"
                    )
                vals = []
                for name, cell in zip(names, row, strict=True):
                    try:
                        val = float(cell)
                    except ValueError:
                        raise InputError(
                            f"{src}: line {lineno}: column '{name}': {cell!r} is not a number"
                        ) from None
                    if (
                        name in KNOWN_COLUMNS
                        and not math.isfinite(val)
                        and not (name in NAN_ALLOWED and math.isnan(val))
                    ):
                        raise InputError(
                            f"{src}: line {lineno}: column '{name}': {cell!r} is not finite"
                        )
                    vals.append(val)
                rows.append(vals)
                lines.append(lineno)
        except csv.Error as exc:
            raise InputError(f"{src}: line {reader.line_num}: {exc}") from None
    if not rows:
        raise InputError(f"{src}: no data rows after the header")
    data = np.array(rows, dtype=float)
    cols = {n: data[:, k].copy() for k, n in enumerate(names)}
    if "t" in cols:
        dt = np.diff(cols["t"])
        bad = np.flatnonzero(~(dt > 0))
        if bad.size:
            k = int(bad[0]) + 1
            raise InputError(
                f"{src}: line {lines[k]}: time t={float(cols['t'][k])!r} does not increase "
                f"(previous {float(cols['t'][k - 1])!r}); t must be strictly increasing"
            )
    return Log(cols, src)


def require_io(log: Log) -> None:
    """Check the log has an input and an output column (the contract's minimum)."""
    if "u" not in log and "F" not in log:
        raise InputError(f"{log.source}: line 1: missing column 'u' (or 'F' for force input)")
    if "u" in log and "v" not in log:
        raise InputError(f"{log.source}: line 1: missing column 'v' (measured speed, m/s)")
    if "F" in log and "u" not in log and "v" not in log and "x" not in log:
        raise InputError(f"{log.source}: line 1: missing column 'v' or 'x' for a force log")


def write_log(path: str | Path, columns: Mapping[str, Iterable[float]]) -> None:
    """Write columns (equal length) as CSV with full float precision."""
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
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(names)
        for k in range(n):
            w.writerow([repr(float(a[k])) for a in arrays])

"""Summaries of closed-loop runs: a text table, JSON-safe metrics, a PNG plot and the
traces in the log format."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from truckd.errors import TruckdError
from truckd.runtime.cycle import LOG_COLUMNS
from truckd.sim.closed_loop import TRUTH_COLUMNS, Trace

_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("scenario", "scenario", "{}"),
    ("collision", "collision", "{}"),
    ("min_gap_m", "min gap m", "{:.3f}"),
    ("gap_error_rms_m", "gap err rms m", "{:.4f}"),
    ("max_abs_voltage_v", "max|u| V", "{:.2f}"),
    ("solve_us_p50", "solve p50 us", "{:.0f}"),
    ("solve_us_p99", "solve p99 us", "{:.0f}"),
    ("step_us_p99", "step p99 us", "{:.0f}"),
    ("solver_failures", "solver fails", "{}"),
    ("deadline_misses", "misses", "{}"),
)


def json_safe(m: dict[str, Any]) -> dict[str, Any]:
    """Metrics with NaN/inf floats replaced by None (strict JSON)."""
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in m.items()}


def table(rows: Sequence[dict[str, Any]]) -> str:
    """A fixed-width text table of the main metrics; ``-`` where a value does not apply."""
    cells = [[title for _, title, _ in _COLUMNS]]
    for m in rows:
        line = []
        for key, _, fmt in _COLUMNS:
            v = m.get(key)
            ok = v is not None and not (isinstance(v, float) and not math.isfinite(v))
            line.append(fmt.format(v) if ok else "-")
        cells.append(line)
    widths = [max(len(r[i]) for r in cells) for i in range(len(_COLUMNS))]
    return "\n".join("  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)) for r in cells)


def plot(path: str | Path, runs: Sequence[tuple[str, Trace]]) -> None:
    """PNG with one column per run: gap and reference gap, speeds, voltage over time."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:  # the optional [plot] extra
        raise TruckdError(f"--plot needs matplotlib (pip install 'truckd[plot]'): {exc}") from None
    n = len(runs)
    fig, axes = plt.subplots(3, n, figsize=(4.5 * n, 8), sharex="col", squeeze=False)
    for j, (name, tr) in enumerate(runs):
        t = np.asarray(tr.t)
        ax = axes[0][j]
        ax.plot(t, tr.gap, label="gap")
        ax.plot(t, tr.gap_ref, "--", label="d_ref = d_0 + h v")
        ax.set_title(name)
        ax.set_ylabel("m")
        ax.legend(loc="best", fontsize="small")
        ax = axes[1][j]
        ax.plot(t, tr.v, label="v")
        ax.plot(t, tr.v_lead, label="v_lead")
        ax.set_ylabel("m/s")
        ax.legend(loc="best", fontsize="small")
        ax = axes[2][j]
        ax.plot(t, tr.u, label="u")
        ax.plot(t, tr.u_ff, label="u_ff")
        ax.set_ylabel("V")
        ax.set_xlabel("t (s)")
        ax.legend(loc="best", fontsize="small")
    fig.tight_layout()
    try:
        fig.savefig(path, dpi=80)
    except OSError as exc:
        raise TruckdError(f"{path}: cannot write plot: {exc.strerror}") from None
    finally:
        plt.close(fig)


def trace_columns() -> tuple[str, ...]:
    """Columns of a trace file: the daemon's log row, then the plant's truth."""
    return (*LOG_COLUMNS, *TRUTH_COLUMNS)


def write_trace(path: str | Path, tr: Trace) -> None:
    """A run's time series in the log format (CONTRACTS.md section 3, the daemon's own
    columns plus the truth), written whole or not at all (TruckdError when impossible)."""
    p = Path(path)
    names = trace_columns()
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "w", newline="", encoding="utf-8") as fh:
            fh.write(",".join(names) + "\n")
            for row in tr.rows:
                if len(row) != len(names):
                    raise ValueError(f"trace row of {len(row)} values, expected {len(names)}")
                fh.write(",".join(repr(float(x)) for x in row) + "\n")
        os.replace(tmp, p)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise TruckdError(f"{p}: cannot write: {exc.strerror}") from None

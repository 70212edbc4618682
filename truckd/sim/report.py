"""Summaries of closed-loop runs: a text table, JSON-safe metrics, a PNG plot and the
traces in the log format."""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from truckd.errors import TruckdError
from truckd.outputs import atomic_text, write_bytes
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
    """Write :func:`plot_image` to ``path`` (format from its suffix), all or nothing."""
    write_bytes(path, plot_image(runs, Path(path).suffix.lower().lstrip(".") or "png"))


def plot_image(runs: Sequence[tuple[str, Trace]], fmt: str = "png") -> bytes:
    """An image (png, svg, pdf) with one column per run: gap and reference gap, speeds,
    voltage over time."""
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
    buf = io.BytesIO()
    try:
        fig.savefig(buf, dpi=80, format=fmt)
    finally:
        plt.close(fig)
    return buf.getvalue()


def trace_columns() -> tuple[str, ...]:
    """Columns of a trace file: the daemon's log row, then the plant's truth."""
    return (*LOG_COLUMNS, *TRUTH_COLUMNS)


def trace_text(tr: Trace) -> str:
    """A run's time series in the log format (reference section 3, the daemon's own
    columns plus the truth), as the file's text."""
    names = trace_columns()
    lines = [",".join(names)]
    for row in tr.rows:
        if len(row) != len(names):
            raise ValueError(f"trace row of {len(row)} values, expected {len(names)}")
        lines.append(",".join(repr(float(x)) for x in row))
    return "\n".join(lines) + "\n"


def write_trace(path: str | Path, tr: Trace) -> None:
    """:func:`trace_text` written whole or not at all (TruckdError when impossible)."""
    with atomic_text(path) as fh:
        fh.write(trace_text(tr))

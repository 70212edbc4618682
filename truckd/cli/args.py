"""Reusable argparse types and checks: numbers with sane ranges, output paths checked
before any long work starts (docs/inputs.md).

A type that refuses its argument raises :class:`argparse.ArgumentTypeError`; argparse
turns it into one line on stderr and exit 2.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Iterable
from pathlib import Path

from truckd.errors import InputError
from truckd.outputs import IMAGE_SUFFIXES, check_output_dir, check_output_file

DAY_S = 86400.0
MAX_SIM_S = 3600.0
"""Longest simulated run (``sim --duration``): an hour, far beyond any scenario (the
run's time series is kept for its figures: about 0.5 MB per simulated second)."""
MAX_PLATOON_TRUCK_S = 10800.0
"""Longest platoon run, counted in truck-seconds (``--duration`` times ``--platoon``):
about 0.13 MB each, so some 1.4 GB of time series at this bound."""
MAX_RUN_S = 365 * DAY_S
"""Longest ``--duration`` of the daemon or the monitor: a year."""
MAX_INTERVAL_S = 3600.0
"""Longest refresh period of the monitor: an hour."""
MAX_VBAT_V = 1000.0
"""Largest supply voltage accepted (``--vbat``); a 1:14 truck runs on 7-12 V."""


def _float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None


def _span(s: float) -> str:
    if s >= 2 * DAY_S:
        return f" ({s / DAY_S:g} days)"
    return f" ({s / 3600:g} h)" if s >= 3600 else ""


def seconds(lo: float, hi: float, *, lo_open: bool = True) -> Callable[[str], float]:
    """A finite number of seconds in ``(lo, hi]`` (``[lo, hi]`` with ``lo_open=False``)."""
    left = "(" if lo_open else "["

    def parse(text: str) -> float:
        val = _float(text)
        ok_lo = val > lo if lo_open else val >= lo
        if not (math.isfinite(val) and ok_lo and val <= hi):
            raise argparse.ArgumentTypeError(
                f"{text!r}: expected a number of seconds in {left}{lo:g}, {hi:.0f}]{_span(hi)}"
            )
        return val

    return parse


sim_duration = seconds(0.0, MAX_SIM_S)
run_duration = seconds(0.0, MAX_RUN_S)
monitor_duration = seconds(0.0, MAX_RUN_S, lo_open=False)
interval = seconds(0.0, MAX_INTERVAL_S)


def volts(text: str) -> float:
    """A supply voltage in (0, 1000] V."""
    val = _float(text)
    if not (math.isfinite(val) and 0 < val <= MAX_VBAT_V):
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected a supply voltage in (0, {MAX_VBAT_V:g}] V"
        )
    return val


MAX_JOBS = 64
"""Most worker processes ``--jobs`` accepts."""


def jobs(text: str) -> int:
    """A number of worker processes in [1, 64]."""
    try:
        val = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if not 1 <= val <= MAX_JOBS:
        raise argparse.ArgumentTypeError(f"{text!r}: expected 1 to {MAX_JOBS} processes")
    return val


def output_file(what: str, suffixes: Iterable[str] | None = None) -> Callable[[str], str]:
    """An output file path: not a directory, its directory exists and is writable."""
    allowed = tuple(suffixes) if suffixes is not None else None

    def parse(text: str) -> str:
        try:
            check_output_file(text, what, allowed)
        except InputError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
        return text

    return parse


def output_dir(what: str) -> Callable[[str], str]:
    """An output directory: an existing writable directory, or one that can be created."""

    def parse(text: str) -> str:
        try:
            check_output_dir(text, what)
        except InputError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
        return text

    return parse


image_file = output_file("plot", IMAGE_SUFFIXES)
json_file = output_file("JSON output")
report_dir = output_dir("report directory")
model_file = output_file("model file")
csv_file = output_file("CSV output")


def report_notes(notes: Iterable[str]) -> None:
    """Print a reader's one-line notes (e.g. which input column is used) on stderr."""
    for note in dict.fromkeys(notes):  # each once, in order (several logs say the same)
        print(f"note: {note}", file=sys.stderr)


def plot_format(path: str | Path) -> str:
    """The image format matplotlib should write for ``path`` (its suffix)."""
    return Path(path).suffix.lower().lstrip(".") or "png"

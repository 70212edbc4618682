"""``truckd replay LOG.csv [--json FILE]``: a daemon log's run fed again through the cycle.

The received-message logs of the run (``<log>.rx.jsonl`` beside each CSV file, recorded by
default) up to and including LOG's are replayed in order through the companion cycle
(:mod:`truckd.runtime.replay`), and the replayed commands set beside LOG's: one line with
the cycles compared, the largest voltage difference, the enable and mode mismatches and the
solves that failed on the car.  Exit 0 when it ran (the comparison is the output), 2 when
LOG or its received-message log is missing or malformed."""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path
from typing import Any

from truckd.errors import InputError
from truckd.logfile import read_log
from truckd.outputs import guard_inputs, write_text
from truckd.runtime.replay import compare, replay
from truckd.runtime.rxlog import SUFFIX, read_rx_recording, solver_failure

_PART = re.compile(r"^(?P<run>.+-p\d+)-(?P<index>\d{4,})(?:-\d+)?$")
"""The recorder's file names: ``<prefix>-<UTC stamp>-p<pid>-NNNN[-K]``."""


def add_subparser(sub: Any) -> None:
    p = sub.add_parser(
        "replay", help="replay a daemon log's received messages and compare the commands"
    )
    p.add_argument("log", metavar="LOG.csv", help="a log the daemon recorded")
    p.add_argument("--json", metavar="FILE", help="write the comparison as JSON")
    p.set_defaults(run=run)


def run_files(log: Path) -> list[Path]:
    """The received-message logs of ``log``'s run, in order, up to and including its own
    (the older ones the recorder still keeps)."""
    own = log.with_suffix(SUFFIX)
    if not own.exists():
        raise InputError(
            f"{log}: no received-message log beside it ({own.name}; recorded unless "
            "runtime.recorder.messages is false)"
        )
    m = _PART.match(log.stem)
    if m is None:
        return [own]
    files = []
    for p in log.parent.glob(f"{m['run']}-*{SUFFIX}"):
        other = _PART.match(p.name.removesuffix(SUFFIX))
        if other is not None and other["run"] == m["run"]:
            files.append((int(other["index"]), p))
    files.sort()
    return [p for index, p in files if index <= int(m["index"])]


def run(args: argparse.Namespace) -> int:
    """Refuses a ``--json`` that is the log or one of its received-message logs."""
    files = run_files(Path(args.log))
    with guard_inputs([args.log, *files], [("--json", args.json)]):
        return _run(args, files)


def _run(args: argparse.Namespace, files: list[Path]) -> int:
    log_path = Path(args.log)
    log = read_log(log_path, require=("t", "u"))
    missing = [c for c in ("seq", "enable", "mode") if c not in log]
    if missing:
        raise InputError(f"{log_path}: line 1: missing column '{missing[0]}' (not a daemon log)")
    first = read_rx_recording(files[0]).seq0
    outs = replay(files)
    c = compare(log, outs)
    failed = sum(solver_failure(o) is not None for o in outs)
    fresh = f" (from a fresh state at cycle {first}: its first cycles may differ)" if first else ""
    print(
        f"{log_path}: {c.cycles} cycles compared, replayed from cycle {first} "
        f"({len(files)} file{'s' if len(files) != 1 else ''}){fresh}; largest voltage "
        f"difference {c.max_abs_du:.3g} V; enable mismatches {c.enable_mismatches}; mode "
        f"mismatches {c.mode_mismatches}; solves failed on the car {failed}"
    )
    if args.json:
        doc = {
            "log": str(log_path),
            "rx_logs": [str(p) for p in files],
            "first_cycle": first,
            "cycles": c.cycles,
            "max_abs_du_v": c.max_abs_du,
            "enable_mismatches": c.enable_mismatches,
            "mode_mismatches": c.mode_mismatches,
            "car_solver_failures": failed,
        }
        write_text(args.json, json.dumps(doc, indent=1) + "\n")
    return 0

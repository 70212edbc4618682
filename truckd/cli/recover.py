"""``truckd recover FILE.mcap|DIR [...]``: finish MCAP logs a crash left unfinished.

Each file without its footer is rewritten with its index and summary from every complete
record (atomically: a temporary file renamed over it); a finished file, or one a running
daemon still writes, is left alone.  A directory means its ``*.mcap`` files (not below).
One line per file; exit 2 for a path that does not exist or a file that is not MCAP."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from truckd.errors import InputError
from truckd.runtime.mcap_recover import recover_file, unfinished


def add_subparser(sub: Any) -> None:
    p = sub.add_parser("recover", help="finish MCAP logs left unfinished by a crash")
    p.add_argument("paths", nargs="+", metavar="FILE.mcap|DIR", help="files or directories")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    files: list[Path] = []
    for text in args.paths:
        p = Path(text)
        if p.is_dir():
            found = unfinished(p)
            if not found:
                print(f"{p}: no unfinished MCAP file")
            files += found
        elif p.exists():
            files.append(p)
        else:
            raise InputError(f"{text}: no such file or directory")
    for f in files:
        print(recover_file(f).line())
    return 0

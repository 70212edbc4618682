"""A benchmark's scratch directory: the configurations, ptys and logs of its runs.

By default a fresh temporary directory, removed when the script exits (normally, by an
exception, or by SIGTERM where the script turns it into an exception); with a path
(``--work-dir DIR``), that directory, new or empty (the run reads its own files back),
created if missing and kept for reading after.
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path


def scratch_dir(prefix: str, keep: str | Path | None = None) -> Path:
    """``keep`` (created, kept) or a new temporary directory named ``prefix...`` that
    is removed at the interpreter's exit."""
    if keep is not None:
        path = Path(keep)
        if path.exists() and any(path.iterdir()):  # a run's figures come from its files
            raise SystemExit(f"--work-dir {path}: not empty; give a new or empty directory")
        path.mkdir(parents=True, exist_ok=True)
        return path
    path = Path(tempfile.mkdtemp(prefix=prefix))
    atexit.register(shutil.rmtree, path, ignore_errors=True)
    return path

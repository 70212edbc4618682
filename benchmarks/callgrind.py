"""A command's instructions, counted by callgrind (repeatable where its wall time is not:
``cycle_work.py``, ``mpc_work.py``, ``diagnose_work.py``)."""

from __future__ import annotations

import re
import subprocess
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path


def counted(
    cmd: Sequence[str], env: Mapping[str, str] | None = None, what: str = "child"
) -> tuple[subprocess.CompletedProcess[str], int]:
    """Run ``cmd`` under ``valgrind --tool=callgrind`` (its output captured): the finished
    process and the instructions it ran.  RuntimeError (``what`` names the command) when
    it fails or callgrind counts nothing."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "callgrind.out"
        proc = subprocess.run(
            ["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", *cmd],
            capture_output=True, text=True, env=env, check=False,
        )  # fmt: skip
    if proc.returncode != 0:
        raise RuntimeError(f"{what} failed: {proc.stderr[-2000:]}")
    m = re.search(r"Collected : (\d+)", proc.stderr)
    if m is None:
        raise RuntimeError("callgrind printed no instruction count")
    return proc, int(m.group(1))

"""Running the CLI in-process or as a subprocess and checking the one-line error rule."""

from __future__ import annotations

import os
import resource
import signal
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

import pytest

from truckd.cli.main import main

ROOT = Path(__file__).resolve().parents[1]


def cli(argv: Sequence[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """Run ``truckd argv`` in this process; returns (exit code, stdout, stderr)."""
    capsys.readouterr()
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line(err: str) -> str:
    """stderr is exactly one non-empty line without a traceback; returns it."""
    assert "Traceback" not in err
    lines = err.splitlines()
    assert len(lines) == 1, f"expected one line on stderr, got {len(lines)}: {err!r}"
    assert lines[0].strip()
    return lines[0]


def bad_input(argv: Sequence[str], capsys: pytest.CaptureFixture[str]) -> str:
    """``truckd argv`` exits 2 with one line on stderr; returns that line."""
    code, _out, err = cli(argv, capsys)
    line = assert_one_line(err)
    assert code == 2, f"exit {code}, expected 2: {err!r}"
    return line


def run_limited(
    argv: Sequence[str],
    cwd: Path,
    *,
    fsize: int | None = None,
    address_space: int | None = None,
    cpu_s: int = 60,
) -> subprocess.CompletedProcess[str]:
    """``python -m truckd.cli.main argv`` in a child with resource limits.

    ``fsize`` limits the size of any file written (SIGXFSZ ignored, so a write past it
    fails with EFBIG); ``address_space`` bounds memory; ``cpu_s`` bounds CPU time.
    """

    def limits() -> None:
        resource.setrlimit(resource.RLIMIT_CPU, (cpu_s, cpu_s))
        if fsize is not None:
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
            resource.setrlimit(resource.RLIMIT_FSIZE, (fsize, fsize))
        if address_space is not None:
            resource.setrlimit(resource.RLIMIT_AS, (address_space, address_space))

    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1", "OPENBLAS_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-m", "truckd.cli.main", *argv],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        preexec_fn=limits,
        timeout=300,
        check=False,
    )

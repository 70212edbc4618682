"""Writing a benchmark's JSON without losing the measurements already in the file.

A results file holds the latest run at its top level and earlier measurements under
keys named by what was measured and when (``loop_60s_deferred_message_2026-11-24``,
``loop_ab_cpu_latency_2026-11-23``): see the README's figures table for which key backs
which figure.  ``--json FILE`` replaces the top level and keeps the named keys;
``--json FILE --key NAME`` stores the run under NAME and leaves the rest alone.
"""

from __future__ import annotations

import json
import os
import platform
import re
import tempfile
from pathlib import Path
from typing import Any

KEY = re.compile(r"[a-z0-9_]+_\d{4}-\d{2}-\d{2}(_[0-9a-f]{7,40}|_[a-z0-9_]+)?")
"""A measurement's name: what (lower case, underscores), then the date (ISO), then
optionally the commit measured or a qualifier."""


def machine() -> dict[str, Any]:
    """The machine a run measured: cores, kernel, Python and the load average (1, 5,
    15 min) at the time of the call."""
    return {
        "cpus": os.cpu_count(),
        "kernel": platform.release(),
        "python": platform.python_version(),
        "loadavg_1_5_15": list(os.getloadavg()),
    }


def merged(old: dict[str, Any], result: dict[str, Any], key: str | None) -> dict[str, Any]:
    """``old`` with ``result`` as its top level (``key`` None) or under ``key``."""
    if key is not None:
        if not KEY.fullmatch(key):
            raise ValueError(f"--key {key!r}: name it what_YYYY-MM-DD (e.g. loop_60s_2026-11-25)")
        return {**old, key: result}
    named = {k: v for k, v in old.items() if KEY.fullmatch(k) and k not in result}
    return {**result, **named}


def write_json(path: str | Path, result: dict[str, Any], key: str | None = None) -> None:
    """Merge ``result`` into the JSON file at ``path`` (see :func:`merged`), written whole
    or not at all."""
    path = Path(path)
    old: dict[str, Any] = {}
    if path.exists():
        loaded = json.loads(path.read_text())
        old = loaded if isinstance(loaded, dict) else {}
    text = json.dumps(merged(old, result, key), indent=2, ensure_ascii=False) + "\n"
    fd, tmp = tempfile.mkstemp(prefix=path.name, dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise

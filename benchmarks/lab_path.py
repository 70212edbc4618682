"""Imported first by the benchmarks that use the helpers they share with the tests
(``tests/labkit``: synthetic logs, protocol fuzzing, not shipped): puts ``tests/`` on
``sys.path``."""

from __future__ import annotations

import sys
from pathlib import Path

TESTS = str(Path(__file__).resolve().parents[1] / "tests")
if TESTS not in sys.path:
    sys.path.insert(0, TESTS)

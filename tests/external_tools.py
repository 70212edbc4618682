"""Tools the pip install does not bring, checked inside a test or fixture (the programs
are also marked ``needs_tool``, tests/tool_markers.py): node with the reference readers
installed in tests/js (not a program on PATH: ``npm ci --prefix tests/js``), and
qemu-system-arm with the Cortex-M4 toolchain for the processor-in-the-loop tests.

``.ci/run`` installs them and sets ``TRUCKD_REQUIRE_TOOLS``: there a missing tool fails
the test.  On a user's machine (``make test``) the test is skipped with a reason naming
what is missing and how to install it.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
from tool_markers import REQUIRE_TOOLS_ENV

ROOT = Path(__file__).resolve().parent.parent
JS_DIR = ROOT / "tests" / "js"
JS_PACKAGES = ("@mcap/core", "@foxglove/ws-protocol", "fzstd", "ws")


def missing(what: str) -> None:
    """Skip (a user's machine) or fail (CI, ``TRUCKD_REQUIRE_TOOLS`` set) naming ``what``."""
    if os.environ.get(REQUIRE_TOOLS_ENV):
        pytest.fail(f"required tool missing: {what} ({REQUIRE_TOOLS_ENV} is set)", pytrace=False)
    pytest.skip(f"missing: {what}")


def node_readers() -> str:
    """The node executable, with the reference readers installed in tests/js."""
    node = shutil.which("node")
    if node is None:
        missing("node (Node.js >= 18) for the reference MCAP and Foxglove readers")
    assert node is not None
    absent = [p for p in JS_PACKAGES if not (JS_DIR / "node_modules" / p / "package.json").exists()]
    if absent:
        missing(f"npm packages {', '.join(absent)}: run `npm ci --prefix tests/js`")
    return node


def qemu_arm() -> str:
    """qemu-system-arm (with the netduinoplus2 machine)."""
    qemu = shutil.which("qemu-system-arm")
    if qemu is None:
        missing("qemu-system-arm: apt-get install -y qemu-system-arm")
    assert qemu is not None
    return qemu


def arm_gcc() -> str:
    """arm-none-eabi-gcc."""
    gcc = shutil.which("arm-none-eabi-gcc")
    if gcc is None:
        missing("arm-none-eabi-gcc: apt-get install -y gcc-arm-none-eabi libnewlib-arm-none-eabi")
    assert gcc is not None
    return gcc

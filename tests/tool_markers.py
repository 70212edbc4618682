"""The ``needs_tool`` marker: a test that runs an external program (a cross compiler,
systemd-analyze, qemu, node) is skipped when the program is not on PATH, with the reason
and the install hint in pytest's summary (``-ra``).  ``make test`` never installs system
packages; CI installs them (``.ci/run``) and sets ``TRUCKD_REQUIRE_TOOLS=1``, which turns
a missing tool into a failure, so no test is skipped there.

    @pytest.mark.needs_tool("arm-none-eabi-gcc", install="apt-get install gcc-arm-none-eabi")
"""

from __future__ import annotations

import os
import shutil

import pytest

REQUIRE_TOOLS_ENV = "TRUCKD_REQUIRE_TOOLS"
"""Set (non-empty) where every tool must be present: a missing one fails the test."""


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "needs_tool(program, install=HINT): skip (fail with TRUCKD_REQUIRE_TOOLS set) "
        "when the program is not on PATH",
    )


def missing_tool_reason(program: str, install: str) -> str:
    """The one line shown when ``program`` is missing."""
    hint = f"; install: {install}" if install else ""
    return f"needs {program}, not on PATH{hint}"


def pytest_runtest_setup(item: pytest.Item) -> None:
    for mark in item.iter_markers("needs_tool"):
        program = str(mark.args[0])
        if shutil.which(program) is None:
            reason = missing_tool_reason(program, str(mark.kwargs.get("install", "")))
            if os.environ.get(REQUIRE_TOOLS_ENV):
                pytest.fail(f"{reason} ({REQUIRE_TOOLS_ENV} is set)", pytrace=False)
            pytest.skip(reason)

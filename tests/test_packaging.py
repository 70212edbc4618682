"""Packaging: one version (pyproject.toml's) behind ``truckd --version`` and
``python -m truckd``; the licence pyproject declares is the one shipped; the
``needs_tool`` marker skips with its reason, and fails where tools are required."""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from truckd.cli.main import main

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_version_is_pyproject_s(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"truckd {PYPROJECT['project']['version']}"


def test_python_m_truckd_is_the_command_line() -> None:
    env = {k: v for k, v in os.environ.items() if k != "TRUCKD_DEBUG"}
    run = subprocess.run(
        [sys.executable, "-m", "truckd", "--version"],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
        check=False,
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == f"truckd {PYPROJECT['project']['version']}"
    bad = subprocess.run(
        [sys.executable, "-m", "truckd", "no-such-command"],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
        check=False,
    )
    assert bad.returncode == 2 and "no-such-command" in bad.stderr


def test_version_and_a_command_s_help_import_no_other_command() -> None:
    """``truckd --version`` imports no command module; ``truckd diagnose --help`` not the
    daemon's nor scipy.signal (a second to import: the diagnosis imports it when it filters)."""
    probe = (
        "import sys, contextlib, io\n"
        "from truckd.cli.main import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    code = main(sys.argv[1:])\n"
        "mods = [m for m in sys.modules if m.startswith(('truckd.cli.', 'scipy.signal'))]\n"
        "print(code, *mods)\n"
    )

    def loaded(*argv: str) -> tuple[str, set[str]]:
        out = subprocess.run(
            [sys.executable, "-c", probe, *argv],
            capture_output=True,
            text=True,
            timeout=120,
            check=True,
        ).stdout.split()
        return out[0], set(out[1:])

    code, mods = loaded("--version")
    assert code == "0" and not {m for m in mods if m != "truckd.cli.main"}, mods
    code, mods = loaded("diagnose", "--help")
    assert code == "0" and "truckd.cli.diagnose" in mods, mods
    assert "truckd.cli.run" not in mods and "scipy.signal" not in mods, mods


def test_the_declared_licence_is_the_shipped_one() -> None:
    assert PYPROJECT["project"]["license"] == "Apache-2.0"
    text = (ROOT / "LICENSE").read_text()
    assert "Apache License" in text and "Version 2.0, January 2004" in text
    assert "LICENSE" in PYPROJECT["project"]["license-files"]


def test_no_second_version_string_in_the_package() -> None:
    """The version is written once (pyproject.toml); the package reads it back."""
    version = PYPROJECT["project"]["version"]
    holders = [
        str(p.relative_to(ROOT))
        for p in (ROOT / "truckd").rglob("*.py")
        if f'"{version}"' in p.read_text()
    ]
    assert holders == []


MARKED = """
import pytest

@pytest.mark.needs_tool("truckd-no-such-program", install="apt-get install nothing")
def test_uses_the_tool():
    raise AssertionError("ran without its tool")
"""


def _run_marked(tmp_path: Path, require: bool) -> subprocess.CompletedProcess[str]:
    (tmp_path / "test_marked.py").write_text(MARKED)
    (tmp_path / "pytest.ini").write_text("[pytest]\naddopts = -ra --strict-markers\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT / "tests"))
    env.pop("TRUCKD_REQUIRE_TOOLS", None)
    if require:
        env["TRUCKD_REQUIRE_TOOLS"] = "1"
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-p", "tool_markers", "-p", "no:cacheprovider"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
        check=False,
    )


def test_a_missing_tool_is_a_skip_with_its_reason(tmp_path: Path) -> None:
    run = _run_marked(tmp_path, require=False)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "SKIPPED" in run.stdout and "needs truckd-no-such-program" in run.stdout
    assert "install: apt-get install nothing" in run.stdout


def test_a_missing_tool_fails_where_tools_are_required(tmp_path: Path) -> None:
    run = _run_marked(tmp_path, require=True)
    assert run.returncode == 1, run.stdout + run.stderr
    assert "needs truckd-no-such-program" in run.stdout and "ran without" not in run.stdout

"""Modules and functions a reader can hold.

No module of the shipped packages (``truckd``, ``firmware_protocol``) is over
:data:`MAX_MODULE_LINES` lines; no function of the diagnosis (``truckd/ident``) is over
:data:`MAX_FUNCTION_LINES` lines unless its docstring says why, in a paragraph that
starts "Long because".
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

PACKAGES = ("truckd", "firmware_protocol")
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80

KNOWN_LONG_MODULES: set[str] = set()
"""Modules allowed over the limit: none."""


def _modules(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


def test_no_module_is_over_the_limit() -> None:
    files = [p for pkg in PACKAGES for p in _modules(pkg)]
    assert len(files) > 100  # the scan sees the packages
    lengths = {
        p.relative_to(ROOT).as_posix(): len(p.read_text("utf-8").splitlines()) for p in files
    }
    long = {name: n for name, n in lengths.items() if n > MAX_MODULE_LINES}
    assert set(long) <= KNOWN_LONG_MODULES, f"modules over {MAX_MODULE_LINES} lines: {long}"


def _long_functions(path: Path) -> list[tuple[str, int, bool]]:
    """``(name, lines, says why)`` of each function in ``path`` over the limit."""
    out = []
    for node in ast.walk(ast.parse(path.read_text("utf-8"))):
        if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            continue
        lines = (node.end_lineno or node.lineno) - node.lineno + 1
        if lines > MAX_FUNCTION_LINES:
            doc = ast.get_docstring(node) or ""
            why = any(par.lstrip().startswith("Long because") for par in doc.split("\n\n"))
            out.append((node.name, lines, why))
    return out


def test_long_functions_say_why() -> None:
    files = [p for pkg in PACKAGES for p in _modules(pkg)]
    assert len(files) > 100
    silent = {
        f"{p.relative_to(ROOT).as_posix()}:{name}": n
        for p in files
        for name, n, why in _long_functions(p)
        if not why
    }
    assert not silent, f"functions over {MAX_FUNCTION_LINES} lines without a reason: {silent}"

"""The package layering: :mod:`truckd.schema` is the bottom, :mod:`truckd.config` the top.

Every package declares its own configuration section with :func:`truckd.schema.spec`;
:mod:`truckd.config.truck` assembles them into one ``TruckConfig``.  So the schema must
import no truckd package, and the model, controller and I/O packages must not import
:mod:`truckd.config` (it imports them: a cycle waiting to happen).
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "truckd"

BOTTOM = {"truckd", "truckd.schema", "truckd.yamlsafe", "truckd.errors"}
"""What importing the schema may load of truckd: itself and two leaf modules."""

LOWER = ("model", "control", "io")
"""Packages below the configuration (they supply its sections)."""


def _loaded(code: str) -> set[str]:
    probe = f"import json, sys\n{code}\nprint(json.dumps(sorted(sys.modules)))"
    r = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True
    )
    return {m for m in json.loads(r.stdout) if m == "truckd" or m.startswith("truckd.")}


def _config_imports(source: str) -> list[str]:
    """The ``truckd.config`` imports in ``source`` (absolute ones: ruff bans relative)."""
    found: list[str] = []
    for node in ast.walk(ast.parse(source)):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        found += [n for n in names if n == "truckd.config" or n.startswith("truckd.config.")]
    return found


def test_the_schema_imports_no_truckd_package() -> None:
    assert _loaded("import truckd.schema") <= BOTTOM
    assert _loaded("import truckd.schema") >= {"truckd.schema", "truckd.yamlsafe"}


def test_the_lower_packages_do_not_import_the_config_package() -> None:
    offenders = {}
    files = [p for pkg in LOWER for p in sorted((ROOT / pkg).rglob("*.py"))]
    files += [ROOT / "schema.py", ROOT / "yamlsafe.py", ROOT / "errors.py"]
    for path in files:
        bad = _config_imports(path.read_text(encoding="utf-8"))
        if bad:
            offenders[str(path.relative_to(ROOT))] = bad
    assert len(files) > 20  # the scan sees the packages
    assert offenders == {}


def test_importing_every_lower_module_leaves_the_config_package_unloaded() -> None:
    """Also through indirect imports: load every module of model, control and io."""
    mods = [
        "truckd." + ".".join(p.relative_to(ROOT).with_suffix("").parts)
        for pkg in LOWER
        for p in sorted((ROOT / pkg).rglob("*.py"))
    ]
    mods = [m.removesuffix(".__init__") for m in mods]
    loaded = _loaded("\n".join(f"import {m}" for m in mods))
    assert "truckd.control.mpc" in loaded and "truckd.model.params" in loaded
    assert not {m for m in loaded if m == "truckd.config" or m.startswith("truckd.config.")}


def test_the_scan_sees_a_config_import() -> None:
    """The checks can fail: both import forms are found, and the top layer loads config."""
    src = "import truckd.config.truck\nfrom truckd.config import truck\nfrom truckd import io\n"
    assert _config_imports(src) == ["truckd.config.truck", "truckd.config", "truckd.config.truck"]
    assert "truckd.config.truck" in _loaded("import truckd.runtime.daemon")

"""The layering of every package: imports go down the layers only, and the car side
never imports the lab side (docs/architecture.md draws it).

From the bottom: the leaf modules (errors, YAML, schema, input and output files), the
protocol and the model, the controller and the transports, the configuration that
assembles their sections, the daemon (``runtime``) and the model file; above them the lab
(the simulator, the identification), then the command line.  A module may import its own
package and any unit of a lower layer, never a unit of its own layer or of a higher one;
this counts every import statement, inside functions and ``if TYPE_CHECKING:`` blocks
too (a lazy import is still a dependency).  The schema is the bottom of the
configuration: every package declares its own section with :func:`truckd.schema.spec`
and :mod:`truckd.config.truck` assembles them.

What the daemon needs on the truck (the car side) must not load what only the lab needs
(:mod:`truckd.sim`, :mod:`truckd.ident`, the tests' ``labkit``): checked on the source
and by importing every car module in a fresh interpreter, which also sees imports made by
name (``importlib``) while loading.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ROOT = REPO / "truckd"
PACKAGES = ("truckd", "firmware_protocol")

LAYERS: tuple[tuple[str, ...], ...] = (
    ("truckd.errors", "truckd.workers"),
    ("truckd.yamlsafe", "truckd.jsonsafe"),
    ("truckd.schema", "truckd.inputs", "truckd.outputs"),
    ("truckd.logfile", "firmware_protocol"),
    ("truckd.model",),
    ("truckd.control", "truckd.io"),
    ("truckd.config",),
    ("truckd.runtime", "truckd.modelfile"),
    ("truckd.sim", "truckd.ident"),
    ("truckd.cli",),
    ("truckd.__main__",),
)
"""Units from the bottom up: a unit may import lower layers only (and itself)."""

LAB = ("truckd.sim", "truckd.ident")
"""What only the lab needs (with the tests' ``labkit``, outside the package)."""
CAR = tuple(u for layer in LAYERS[: LAYERS.index(("truckd.sim", "truckd.ident"))] for u in layer)
"""What the daemon on the truck needs: every unit below the lab."""

ALLOWED_UP: set[tuple[str, str]] = set()
"""Known imports back up (``(module, imported)`` pairs), to be removed: none today."""


def _allowed(module: str, name: str) -> bool:
    return any(module == m and (name == n or name.startswith(n + ".")) for m, n in ALLOWED_UP)


def _module_name(path: Path) -> str:
    rel = path.relative_to(REPO).with_suffix("")
    return ".".join(rel.parts).removesuffix(".__init__")


def _unit(module: str) -> str | None:
    """The layering unit of a module: a subpackage, or a module of the package root."""
    parts = module.split(".")
    if parts[0] == "firmware_protocol":
        return "firmware_protocol"
    if parts[0] != "truckd":
        return None
    return "truckd" if len(parts) == 1 else f"truckd.{parts[1]}"


RANK = {u: i for i, layer in enumerate(LAYERS) for u in layer}


def _sources() -> dict[str, str]:
    return {
        _module_name(p): p.read_text(encoding="utf-8")
        for pkg in PACKAGES
        for p in sorted((REPO / pkg).rglob("*.py"))
    }


def _imports(module: str, source: str) -> list[str]:
    """Every truckd/firmware_protocol module ``source`` imports (absolute names; a
    ``from X import y`` counts as X and as X.y, since y may be a module)."""
    found: list[str] = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            assert node.level == 0, f"{module}: relative import"
            found += [node.module] + [f"{node.module}.{a.name}" for a in node.names]
    return [n for n in found if _unit(n) is not None or n.split(".")[0] == "labkit"]


def layering_violations(sources: dict[str, str]) -> list[str]:
    """``importer -> imported: why`` for each import that breaks the layers (once per
    importing module and imported unit)."""
    bad: list[str] = []
    seen: set[tuple[str, str | None]] = set()
    for module, source in sources.items():
        src = _unit(module)
        if src == "truckd":  # the package's own __init__ imports nothing of it
            src = "truckd.__init__"
        for name in _imports(module, source):
            if name.split(".")[0] == "labkit":
                if (module, "labkit") in seen:
                    continue
                seen.add((module, "labkit"))
                bad.append(f"{module} -> {name}: test helpers are not shipped")
                continue
            dst = _unit(name)
            if dst == src or dst == "truckd" or _allowed(module, name) or (module, dst) in seen:
                continue  # own unit; ``import truckd`` / ``from truckd import x`` below
            seen.add((module, dst))
            if src == "truckd.__init__" or src not in RANK or dst not in RANK:
                bad.append(f"{module} -> {name}: unit not in LAYERS")
            elif src in CAR and dst in LAB:
                bad.append(f"{module} -> {name}: the car side imports the lab")
            elif RANK[dst] >= RANK[src]:
                bad.append(f"{module} -> {name}: {dst} is not below {src}")
    return bad


def _loaded(code: str) -> set[str]:
    probe = f"import json, sys\n{code}\nprint(json.dumps(sorted(sys.modules)))"
    r = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True
    )
    names = json.loads(r.stdout)
    return {m for m in names if _unit(m) is not None or m.split(".")[0] == "labkit"}


def test_every_unit_has_a_layer() -> None:
    units = {_unit(m) for m in _sources()}
    assert units - {"truckd"} == set(RANK)  # each unit placed once, none missing
    assert sum(len(layer) for layer in LAYERS) == len(RANK)


def test_imports_go_down_the_layers_only() -> None:
    sources = _sources()
    assert len(sources) > 120  # the scan sees both packages
    assert layering_violations(sources) == []


@pytest.mark.parametrize(
    ("module", "source", "why"),
    [
        ("truckd.model.motor", "from truckd.control.qp import ControlModel", "not below"),
        ("truckd.control.mpc", "import truckd.io.link", "not below"),  # a sibling
        ("truckd.runtime.daemon", "import truckd.sim.backend", "car side imports the lab"),
        ("truckd.io.port", "def f():\n    from truckd.ident import api", "the lab"),
        ("truckd.io.port", "if TYPE_CHECKING:\n    from truckd import cli", "not below"),
        ("truckd.schema", "from truckd.config import truck", "not below"),
        ("truckd.sim.plant", "from truckd.cli.main import main", "not below"),
        ("truckd.ident.api", "from truckd.sim.plant import Plant", "not below"),
        ("firmware_protocol.codec", "import truckd.model", "not below"),
        ("truckd.sim.plant", "from labkit.synth import plant_log", "not shipped"),
    ],
)
def test_an_import_back_up_is_caught(module: str, source: str, why: str) -> None:
    (found,) = layering_violations({module: source})
    assert why in found and module in found


def test_the_schema_imports_no_truckd_package() -> None:
    bottom = {"truckd", "truckd.schema", "truckd.yamlsafe", "truckd.errors"}
    assert {"truckd.schema", "truckd.yamlsafe"} <= _loaded("import truckd.schema") <= bottom


def test_loading_the_car_side_loads_nothing_of_the_lab() -> None:
    """Every module of the car side, and ``truckd run``'s command line, in one fresh
    interpreter: no simulator, no identification, no test helper is loaded."""
    mods = [m for m in _sources() if _unit(m) in CAR]
    mods += ["truckd.cli.main", "truckd.cli.run"]
    loaded = _loaded("\n".join(f"import {m}" for m in mods))
    assert {"truckd.runtime.daemon", "truckd.io.serial_link", "truckd.control.mpc"} <= loaded
    lab = sorted(m for m in loaded if _unit(m) in LAB or m.split(".")[0] == "labkit")
    assert lab == []


def test_the_load_check_sees_a_lab_module() -> None:
    """The check above can fail: the lab's backend loads the simulator."""
    assert "truckd.sim.plant" in _loaded("import truckd.sim.backend")


def test_the_test_helpers_are_not_shipped() -> None:
    """pyproject's package list finds the two packages, and neither the tests nor their
    helpers (``labkit``)."""
    import tomllib

    from setuptools import find_namespace_packages

    find = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    found = find_namespace_packages(str(REPO), include=find["packages"]["find"]["include"])
    assert {"truckd", "truckd.sim", "truckd.ident", "firmware_protocol"} <= set(found)
    assert not [p for p in found if "labkit" in p or p.split(".")[0] == "tests"]
    assert (REPO / "tests" / "labkit" / "synth.py").is_file()

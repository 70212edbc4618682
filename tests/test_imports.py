"""`truckd run` loads only what the car needs (subprocesses: a fresh interpreter each)."""

from __future__ import annotations

import json
import subprocess
import sys

PROBE = """
import json, sys
{imports}
print(json.dumps(sorted(sys.modules)))
"""


def _modules(imports: str) -> set[str]:
    out = subprocess.run(
        [sys.executable, "-c", PROBE.format(imports=imports)],
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    )
    return set(json.loads(out.stdout))


FORBIDDEN = ("matplotlib", "cvxpy", "truckd.ident", "truckd.cli.diagnose", "truckd.cli.identify")


def _offenders(mods: set[str], baseline: set[str]) -> list[str]:
    bad = [m for m in mods if any(m == f or m.startswith(f + ".") for f in FORBIDDEN)]
    # scipy only as far as osqp itself needs it (scipy.sparse for its matrices).
    bad += [m for m in mods if m.split(".")[0] == "scipy" and m not in baseline]
    return sorted(bad)


def test_the_run_path_imports_no_offline_tools() -> None:
    """The daemon's command line (``truckd run``, parsing included) loads no scipy beyond
    what osqp loads, no matplotlib, no cvxpy, no diagnosis or identification."""
    baseline = _modules("import osqp")
    assert "scipy.sparse" in baseline  # osqp's own dependency: the allowance is not empty
    mods = _modules(
        "from truckd.cli.main import build_parser\n"
        "import truckd.cli.run\n"
        "build_parser('run').parse_args(['run', '--config', 'x.yaml'])"
    )
    assert "truckd.runtime.daemon" in mods and "osqp" in mods
    assert _offenders(mods, baseline) == []


def test_the_probe_sees_an_offline_tool() -> None:
    """The check can fail: the diagnose command loads what the run path must not."""
    baseline = _modules("import osqp")
    mods = _modules("from truckd.cli.main import build_parser\nbuild_parser('diagnose')")
    assert "truckd.ident" in _offenders(mods, baseline)

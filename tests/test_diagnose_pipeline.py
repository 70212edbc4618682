"""The voltage diagnosis is a pipeline: seven stages, each a module, called once, in order.

``diagnose_voltage`` calls each stage's function exactly once, in the order of
:data:`STAGES`; a stage's module imports from earlier stages only (their outputs'
types and constants), never from a later one: stages follow one another, they do not
call each other.
"""

from __future__ import annotations

import ast
from pathlib import Path

IDENT = Path(__file__).resolve().parents[1] / "truckd" / "ident"

STAGES = (
    ("runs", "prepare"),
    ("linear", "least_squares_stage"),
    ("seed", "seed_stage"),
    ("trials", "candidates_stage"),
    ("choice", "selection_stage"),
    ("refit", "refit_stage"),
    ("verdict", "report_stage"),
)
"""(module of truckd.ident, its stage function), in pipeline order."""


def _function(tree: ast.Module, name: str) -> ast.FunctionDef:
    found = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == name]
    assert found, f"no function {name}"
    return found[0]


def test_diagnose_calls_each_stage_once_in_order() -> None:
    tree = ast.parse((IDENT / "diagnose.py").read_text("utf-8"))
    body = _function(tree, "diagnose_voltage")
    calls = [
        n.func.id
        for stmt in body.body
        for n in ast.walk(stmt)
        if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)
    ]
    stage_calls = [c for c in calls if c in {f for _, f in STAGES}]
    assert stage_calls == [f for _, f in STAGES]
    for module, fn in STAGES:
        _function(ast.parse((IDENT / f"{module}.py").read_text("utf-8")), fn)


def test_a_stage_imports_no_later_stage() -> None:
    order = {f"truckd.ident.{m}": k for k, (m, _) in enumerate(STAGES)}
    backwards = {}
    for module, k in order.items():
        path = IDENT / f"{module.rsplit('.', 1)[1]}.py"
        for node in ast.walk(ast.parse(path.read_text("utf-8"))):
            if isinstance(node, ast.ImportFrom) and order.get(node.module or "", -1) > k:
                backwards[module] = node.module
    assert not backwards, f"stages importing a later stage: {backwards}"

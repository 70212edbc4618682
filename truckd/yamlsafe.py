"""A strict, bounded YAML loader for configuration and model files.

On top of PyYAML's safe loader:

- aliases (``*name``) are refused, so an "alias bomb" cannot expand (anchors alone are
  harmless and allowed);
- nesting deeper than :data:`MAX_DEPTH` is refused (no ``RecursionError``);
- a key given twice in one mapping is an error naming the key and both lines;
- numbers are read as YAML 1.2 does: ``1e308``, ``1.0e308`` and ``1E-3`` are floats
  (PyYAML's YAML 1.1 rules read them as text); the forms whose value the two versions
  disagree on are refused: a leading zero (``040``: 32 in 1.1, 40 in 1.2) and base 60
  (``3:30``: 210 in 1.1, text in 1.2); a date is text, as in YAML 1.2;
- a syntax error is one line: ``FILE:LINE:COL: ...``.

Errors are :class:`InputError` and never render a large value.
"""

from __future__ import annotations

import re
from typing import Any

import yaml
from yaml.nodes import MappingNode, Node

from truckd.errors import InputError

MAX_DEPTH = 32
"""Deepest nesting of mappings/lists accepted; the configuration uses 4 levels."""

MAX_BYTES = 1024 * 1024
"""Largest configuration or model file read (the shipped configuration is ~10 KiB)."""

_FLOAT_12 = re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$")
"""Exponent forms YAML 1.2 reads as floats and PyYAML's 1.1 rules read as text."""


def short(value: object, limit: int = 60) -> str:
    """``repr(value)`` cut to ``limit`` characters (error messages stay one short line)."""
    text = repr(value)
    text = text.replace("\n", "\\n").replace("\r", "\\r")
    return text if len(text) <= limit else text[: limit - 3] + "..."


class _Loader(yaml.SafeLoader):
    """SafeLoader without aliases, with a depth bound, duplicate-key and 1.2 float checks."""

    def __init__(self, stream: str, source: str) -> None:
        super().__init__(stream)
        self.source = source
        self.depth = 0

    def _where(self, node_or_mark: Any) -> str:
        mark = getattr(node_or_mark, "start_mark", node_or_mark)
        if mark is None:
            return self.source
        return f"{self.source}:{mark.line + 1}:{mark.column + 1}"

    def compose_node(self, parent: Node | None, index: Any) -> Node | None:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()  # type: ignore[no-untyped-call]
            raise InputError(
                f"{self._where(event.start_mark)}: alias '*{short(event.anchor, 30)[1:-1]}' is "
                "not allowed; expected the value written out in full"
            )
        self.depth += 1
        try:
            if self.depth > MAX_DEPTH:
                event = self.peek_event()  # type: ignore[no-untyped-call]
                raise InputError(
                    f"{self._where(event.start_mark)}: nested deeper than {MAX_DEPTH} levels; "
                    "expected a configuration of a few levels"
                )
            return super().compose_node(parent, index)
        finally:
            self.depth -= 1

    def construct_mapping(self, node: MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: dict[Any, Node] = {}
        for key_node, _value in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                first = seen.get(key)
            except TypeError:  # unhashable key: PyYAML's own error below
                continue
            if first is not None:
                raise InputError(
                    f"{self._where(key_node)}: key {short(key, 40)} given twice (first at line "
                    f"{first.start_mark.line + 1}); expected each key once"
                )
            seen[key] = key_node
        return super().construct_mapping(node, deep=deep)

    def construct_yaml_int(self, node: Node) -> int:
        text = str(self.construct_scalar(node))  # type: ignore[arg-type]
        body = text.replace("_", "").lstrip("+-")
        self._ambiguous(node, text, body)
        if len(body) > 1 and body[0] == "0" and body[1].isdigit():
            sign = "-" if text.lstrip().startswith("-") else ""
            raise InputError(
                f"{self._where(node)}: {short(text, 30)} has a leading zero (YAML 1.1 reads "
                f"it as octal, YAML 1.2 as decimal); expected {sign}{body.lstrip('0') or '0'}"
            )
        if body.lower().startswith("0b"):
            raise InputError(
                f"{self._where(node)}: {short(text, 30)} is a binary number in YAML 1.1 and "
                "text in YAML 1.2; expected a decimal number"
            )
        return int(super().construct_yaml_int(node))  # type: ignore[arg-type]

    def construct_yaml_float(self, node: Node) -> float:
        text = str(self.construct_scalar(node))  # type: ignore[arg-type]
        self._ambiguous(node, text, text)
        return float(super().construct_yaml_float(node))  # type: ignore[arg-type]

    def _ambiguous(self, node: Node, text: str, body: str) -> None:
        if ":" in body:
            raise InputError(
                f"{self._where(node)}: {short(text, 30)} is a base-60 number in YAML 1.1 "
                "and text in YAML 1.2; expected a plain number (quote it for text)"
            )


_Loader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT_12, list("-+0123456789."))
# YAML 1.2's core schema has no timestamps: `vehicle_id: 2026-01-01` is that text, not a
# date (add_implicit_resolver above gave _Loader its own copy of the table)
for _first, _resolvers in _Loader.yaml_implicit_resolvers.items():
    _resolvers[:] = [(tag, rx) for tag, rx in _resolvers if tag != "tag:yaml.org,2002:timestamp"]
_Loader.add_constructor("tag:yaml.org,2002:int", _Loader.construct_yaml_int)
_Loader.add_constructor("tag:yaml.org,2002:float", _Loader.construct_yaml_float)


def load_yaml(text: str, source: str) -> Any:
    """Parse one YAML document from ``text``; ``source`` names it in error messages."""
    loader: _Loader | None = None
    try:
        loader = _Loader(text, source)
        return loader.get_single_data()
    except yaml.reader.ReaderError as exc:
        line = text.count("\n", 0, exc.position) + 1
        raise InputError(
            f"{source}: line {line}: character U+{exc.character:04X} is not allowed in YAML; "
            "expected printable text"
        ) from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f"{source}:{mark.line + 1}:{mark.column + 1}" if mark is not None else source
        problem = exc.problem or exc.context or "invalid YAML"
        raise InputError(f"{where}: invalid YAML: {short(problem, 120)[1:-1]}") from None
    except yaml.YAMLError as exc:
        first = str(exc).splitlines()[0] if str(exc) else "invalid YAML"
        raise InputError(f"{source}: YAML error: {short(first, 120)}") from None
    except RecursionError:
        raise InputError(f"{source}: nested too deeply; expected a few levels") from None
    finally:
        if loader is not None:
            loader.dispose()

"""Numbers as JSON can carry them: JSON has no NaN or infinity, so they become ``null``."""

from __future__ import annotations

import math
from typing import Any


def json_number(x: float) -> float | None:
    """``x`` itself when finite, else None (``null`` in JSON)."""
    return x if math.isfinite(x) else None


def json_clean(x: Any) -> Any:
    """``x`` with every non-finite float inside dicts, lists and tuples replaced by None."""
    if isinstance(x, float):
        return json_number(x)
    if isinstance(x, dict):
        return {k: json_clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [json_clean(v) for v in x]
    return x

"""Names that end up inside Zenoh key expressions (``truckd/<vehicle_id>/state``).

Only ``A-Z a-z 0-9 _ -``, 1 to 64 characters: no ``/`` (another key level), no ``*`` or
``$*`` (wildcards: ``*`` would publish on every vehicle's keys), no ``?`` or ``#``
(forbidden in Zenoh keys), no empty name (``truckd//state`` is not a key).
"""

from __future__ import annotations

import re

VEHICLE_ID_RE = re.compile(r"[A-Za-z0-9_-]{1,64}")
VEHICLE_ID_EXPECTED = "1 to 64 characters from A-Z a-z 0-9 _ - (a Zenoh key chunk)"


def vehicle_id_problem(value: str, key: str = "vehicle_id") -> str | None:
    """None when ``value`` is a safe vehicle id, else the one-line problem naming ``key``."""
    if VEHICLE_ID_RE.fullmatch(value):
        return None
    return f"key '{key}' = {value[:80]!r}: expected {VEHICLE_ID_EXPECTED}"

"""The platoons among the vehicles a monitor sees, in order (pure: messages in, text out).

A vehicle's health names its predecessor (``platoon.predecessor``); its state carries the
gap (m) to the truck ahead and ``platoon`` (CACC/ACC).  Chains are followed from each
leading truck (one that is nobody's follower) down to the last follower.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any


def predecessor(health: Mapping[str, Any]) -> str | None:
    """The predecessor named in a health message, None when not following."""
    p = health.get("platoon")
    if isinstance(p, Mapping):
        pred = p.get("predecessor")
        return pred if isinstance(pred, str) and pred else None
    return None


def platoons(
    vehicles: Mapping[str, tuple[Mapping[str, Any], Mapping[str, Any]]],
) -> list[list[str]]:
    """Chains of vehicle ids, lead first, from ``{id: (state, health)}``; a vehicle whose
    predecessor is not seen is listed behind that (unseen) id; vehicles in a cycle of
    predecessors (a misconfiguration) have no lead and are not listed."""
    ahead = {vid: predecessor(h) for vid, (_s, h) in vehicles.items()}
    behind: dict[str, list[str]] = {}
    for vid, pred in ahead.items():
        if pred is not None:
            behind.setdefault(pred, []).append(vid)
    heads = sorted(pred for pred in behind if ahead.get(pred) is None)
    chains: list[list[str]] = []
    for head in heads:
        chain, seen = [head], {head}
        while True:
            nxt = sorted(v for v in behind.get(chain[-1], []) if v not in seen)
            if not nxt:
                break
            chain.append(nxt[0])  # two trucks behind one: the first by id (misconfigured)
            seen.add(nxt[0])
        chains.append(chain)
    return chains


def _gap(x: Any) -> str:
    ok = isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)
    return f"{x:.2f} m" if ok else "- m"


def platoon_lines(vehicles: Mapping[str, tuple[Mapping[str, Any], Mapping[str, Any]]]) -> list[str]:
    """One line per platoon: ``lead -> [gap, CACC] follower -> ...``."""
    lines = []
    for chain in platoons(vehicles):
        parts = [chain[0] if chain[0] in vehicles else f"{chain[0]} (not seen)"]
        for vid in chain[1:]:
            s = vehicles[vid][0]
            mode = s.get("platoon")
            parts.append(f"[{_gap(s.get('gap'))} {mode if isinstance(mode, str) else '-'}] {vid}")
        lines.append("platoon: " + " -> ".join(parts))
    return lines

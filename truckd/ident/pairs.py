"""Pairs of causes, when one is not enough.

The greedy selection (:mod:`truckd.ident.diagnose`) accepts causes one at a time: a
cause that explains little alone while another one distorts the rest of the response
(a backlash behind a current limit, a Stribeck friction next to an input delay) is
never accepted.  Here the causes are ranked by their validation cost alone, the best
:data:`PAIR_TOP` are fitted in pairs with the one accepted (and with each other when
each helped alone), each jointly with the other, and a pair
is kept only when *each* member earns its place on the validation data: the pair beats
each member alone by the selection's rule (:func:`truckd.ident.selection.passes`), and
beats the model the greedy selection reached.  Pure numerics: the fitting and the
comparison are the caller's.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import TypeVar

from truckd.ident.selection import REL_MIN

PAIR_TOP = 3
"""Causes (the best alone on the validation data) fitted in pairs: 3 pairs at most."""

M = TypeVar("M")


def pair_order(
    single_cost: Mapping[str, float],
    base_cost: float,
    top: int = PAIR_TOP,
    skip: Sequence[str] = (),
    accepted: Sequence[str] = (),
) -> list[tuple[str, str]]:
    """Pairs to fit, best first by the sum of their validation costs alone: the cause
    already ``accepted`` with each of the ``top`` best others (a second cause can be
    hidden behind the first: it may not help alone), and pairs of the ``top`` best
    among those that lowered the validation cost alone (below ``base_cost``); ``skip``
    leaves causes out (those found physically impossible)."""
    others = sorted(
        (n for n in single_cost if n not in skip and n not in accepted),
        key=lambda n: single_cost[n],
    )[:top]
    pairs = [(a, b) for a in accepted for b in others]
    helping = [n for n in others if single_cost[n] < base_cost]
    pairs += [(a, b) for i, a in enumerate(helping) for b in helping[i + 1 :]]
    return sorted(pairs, key=lambda ab: single_cost[ab[0]] + single_cost[ab[1]])


def best_pair(
    pairs: Sequence[tuple[str, str]],
    current_cost: float,
    fit: Callable[[str, str], M | None],
    cost: Callable[[M], float],
    earns: Callable[[M, str], bool],
) -> M | None:
    """The pair model with the lowest validation cost among those where each member
    earns its place (``earns(model, name)``: the pair beats the other member alone) and
    that beat ``current_cost`` (the greedy selection's) by :data:`REL_MIN`; None when
    no pair does.  ``fit(a, b)`` fits a pair (None: physically impossible)."""
    best: M | None = None
    for a, b in pairs:
        m = fit(a, b)
        if m is None or not (earns(m, a) and earns(m, b)):
            continue
        if cost(m) >= (1.0 - REL_MIN) * current_cost:
            continue
        if best is None or cost(m) < cost(best):
            best = m
    return best

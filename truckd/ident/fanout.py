"""A stage's independent fits, one after another or side by side, with the same output.

The candidate stage fits every candidate alone on the seed; the selection tries the
remaining candidates on top of the accepted ones and fits the pairs: each of those fits
depends only on what came before the stage. :func:`fan_out` runs such a list through a
:class:`Mapper` (the plain loop by default; :class:`truckd.workers.ForkMap` on forked
workers when the caller gives one) and replays each task's progress lines in the tasks'
order, so the result and the progress read the same whichever way they ran. Pure
numerics: the caller chooses the mapper.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol, TypeVar

from truckd.ident.scoring import Progress

T = TypeVar("T")
R = TypeVar("R")


class Mapper(Protocol):
    """``map``: ``fn`` over ``items``, the results in the items' order."""

    def __call__(self, fn: Callable[[T], R], items: Sequence[T], /) -> list[R]: ...


def in_order(fn: Callable[[T], R], items: Sequence[T], /) -> list[R]:
    """The plain loop (the default :class:`Mapper`)."""
    return [fn(x) for x in items]


def side_by_side(mapper: Mapper) -> bool:
    """Whether ``mapper`` runs a list's items at once: not the plain loop; another mapper
    may say with a ``side_by_side()`` method (:class:`truckd.workers.ForkMap` does: not
    where it cannot fork), else it is taken to."""
    if mapper is in_order:
        return False
    ask = getattr(mapper, "side_by_side", None)
    return True if ask is None else bool(ask())


def as_start(result: T, start: T) -> T:
    """``start`` itself when ``result`` equals it: a fit no better than its start is
    its start, and a worker hands back an equal copy, not the object (the identity keys
    and ``is`` checks downstream then hold as in one process)."""
    return start if result is not start and result == start else result


def kept_lines(
    mapper: Mapper,
    task: Callable[[T, Progress], R],
    items: Sequence[T],
    work: Callable[[T], float] | None = None,
) -> list[tuple[R, list[str]]]:
    """``task(item, say)`` for each item through ``mapper``, each with the progress lines
    it said, in the items' order.  ``work``: the items' expected cost; the mapper starts
    the costliest first (a long task started last leaves the other workers idle)."""

    def kept(k: int) -> tuple[R, list[str]]:
        lines: list[str] = []
        return task(items[k], lines.append), lines

    order = list(range(len(items)))
    if work is not None:
        order.sort(key=lambda k: -work(items[k]))
    done = dict(zip(order, mapper(kept, order), strict=True))
    return [done[k] for k in range(len(items))]


def fan_out(
    mapper: Mapper,
    task: Callable[[T, Progress], R],
    items: Sequence[T],
    progress: Progress,
    work: Callable[[T], float] | None = None,
) -> list[R]:
    """``task(item, progress)`` for each item through ``mapper``; with the plain loop
    the progress goes straight through, else each task's lines are kept and said in the
    items' order once all are done (:func:`kept_lines`, ``work`` as there)."""
    if mapper is in_order or len(items) < 2:
        return [task(x, progress) for x in items]
    out: list[R] = []
    for result, lines in kept_lines(mapper, task, items, work):
        for line in lines:
            progress(line)
        out.append(result)
    return out

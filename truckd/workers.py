"""Independent CPU-bound tasks on forked copies of this process (the diagnosis's fits).

:class:`ForkMap` is a ``map`` that runs ``fn`` over ``items`` on up to ``workers`` child
processes forked for the call: each child starts as a copy of the parent (its data and
caches, nothing pickled on the way in) and sends back only the results, in order. It
falls back to running the tasks here, one after another, with the same results:

- with fewer than two workers or two tasks, or where ``fork`` does not exist;
- when this process runs other Python threads (a lock one of them holds at the fork
  would stay held in the child: pytest's workers, a daemon's threads);
- when a child dies (killed, out of memory): the whole list is run here again.

An exception a task raises in a child is raised here, as ``map`` would. The children
end with the call (the executor waits for them; on an exception here, Ctrl-C or SIGTERM,
for the tasks already running only); nothing outlives it.
"""

from __future__ import annotations

import contextlib
import gc
import os
import signal
import threading
import warnings
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar

T = TypeVar("T")
R = TypeVar("R")

_TASK: tuple[Callable[[Any], Any], Sequence[Any]] | None = None
"""The call's function and items, set before the children fork (they inherit it)."""


def _run(k: int) -> Any:
    """Run the ``k``-th task of the inherited call (in a child)."""
    if _TASK is None:  # pragma: no cover - only a child started outside ForkMap sees this
        raise RuntimeError("no task: a ForkMap child runs only what its parent set")
    fn, items = _TASK
    return fn(items[k])


_HELD_SIGNALS = frozenset(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name)
)
"""Signals held while a pool starts (Ctrl-C, systemd's stop, a closed terminal)."""


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """Hold :data:`_HELD_SIGNALS` in this thread for the block; one that arrives meanwhile
    is delivered when the block ends (its handler runs then). Threads started in the block
    inherit the held mask, so the signal is this thread's to handle."""
    if not hasattr(signal, "pthread_sigmask"):  # pragma: no cover - not POSIX
        yield
        return
    before = signal.pthread_sigmask(signal.SIG_BLOCK, _HELD_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def _release_signals() -> None:
    """A child's first step: take the signals its parent held at the fork (a Ctrl-C to the
    group that arrived meanwhile ends the child here, quietly: its parent has it too)."""
    if not hasattr(signal, "pthread_sigmask"):  # pragma: no cover - not POSIX
        return
    pending = signal.sigpending() & _HELD_SIGNALS
    if pending:
        os._exit(128 + int(min(pending)))
    signal.pthread_sigmask(signal.SIG_UNBLOCK, _HELD_SIGNALS)


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity where the OS tells it, else the count)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def can_fork() -> bool:
    """Whether a fork here is safe: the ``fork`` start method exists and no other
    Python thread runs."""
    import multiprocessing  # here: importing this module costs nothing until a fork

    return "fork" in multiprocessing.get_all_start_methods() and threading.active_count() == 1


class ForkMap:
    """``map(fn, items)`` on up to ``workers`` forked children (see the module)."""

    def __init__(self, workers: int) -> None:
        if workers < 1:
            raise ValueError(f"workers must be at least 1, got {workers}")
        self.workers = workers
        self.fallbacks = 0
        """Calls that ran here although they asked for children (a child died)."""

    def side_by_side(self) -> bool:
        """Whether a call now runs its items on children (not here, one after another)."""
        return self.workers > 1 and can_fork()

    def __call__(self, fn: Callable[[T], R], items: Sequence[T]) -> list[R]:
        n = min(self.workers, len(items))
        if n < 2 or not can_fork():
            return [fn(x) for x in items]
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor
        from concurrent.futures.process import BrokenProcessPool

        global _TASK
        _TASK = (fn, items)
        # The children's collector then leaves the inherited objects alone: it would
        # write to every one and copy each page the fork shares.
        gc.freeze()
        try:
            with warnings.catch_warnings():
                # Python 3.12+ warns on a fork beside native threads (OpenBLAS's pool,
                # idle under threadpoolctl's limit): the children run no code of theirs.
                warnings.filterwarnings(
                    "ignore", message=r".*use of fork\(\) may lead to deadlocks",
                    category=DeprecationWarning,
                )  # fmt: skip
                ctx = multiprocessing.get_context("fork")
                pool = ProcessPoolExecutor(
                    max_workers=n, mp_context=ctx, initializer=_release_signals
                )
                try:
                    # The pool starts (children forked, its manager thread started) on the
                    # first submit: a Ctrl-C in between would leave a pool that cannot be
                    # shut down ("cannot join thread before it is started") and children
                    # waiting for work. Held until the pool runs, then delivered here.
                    with _signals_held():
                        futures = [pool.submit(_run, k) for k in range(len(items))]
                    return [f.result() for f in futures]
                finally:  # on an exception (Ctrl-C, SIGTERM) the tasks not started are dropped
                    pool.shutdown(wait=True, cancel_futures=True)
        except BrokenProcessPool:
            self.fallbacks += 1
            return [fn(x) for x in items]
        finally:
            gc.unfreeze()
            _TASK = None

"""Independent CPU-bound tasks on forked copies of this process (the diagnosis's fits).

:class:`ForkMap` is a ``map`` that runs ``fn`` over ``items`` on up to ``workers`` child
processes forked for the call: each child starts as a copy of the parent (its data and
caches, nothing pickled on the way in) and sends back only the results, which come back
in order. It falls back to running the tasks here, one after another, with the same
results:

- with fewer than two workers or two tasks, or where ``fork`` does not exist;
- when this process runs other Python threads (a lock one of them holds at the fork
  would stay held in the child: pytest's workers, a daemon's threads);
- when a child dies (killed, out of memory): the whole list is run here again.

An exception a task raises in a child is raised here, as ``map`` would (the first item's
in order), with the child's traceback as a note.

Each child has two pipes of its own (its task numbers in, its pickled results out) and
shares no lock with anybody, so a child that dies at any instant, even halfway through a
result, costs only its own pipe. The children ignore Ctrl-C: the terminal's SIGINT reaches
the whole group, and this process, on Ctrl-C, SIGTERM or any exception, kills its
children (SIGKILL) and reaps them before the exception goes on. SIGTERM and SIGHUP end a
child at once. Nothing outlives the call; a child whose parent is gone reads the end of
its task pipe and exits.
"""

from __future__ import annotations

import contextlib
import gc
import os
import pickle
import select
import signal
import struct
import sys
import threading
import traceback
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, NoReturn, TypeVar

T = TypeVar("T")
R = TypeVar("R")

_TASK: tuple[Callable[[Any], Any], Sequence[Any]] | None = None
"""The call's function and items, set before the children fork (they inherit it)."""

_HELD_SIGNALS = frozenset(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name)
)
"""Signals held while the children are forked (Ctrl-C, systemd's stop, a closed terminal)."""

_INDEX = struct.Struct("<i")
"""A task number on a child's task pipe."""
_LENGTH = struct.Struct("<Q")
"""The length in bytes of the pickled result that follows it on a result pipe."""


class _ChildDiedError(Exception):
    """A child ended before it sent every result it owed."""


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """Hold :data:`_HELD_SIGNALS` for the block; one that arrives meanwhile is delivered
    when the block ends (its handler runs then)."""
    if not hasattr(signal, "pthread_sigmask"):  # pragma: no cover - not POSIX
        yield
        return
    before = signal.pthread_sigmask(signal.SIG_BLOCK, _HELD_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity where the OS tells it, else the count)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def can_fork() -> bool:
    """Whether a fork here is safe: ``os.fork`` exists and no other Python thread runs."""
    return hasattr(os, "fork") and threading.active_count() == 1


def _read_exactly(fd: int, n: int) -> bytes | None:
    """``n`` bytes from ``fd``; None at its end (the writer is gone)."""
    parts: list[bytes] = []
    while n > 0:
        chunk = os.read(fd, min(n, 1 << 20))
        if not chunk:
            return None
        parts.append(chunk)
        n -= len(chunk)
    return b"".join(parts)


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]


def _child(tasks: int, results: int, inherited: Sequence[int]) -> NoReturn:
    """A child's life: run the task numbers read from ``tasks``, send each outcome on
    ``results`` (``(True, value)`` or ``(False, exception, traceback text)``), exit at
    the end of ``tasks``. Never returns; no exit handler of the parent runs."""
    code = 0
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent answers Ctrl-C
        for sig in _HELD_SIGNALS - {signal.SIGINT}:
            signal.signal(sig, signal.SIG_DFL)  # a pending SIGTERM ends the child here
        if hasattr(signal, "pthread_sigmask"):
            signal.pthread_sigmask(signal.SIG_UNBLOCK, _HELD_SIGNALS)
        for fd in inherited:  # the parent's ends of the other children's pipes
            os.close(fd)
        assert _TASK is not None, "a ForkMap child runs only what its parent set"
        fn, items = _TASK
        while True:
            head = _read_exactly(tasks, _INDEX.size)
            if head is None:
                break
            (k,) = _INDEX.unpack(head)
            try:
                outcome: tuple[Any, ...] = (True, fn(items[k]))
            except BaseException as exc:  # the parent raises it
                outcome = (False, exc, traceback.format_exc())
            try:
                body = pickle.dumps(outcome, pickle.HIGHEST_PROTOCOL)
            except Exception as exc:  # a result or exception that does not pickle
                text = f"{type(exc).__name__}: {exc}"
                body = pickle.dumps((False, RuntimeError(f"a task's outcome: {text}"), ""))
            _write_all(results, _LENGTH.pack(len(body)) + body)
    except BrokenPipeError:  # the parent is gone
        code = 1
    except BaseException:  # pragma: no cover - a fault of this module: say it, end
        traceback.print_exc()
        code = 70
    finally:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
    os._exit(code)


@dataclass
class _Child:
    """One forked child, as the parent sees it."""

    pid: int
    tasks: int
    """The parent's end of its task pipe (write)."""
    results: int
    """The parent's end of its result pipe (read)."""
    running: int | None = None
    """The task number sent and not yet answered (one at a time)."""


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
        global _TASK
        _TASK = (fn, items)
        # The children's collector then leaves the inherited objects alone: it would
        # write to every one and copy each page the fork shares.
        gc.freeze()
        children: list[_Child] = []
        try:
            try:
                with _signals_held():
                    children = _fork(n)
                return _collect(children, len(items))
            finally:
                with _signals_held():  # a second Ctrl-C waits until they are reaped
                    _end(children)
        except _ChildDiedError:
            self.fallbacks += 1
        finally:
            gc.unfreeze()
            _TASK = None
        return [fn(x) for x in items]


def _fork(n: int) -> list[_Child]:
    """Fork ``n`` children (signals held by the caller: the list is whole when one of
    them is delivered)."""
    # nothing the parent buffered is written twice (a child flushes its own at exit)
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    children: list[_Child] = []
    for _ in range(n):
        task_r, task_w = os.pipe()
        result_r, result_w = os.pipe()
        inherited = [fd for c in children for fd in (c.tasks, c.results)]
        with warnings.catch_warnings():
            # Python 3.12+ warns on a fork beside native threads (OpenBLAS's pool, idle
            # under threadpoolctl's limit): the children run no code of theirs.
            warnings.filterwarnings(
                "ignore", message=r".*use of fork\(\) may lead to deadlocks",
                category=DeprecationWarning,
            )  # fmt: skip
            try:
                pid = os.fork()
            except OSError:
                for fd in (task_r, task_w, result_r, result_w):
                    os.close(fd)
                if children:
                    break  # fewer children than asked (out of processes): still a pool
                raise _ChildDiedError("no child could be forked") from None
        if pid == 0:  # pragma: no cover - the child (coverage does not follow a fork)
            os.close(task_w)
            os.close(result_r)
            _child(task_r, result_w, inherited)
        os.close(task_r)
        os.close(result_w)
        children.append(_Child(pid, task_w, result_r))
    return children


def _collect(children: list[_Child], count: int) -> list[Any]:
    """Hand the task numbers 0..count-1 out, the next to whichever child answers first
    (the costliest tasks come first, so the last ones even out), and gather the
    outcomes; the first exception in the items' order is raised once every item before
    it is in."""
    results: list[Any] = [None] * count
    answered = [False] * count
    failed: dict[int, tuple[BaseException, str]] = {}
    next_k = 0

    def send(c: _Child) -> None:
        nonlocal next_k
        if next_k < count and not failed:
            # marked running before it is written: a Ctrl-C landing right after the
            # write then kills this child too, not only the others (a child left
            # running its task would keep the reaping waiting until the task ends)
            c.running = next_k
            next_k += 1
            _write_all(c.tasks, _INDEX.pack(c.running))

    for c in children:
        send(c)
    by_fd = {c.results: c for c in children}
    poll = select.poll()
    for c in children:
        poll.register(c.results, select.POLLIN)
    while not all(answered[: min(failed, default=count)]):
        for fd, _ in poll.poll():
            c = by_fd[fd]
            head = _read_exactly(fd, _LENGTH.size)
            body = None if head is None else _read_exactly(fd, _LENGTH.unpack(head)[0])
            if body is None or c.running is None:
                raise _ChildDiedError(f"child {c.pid} ended with task {c.running} unanswered")
            k, c.running = c.running, None
            outcome = pickle.loads(body)
            answered[k] = True
            if outcome[0]:
                results[k] = outcome[1]
            else:
                failed[k] = (outcome[1], outcome[2])
            send(c)
    if failed:
        exc, text = failed[min(failed)]
        if text:
            exc.add_note(f"raised in a worker process:\n{text.rstrip()}")
        raise exc
    return results


def _end(children: list[_Child]) -> None:
    """Close the pipes, end the children and reap them: those that finished exit at the
    end of their task pipe; any still working (an exception here, Ctrl-C) is killed."""
    for c in children:
        with contextlib.suppress(OSError):
            os.close(c.tasks)
        with contextlib.suppress(OSError):
            os.close(c.results)
        if c.running is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(c.pid, signal.SIGKILL)
    for c in children:
        with contextlib.suppress(ChildProcessError):
            os.waitpid(c.pid, 0)

"""How a foreground tool that runs until stopped (``truckd monitor``, its Foxglove relay)
hears the signals that stop it.

SIGTERM (a service manager, ``kill``) is the orderly stop: the loop ends, the tool closes
what it holds and exits 0 (reference section 1).  SIGINT (Ctrl-C) stays an interruption:
KeyboardInterrupt, exit 130.  Only the main thread can install handlers; from another
thread the process's handlers stay as they are.  :func:`ticks` is the tools' loop: a
period's sleep, then one round, until a duration has passed.
"""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType


class StopRequested(BaseException):
    """SIGTERM asked the tool to stop: end the loop, close, exit 0 (a BaseException, as
    KeyboardInterrupt: no ``except Exception`` on the way takes it for an error)."""


def _terminated(_signum: int, _frame: FrameType | None) -> None:
    raise StopRequested


def _interrupted(_signum: int, _frame: FrameType | None) -> None:
    raise KeyboardInterrupt


@contextmanager
def stop_signals() -> Iterator[None]:
    """SIGTERM ends the block (:class:`StopRequested`, taken here: the code after the
    block runs as after its normal end) and SIGINT raises KeyboardInterrupt, in the main
    thread while the block runs; the previous handlers come back after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {
        signal.SIGTERM: signal.signal(signal.SIGTERM, _terminated),
        signal.SIGINT: signal.signal(signal.SIGINT, _interrupted),
    }
    try:
        yield
    except StopRequested:
        pass
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def ticks(interval: float, duration: float | None, clock: Callable[[], float]) -> Iterator[None]:
    """Sleep ``interval`` s, then yield, until ``duration`` s of ``clock`` have passed
    (the last sleep shortened to end there; None: forever)."""
    t_end = None if duration is None else clock() + duration
    while t_end is None or clock() < t_end:
        time.sleep(interval if t_end is None else max(0.0, min(interval, t_end - clock())))
        yield

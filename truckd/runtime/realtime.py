"""Real-time set-up of the loop thread: garbage collection frozen, SCHED_FIFO and
mlockall when permitted.  Each step logs one clear line saying what it did or why not.

Call :func:`setup_realtime` after every other thread (Zenoh, telemetry, recorder) has
started and right before the loop: SCHED_FIFO applies to the calling thread only, and gc
freezing moves every object allocated during start-up out of the collector's sight.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import logging
import os
import resource
import threading
from dataclasses import dataclass, field

log = logging.getLogger("truckd.realtime")

MCL_CURRENT = 1
MCL_FUTURE = 2


@dataclass
class RealtimeReport:
    """What :func:`setup_realtime` achieved."""

    gc_frozen: int = 0
    sched_fifo: bool = False
    mlock: bool = False
    notes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, object]:
        return {
            "gc_frozen": self.gc_frozen,
            "sched_fifo": self.sched_fifo,
            "mlock": self.mlock,
            "notes": list(self.notes),
        }


def freeze_gc() -> int:
    """Collect once, then freeze: start-up objects are never scanned again.

    Returns the number of frozen objects.  Generation-0 threshold raised so the few
    allocations per cycle rarely trigger a collection.
    """
    gc.collect()
    gc.freeze()
    gc.set_threshold(50_000, 50, 1000)
    return gc.get_freeze_count()


def _note(rep: RealtimeReport, level: int, msg: str) -> None:
    rep.notes.append(msg)
    log.log(level, "%s", msg)


def _sched_fifo(priority: int, rep: RealtimeReport) -> None:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (PermissionError, OSError) as exc:
        _note(
            rep,
            logging.WARNING,
            f"SCHED_FIFO {priority} not permitted ({exc.strerror}): running with normal "
            "scheduling; grant CAP_SYS_NICE or LimitRTPRIO (see systemd/truckd.service)",
        )
        return
    rep.sched_fifo = True
    _note(rep, logging.INFO, f"SCHED_FIFO priority {priority} set on the control loop thread")


def _mlockall(rep: RealtimeReport) -> None:
    soft, _hard = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    if soft != resource.RLIM_INFINITY and os.geteuid() != 0:
        # with a finite limit, MCL_FUTURE would make later allocations fail: skip it
        _note(
            rep,
            logging.WARNING,
            f"mlockall skipped: RLIMIT_MEMLOCK is {soft} B, not unlimited "
            "(set LimitMEMLOCK=infinity); page faults may add latency",
        )
        return
    libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
    if libc.mlockall(MCL_CURRENT | MCL_FUTURE) != 0:
        err = ctypes.get_errno()
        _note(rep, logging.WARNING, f"mlockall failed ({os.strerror(err)}): memory not locked")
        return
    rep.mlock = True
    _note(rep, logging.INFO, "mlockall(MCL_CURRENT|MCL_FUTURE): memory locked")


def setup_realtime(enabled: bool, priority: int) -> RealtimeReport:
    """Freeze gc always; SCHED_FIFO and mlockall when ``enabled`` and permitted."""
    rep = RealtimeReport()
    rep.gc_frozen = freeze_gc()
    _note(rep, logging.INFO, f"gc frozen after start-up ({rep.gc_frozen} objects)")
    if not enabled:
        _note(rep, logging.INFO, "real-time scheduling disabled by configuration")
        return rep
    _sched_fifo(priority, rep)
    _mlockall(rep)
    return rep


def promote_helpers(priority: int, rep: RealtimeReport, prefix: str = "truckd-") -> None:
    """SCHED_FIFO at ``priority`` for the daemon's own helper threads (named ``prefix``:
    telemetry, recorder).  They take the GIL the loop needs: at normal priority a busy
    host deschedules one while it holds the GIL and the real-time loop waits behind it
    (priority inversion; measured: cycles waiting seconds at load 9 on 2 cores).  Their
    work is short and event-driven, so they cannot starve the machine."""
    names = []
    for th in threading.enumerate():
        tid = th.native_id
        if not th.name.startswith(prefix) or tid is None or not th.is_alive():
            continue
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
        except OSError as exc:
            _note(rep, logging.WARNING, f"SCHED_FIFO for {th.name} failed ({exc.strerror})")
            continue
        names.append(th.name)
    if names:
        _note(rep, logging.INFO, f"SCHED_FIFO priority {priority} on {', '.join(names)}")


def unfreeze_gc() -> None:
    """Undo :func:`freeze_gc` (for tests and in-process runs)."""
    gc.unfreeze()
    gc.set_threshold(700, 10, 10)

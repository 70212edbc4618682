"""Real-time set-up of the loop thread: garbage collection frozen, SCHED_FIFO, mlockall
and a CPU wake-up latency request when permitted.  Each step logs one clear line saying
what it did or why not.

The wake-up latency request is Linux's PM QoS interface (``/dev/cpu_dma_latency``, as
``cyclictest`` uses it): while the file stays open, no core enters an idle state whose
exit takes longer than the value written (µs).  A control loop sleeps about 90 % of each
period; from a deep idle state every cycle starts with cold caches and a slow wake-up.
Measured here (2-vCPU VM, haltpoll idle driver, ``benchmarks/loop_bench.py`` run
alternately): the daemon's cycle compute p50 fell from 939-1047 µs to 775-827 µs with 0 µs.
On a board without a cpuidle driver it changes nothing.  It costs power (the cores
poll instead of sleeping), so it is applied with ``runtime.realtime`` only and can be
switched off with ``runtime.cpu_latency_us: -1``.

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
import struct
import threading
from dataclasses import dataclass, field

log = logging.getLogger("truckd.realtime")

MCL_CURRENT = 1
MCL_FUTURE = 2
CPU_LATENCY_DEV = "/dev/cpu_dma_latency"
"""Linux PM QoS: the CPU wake-up latency request (a 32-bit integer, µs), held while open."""
_latency_fd: int | None = None


@dataclass
class RealtimeReport:
    """What :func:`setup_realtime` achieved."""

    gc_frozen: int = 0
    sched_fifo: bool = False
    mlock: bool = False
    cpu_latency_us: int | None = None
    """The CPU wake-up latency held (µs); None when none is requested."""
    kernel_preemption: str = "unknown"
    """The kernel's preemption model (:func:`preemption_model`): ``rt``, ``full``,
    ``lazy``, ``voluntary``, ``none`` or ``unknown``."""
    notes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, object]:
        return {
            "gc_frozen": self.gc_frozen,
            "sched_fifo": self.sched_fifo,
            "mlock": self.mlock,
            "cpu_latency_us": self.cpu_latency_us,
            "kernel_preemption": self.kernel_preemption,
            "notes": list(self.notes),
        }


PREEMPTIBLE = ("rt", "full", "lazy")
"""Preemption models under which a SCHED_FIFO thread that wakes runs at once, even while
another task is inside the kernel (``lazy`` defers only fair tasks)."""

_MODES = ("none", "voluntary", "full", "lazy")


def preemption_model(
    uname_version: str,
    cmdline: str = "",
    config: str = "",
    debugfs: str = "",
    realtime_flag: str = "",
) -> tuple[str, str]:
    """The kernel's preemption model and how it was known, from the texts the kernel
    gives: ``/sys/kernel/realtime`` (``1`` on PREEMPT_RT), ``/sys/kernel/debug/sched/preempt``
    (the dynamic mode in parentheses), ``uname -v``, ``/proc/cmdline`` (``preempt=``) and
    the build configuration (``/proc/config.gz``); each may be empty (not readable).

    Under ``none`` or ``voluntary`` a task inside a system call or a kernel thread keeps
    its CPU until it reaches a preemption point: a SCHED_FIFO loop that wakes meanwhile
    waits, for milliseconds on a busy machine."""
    if realtime_flag.strip() == "1" or "PREEMPT_RT" in uname_version.split():
        return "rt", "PREEMPT_RT kernel"
    chosen = debugfs.split("(", 1)[1].split(")", 1)[0] if "(" in debugfs else ""
    if chosen in _MODES:
        return chosen, "sched/preempt"
    words = uname_version.split()
    dynamic = "PREEMPT_DYNAMIC" in words
    if dynamic:
        for arg in cmdline.split():
            if arg.startswith("preempt=") and arg[8:] in _MODES:
                return arg[8:], "preempt= on the kernel command line"
    options = set(config.splitlines())
    if "CONFIG_PREEMPT_RT=y" in options:
        return "rt", "the kernel's configuration"
    for mode in _MODES:  # the configuration's choice: exactly one of these is set
        if f"CONFIG_PREEMPT{'' if mode == 'full' else '_' + mode.upper()}=y" in options:
            return mode, "the default of the kernel's configuration"
    if dynamic:
        return "unknown", "a PREEMPT_DYNAMIC kernel whose mode is not readable"
    if "PREEMPT" in words:
        return "full", "uname"
    if "PREEMPT_LAZY" in words:
        return "lazy", "uname"
    return "unknown", "neither uname nor the kernel's configuration says"


def _read_text(path: str, gzipped: bool = False) -> str:
    try:
        if gzipped:
            import gzip

            with gzip.open(path, "rt", errors="replace") as f:
                return f.read()
        with open(path, errors="replace") as f:
            return f.read()
    except OSError:
        return ""


def _kernel_preemption(rep: RealtimeReport) -> None:
    mode, how = preemption_model(
        os.uname().version,
        _read_text("/proc/cmdline"),
        _read_text("/proc/config.gz", gzipped=True),
        _read_text("/sys/kernel/debug/sched/preempt"),
        _read_text("/sys/kernel/realtime"),
    )
    rep.kernel_preemption = mode
    if mode in PREEMPTIBLE:
        _note(rep, logging.INFO, f"kernel preemption: {mode} ({how})")
        return
    _note(
        rep,
        logging.WARNING,
        f"kernel preemption: {mode} ({how}): the loop can wait behind other tasks' kernel "
        "work and miss deadlines; use a PREEMPT_RT kernel or boot with preempt=full "
        '(docs/daemon.md, "Performance")',
    )


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


def hold_cpu_latency(us: int, rep: RealtimeReport, device: str = CPU_LATENCY_DEV) -> None:
    """Ask the kernel to keep every core's wake-up latency at most ``us`` µs (PM QoS,
    module docstring) until :func:`release_cpu_latency` or the process ends (the kernel
    drops the request when the file closes).  A second call replaces the value."""
    global _latency_fd
    fd = _latency_fd
    try:
        if fd is None:
            fd = os.open(device, os.O_WRONLY | os.O_CLOEXEC)
        os.write(fd, struct.pack("=i", us))
    except OSError as exc:
        if fd is not None and fd != _latency_fd:
            os.close(fd)
        _note(
            rep,
            logging.WARNING,
            f"CPU wake-up latency {us} us not requested ({device}: {exc.strerror}): cores "
            "may sleep in deep idle states between cycles (slower cycles); allow the "
            "device (see systemd/60-truckd-cpu-latency.rules) or set cpu_latency_us: -1",
        )
        return
    _latency_fd = fd
    rep.cpu_latency_us = us
    _note(rep, logging.INFO, f"CPU wake-up latency held at {us} us ({device})")


def release_cpu_latency() -> None:
    """Drop the wake-up latency request (the daemon's shutdown; the kernel drops it too
    when the process ends)."""
    global _latency_fd
    fd, _latency_fd = _latency_fd, None
    if fd is not None:
        os.close(fd)


def setup_realtime(enabled: bool, priority: int, cpu_latency_us: int = -1) -> RealtimeReport:
    """Freeze gc always; SCHED_FIFO, mlockall and (``cpu_latency_us`` >= 0) the CPU
    wake-up latency request when ``enabled`` and permitted."""
    rep = RealtimeReport()
    rep.gc_frozen = freeze_gc()
    _note(rep, logging.INFO, f"gc frozen after start-up ({rep.gc_frozen} objects)")
    if not enabled:
        _note(rep, logging.INFO, "real-time scheduling disabled by configuration")
        return rep
    _sched_fifo(priority, rep)
    _kernel_preemption(rep)
    _mlockall(rep)
    if cpu_latency_us >= 0:
        hold_cpu_latency(cpu_latency_us, rep)
    return rep


ZENOH_CALLBACK_THREAD = "pyo3-closure"
"""Part of the name zenoh-python gives the Python threads that run our callbacks (the
params queryable, the inject and plan subscribers)."""


def promote_helpers(
    priority: int,
    rep: RealtimeReport,
    prefix: str = "truckd-",
    also: tuple[str, ...] = (ZENOH_CALLBACK_THREAD,),
) -> None:
    """SCHED_FIFO at ``priority`` for the daemon's helper threads: its own (named
    ``prefix``: telemetry, recorder) and zenoh-python's callback threads (a name containing
    one of ``also``).  Every one of them takes the GIL the loop needs: at normal priority a
    busy host deschedules one while it holds the GIL and the real-time loop waits behind
    it (priority inversion; measured: cycles waiting seconds at load 9 on 2 cores, and,
    with only the zenoh callback threads left at normal priority, cycles of 12-216 ms that
    spent 1.2 ms computing at load 3).  Their work is short and event-driven, so they
    cannot starve the machine."""
    names = []
    for th in threading.enumerate():
        tid = th.native_id
        ours = th.name.startswith(prefix) or any(a in th.name for a in also)
        if not ours or tid is None or not th.is_alive():
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

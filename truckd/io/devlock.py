"""One daemon per device: an advisory lock taken before the device is opened.

:func:`claim_device` locks a file named after the device (the serial device's real path,
or the CAN interface and channel) with ``flock(LOCK_EX | LOCK_NB)`` and writes its pid
into it.  A second process asking for the same device gets :class:`DeviceBusyError` at
once, naming the device and the pid holding it, before it has opened (let alone written
to) the device.  The lock dies with its process (the kernel drops it), so a crashed
daemon never leaves the device claimed.

Lock directory: ``$TRUCKD_LOCK_DIR`` when set, else the first writable of ``/run/lock``,
``$XDG_RUNTIME_DIR`` and the temporary directory.  Processes that see different
directories (other users, a service with a private /run) are kept apart by the device
itself: the serial link opens the tty with ``flock`` and ``TIOCEXCL``
(:mod:`truckd.io.serial_link`).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import re
from pathlib import Path

from truckd.errors import TruckdError

log = logging.getLogger("truckd.devlock")

LOCK_DIR_ENV = "TRUCKD_LOCK_DIR"


class DeviceBusyError(TruckdError):
    """The device is held by another process (exit code 1: not bad input)."""


def lock_dir() -> Path:
    """Where lock files live (see module docstring)."""
    import tempfile  # only here: keeps `truckd run` import-lean

    env = os.environ.get(LOCK_DIR_ENV)
    if env:
        return Path(env)
    candidates = ["/run/lock", os.environ.get("XDG_RUNTIME_DIR", ""), tempfile.gettempdir()]
    for c in candidates:
        if c and os.path.isdir(c) and os.access(c, os.W_OK | os.X_OK):
            return Path(c)
    return Path(tempfile.gettempdir())


def serial_keys(device: str) -> list[str]:
    """Lock keys of a serial device: its path as given and its real path (a symlink and
    its target, or two names of one device, share a lock).  URLs (``loop://``) have none."""
    if "://" in device:
        return []
    given = os.path.abspath(device)
    real = os.path.realpath(device)
    return [given] if given == real else [given, real]


SERIAL_LINE_CAN = frozenset({"slcan", "serial", "robotell", "seeedstudio"})
"""python-can interfaces whose channel is a serial device (``/dev/ttyACM0@115200``)."""


def can_keys(interface: str, channel: str) -> list[str]:
    """Lock keys of a CAN interface + channel; none for python-can's ``virtual`` buses,
    which live inside one process.  A CAN adapter on a serial line (slcan and the like)
    is its serial device: the keys of :func:`serial_keys` for the channel without its
    ``@bitrate`` (a symlink, the same path with another rate, or the serial backend on
    the same tty share the lock)."""
    if interface == "virtual":
        return []
    if interface in SERIAL_LINE_CAN:
        keys = serial_keys(channel.split("@", 1)[0])
        if keys:
            return keys
    return [f"can:{interface}:{channel}"]


def _file_name(key: str) -> str:
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", key).strip("_")
    return f"truckd-{safe[-150:]}.lock"


def holder_pid(path: Path) -> int | None:
    """The pid written in a lock file (None when unreadable or empty)."""
    try:
        text = path.read_text(encoding="ascii", errors="replace").strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


class DeviceLock:
    """Locks held on one device (released by :meth:`release` or process exit)."""

    def __init__(self, what: str, keys: list[str]) -> None:
        self.what = what
        self.keys = keys
        self._held: list[tuple[Path, int]] = []

    @property
    def held(self) -> bool:
        """True while every lock is held (a device without keys counts as held)."""
        return len(self._held) == len(self.keys)

    def acquire(self) -> DeviceLock:
        """Take every lock or none; DeviceBusyError when another process holds one."""
        d = lock_dir()
        try:
            d.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise TruckdError(f"{self.what}: cannot create lock directory {d}: {exc}") from None
        try:
            for key in self.keys:
                self._held.append(self._take(d / _file_name(key)))
        except BaseException:
            self.release()
            raise
        return self

    def _take(self, path: Path) -> tuple[Path, int]:
        while True:
            try:
                fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            except PermissionError:  # another user's lock file: locking works read-only
                fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
            except OSError as exc:
                raise TruckdError(f"{self.what}: cannot create lock {path}: {exc}") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                os.close(fd)
                if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                    raise TruckdError(f"{self.what}: cannot lock {path}: {exc}") from None
                pid = holder_pid(path)
                by = f"process {pid}" if pid is not None else "another process"
                raise DeviceBusyError(
                    f"{self.what} is in use by {by} (lock {path}); one daemon per device"
                ) from None
            # the holder before us may have removed the file between our open and lock
            try:
                same = os.stat(path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)
                os.write(fd, f"{os.getpid()}\n".encode())
            return path, fd

    def release(self) -> None:
        """Remove and unlock (idempotent; removal while locked keeps the hand-over safe)."""
        held, self._held = self._held, []
        for path, fd in reversed(held):
            with contextlib.suppress(OSError):
                os.unlink(path)
            with contextlib.suppress(OSError):
                os.close(fd)


def claim_device(what: str, keys: list[str]) -> DeviceLock:
    """Lock the device named ``what`` by ``keys`` (DeviceBusyError when taken)."""
    lock = DeviceLock(what, keys).acquire()
    if keys:
        log.debug("%s: locked (%s)", what, ", ".join(keys))
    return lock


def pids_holding(device: str) -> list[int]:
    """Processes (that this user may inspect) with ``device`` open, from /proc."""
    real = os.path.realpath(device)
    out: list[int] = []
    try:
        procs = [p for p in os.listdir("/proc") if p.isdigit()]
    except OSError:
        return out
    for p in procs:
        if int(p) == os.getpid():
            continue
        try:
            fds = os.listdir(f"/proc/{p}/fd")
            if any(os.readlink(f"/proc/{p}/fd/{fd}") == real for fd in fds):
                out.append(int(p))
        except OSError:
            continue
    return out

"""The daemon's own log: the contract CSV format (reference section 3) plus extra
columns, rotated by size, written by a background thread.

The loop calls :meth:`Recorder.record` with one tuple of floats per cycle (an append to a
bounded deque: no formatting, no I/O in the loop).  The writer thread formats, writes,
flushes every ``flush_period_s`` and starts a new file (with its own header, so every
file feeds ``identify``/``diagnose`` on its own) once the current one reaches
``max_bytes``; beyond ``keep`` files the oldest of this recorder's files are deleted.
:meth:`stop` writes everything still queued, flushes and closes.

File names are unique even for two daemons started in one directory within the same
second: ``<prefix>-<UTC stamp>-p<pid>-NNNN.csv``, created exclusively (``O_EXCL``); a name
that exists already gets a ``-K`` suffix, so no daemon ever appends to another's file.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import deque
from collections.abc import Sequence
from pathlib import Path
from typing import BinaryIO, Protocol

from truckd.config.runtime import RecorderConfig
from truckd.errors import TruckdError

log = logging.getLogger("truckd.recorder")


class Sidecar(Protocol):
    """A second log written on the recorder's thread and rotated with the CSV (the MCAP
    log, :class:`truckd.runtime.mcap_log.McapLog`; the received-message log,
    :class:`truckd.runtime.rxlog.RxLog`), opened as ``<csv stem><suffix>``.  Its methods
    never raise."""

    @property
    def suffix(self) -> str: ...
    def open(self, path: Path, rows: int = 0) -> None:
        """Start ``path``; ``rows``: the rows the CSV files hold so far (the CSV rotated
        after them)."""
        ...

    def write_pending(self, rows: int | None = None) -> None:
        """Write what is queued; ``rows``: the rows the CSV files hold so far (a sidecar
        with one record per row writes no further)."""
        ...

    def flush(self, force: bool = False) -> None: ...
    def close(self) -> None: ...


class Recorder:
    """Size-rotated CSV log with a fixed set of columns."""

    def __init__(
        self,
        cfg: RecorderConfig,
        columns: Sequence[str],
        prefix: str = "truckd",
        maxlen: int = 100_000,
        sidecar: Sidecar | None = None,
        sidecars: Sequence[Sidecar | None] = (),
    ) -> None:
        if len(set(columns)) != len(columns) or "t" not in columns:
            raise ValueError(f"columns must be unique and include 't': {columns!r}")
        self.cfg = cfg
        self.columns = tuple(columns)
        self.dir = Path(cfg.dir)
        self.prefix = prefix
        self.sidecars = [s for s in (sidecar, *sidecars) if s is not None]
        """Opened beside each CSV as ``<stem><suffix>``, written after it."""
        self._q: deque[tuple[float, ...]] = deque(maxlen=maxlen)
        self._event = threading.Event()
        self._stop = False
        self._thread: threading.Thread | None = None
        self._fh: BinaryIO | None = None
        self._bytes = 0  # written or attempted in the current file (rotation)
        self._on_disk = 0  # written to the current file
        self._index = 0
        self._stamp = ""
        self.files: list[Path] = []  # every file this recorder opened, oldest first
        self.rows = 0
        self.dropped = 0
        self.errors = 0

    def start(self) -> None:
        """Create the directory and the first file (raises TruckdError when impossible)."""
        self._stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime())
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            self._open_next()
        except OSError as exc:
            raise TruckdError(f"cannot write logs in {self.dir}: {exc.strerror or exc}") from None
        self._thread = threading.Thread(target=self._run, name="truckd-recorder", daemon=True)
        self._thread.start()

    @property
    def path(self) -> Path | None:
        """The file being written."""
        return self.files[-1] if self.files else None

    def _open_next(self) -> None:
        fh, self._fh = self._fh, None  # never keep a closed file (a full disk at rotation)
        if fh is not None:
            try:
                fh.close()
            except OSError as exc:  # its last buffered rows are lost: counted, go on
                self.errors += 1
                log.error("log close failed: %s", exc.strerror)
        self._index += 1
        base = f"{self.prefix}-{self._stamp}-p{os.getpid()}-{self._index:04d}"
        p, fh = self._create(base)
        self._fh = fh
        self._bytes = self._on_disk = 0
        self.files.append(p)
        for sc in self.sidecars:
            sc.open(p.with_suffix(sc.suffix), self.rows)
        while len(self.files) > self.cfg.keep:
            old = self.files.pop(0)
            try:
                old.unlink()
            except OSError as exc:
                log.warning("cannot delete old log %s: %s", old, exc.strerror)
        self._write_all(fh, (",".join(self.columns) + "\n").encode())  # may fail: last

    def _create(self, base: str) -> tuple[Path, BinaryIO]:
        """A new file ``base.csv`` (``base-K.csv`` when taken), created exclusively,
        unbuffered (every write goes to the OS whole: see :meth:`_write_all`)."""
        for k in range(1000):
            p = self.dir / (f"{base}.csv" if k == 0 else f"{base}-{k}.csv")
            try:
                return p, open(p, "xb", buffering=0)
            except FileExistsError:
                continue
        raise FileExistsError(f"{self.dir}: no free name for {base}.csv")

    def record(self, values: Sequence[float]) -> None:
        """Queue one row, values in column order (never blocks)."""
        if len(self._q) == self._q.maxlen:
            self.dropped += 1
        self._q.append(tuple(values))
        if len(self._q) >= 64:
            self._event.set()

    def _write_all(self, fh: BinaryIO, data: bytes) -> None:
        """Append whole rows with unbuffered writes: the file never holds a torn row, even
        when the process is killed (the OS has every byte of a write that returned) or the
        disk fills (a write cut short is truncated back to the last whole row)."""
        start, done = self._on_disk, 0
        self._bytes += len(data)  # towards rotation, written or not (as a full disk stays)
        try:
            while done < len(data):
                n = fh.write(data[done:])
                if not n:
                    raise OSError(28, "no space left on device")
                done += n
        except OSError:
            if done:
                try:
                    fh.truncate(start)
                    fh.seek(start)
                except OSError:
                    pass
            raise
        self._on_disk = start + done

    def _write_pending(self) -> None:
        if self._fh is None and self.files:  # a file could not be opened: try again
            self._open_next()
        fh = self._fh
        if fh is None:
            return
        n = len(self.columns)
        lines: list[str] = []
        size = self._bytes
        while self._q:
            row = self._q.popleft()
            if len(row) != n:
                self.errors += 1
                continue
            line = ",".join(format(x, ".10g") for x in row) + "\n"
            lines.append(line)
            size += len(line)
            if size >= self.cfg.max_bytes:
                data, lines = "".join(lines).encode(), []
                try:
                    self._write_all(fh, data)
                    self.rows += data.count(b"\n")
                finally:
                    self._open_next()
                fh = self._fh
                assert fh is not None
                size = self._bytes
        if lines:
            self._write_all(fh, "".join(lines).encode())
            self.rows += len(lines)

    def _run(self) -> None:
        period = max(self.cfg.flush_period_s, 0.01)
        while True:
            self._event.wait(period)
            self._event.clear()
            try:
                self._write_pending()  # unbuffered: every row is with the OS
                for sc in self.sidecars:
                    sc.write_pending(self.rows)
                    sc.flush()
            except OSError as exc:
                self.errors += 1
                if self.errors <= 3:
                    log.error("log write failed: %s", exc.strerror)
            if self._stop:
                return

    def discard(self) -> None:
        """Stop and delete this recorder's files if no row was written (a daemon that
        failed to start leaves no header-only log behind)."""
        self.stop()
        if self.rows:
            return
        for p in self.files:
            try:
                p.unlink()
            except OSError as exc:
                log.warning("cannot delete empty log %s: %s", p, exc.strerror)
        self.files.clear()

    def stop(self) -> None:
        """Write everything queued, flush and close (idempotent)."""
        self._stop = True
        self._event.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._fh is not None:
            try:
                self._write_pending()
                self._fh.close()
            except OSError as exc:
                self.errors += 1
                log.error("log close failed: %s", exc.strerror)
            self._fh = None
        for sc in self.sidecars:
            sc.close()

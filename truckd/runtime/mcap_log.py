"""MCAP logs of the telemetry messages (reference section 5), readable by Foxglove and
PlotJuggler.

Channels ``/truckd/<vehicle_id>/state``, ``/health`` and ``/plan``, JSON messages, one JSON
schema per channel (:mod:`truckd.runtime.msg_schemas`, schema encoding ``jsonschema``).
The log time of a message is the time of the cycle that made it, in ns: wall-clock
(Unix epoch) in the daemon, taken once at the first message and advanced by the loop's own
``t`` after that, so the spacing is the loop's; simulated time from 0 in ``truckd sim``.

:class:`McapFile` writes one file.  :class:`McapLog` is the daemon's: the loop thread only
appends to a bounded deque (``record_state``/``record_health``/``record_plan``: no JSON, no
I/O; the oldest message is dropped and counted when full); the CSV recorder's writer thread
(:class:`truckd.runtime.recorder.Recorder`, which it is a sidecar of) builds the deferred
state messages (:class:`truckd.runtime.deferred.Deferred`), encodes and writes,
releasing the GIL every ``YIELD_S`` (so the loop thread, waking, waits about that long at
most, not the interpreter's 5 ms switch interval),
closes a chunk at least every ``flush_period_s`` (so a SIGKILL loses at most that much: the
file reads up to its last complete chunk, see :func:`read_mcap`), rotates with the CSV
(``<csv stem>.mcap`` beside each CSV) and finishes the file (summary, footer) on stop.
The CSV stays the input of ``identify``/``diagnose``.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import math
import os
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from mcap.exceptions import McapError
from mcap.records import Channel, Footer, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from truckd.config.runtime import RecorderConfig
from truckd.jsonsafe import json_clean
from truckd.runtime.deferred import MessageSource, resolve
from truckd.runtime.msg_schemas import KINDS, MESSAGE_ENCODING, SCHEMA_ENCODING, schema_bytes
from truckd.runtime.msg_schemas import topic as topic_of

log = logging.getLogger("truckd.mcap")

COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}
"""Chunk compression by its configuration name."""

YIELD_S = 200e-6
"""The writer releases the GIL at least this often while it encodes and writes."""

Extra = Callable[[], Mapping[str, Any]] | None
"""Computed on the writer thread and merged into a health message (costly statistics)."""


def to_json(msg: Mapping[str, Any]) -> bytes:
    """Strict JSON bytes of a message: NaN and infinities become ``null`` (JSON has none)."""
    try:
        return json.dumps(msg, allow_nan=False, separators=(",", ":")).encode()
    except ValueError:  # a non-finite number somewhere: the rare path
        return json.dumps(json_clean(dict(msg)), allow_nan=False, separators=(",", ":")).encode()


class McapFile:
    """One MCAP file with the three JSON channels of one vehicle.

    ``chunk_bytes``: a chunk is closed (compressed, written) once it holds this much;
    :meth:`flush` closes it earlier.  Raises OSError when the file cannot be created.
    """

    def __init__(
        self,
        path: str | Path,
        vehicle_id: str,
        *,
        compression: str = "zstd",
        chunk_bytes: int = 256 * 1024,
        metadata: Mapping[str, str] | None = None,
    ) -> None:
        self.path = Path(path)
        self._fh: IO[bytes] | None = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        with contextlib.suppress(OSError):  # held while writing: recovery leaves it alone
            fcntl.flock(self._fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        self._w = Writer(self._fh, chunk_size=chunk_bytes, compression=COMPRESSION[compression])
        self._w.start(profile="", library="truckd")
        if metadata:
            self._w.add_metadata("truckd", dict(metadata))
        self._channels: dict[str, int] = {}
        self._seq: dict[str, int] = {}
        for kind in KINDS:
            sid = self._w.register_schema(f"truckd.{kind}", SCHEMA_ENCODING, schema_bytes(kind))
            self._channels[kind] = self._w.register_channel(
                topic_of(vehicle_id, kind), MESSAGE_ENCODING, sid
            )
            self._seq[kind] = 0
        self.messages = 0

    def write(self, kind: str, log_time_ns: int, data: bytes) -> None:
        """Append one JSON message on channel ``kind`` (state, health or plan)."""
        seq = self._seq[kind]
        self._seq[kind] = seq + 1
        self._w.add_message(self._channels[kind], log_time_ns, data, log_time_ns, seq & 0xFFFFFFFF)
        self.messages += 1

    def flush(self) -> None:
        """Close the chunk in progress and push everything to the OS."""
        self._w.flush()  # type: ignore[no-untyped-call]

    def close(self) -> None:
        """Write the summary and footer and close the file (idempotent)."""
        if self._fh is None:
            return
        try:
            self._w.finish()  # type: ignore[no-untyped-call]
        finally:
            self._fh.close()
            self._fh = None


_Pending = tuple[str, float, MessageSource, Extra]
"""A queued message: kind, cycle time (s), message, extra."""


class McapLog:
    """The daemon's MCAP log: a sidecar of the CSV recorder (see module docstring).

    ``origin_ns``: the epoch of the cycle time ``t`` in ns (None: wall-clock now minus
    the first message's ``t``).  ``state_every``: the daemon records every N-th cycle's
    state (it asks :meth:`wants_state`); ``plan_every``: every N-th plan offered is kept.
    Never raises on the writer side: failures are counted in ``errors`` and logged (three
    times at most).
    """

    suffix = ".mcap"
    """Beside each CSV file: ``<log>.mcap``."""

    def __init__(
        self,
        vehicle_id: str,
        *,
        keep: int = 20,
        flush_period_s: float = 1.0,
        state_every: int = 1,
        plan_every: int = 1,
        compression: str = "zstd",
        chunk_bytes: int = 256 * 1024,
        maxlen: int = 4096,
        origin_ns: int | None = None,
        clock_ns: Callable[[], int] = time.time_ns,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        if compression not in COMPRESSION:
            raise ValueError(f"compression {compression!r}: expected one of {list(COMPRESSION)}")
        self.vehicle_id = vehicle_id
        self.keep = keep
        self.flush_period_s = flush_period_s
        self.state_every = max(1, state_every)
        self.plan_every = max(1, plan_every)
        self._plans = 0  # plans offered (record_plan keeps every plan_every-th)
        self.compression = compression
        self.chunk_bytes = chunk_bytes
        self.origin_ns = origin_ns
        self._clock_ns = clock_ns
        self._monotonic = monotonic
        self._q: deque[_Pending] = deque(maxlen=maxlen)
        self._file: McapFile | None = None
        self._last_flush = -math.inf
        self._lock = threading.Lock()  # open/write/close come from one thread; stop() races
        self.files: list[Path] = []  # every file this log opened (kept ones), oldest first
        self.counts: dict[str, int] = dict.fromkeys(KINDS, 0)  # messages written per channel
        self.dropped = 0
        self.errors = 0

    @classmethod
    def for_recorder(cls, vehicle_id: str, cfg: RecorderConfig) -> McapLog | None:
        """The daemon's MCAP log as configured in ``runtime.recorder`` (None: ``mcap`` off)."""
        if not cfg.mcap:
            return None
        return cls(
            vehicle_id,
            keep=cfg.keep,
            flush_period_s=cfg.flush_period_s,
            state_every=cfg.mcap_state_every,
            plan_every=cfg.mcap_plan_every,
            compression=cfg.mcap_compression,
        )

    def health(self) -> dict[str, Any]:
        """Counters for the health message."""
        return {
            "messages": dict(self.counts),
            "dropped": self.dropped,
            "errors": self.errors,
            "file": str(self.path) if self.path else None,
        }

    # -- loop side (cheap, never blocks) --------------------------------------------
    def wants_state(self, seq: int) -> bool:
        """Whether cycle ``seq``'s state is recorded (decimation)."""
        return seq % self.state_every == 0

    def _put(self, kind: str, t: float, msg: MessageSource, extra: Extra = None) -> None:
        if self.origin_ns is None:
            self.origin_ns = self._clock_ns() - round(t * 1e9)
        if len(self._q) == self._q.maxlen:
            self.dropped += 1
        self._q.append((kind, t, msg, extra))

    def record_state(self, t: float, msg: MessageSource) -> None:
        """Queue one state message (cycle time ``t`` in s), or a
        :class:`~truckd.runtime.deferred.Deferred` that builds it on the writer thread."""
        self._put("state", t, msg)

    def record_health(self, t: float, msg: Mapping[str, Any], extra: Extra = None) -> None:
        """Queue one health message; ``extra()`` is merged into it on the writer thread.
        ``msg`` must not change afterwards (pass a copy if another thread mutates it)."""
        self._put("health", t, msg, extra)

    def record_plan(self, t: float, msg: Mapping[str, Any]) -> None:
        """Offer one plan message (reference section 5: ``t, seq, dt, v, a``); every
        ``plan_every``-th is queued, starting with the first."""
        n = self._plans
        self._plans = n + 1
        if n % self.plan_every == 0:
            self._put("plan", t, msg)

    # -- writer side (the recorder's thread) -----------------------------------------
    def _error(self, what: str, exc: BaseException) -> None:
        self.errors += 1
        if self.errors <= 3:
            log.error("mcap %s failed: %s", what, exc)

    def open(self, path: Path, rows: int = 0) -> None:
        """Finish the current file and start ``path`` (the recorder rotated its CSV after
        ``rows`` rows: not used, messages go to the file open when they are written)."""
        with self._lock:
            self._finish()
            try:
                self._file = McapFile(
                    path,
                    self.vehicle_id,
                    compression=self.compression,
                    chunk_bytes=self.chunk_bytes,
                )
            except OSError as exc:
                self._error(f"open {path}", exc)
                return
            self.files.append(path)
            self._last_flush = self._monotonic()
            while len(self.files) > self.keep:
                old = self.files.pop(0)
                try:
                    old.unlink()
                except OSError as exc:
                    log.warning("cannot delete old log %s: %s", old, exc.strerror)

    def write_pending(self, rows: int | None = None) -> None:
        """Encode and write every queued message (``rows``, the CSV's, not used)."""
        with self._lock:
            f = self._file
            origin = self.origin_ns or 0
            last_yield = time.perf_counter()
            while self._q:
                try:
                    p = self._q.popleft()
                except IndexError:
                    break
                if f is None:
                    self.dropped += 1
                    continue
                kind, t, msg, extra = p
                try:
                    msg = resolve(msg)  # a deferred one is built here, off the control loop
                    if extra is not None:
                        msg = {**msg, **extra()}
                    f.write(kind, origin + round(t * 1e9), to_json(msg))
                    self.counts[kind] += 1
                except Exception as exc:  # a bad message must not stop the log
                    self._error("write", exc)
                now = time.perf_counter()
                if now - last_yield > YIELD_S:  # let a waking loop thread take the GIL
                    time.sleep(0)
                    last_yield = time.perf_counter()

    def flush(self, force: bool = False) -> None:
        """Close the chunk in progress when ``flush_period_s`` has passed (or ``force``)."""
        with self._lock:
            now = self._monotonic()
            if self._file is None or not (force or now - self._last_flush >= self.flush_period_s):
                return
            self._last_flush = now
            try:
                self._file.flush()
            except Exception as exc:
                self._error("flush", exc)

    def _finish(self) -> None:
        if self._file is not None:
            try:
                self._file.close()
            except Exception as exc:
                self._error("close", exc)
            self._file = None

    def close(self) -> None:
        """Write what is queued, then the summary and footer; close (idempotent)."""
        self.write_pending()
        with self._lock:
            self._finish()

    @property
    def path(self) -> Path | None:
        """The file being written."""
        return self.files[-1] if self.files else None


# -- reading -------------------------------------------------------------------------
@dataclass
class McapContent:
    """What :func:`read_mcap` found: schemas and channels by id, messages in file order,
    and whether the file ended with its footer (False: cut short, e.g. by SIGKILL)."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    messages: list[Message] = field(default_factory=list)
    complete: bool = False

    def topic(self, m: Message) -> str:
        return self.channels[m.channel_id].topic

    def by_topic(self) -> dict[str, list[Message]]:
        out: dict[str, list[Message]] = {c.topic: [] for c in self.channels.values()}
        for m in self.messages:
            out[self.topic(m)].append(m)
        return out


def read_mcap(path: str | Path) -> McapContent:
    """Read every complete record of an MCAP file with the ``mcap`` stream reader.

    A file cut short (no footer: the writer was killed) reads up to its last complete
    chunk; a partial record at the end is ignored and ``complete`` is False.
    """
    out = McapContent()
    with open(path, "rb") as fh:
        try:
            for rec in StreamReader(fh, validate_crcs=True).records:
                if isinstance(rec, Schema):
                    out.schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    out.channels[rec.id] = rec
                elif isinstance(rec, Message):
                    out.messages.append(rec)
                elif isinstance(rec, Footer):
                    out.complete = True
        except (McapError, EOFError, struct.error, ValueError) as exc:
            log.debug("%s ends early: %r", path, exc)
        except Exception as exc:  # zstd/lz4 errors on a chunk cut mid-way
            log.debug("%s ends in a broken record: %r", path, exc)
    return out


def write_messages(
    path: str | Path,
    vehicle_id: str,
    messages: Iterable[tuple[str, int, Mapping[str, Any]]],
    metadata: Mapping[str, str] | None = None,
) -> int:
    """Write ``(kind, log_time_ns, message)`` triples to ``path`` all or nothing (a
    temporary file beside it, renamed at the end).  Returns the number of messages.
    Raises OSError."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        f = McapFile(tmp, vehicle_id, metadata=metadata)
        try:
            for kind, t_ns, msg in messages:
                f.write(kind, t_ns, to_json(msg))
        finally:
            f.close()
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return f.messages

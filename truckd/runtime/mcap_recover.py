"""Recovery of MCAP files left unfinished (the writer was killed, the host lost power).

The daemon's MCAP writer closes a chunk at least every ``recorder.flush_period_s``, so a
file cut short holds every message up to its last complete chunk, but it has no summary,
no index and no footer: indexed readers (Foxglove, ``mcap``'s seeking reader) refuse it.
:func:`recover_file` reads every complete record with the stream reader and writes them
again as a finished file (chunks, index, summary, footer) in a temporary file beside it,
renamed over the original only when complete (a failure leaves the original as it was).

A file being written is never touched: the writer holds an advisory lock on it
(``flock``; the OS releases it when the process ends, however it ends), and
:func:`recover_file` skips a file whose lock it cannot take.  Run by the daemon at start
on its log directory (:func:`recover_dir`) and by ``truckd recover FILE|DIR``.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from mcap.exceptions import McapError
from mcap.records import Attachment, Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from truckd.errors import InputError, TruckdError

MAGIC = b"\x89MCAP0\r\n"
"""The MCAP magic: at the start of every file and at the end of a finished one."""


@dataclass(frozen=True)
class Recovery:
    """What :func:`recover_file` did to one file."""

    path: Path
    status: str
    """``recovered``, ``complete`` (finished already: untouched) or ``busy`` (a writer
    holds it: untouched)."""
    messages: int = 0
    lost_bytes: int = 0
    """Bytes at the end that were no complete record (the chunk in progress)."""

    def line(self) -> str:
        """One line for the operator."""
        if self.status == "recovered":
            return (
                f"{self.path}: recovered {self.messages} messages, index rewritten "
                f"({self.lost_bytes} bytes of an unfinished record at the end dropped)"
            )
        if self.status == "busy":
            return f"{self.path}: being written by a running process, left alone"
        return f"{self.path}: complete, nothing to do"


@contextlib.contextmanager
def writer_lock(fh: IO[bytes]) -> Iterator[bool]:
    """Hold the advisory lock of an MCAP file being written (non-blocking); yields
    whether it was taken."""
    try:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        yield False
        return
    try:
        yield True
    finally:
        with contextlib.suppress(OSError):
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def is_finished(fh: IO[bytes]) -> bool:
    """Whether the file starts and ends with the MCAP magic (a footer was written)."""
    fh.seek(0, os.SEEK_END)
    size = fh.tell()
    if size < 2 * len(MAGIC):
        return False
    fh.seek(size - len(MAGIC))
    end = fh.read(len(MAGIC))
    fh.seek(0)
    return end == MAGIC and fh.read(len(MAGIC)) == MAGIC


def _copy(src: IO[bytes], out: IO[bytes]) -> tuple[int, int]:
    """Every complete record of ``src`` into a finished MCAP on ``out``: (messages, offset
    in ``src`` after the last complete record)."""
    w = Writer(out, chunk_size=256 * 1024, compression=CompressionType.ZSTD)
    w.start(profile="", library="truckd recover")
    schemas: dict[int, int] = {}
    channels: dict[int, int] = {}
    messages = 0
    good = len(MAGIC)
    reader = StreamReader(src, validate_crcs=True)
    try:
        for rec in reader.records:
            if isinstance(rec, Schema):
                if rec.id not in schemas:
                    schemas[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
            elif isinstance(rec, Channel):
                if rec.id not in channels:
                    channels[rec.id] = w.register_channel(
                        rec.topic, rec.message_encoding, schemas.get(rec.schema_id, 0),
                        dict(rec.metadata),
                    )  # fmt: skip
            elif isinstance(rec, Message):
                cid = channels.get(rec.channel_id)
                if cid is not None:
                    w.add_message(cid, rec.log_time, rec.data, rec.publish_time, rec.sequence)
                    messages += 1
            elif isinstance(rec, Metadata):
                w.add_metadata(rec.name, dict(rec.metadata))
            elif isinstance(rec, Attachment):
                w.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
            elif isinstance(rec, Footer):
                break
            good = src.tell()
    except (McapError, EOFError, struct.error, ValueError):
        pass  # the unfinished record at the end
    except Exception:  # zstd/lz4 errors on a chunk cut mid-way: the same
        pass
    w.finish()  # type: ignore[no-untyped-call]
    return messages, good


def recover_file(path: str | Path) -> Recovery:
    """Finish ``path`` if it was left unfinished (see module docstring).  InputError when
    it is not an MCAP file at all; TruckdError when the recovered file cannot be written
    (the original is then unchanged)."""
    p = Path(path)
    try:
        fh = open(p, "rb")  # noqa: SIM115 - closed below
    except OSError as exc:
        raise InputError(f"{p}: cannot open: {exc.strerror or exc}") from None
    with fh:
        if not os.path.isfile(p):
            raise InputError(f"{p}: not a regular file")
        if fh.read(len(MAGIC)) != MAGIC:
            raise InputError(f"{p}: not an MCAP file (no MCAP magic at the start)")
        with writer_lock(fh) as free:
            if not free:
                return Recovery(p, "busy")
            if is_finished(fh):
                return Recovery(p, "complete")
            size = os.fstat(fh.fileno()).st_size
            fh.seek(0)
            tmp = p.with_name(f".{p.name}.recover{os.getpid()}.tmp")
            try:
                with open(tmp, "xb") as out:
                    messages, good = _copy(fh, out)
                    out.flush()
                    os.fsync(out.fileno())
                with contextlib.suppress(OSError):
                    os.chmod(tmp, os.stat(p).st_mode & 0o777)
                os.replace(tmp, p)
            except OSError as exc:
                tmp.unlink(missing_ok=True)
                raise TruckdError(f"{p}: cannot write the recovered file: {exc}") from None
            except BaseException:
                tmp.unlink(missing_ok=True)
                raise
    return Recovery(p, "recovered", messages, max(0, size - good))


def unfinished(directory: str | Path) -> list[Path]:
    """The ``*.mcap`` files in ``directory`` (not below) that lack their footer."""
    out = []
    for p in sorted(Path(directory).glob("*.mcap")):
        try:
            with open(p, "rb") as fh:
                if not is_finished(fh):
                    out.append(p)
        except OSError:
            continue
    return out


def recover_dir(directory: str | Path) -> list[Recovery]:
    """Recover every unfinished ``*.mcap`` in ``directory``; files that are not MCAP at
    all are skipped (their name is a mistake, not ours to fix)."""
    done = []
    for p in unfinished(directory):
        try:
            done.append(recover_file(p))
        except InputError:
            continue
    return done

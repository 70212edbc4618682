"""Reading input files (logs, configuration, models) with bounds and one-line errors.

An input must be an existing regular file (not a directory, device or pipe: ``/dev/zero``
would never end), no larger than the limit for its kind, and UTF-8 text (a byte-order
mark is accepted and dropped).  Every refusal is an :class:`InputError` naming the file
and what was expected.  See docs/inputs.md.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from truckd.errors import InputError

MIB = 1024 * 1024


def open_regular(path: str | Path, what: str, max_bytes: int) -> int:
    """Open ``path`` for reading after checking it is a regular file of at most ``max_bytes``.

    Returns the file descriptor (the caller closes it).  The checks are made on the opened
    file, so a file swapped in between cannot slip through.
    """
    src = os.fspath(path)
    if src == "":
        raise InputError(f"'': expected the name of a {what}")
    try:
        fd = os.open(src, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except IsADirectoryError:
        raise InputError(f"{src}: is a directory; expected a {what}") from None
    except FileNotFoundError:
        raise InputError(f"{src}: no such file; expected a {what}") from None
    except OSError as exc:
        raise InputError(f"{src}: cannot read the {what}: {exc.strerror}") from None
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise InputError(f"{src}: is a directory; expected a {what}")
        if not stat.S_ISREG(st.st_mode):
            raise InputError(f"{src}: is not a regular file (a device or pipe); expected a {what}")
        if st.st_size > max_bytes:
            raise InputError(
                f"{src}: {st.st_size} bytes, more than the limit of {_size(max_bytes)} for a {what}"
            )
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
    except BaseException:
        os.close(fd)
        raise
    return fd


def read_text(path: str | Path, what: str, max_bytes: int) -> str:
    """The whole of a small text file (configuration, model), decoded as UTF-8."""
    src = os.fspath(path)
    fd = open_regular(path, what, max_bytes)
    try:
        with os.fdopen(fd, "rb") as fh:
            data = fh.read(max_bytes + 1)
    except OSError as exc:
        raise InputError(f"{src}: cannot read the {what}: {exc.strerror}") from None
    if len(data) > max_bytes:
        raise InputError(f"{src}: more than the limit of {_size(max_bytes)} for a {what}")
    return decode_utf8(data, src, what)


def decode_utf8(data: bytes, src: str, what: str) -> str:
    """``data`` decoded as UTF-8 (BOM dropped); a one-line error names the line and byte."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise InputError(
            f"{src}: line {line}: byte 0x{data[exc.start]:02x} at offset {exc.start} is not "
            f"UTF-8; expected a UTF-8 text {what}"
        ) from None


def _size(n: int) -> str:
    return f"{n // MIB} MiB" if n % MIB == 0 else f"{n} bytes"

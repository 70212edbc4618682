"""All-or-nothing output files, and checks of output paths before any long work starts.

Every file the command line writes goes through :func:`atomic_text` or
:func:`atomic_binary` (or the helpers built on them): the content goes to a temporary file
in the target's directory, is flushed and fsync'ed, then renamed over the target with
:func:`os.replace`.  A write that fails part-way (no space, file size limit, the target is
a directory) removes the temporary file, so the target is either the complete new file or
untouched.

A report directory is built in a temporary sibling directory and published by
:func:`atomic_dir`: renamed into place when the target does not exist (or is empty),
otherwise each finished file is renamed over its old version.

:func:`check_output_file` and :func:`check_output_dir` are the up-front checks (used as
argparse types in :mod:`truckd.cli.args`); :func:`check_distinct` refuses one path given
for two outputs; :func:`guard_inputs` refuses an output that is one of the command's
inputs (the same file by device and inode, also through a link), up front and again at
every write.  Failures of the checks are :class:`InputError` (exit 2); failures of
the write itself are :class:`TruckdError` (exit 1).
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import shutil
import tempfile
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import IO

from truckd.errors import InputError, TruckdError

IMAGE_SUFFIXES = (".png", ".svg", ".pdf")


def _strerror(exc: OSError) -> str:
    return exc.strerror or exc.__class__.__name__


def _nearest_existing(p: Path) -> Path:
    q = p
    while not q.exists() and q != q.parent:
        q = q.parent
    return q


def _writable(directory: Path) -> bool:
    """A file can be created in ``directory``: the permission bits, then tried (the bits
    alone pass for root on a read-only or virtual file system, /proc)."""
    if not os.access(directory, os.W_OK | os.X_OK):
        return False
    try:
        fd, name = tempfile.mkstemp(prefix=".truckd-probe-", dir=directory)
    except OSError:
        return False
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(name)
    return True


def check_output_file(
    path: str | Path, what: str = "output file", suffixes: Iterable[str] | None = None
) -> Path:
    """Check that ``path`` can be created or replaced as a regular file.

    It must not be a directory (nor end with a path separator), its directory must exist
    and be writable, and its suffix must be one of ``suffixes`` (when given).
    """
    s = str(path)
    p = Path(path)
    if not s or s.endswith(("/", os.sep)) or p.name in ("", ".", ".."):
        raise InputError(f"{s!r}: expected a file name for the {what}, not a directory")
    if suffixes is not None:
        allowed = tuple(suffixes)
        if p.suffix.lower() not in allowed:
            raise InputError(f"{s}: {what} must end in one of {', '.join(allowed)}")
    if p.is_dir():
        raise InputError(f"{s}: is a directory; expected a file name for the {what}")
    if p.exists() and not p.is_file():
        raise InputError(f"{s}: exists and is not a regular file; refusing to replace it")
    parent = p.parent
    if not parent.is_dir():
        raise InputError(f"{s}: directory {str(parent)!r} does not exist (for the {what})")
    if not _writable(parent):
        raise InputError(f"{s}: directory {str(parent)!r} is not writable (for the {what})")
    return p


def check_output_dir(path: str | Path, what: str = "output directory") -> Path:
    """Check that ``path`` is a writable directory or can be created (with its parents)."""
    s = str(path)
    if not s:
        raise InputError(f"expected a directory name for the {what}, got ''")
    p = Path(path)
    if p.exists():
        if not p.is_dir():
            raise InputError(f"{s}: exists and is not a directory (for the {what})")
        if not _writable(p):
            raise InputError(f"{s}: directory is not writable (for the {what})")
        return p
    base = _nearest_existing(p.absolute().parent)
    if not base.is_dir():
        raise InputError(f"{s}: {str(base)!r} is not a directory (for the {what})")
    if not _writable(base):
        raise InputError(f"{s}: cannot create it, {str(base)!r} is not writable ({what})")
    return p


def check_distinct(
    paths: Iterable[tuple[str, str | Path | None]],
    dirs: Iterable[tuple[str, str | Path | None, tuple[str, ...]]] = (),
) -> None:
    """Refuse one path given for two outputs (``(option, path)`` pairs; None is skipped),
    and an output file where an output directory writes (``dirs``: ``(option, path,
    suffixes)``, the suffixes of the files it writes, () for a directory published whole,
    which replaces everything in it): the one would replace the other."""
    seen: dict[str, str] = {}
    for option, path in paths:
        if path is None:
            continue
        key = os.path.realpath(os.fspath(path))
        if key in seen:
            raise InputError(f"{path}: given for both {seen[key]} and {option}; expected two paths")
        seen[key] = option
    roots: list[tuple[str, str, tuple[str, ...]]] = []
    for option, d, suffixes in dirs:
        if d is None:
            continue
        root = os.path.realpath(os.fspath(d))
        for key, other in seen.items():
            inside = key.startswith(root.rstrip(os.sep) + os.sep)
            if key == root or (inside and (not suffixes or key.endswith(suffixes))):
                raise InputError(
                    f"{d}: {option} holds the {other} output ({key}); expected a path "
                    "outside that directory"
                )
        for other_root, other, other_suffixes in roots:  # one directory, two writers
            clash = not suffixes or not other_suffixes or set(suffixes) & set(other_suffixes)
            if other_root == root and clash:
                raise InputError(f"{d}: given for both {other} and {option}; expected two paths")
        roots.append((root, option, suffixes))


PathLike = str | Path


def _identity(path: PathLike) -> tuple[int, int] | None:
    """The file ``path`` resolves to (links followed): (device, inode); None when absent."""
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return st.st_dev, st.st_ino


_INPUTS: contextvars.ContextVar[dict[tuple[int, int], str] | None] = contextvars.ContextVar(
    "truckd_inputs", default=None
)
"""The inputs of the running command (set by :func:`guard_inputs`): every write refuses
to replace one of them."""


def _refuse_input(target: PathLike, option: str = "output") -> None:
    """InputError when ``target`` is (resolves to) one of the guarded inputs."""
    ident = _identity(target)
    if ident is None:
        return
    name = (_INPUTS.get() or {}).get(ident)
    if name is not None:
        same = "" if os.fspath(target) == name else f" (the same file as {name})"
        raise InputError(
            f"{target}: {option} would replace the input {name}{same}; "
            "an output never replaces an input, choose another path"
        )


@contextlib.contextmanager
def guard_inputs(
    inputs: Iterable[PathLike | None], outputs: Iterable[tuple[str, PathLike | None]] = ()
) -> Iterator[None]:
    """Inside the block no output replaces one of ``inputs`` (compared as files, by
    device and inode: also through a symbolic or hard link).  ``outputs`` (option,
    path) are checked at once, before any work; every file written through this module
    (and every file a report directory publishes) is checked again when written.
    A clash is an :class:`InputError` (exit 2) and nothing is written."""
    ids = dict(_INPUTS.get() or {})
    for p in inputs:
        if p is not None:
            ident = _identity(p)
            if ident is not None:
                ids.setdefault(ident, os.fspath(p))
    token = _INPUTS.set(ids)
    try:
        for option, out in outputs:
            if out is not None:
                _refuse_input(out, option)
        yield
    finally:
        _INPUTS.reset(token)


def _remove(path: str) -> None:
    with contextlib.suppress(OSError):
        os.unlink(path)


@contextlib.contextmanager
def atomic_text(path: str | Path) -> Iterator[IO[str]]:
    """A UTF-8 text file (``newline=""``) that replaces ``path`` only if the block succeeds.

    An ``OSError`` while writing or publishing becomes :class:`TruckdError` naming
    ``path``; any exception leaves ``path`` untouched and no temporary file behind.
    """
    with _atomic(path) as fd, os.fdopen(os.dup(fd), "w", encoding="utf-8", newline="") as fh:
        yield fh


@contextlib.contextmanager
def atomic_binary(path: str | Path) -> Iterator[IO[bytes]]:
    """A binary file that replaces ``path`` only if the block succeeds (see atomic_text)."""
    with _atomic(path) as fd, os.fdopen(os.dup(fd), "wb") as fh:
        yield fh


@contextlib.contextmanager
def _atomic(path: str | Path) -> Iterator[int]:
    target = os.fspath(path)
    if os.path.isdir(target):
        raise TruckdError(f"{target}: is a directory; cannot write the file there")
    _refuse_input(target)
    directory = os.path.dirname(os.path.abspath(target))
    name = os.path.basename(target)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=directory)
    except OSError as exc:
        raise TruckdError(f"{target}: cannot write: {_strerror(exc)}") from None
    try:
        try:
            yield fd  # the caller writes through a dup and closes (flushes) it
            os.fsync(fd)
        finally:
            os.close(fd)
        with contextlib.suppress(OSError):
            os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, target)
    except OSError as exc:
        _remove(tmp)
        raise TruckdError(f"{target}: cannot write: {_strerror(exc)}") from None
    except BaseException:
        _remove(tmp)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_text(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` all or nothing."""
    with atomic_text(path) as fh:
        fh.write(text)


def write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` all or nothing."""
    with atomic_binary(path) as fh:
        fh.write(data)


def write_with(path: str | Path, writer: Callable[[IO[bytes]], None]) -> None:
    """Call ``writer`` with a binary file that replaces ``path`` only if it returns."""
    with atomic_binary(path) as fh:
        writer(fh)


@contextlib.contextmanager
def atomic_dir(path: str | Path) -> Iterator[Path]:
    """Context manager: a temporary directory whose files are published to ``path``.

    Everything is built first; nothing reaches ``path`` if the block raises.  A new (or
    empty) ``path`` receives the whole directory in one rename; an existing one gets each
    file renamed over its old version (every file complete, the set replaced at the end).
    """
    target = Path(path)
    check_output_dir(target)
    target.absolute().parent.mkdir(parents=True, exist_ok=True)
    try:
        tmp = Path(
            tempfile.mkdtemp(prefix=f".{target.name or 'out'}.", dir=target.absolute().parent)
        )
    except OSError as exc:
        raise TruckdError(f"{target}: cannot create the directory: {_strerror(exc)}") from None
    try:
        yield tmp
        for item in tmp.iterdir():  # before any rename: nothing published on a clash
            _refuse_input(target / item.name)
        _fsync_tree(tmp)
        try:
            os.rename(tmp, target)  # new or empty target: one step
            with contextlib.suppress(OSError):
                target.chmod(0o777 & ~_umask())
            return
        except OSError:
            pass
        for item in sorted(tmp.iterdir()):
            dest = target / item.name
            if dest.is_dir() and not item.is_dir():
                raise TruckdError(f"{dest}: is a directory; cannot replace it with a file")
            os.replace(item, dest)
    except OSError as exc:
        raise TruckdError(f"{target}: cannot write: {_strerror(exc)}") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _fsync_tree(root: Path) -> None:
    for item in root.rglob("*"):
        if item.is_file():
            with open(item, "rb") as fh:
                os.fsync(fh.fileno())


def write_set(files: Iterable[tuple[str | Path, str | bytes]]) -> None:
    """Write several files (text: UTF-8) as a set: every one complete, or none changed.

    Each is written to its temporary file first; only when all are written and synced are
    they renamed into place (a failure of the rename itself, rarer, can still leave the
    earlier ones replaced).
    """
    files = list(files)
    for path, _content in files:  # before any is written: nothing replaced on a clash
        _refuse_input(path)
    with contextlib.ExitStack() as stack:
        for path, content in files:
            if isinstance(content, bytes):
                stack.enter_context(atomic_binary(path)).write(content)
            else:
                stack.enter_context(atomic_text(path)).write(content)


def ensure_dir(path: str | Path, what: str = "output directory") -> Path:
    """``path`` as a directory, created with its parents if missing (InputError naming
    ``what`` when it cannot be one)."""
    d = check_output_dir(path, what)
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{path}: cannot use as the {what}: {_strerror(exc)}") from None
    return d

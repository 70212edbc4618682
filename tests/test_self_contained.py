"""The repository stands alone: no tracked file reads a path outside it.

A clone with nothing beside it must pass its own tests, so no code, test, build file or
document may point above the repository (``../`` beyond its root, an absolute path into a
sibling directory, or code that climbs past the checkout with ``.parent``).  Data a test
needs is copied into ``tests/data/`` with a README giving provenance and licence.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

RELATIVE = re.compile(r"(?:\.\./)+[A-Za-z0-9_.-]+")
"""A relative path that climbs (``../x``): outside the repository when, resolved from the
file's own directory, it leaves the root, or names nothing there while, resolved from the
root (as a command run there would), it leaves the root."""

CLIMB = re.compile(
    r"parents\[\d+\]\s*\.parent\b"  # the checkout's parent, in code
    r"|\.parent\s*/\s*[\"']shared[\"']"
    r"|[\"']shared[\"']\s*/\s*[\"']data[\"']"
    r"|/work/shared\b"
)
"""Code or text that reaches a directory beside the checkout."""

BINARY_SUFFIXES = {".mat", ".png", ".gz", ".mcap", ".so", ".o", ".elf", ".bin"}


def tracked_files() -> list[Path]:
    """The files git tracks (every file under the root when this is not a git checkout)."""
    try:
        out = subprocess.run(
            ["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True, timeout=60
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        skip = {".git", ".venv", "out", "build", "dist", ".mypy_cache", ".pytest_cache"}
        return [p for p in ROOT.rglob("*") if p.is_file() and not skip & set(p.parts)]
    return [ROOT / name for name in out.decode().split("\0") if name]


def outside_references(path: Path, text: str) -> list[str]:
    """``file:line: reference`` for each reference in ``text`` to a path outside ROOT."""
    found = []
    rel = path.relative_to(ROOT)
    for no, line in enumerate(text.splitlines(), 1):
        for m in RELATIVE.finditer(line):
            here = (path.parent / m.group(0)).resolve()
            from_root = (ROOT / m.group(0)).resolve()
            inside = here.is_relative_to(ROOT) and (here.exists() or from_root.is_relative_to(ROOT))
            if not inside:
                found.append(f"{rel}:{no}: {m.group(0)}")
        found.extend(f"{rel}:{no}: {m.group(0)}" for m in CLIMB.finditer(line))
    return found


def test_no_tracked_file_reads_outside_the_repository() -> None:
    found: list[str] = []
    for path in tracked_files():
        if path == Path(__file__).resolve() or path.suffix in BINARY_SUFFIXES:
            continue
        try:
            text = path.read_text(encoding="utf-8")
        except (UnicodeDecodeError, FileNotFoundError):
            continue
        found.extend(outside_references(path, text))
    assert not found, "paths outside the repository:\n" + "\n".join(found)


def test_the_check_sees_each_kind_of_reference() -> None:
    """The patterns catch what they are for, and leave paths inside the tree alone."""
    doc = ROOT / "docs" / "page.md"
    assert outside_references(doc, "see [x](../README.md)") == []
    assert outside_references(doc, "see ../../shared/CONTRACTS.md") != []
    assert outside_references(doc, "data in <repo>/../shared/data") != []
    top = ROOT / "README.md"
    assert outside_references(top, "the contract: ../shared/CONTRACTS.md") != []
    code = ROOT / "truckd" / "ident" / "x.py"
    assert outside_references(code, 'Path(__file__).parents[2] / "tests"') == []
    assert outside_references(code, 'Path(__file__).parents[2].parent / "d"') != []
    assert outside_references(code, 'root.parent / "shared" / "data"') != []


LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
"""A Markdown link's target."""


def anchors(markdown: str) -> set[str]:
    """GitHub's anchors for the headings of a Markdown text (lower case, punctuation other
    than ``-`` and ``_`` dropped, spaces to ``-``; links reduced to their text)."""
    out = set()
    for line in markdown.splitlines():
        if line.startswith("#"):
            title = LINK.sub(lambda m: m.group(0)[1 : m.group(0).index("]")], line.lstrip("#"))
            slug = re.sub(r"[^\w\- ]", "", title.strip().lower()).replace(" ", "-")
            out.add(slug)
    return out


def broken_links(path: Path, text: str) -> list[str]:
    """``file:line: target`` for each relative link whose file or heading is missing."""
    found = []
    for no, line in enumerate(text.splitlines(), 1):
        for m in LINK.finditer(line):
            target = m.group(1)
            if re.match(r"[a-z]+:", target):
                continue  # https:, mailto:
            file_part, _, anchor = target.partition("#")
            dest = (path.parent / file_part).resolve() if file_part else path
            ok = dest.exists() and dest.is_relative_to(ROOT)
            if ok and anchor and dest.suffix == ".md":
                ok = anchor in anchors(dest.read_text(encoding="utf-8"))
            if not ok:
                found.append(f"{path.relative_to(ROOT)}:{no}: {target}")
    return found


def test_markdown_links_resolve_inside_the_repository() -> None:
    found: list[str] = []
    for path in tracked_files():
        if path.suffix == ".md" and path.is_file():
            found.extend(broken_links(path, path.read_text(encoding="utf-8")))
    assert not found, "broken links:\n" + "\n".join(found)


def test_the_link_check_sees_a_missing_file_and_heading() -> None:
    readme = ROOT / "README.md"
    assert broken_links(readme, "[ref](docs/reference.md)") == []
    assert broken_links(readme, "[x](docs/no-such-page.md)") != []
    assert broken_links(readme, "[x](docs/reference.md#no-such-heading)") != []
    assert broken_links(readme, "[x](docs/reference.md#1-command-line)") == []

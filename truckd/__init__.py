"""truckd: model, controller, firmware link and diagnosis for a 1:14 model truck."""

from __future__ import annotations

DISTRIBUTION = "truckd"
"""The distribution name; its version is declared once, in pyproject.toml."""


def version() -> str:
    """The installed distribution's version (pyproject.toml's), or ``0+unknown`` when the
    package runs from a tree that was never installed."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version(DISTRIBUTION)
    except PackageNotFoundError:
        return "0+unknown"


def __getattr__(name: str) -> str:
    # ``truckd.__version__`` on demand: importlib.metadata stays off the daemon's import path.
    if name == "__version__":
        return version()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

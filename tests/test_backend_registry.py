"""One registry of backends (truckd/io/backends.py): every name loads its class on first
use, the daemon opens whatever the registry names, and a wrong entry is refused."""

from __future__ import annotations

import subprocess
import sys

import pytest

from truckd.config.truck import load_config
from truckd.io import backends
from truckd.io.devlock import DeviceLock
from truckd.io.inproc import inproc_pair
from truckd.runtime.backend import Backend, Clock, backend_class, claim_backend, open_backend


class LoopBackend(Backend):
    """A backend from outside the package: an in-process pair, nothing to lock."""

    name = "loop"

    @classmethod
    def open(cls, cfg: object, control: object, clock: Clock, lock: DeviceLock | None) -> Backend:
        link, _mcu, _wire = inproc_pair("frames")
        return cls(link, lock)


def test_every_registered_name_is_its_backend_class() -> None:
    assert set(backends.BACKENDS) == {"sim", "serial", "can"}
    for name in backends.BACKEND_NAMES:
        cls = backend_class(name)
        assert issubclass(cls, Backend) and cls.name == name


def test_the_registry_alone_names_a_backend(monkeypatch: pytest.MonkeyPatch) -> None:
    """An entry added to the table is opened and claimed by name, as the daemon does."""
    monkeypatch.setitem(backends.BACKENDS, "loop", (__name__, "LoopBackend"))
    cfg = load_config(None)
    claim_backend("loop", cfg.link).release()
    b = open_backend("loop", cfg, cfg.control)
    try:
        assert isinstance(b, LoopBackend) and b.link.connected
    finally:
        b.close()


def test_a_wrong_entry_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(backends.BACKENDS, "bad", ("truckd.io.link", "Link"))
    with pytest.raises(TypeError, match=r"truckd\.io\.link\.Link is not a Backend"):
        backend_class("bad")
    with pytest.raises(ValueError, match="unknown backend 'nope'; expected one of"):
        backend_class("nope")


def test_the_real_backends_load_no_simulator() -> None:
    """Naming serial or can loads nothing of truckd.sim; naming sim loads it."""
    probe = (
        "import sys\nfrom truckd.runtime.backend import backend_class\n"
        "def sim():\n    return sorted(m for m in sys.modules if m.startswith('truckd.sim'))\n"
        "backend_class('serial'); backend_class('can'); print(len(sim()))\n"
        "backend_class('sim'); print('truckd.sim.backend' in sim())"
    )
    r = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True
    )
    assert r.stdout.split() == ["0", "True"]

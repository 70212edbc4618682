"""The backends the daemon opens by name: one table, python-can style.

Each name maps to the module and class that implement it
(:class:`truckd.runtime.backend.Backend`); :func:`truckd.runtime.backend.backend_class`
imports the module only when the name is asked for.  So the table costs no import: the
configuration takes its choices for ``runtime.backend`` from it, and ``truckd run`` on the
car never loads the simulator or a hardware library it does not use.  The simulator is one
more backend (``sim``), registered here like the others.
"""

from __future__ import annotations

BACKENDS: dict[str, tuple[str, str]] = {
    "sim": ("truckd.sim.backend", "SimBackend"),
    "serial": ("truckd.runtime.backend", "SerialBackend"),
    "can": ("truckd.runtime.backend", "CanBackend"),
}
"""Backend name -> (module, class), imported on first use."""

BACKEND_NAMES: tuple[str, ...] = tuple(BACKENDS)
"""The names, for ``runtime.backend`` and ``--backend``."""

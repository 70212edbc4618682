"""``truckd sim --mcap``: a simulated run as an MCAP file with the daemon's channels
(``/truckd/<vehicle_id>/state``, ``/health``, ``/plan``; docs/foxglove.md), so the same
Foxglove layout opens a simulation and a drive.

Log time = simulated time (ns from 0).  The simulation runs the daemon's cycle: ``mode``
is the supervisor's mode, ``enable`` the driver enable sent and ``solve_us`` OSQP's time,
as the daemon records them; ``ctrl`` is the controller's mode.  The state holds the
plant's truth (``v``, ``gap``, ``v_lead``) and the controller's estimate of the gap
(``gap_est``); ``gap_ref`` is ``d_0 + h v``.  ``health`` is written every 0.5 s with the
scenario name.  ``plan`` holds the plans the daemon would publish (the MPC's predicted
speeds, standstill while holding; none on a fallback), every ``plan_every``-th from the
first, as the daemon records them (``runtime.recorder.mcap_plan_every``), stamped with
the simulated time and the configured vehicle id.
"""

from __future__ import annotations

import dataclasses
import tempfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from truckd.errors import InputError, TruckdError
from truckd.jsonsafe import json_number
from truckd.outputs import check_output_dir, check_output_file
from truckd.runtime.cycle import LOG_COLUMNS
from truckd.runtime.mcap_log import write_messages
from truckd.sim.closed_loop import Trace

HEALTH_PERIOD_S = 0.5
_ENABLE = LOG_COLUMNS.index("enable")
_SOLVE_US = LOG_COLUMNS.index("solve_us")


def trace_messages(
    scenario: str, tr: Trace, vehicle_id: str = "", plan_every: int = 1
) -> Iterator[tuple[str, int, Mapping[str, Any]]]:
    """``(kind, log_time_ns, message)`` for every cycle of the trace; of the plans, every
    ``plan_every``-th offered is kept, starting with the first (as ``McapLog.record_plan``)."""
    if plan_every < 1:
        raise ValueError(f"plan_every must be >= 1, got {plan_every}")
    next_health = 0.0
    plans_offered = 0
    for k, t in enumerate(tr.t):
        ns = round(t * 1e9)
        mode = tr.supervisor[k]
        row = tr.rows[k]
        yield (
            "state",
            ns,
            {
                "seq": k,
                "t": t,
                "mode": mode,
                "v": json_number(tr.v[k]),
                "gap": json_number(tr.gap[k]),
                "gap_ref": json_number(tr.gap_ref[k]),
                "v_lead": json_number(tr.v_lead[k]),
                "u": tr.u[k],
                "u_ff": json_number(tr.u_ff[k]),
                "solve_us": json_number(row[_SOLVE_US]),
                "enable": bool(row[_ENABLE]),
                "ctrl": tr.mode[k],
                "gap_est": json_number(tr.gap_est[k]),
            },
        )
        plan = tr.plans[k] if k < len(tr.plans) else None
        if plan is not None:
            if plans_offered % plan_every == 0:
                yield "plan", ns, dataclasses.replace(plan, vehicle_id=vehicle_id).as_dict()
            plans_offered += 1
        if t >= next_health - 1e-9:
            yield "health", ns, {"t": t, "mode": mode, "faults": [], "sim": scenario}
            next_health = t + HEALTH_PERIOD_S


def mcap_paths(target: str, scenarios: tuple[str, ...]) -> dict[str, Path]:
    """Where each scenario's MCAP goes: ``target`` itself when it ends in ``.mcap`` (one
    scenario only), else ``target/<scenario>.mcap`` (the directory is created).  Raises
    InputError for a bad target."""
    if not target.strip():
        raise InputError(f"--mcap {target!r}: expected a directory or a *.mcap file name")
    p = Path(target)
    if p.suffix == ".mcap":
        if len(scenarios) != 1:
            raise InputError(
                f"--mcap {target}: one file holds one scenario; give a directory for "
                f"{len(scenarios)} scenarios"
            )
        if p.is_dir():
            raise InputError(f"--mcap {target}: is a directory; expected a file name")
        if not p.parent.is_dir():
            raise InputError(f"--mcap {target}: directory {p.parent} does not exist")
        check_output_file(p, "MCAP file")  # writable, before any scenario runs
        return {scenarios[0]: p}
    if p.suffix and not p.exists():
        raise InputError(
            f"--mcap {target}: expected a *.mcap file name or a directory (a new directory "
            f"has no suffix; '{p.suffix}' looks like a mistyped file name)"
        )
    if p.exists() and not p.is_dir():
        raise InputError(f"--mcap {target}: not a directory; expected a directory or *.mcap")
    check_output_dir(p, "MCAP directory")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise TruckdError(f"--mcap {target}: cannot create: {exc.strerror}") from None
    return {s: p / f"{s}.mcap" for s in scenarios}


def trace_mcap_bytes(vehicle_id: str, scenario: str, tr: Trace, plan_every: int = 1) -> bytes:
    """One run as an MCAP file's bytes (to be written with the other outputs as a set)."""
    with tempfile.TemporaryDirectory(prefix="truckd-mcap-") as tmp:
        path = Path(tmp) / f"{scenario}.mcap"
        write_trace_mcap(path, vehicle_id, scenario, tr, plan_every)
        return path.read_bytes()


def write_trace_mcap(
    path: Path, vehicle_id: str, scenario: str, tr: Trace, plan_every: int = 1
) -> int:
    """Write one run (all or nothing); returns the number of messages."""
    try:
        return write_messages(
            path,
            vehicle_id,
            trace_messages(scenario, tr, vehicle_id, plan_every),
            metadata={"source": "truckd sim", "scenario": scenario, "time": "simulated"},
        )
    except OSError as exc:
        raise TruckdError(f"{path}: cannot write: {exc.strerror}") from None

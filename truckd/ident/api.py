"""Entry points the CLI calls: identify and diagnose logs, build the model file."""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager

from threadpoolctl import threadpool_limits

from truckd.errors import InputError, TruckdError
from truckd.ident.data import runs_from_logs, series_from_log
from truckd.ident.diagnose import diagnose_voltage, identify_voltage
from truckd.ident.fanout import Mapper, in_order
from truckd.ident.force import diagnose_force
from truckd.ident.physics import configuration_notes
from truckd.ident.result import Diagnosis
from truckd.ident.rotational import in_rotational_units
from truckd.ident.verdict import suspect_columns, unit_notes
from truckd.logfile import Log
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams
from truckd.modelfile import ModelFile
from truckd.workers import ForkMap


def _quiet(_: str) -> None:
    return None


_BLAS_LOCK = threading.Lock()
_blas_users = 0
_blas_limiter: threadpool_limits | None = None


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """Linear algebra on one thread while a diagnosis runs.

    The fits' matrices are small (a Jacobian of at most some 16 000 rows by 8 columns, the
    terrain's 8 000 by 120): split over threads they gain nothing, and on a machine whose
    other cores are busy OpenBLAS's threads wait for each other, an SVD of the fitting
    loop taking 16 ms instead of 1 ms (2 cores, one busy).  The limit is process-wide: the
    first of overlapping diagnoses (on several threads) sets it, the last lifts it."""
    global _blas_users, _blas_limiter
    with _BLAS_LOCK:
        if _blas_users == 0:
            _blas_limiter = threadpool_limits(limits=1, user_api="blas")
        _blas_users += 1
    try:
        yield
    finally:
        with _BLAS_LOCK:
            _blas_users -= 1
            if _blas_users == 0 and _blas_limiter is not None:
                _blas_limiter.restore_original_limits()
                _blas_limiter = None


def _as_list(logs: Log | Sequence[Log]) -> list[Log]:
    return [logs] if isinstance(logs, Log) else list(logs)


def read_logs(
    paths: Sequence[str], vbat: float | None = None, max_rows: int | None = None
) -> list[Log]:
    """Logs from CSV files and WPILib SysId ``.json`` files (one log per SysId test);
    ``vbat`` (V) is the supply for a CSV's ``duty`` column (the ``--vbat`` option).
    ``max_rows``: a longer CSV log is read whole but kept as evenly spread stretches of
    about that many rows in all, one log each (see
    :func:`truckd.logfile.read_log_windows`)."""
    from truckd.ident.sysid import is_sysid_path, read_sysid
    from truckd.logfile import read_log_windows

    out: list[Log] = []
    for path in paths:
        if is_sysid_path(path):
            out.extend(read_sysid(path))
        else:
            out.extend(read_log_windows(path, ("t",), vbat, max_rows))
    return out


def diagnose_log(
    log: Log | Sequence[Log],
    p0: VehicleParams,
    validate: Log | Sequence[Log] | None = None,
    progress: Callable[[str], None] = _quiet,
    gap: float | None = None,
    workers: int = 1,
) -> Diagnosis:
    """Diagnose logs (voltage or force input) against the configured vehicle ``p0``.

    Several logs, and the pauses inside one (time steps above ``gap`` s, default 10
    median steps), are separate runs, each simulated from its own measured start.
    ``workers`` above 1: the fits that do not depend on each other run on that many
    forked processes (:class:`truckd.workers.ForkMap`; the same result, sooner on as
    many free cores; one after another here when this process runs other threads).
    """
    mapper: Mapper = in_order if workers <= 1 else ForkMap(workers)
    with one_blas_thread():
        return _diagnose(
            _as_list(log), [] if validate is None else _as_list(validate), p0, progress, gap,
            mapper,
        )  # fmt: skip


def _diagnose(
    logs: list[Log],
    vals: list[Log],
    p0: VehicleParams,
    progress: Callable[[str], None],
    gap: float | None,
    mapper: Mapper,
) -> Diagnosis:
    """:func:`diagnose_log` on lists of logs, the thread limit set."""
    kind = logs[0].input_kind if logs else "voltage"
    unit = position_unit([*logs, *vals])
    for v in vals:
        if v.input_kind != kind:
            raise InputError(
                f"{v.source}: line 1: a {v.input_kind}-input log cannot validate "
                f"a {kind}-input log ({logs[0].source})"
            )
    if kind == "force":
        if len(logs) > 1 or len(vals) > 1:
            raise InputError(
                f"{logs[-1].source}: force-input diagnosis takes one log (and one "
                "validation log); join the runs into one file"
            )
        data = series_from_log(logs[0])
        val = series_from_log(vals[0]) if vals else None
        return _with_log_notes(diagnose_force(data, val, progress), [*logs, *vals])
    runs = runs_from_logs(logs, gap)
    val_runs = runs_from_logs(vals, gap) if vals else None
    if unit == "rad":
        said = progress

        def progress(line: str) -> None:
            said(in_rotational_units(line))

    d = diagnose_voltage(p0, runs, val_runs, progress, mapper)
    slips = unit_notes([*runs, *(val_runs or [])], p0, speed=unit == "m")
    d.notes[:0], d.alerts[:0] = slips, slips
    for group, what in ((logs, "fitted"), (vals, "validated")):
        with_i = [lg.source for lg in group if "i" in lg.columns]
        if with_i and len(with_i) < len(group):  # runs_from_logs dropped it: said
            note = (
                f"the current column of {', '.join(with_i)} is not used: the other logs "
                f"{what} with it have none (those runs are taken on speed alone)"
            )
            d.notes.insert(0, note)
            d.alerts.insert(0, note)
    return _with_log_notes(d, [*logs, *vals])


def _relabel_rotational(d: Diagnosis) -> None:
    """``d``'s notes, alerts and reasons in a rotating machine's units
    (:func:`truckd.ident.rotational.in_rotational_units`)."""
    d.notes[:] = [in_rotational_units(n) for n in d.notes]
    d.alerts[:] = [in_rotational_units(n) for n in d.alerts]
    d.rejected[:] = [
        dataclasses.replace(r, reason=in_rotational_units(r.reason)) for r in d.rejected
    ]


def position_unit(logs: Sequence[Log]) -> str:
    """The logs' unit of position (``m``; ``rad`` for rotational SysId logs); InputError
    when they mix the two: a rotating and a translating machine are not one fit."""
    for lg in logs:
        if lg.position_unit != logs[0].position_unit:
            raise InputError(
                f"{lg.source}: line 1: its positions are in {lg.position_unit}, those of "
                f"{logs[0].source} in {logs[0].position_unit}: a rotating and a "
                "translating machine cannot be fitted together"
            )
    return logs[0].position_unit if logs else "m"


def identify_notes(
    logs: Sequence[Log], p0: VehicleParams, model: ModelFile, gap: float | None = None
) -> list[str]:
    """What ``identify`` says of its logs and its fit, as ``diagnose`` does: columns that
    look wired or scaled wrongly (sign, t in ms, speed in rpm, current in mA) and a
    machine unlike the configured truck ``p0``."""
    runs = runs_from_logs(list(logs), gap)
    return [
        *suspect_columns(runs),
        *unit_notes(runs, p0, speed=position_unit(logs) == "m"),
        *configuration_notes(model.vehicle, p0),
    ]


def _with_log_notes(d: Diagnosis, logs: Sequence[Log]) -> Diagnosis:
    """``d`` with the logs' unit of position (its own notes said in it) and the readers'
    remarks on its logs first in its notes (once each: a SysId file's unit conversion,
    which column is the input), as the CLI prints them."""
    d.position_unit = logs[0].position_unit if logs else "m"
    if d.position_unit == "rad":
        _relabel_rotational(d)
    said = list(dict.fromkeys(n for lg in logs for n in lg.notes))
    d.notes[:0] = [n for n in said if n not in d.notes]
    return d


def identify_log(
    log: Log | Sequence[Log],
    p0: VehicleParams,
    progress: Callable[[str], None] = _quiet,
    gap: float | None = None,
) -> ModelFile:
    """The seed model fitted to voltage-input logs (all their runs), as a model file."""
    logs = _as_list(log)
    position_unit(logs)
    for one in logs:
        if one.input_kind != "voltage":
            raise InputError(
                f"{one.source}: line 1: identify fits the truck's voltage-driven model and "
                "needs column 'u'; for a force-input log use 'truckd diagnose'"
            )
    with one_blas_thread():
        fit = identify_voltage(p0, runs_from_logs(logs, gap), progress)
    names = " ".join(one.source for one in logs)
    return ModelFile(vehicle=fit.params, effects=Effects(), source=f"identify {names}")


def require_physical(model: ModelFile, source: str, what: str) -> ModelFile:
    """``model`` when its vehicle passes :meth:`VehicleParams.validate`; else TruckdError
    naming ``what`` (e.g. "fitted model"): a model no command could load is not written
    (a log in the wrong units fits one)."""
    why = model.vehicle.validate()
    if why is not None:
        raise TruckdError(
            f"{source}: the {what} is not physical ({why}); check the log's units "
            "(t in s, u in V, v in m/s); nothing written"
        )
    return model


def model_of(diag: Diagnosis, source: str) -> ModelFile:
    """The extended model of a voltage-input diagnosis, as a model file."""
    if diag.vehicle is None or diag.model_effects is None:
        raise InputError(
            f"{source}: --out writes a truck model (MODEL.yaml) and needs a voltage-input "
            "log; this log has a force input"
        )
    return ModelFile(vehicle=diag.vehicle, effects=diag.model_effects, source=f"diagnose {source}")

"""Entry points the CLI calls: identify and diagnose a log, build the model file."""

from __future__ import annotations

from collections.abc import Callable

from truckd.errors import InputError
from truckd.ident.data import series_from_log
from truckd.ident.diagnose import diagnose_voltage, identify_voltage
from truckd.ident.force import diagnose_force
from truckd.ident.result import Diagnosis
from truckd.logfile import Log
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams
from truckd.modelfile import ModelFile


def _quiet(_: str) -> None:
    return None


def diagnose_log(
    log: Log,
    p0: VehicleParams,
    validate: Log | None = None,
    progress: Callable[[str], None] = _quiet,
) -> Diagnosis:
    """Diagnose a log (voltage or force input) against the configured vehicle ``p0``."""
    data = series_from_log(log)
    val = None
    if validate is not None:
        if validate.input_kind != log.input_kind:
            raise InputError(
                f"{validate.source}: line 1: a {validate.input_kind}-input log cannot validate "
                f"a {log.input_kind}-input log ({log.source})"
            )
        val = series_from_log(validate)
    if log.input_kind == "force":
        return diagnose_force(data, val, progress)
    return diagnose_voltage(p0, data, val, progress)


def identify_log(
    log: Log, p0: VehicleParams, progress: Callable[[str], None] = _quiet
) -> ModelFile:
    """The seed model fitted to a voltage-input log, as a model file."""
    if log.input_kind != "voltage":
        raise InputError(
            f"{log.source}: line 1: identify fits the truck's voltage-driven model and needs "
            "column 'u'; for a force-input log use 'truckd diagnose'"
        )
    fit = identify_voltage(p0, series_from_log(log), progress)
    return ModelFile(vehicle=fit.params, effects=Effects(), source=f"identify {log.source}")


def model_of(diag: Diagnosis, source: str) -> ModelFile:
    """The extended model of a voltage-input diagnosis, as a model file."""
    if diag.vehicle is None or diag.model_effects is None:
        raise InputError(
            f"{source}: --out writes a truck model (MODEL.yaml) and needs a voltage-input "
            "log; this log has a force input"
        )
    return ModelFile(vehicle=diag.vehicle, effects=diag.model_effects, source=f"diagnose {source}")

"""MODEL.yaml: a fitted model, written by ``identify``/``diagnose``, read by ``sim``,
``simulate`` and the MPC.

Format (YAML, validated like the configuration)::

    vehicle: {R_m: ..., L_m: ..., ...}     # complete VehicleParams (SI)
    effects: {viscous_friction: ..., ...}  # optional; the effects found (0 = absent)
    source: "diagnose LOG.csv"             # optional free text
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import yaml

from truckd.config.cross import model_vehicle_problem
from truckd.config.truck import TruckConfig
from truckd.control.feedforward import torque_to_voltage
from truckd.errors import InputError
from truckd.inputs import read_text
from truckd.model.effects import Effects, driver_output
from truckd.model.params import VehicleParams
from truckd.outputs import write_text
from truckd.schema import load_dataclass, spec, to_plain
from truckd.yamlsafe import MAX_BYTES, load_yaml


@dataclass(frozen=True)
class ModelFile:
    """A fitted truck model: seed parameters plus effects."""

    vehicle: VehicleParams = spec("motor, drivetrain and friction parameters")
    effects: Effects = spec("effects found in the data", default_factory=Effects)
    source: str = spec("where the model came from", default="")

    def validate(self) -> str | None:
        """A model whose driver passes no voltage that breaks the truck away (a saturation
        of a millivolt, a dead zone above the battery) describes a truck that cannot move:
        refused (called by the loader)."""
        p = self.vehicle
        top, _ = driver_output(p.V_batt, self.effects, p.V_batt)
        breakaway = torque_to_voltage(p, p.K_stiction)
        if top <= breakaway:
            return (
                f"effects: at most {top:.3g} V reach the motor (vehicle.V_batt {p.V_batt:g} V "
                "through dead_zone, dead_zone_offset and voltage_saturation) and the truck "
                f"breaks away at {breakaway:.3g} V: this model's truck cannot move"
            )
        return None


def read_model(path: str | Path) -> ModelFile:
    """Load and validate a model file."""
    src = str(path)
    data = load_yaml(read_text(path, "model file (YAML)", MAX_BYTES), src)
    return load_dataclass(ModelFile, data, src)


def read_controller_model(cfg: TruckConfig, path: str | Path) -> ModelFile:
    """A controller's model file (``run``/``sim --model``), refused when its truck cannot
    move under ``cfg``'s ``control.u_max`` (:func:`truckd.config.cross.model_vehicle_problem`:
    its stiction above the stall torque)."""
    model = read_model(path)
    why = model_vehicle_problem(cfg, model.vehicle, str(path))
    if why is not None:
        raise InputError(why)
    return model


def model_text(model: ModelFile) -> str:
    """A model file's text (YAML; round-trips through :func:`read_model`)."""
    return "# truckd model file (SI units); see truckd/modelfile.py\n" + yaml.safe_dump(
        to_plain(model), sort_keys=False
    )


def write_model(path: str | Path, model: ModelFile) -> None:
    """Write a model file, all or nothing (round-trips through :func:`read_model`)."""
    write_text(path, model_text(model))


def load_model_into(cfg: TruckConfig, path: str | Path) -> TruckConfig:
    """The configuration with the simulated truck replaced by the model in ``path``."""
    model = read_model(path)
    plant = dataclasses.replace(cfg.plant, effects=model.effects)
    return dataclasses.replace(cfg, vehicle=model.vehicle, plant=plant)

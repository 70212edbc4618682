"""The top-level configuration file (``config/truck.yaml``) and its loader.

Each section is a frozen dataclass owned by the package that uses it; this module only
assembles them.  :func:`load_config` validates everything before returning anything.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from truckd.config.characterize import CharacterizeConfig
from truckd.config.cross import cross_section_problem
from truckd.config.ids import vehicle_id_problem
from truckd.config.runtime import RuntimeConfig
from truckd.control.config import ControlConfig
from truckd.control.platoon import PlatoonConfig
from truckd.inputs import read_text
from truckd.io.config import LinkConfig
from truckd.model.params import VehicleParams
from truckd.model.plant_config import PlantConfig, encoder_ticks_per_rev
from truckd.schema import load_dataclass, spec
from truckd.yamlsafe import MAX_BYTES, load_yaml


@dataclass(frozen=True)
class TruckConfig:
    """Everything configurable about one truck and its software."""

    vehicle: VehicleParams = spec("motor, drivetrain and friction parameters")
    vehicle_id: str = spec("name used in Zenoh keys", default="truck1")
    plant: PlantConfig = spec(
        "the simulated truck's effects and sensors", default_factory=PlantConfig
    )
    link: LinkConfig = spec(
        "transport to the microcontroller and receive checks", default_factory=LinkConfig
    )
    control: ControlConfig = spec(
        "the adaptive cruise controller: MPC, limits, feedforward, estimator",
        default_factory=ControlConfig,
    )
    platoon: PlatoonConfig = spec(
        "platooning: the truck ahead and the CACC/ACC headways", default_factory=PlatoonConfig
    )
    runtime: RuntimeConfig = spec(
        "the daemon: loop, backend, supervisor, telemetry, recorder", default_factory=RuntimeConfig
    )

    characterize: CharacterizeConfig = spec(
        "truckd characterize: bring-up limits, experiments, distance budget",
        default_factory=CharacterizeConfig,
    )

    def validate(self) -> str | None:
        """Checks across sections after loading (None when fine): the vehicle id, the
        simulated truck, and every pair of keys that cannot work together
        (:mod:`truckd.config.cross`)."""
        problem = vehicle_id_problem(self.vehicle_id)
        ahead = self.platoon.predecessor
        if problem is None and ahead:
            problem = vehicle_id_problem(ahead, "platoon.predecessor")
            if problem is None and ahead == self.vehicle_id:
                problem = (
                    f"key 'platoon.predecessor' = {ahead!r}: the truck's own vehicle_id "
                    "(a truck would follow its own plan at the CACC gap); name the truck "
                    "ahead, or leave it empty"
                )
        if problem is None and self.plant.vehicle.given():
            why = self.plant_vehicle.validate()
            if why is not None:
                problem = f"plant.vehicle: the simulated truck is not physical: {why}"
        return problem or cross_section_problem(self)

    @property
    def plant_vehicle(self) -> VehicleParams:
        """The simulated truck's parameters: ``vehicle`` with ``plant.vehicle`` over it."""
        return self.plant.vehicle.over(self.vehicle)

    @property
    def ticks_per_rev(self) -> int:
        """Encoder ticks per wheel revolution both sides use (the plant's when it models
        an encoder, else the link's)."""
        return encoder_ticks_per_rev(
            self.plant.encoder_ticks_per_rev, self.link.encoder_ticks_per_rev
        )


def default_config_path() -> Path:
    """The shipped default configuration (``config/truck.yaml`` in the source tree)."""
    return Path(str(resources.files("truckd") / "defaults" / "truck.yaml"))


def parse_config(text: str, source: str) -> TruckConfig:
    """Validate YAML text; ``source`` names it in error messages."""
    return load_dataclass(TruckConfig, load_yaml(text, source), source)


def load_config(path: str | Path | None = None) -> TruckConfig:
    """Load and validate a configuration file (the shipped default when path is None)."""
    p = Path(path) if path is not None else default_config_path()
    return parse_config(read_text(p, "configuration file", MAX_BYTES), str(p))

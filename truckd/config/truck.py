"""The top-level configuration file (``config/truck.yaml``) and its loader.

Each section is a frozen dataclass owned by the package that uses it; this module only
assembles them.  :func:`load_config` validates everything before returning anything.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import yaml

from truckd.config.schema import load_dataclass, spec
from truckd.control.config import ControlConfig
from truckd.control.platoon import PlatoonConfig
from truckd.errors import InputError
from truckd.io.config import LinkConfig
from truckd.model.params import VehicleParams
from truckd.model.plant_config import PlantConfig, encoder_ticks_per_rev
from truckd.runtime.config import RuntimeConfig


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
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f" line {mark.line + 1}" if mark is not None else ""
        raise InputError(f"{source}:{line} is not valid YAML: {exc}") from None
    return load_dataclass(TruckConfig, data, source)


def load_config(path: str | Path | None = None) -> TruckConfig:
    """Load and validate a configuration file (the shipped default when path is None)."""
    p = Path(path) if path is not None else default_config_path()
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(f"{p}: cannot read configuration: {exc.strerror}") from None
    return parse_config(text, str(p))

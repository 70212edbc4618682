"""Shared fixtures: the shipped default vehicle."""

from __future__ import annotations

import pytest

from truckd.config.truck import load_config
from truckd.model.params import VehicleParams


@pytest.fixture(scope="session")
def params() -> VehicleParams:
    """The default truck's parameters (config/truck.yaml)."""
    return load_config().vehicle

"""Shared fixtures: the shipped default vehicle."""

from __future__ import annotations

import pytest

from truckd.config.truck import load_config
from truckd.model.params import VehicleParams

pytest_plugins = ["tool_markers"]  # the needs_tool marker (tests/tool_markers.py)


@pytest.fixture(scope="session")
def params() -> VehicleParams:
    """The default truck's parameters (config/truck.yaml)."""
    return load_config().vehicle

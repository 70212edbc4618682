"""A truck that accelerates harder than the estimator's configured ``accel_max``: its own
acceleration is motion, not a counter reset (a light truck crawled, the filter restarting
on every speed step)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from truckd.config.truck import load_config
from truckd.control.estimator import for_truck
from truckd.sim.closed_loop import SimSetup, run_scenario
from truckd.sim.scenarios import make_scenario

ROOT = Path(__file__).resolve().parents[1]


def _truck(tmp_path: Path, inertia: float, mass: float, battery: float) -> Path:
    """The default configuration with the truck's (and the simulated plant's) inertia,
    mass and battery scaled; the driver's limit follows the battery."""
    doc = yaml.safe_load((ROOT / "config" / "truck.yaml").read_text())
    v = doc["vehicle"]
    v["J_S"], v["m"], v["V_batt"] = v["J_S"] * inertia, v["m"] * mass, v["V_batt"] * battery
    doc["control"]["u_max"] = min(doc["control"]["u_max"] * battery, v["V_batt"])
    path = tmp_path / "truck.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_the_bound_is_the_models_stall_acceleration_where_that_is_higher() -> None:
    tc = load_config()
    p, est = tc.vehicle, tc.control.estimator
    assert for_truck(est, p, tc.control.u_max) is est  # the default truck: 23 < 30 m/s^2
    light = p.replace(J_S=p.J_S / 10.0)
    raised = for_truck(est, light, tc.control.u_max)
    stall = (
        light.K_T
        * tc.control.u_max
        / (light.R_m * light.J_S)
        * light.r_w
        / (light.n_g * light.n_fd)
    )
    assert raised.accel_max == pytest.approx(stall) and stall > 200.0
    assert raised.speed_max == est.speed_max  # nothing else moves


@pytest.mark.parametrize(
    ("inertia", "mass", "battery"),
    [(0.1, 0.1, 1.0), (0.25, 0.5, 1.0), (0.5, 1.0, 12.0 / 7.2), (1.0, 1.0, 1.0)],
)
def test_a_light_or_strong_truck_holds_its_set_speed(
    tmp_path: Path, inertia: float, mass: float, battery: float
) -> None:
    tc = load_config(_truck(tmp_path, inertia, mass, battery))
    m, _trace = run_scenario(
        make_scenario("cruise", tc.vehicle, tc.control), SimSetup.from_config(tc), 15.0
    )
    assert not m["collision"] and m["all_finite"]
    assert m["mode_time_s"]["SAFE_STOP"] == 0.0 and m["mode_time_s"]["FAULT"] == 0.0
    assert m["final_speed_m_s"] == pytest.approx(tc.control.v_set, rel=0.03)

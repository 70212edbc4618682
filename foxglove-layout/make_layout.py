"""Write the Foxglove layout for truckd's channels (docs/foxglove.md).

    python foxglove-layout/make_layout.py [VEHICLE_ID ...] > foxglove-layout/truckd-layout.json

Default vehicles: truck1 truck2 truck3.  One tab per vehicle (gap and its reference,
speeds, voltage and feedforward, supervisor mode, loop timing) and a ``fleet`` tab (every
vehicle's speed, gap and mode side by side).  The classic layout format (``configById`` +
``layout``), which Foxglove's "Import from file" and Lichtblick both read.  Topics that are
absent (fewer vehicles) simply stay empty.
"""

from __future__ import annotations

import json
import sys
from typing import Any

DEFAULT_VEHICLES = ("truck1", "truck2", "truck3")


def series(path: str, label: str) -> dict[str, Any]:
    return {"value": path, "enabled": True, "timestampMethod": "receiveTime", "label": label}


def plot(title: str, paths: list[dict[str, Any]]) -> dict[str, Any]:
    return {
        "foxglovePanelTitle": title,
        "lichtblickPanelTitle": title,
        "paths": paths,
        "showXAxisLabels": True,
        "showYAxisLabels": True,
        "showLegend": True,
        "legendDisplay": "floating",
        "showPlotValuesInLegend": True,
        "isSynced": True,
        "xAxisVal": "timestamp",
        "followingViewWidth": 30,
    }


def transitions(title: str, paths: list[dict[str, Any]]) -> dict[str, Any]:
    return {
        "foxglovePanelTitle": title,
        "lichtblickPanelTitle": title,
        "paths": [{k: p[k] for k in ("value", "timestampMethod", "label")} for p in paths],
        "isSynced": True,
    }


def column(ids: list[str]) -> str | dict[str, Any]:
    """Panels stacked top to bottom, equal heights."""
    if len(ids) == 1:
        return ids[0]
    return {
        "first": ids[0],
        "second": column(ids[1:]),
        "direction": "column",
        "splitPercentage": 100.0 / len(ids),
    }


def vehicle_panels(vid: str, config: dict[str, Any]) -> list[str]:
    s, h = f"/truckd/{vid}/state", f"/truckd/{vid}/health"
    panels = {
        f"Plot!{vid}-gap": plot(
            f"{vid}: gap and reference (m)",
            [series(f"{s}.gap", "gap"), series(f"{s}.gap_ref", "gap_ref")],
        ),
        f"Plot!{vid}-speed": plot(
            f"{vid}: speed and lead speed (m/s)",
            [series(f"{s}.v", "v"), series(f"{s}.v_lead", "v_lead")],
        ),
        f"Plot!{vid}-voltage": plot(
            f"{vid}: voltage command and feedforward (V)",
            [series(f"{s}.u", "u"), series(f"{s}.u_ff", "u_ff")],
        ),
        f"StateTransitions!{vid}-mode": transitions(
            f"{vid}: mode", [series(f"{s}.mode", "mode"), series(f"{s}.ctrl", "controller")]
        ),
        f"Plot!{vid}-timing": plot(
            f"{vid}: loop timing (us)",
            [
                series(f"{s}.lateness_us", "wake lateness"),
                series(f"{s}.solve_us", "MPC solve"),
                series(f"{h}.loop.lateness_us_p99", "lateness p99"),
                series(f"{h}.loop.compute_us_p99", "compute p99"),
            ],
        ),
    }
    config.update(panels)
    return list(panels)


def fleet_panels(vehicles: list[str], config: dict[str, Any]) -> list[str]:
    panels = {
        "Plot!fleet-speed": plot(
            "speeds (m/s)", [series(f"/truckd/{v}/state.v", v) for v in vehicles]
        ),
        "Plot!fleet-gap": plot("gaps (m)", [series(f"/truckd/{v}/state.gap", v) for v in vehicles]),
        "StateTransitions!fleet-mode": transitions(
            "modes", [series(f"/truckd/{v}/state.mode", v) for v in vehicles]
        ),
    }
    config.update(panels)
    return list(panels)


def layout(vehicles: list[str]) -> dict[str, Any]:
    """The whole layout document."""
    config: dict[str, Any] = {}
    tabs = [{"title": "fleet", "layout": column(fleet_panels(vehicles, config))}]
    tabs += [{"title": v, "layout": column(vehicle_panels(v, config))} for v in vehicles]
    config["Tab!truckd"] = {"activeTabIdx": 1 if vehicles else 0, "tabs": tabs}
    return {
        "configById": config,
        "globalVariables": {},
        "userNodes": {},
        "playbackConfig": {"speed": 1},
        "layout": "Tab!truckd",
    }


def main(argv: list[str]) -> int:
    vehicles = argv or list(DEFAULT_VEHICLES)
    sys.stdout.write(json.dumps(layout(vehicles), indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

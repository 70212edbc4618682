"""The monitor's platoon listing: order from the predecessors, gaps, CACC/ACC."""

from __future__ import annotations

from typing import Any

from truckd.runtime.monitor import FleetView
from truckd.runtime.platoon_view import platoon_lines, platoons


def _v(pred: str | None, gap: float | None = None, mode: str | None = None) -> Any:
    return ({"gap": gap, "platoon": mode}, {"platoon": {"predecessor": pred}})


def test_chains_in_order_from_the_lead() -> None:
    vs = {
        "t2": _v("t1", 1.1, "ACC"),
        "t0": _v(None),
        "t1": _v("t0", 0.95, "CACC"),
        "solo": _v(None),
        "x1": _v("ghost", 2.0, "ACC"),
        "c1": _v("c2"),
        "c2": _v("c1"),
    }
    assert platoons(vs) == [["ghost", "x1"], ["t0", "t1", "t2"]]
    lines = platoon_lines(vs)
    assert lines[1] == "platoon: t0 -> [0.95 m CACC] t1 -> [1.10 m ACC] t2"
    assert lines[0].startswith("platoon: ghost (not seen) -> [2.00 m ACC] x1")


def test_fleet_view_lists_the_platoon_below_the_table() -> None:
    view = FleetView()
    view.on_sample("truckd/a/health", b'{"platoon": {"predecessor": null}}', 0.0)
    view.on_sample("truckd/b/health", b'{"platoon": {"predecessor": "a"}}', 0.0)
    view.on_sample("truckd/b/state", b'{"gap": 0.8, "platoon": "CACC"}', 0.0)
    assert view.render().splitlines()[-1] == "platoon: a -> [0.80 m CACC] b"

"""Zenoh telemetry: keys, payloads, liveliness, params query, and never blocking the loop."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest
import zenoh
from runtime_support import endpoint, free_port, wait_for, write_config

from truckd.config.runtime import TelemetryConfig
from truckd.errors import InputError
from truckd.runtime.telemetry import Telemetry, keys, zenoh_config


def _wait(pred: Any, timeout: float = 5.0) -> bool:
    return wait_for(pred, timeout)


def test_shipped_zenoh_config_is_loopback_only() -> None:
    conf = zenoh_config()
    assert json.loads(conf.get_json("mode")) == "peer"
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("scouting/gossip/enabled")) is False


def test_state_health_params_and_liveliness_over_zenoh() -> None:
    port = free_port()
    cfg = TelemetryConfig(listen=(endpoint(port),))
    tel = Telemetry("truckT", cfg, lambda: {"vehicle": {"R_m": 0.0847}, "rate_hz": 100.0})
    tel.start()
    got: list[tuple[str, dict[str, Any]]] = []
    alive: list[tuple[str, bool]] = []
    sub_conf = zenoh_config(listen=[], connect=[endpoint(port)])
    s = zenoh.open(sub_conf)
    try:
        s.declare_subscriber(
            "truckd/*/*",
            lambda smp: got.append((str(smp.key_expr), json.loads(smp.payload.to_bytes()))),
        )
        s.liveliness().declare_subscriber(
            "truckd/*/alive",
            lambda smp: alive.append((str(smp.key_expr), smp.kind == zenoh.SampleKind.PUT)),
            history=True,
        )
        assert _wait(lambda: ("truckd/truckT/alive", True) in alive)
        # the subscriber is matched once the publisher sees it (MatchingStatus is truthy
        # whatever it says: ask .matching)
        assert _wait(lambda: tel._pubs["state"].matching_status.matching)
        for k in range(20):
            tel.publish_state({"seq": k, "mode": "ACTIVE"})
        tel.publish_health({"faults": []}, lambda: {"loop": {"misses": 0}})
        assert _wait(lambda: len(got) >= 21)
        states = [m for key, m in got if key == keys("truckT")["state"]]
        assert [m["seq"] for m in states] == list(range(20))
        health = [m for key, m in got if key == "truckd/truckT/health"]
        assert health == [{"faults": [], "loop": {"misses": 0}}]
        replies = list(s.get("truckd/truckT/params", timeout=5.0))
        assert len(replies) == 1
        ok = replies[0].ok
        assert ok is not None
        assert json.loads(ok.payload.to_bytes())["vehicle"]["R_m"] == 0.0847
        # a query across the fleet: each reply on its truck's own key
        (fleet,) = list(s.get("truckd/*/params", timeout=5.0))
        assert fleet.ok is not None and str(fleet.ok.key_expr) == "truckd/truckT/params"
        tel.close()
        assert _wait(lambda: ("truckd/truckT/alive", False) in alive)
    finally:
        tel.close()
        s.close()
    assert tel.dropped == 0 and tel.errors == 0


class _StuckPublisher:
    """A publisher whose put blocks until released: a stalled network."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.puts = 0

    def put(self, payload: str) -> None:
        self.release.wait()
        self.puts += 1


def test_stalled_publisher_never_blocks_the_caller_and_drops_oldest() -> None:
    tel = Telemetry("truckT", TelemetryConfig(queue_size=8), dict)
    stuck = _StuckPublisher()
    tel._pubs = {"state": stuck, "health": stuck}  # type: ignore[dict-item]
    worker = threading.Thread(target=tel._run, daemon=True)
    worker.start()
    tel.publish_state({"seq": -1})  # the worker takes this one and blocks in put()
    assert _wait(lambda: len(tel._q) == 0)
    done = threading.Event()

    def producer() -> None:
        for k in range(1000):
            tel.publish_state({"seq": k})
        done.set()

    threading.Thread(target=producer, daemon=True).start()
    # with a blocking design the producer would hang behind the stuck put forever
    assert done.wait(10.0)
    assert tel.dropped == 1000 - 8
    assert [m["seq"] for _, m, _ in tel._q] == list(range(992, 1000))  # newest kept
    stuck.release.set()
    tel._stop = True
    tel._event.set()
    worker.join(5.0)
    assert not worker.is_alive()
    assert stuck.puts == 1 + 8


def test_bad_endpoint_is_an_input_error_naming_it() -> None:
    with pytest.raises(InputError, match=r"runtime\.telemetry\.connect 'tcpp:1'"):
        zenoh_config(
            connect=["tcp/127.0.0.1:7447", "tcpp:1"],
            names=("runtime.telemetry.listen", "runtime.telemetry.connect"),
        )
    with pytest.raises(InputError, match=r"listen 'nowhere'"):
        zenoh_config(listen=["nowhere"])
    # a port above 65535, which Zenoh takes and never reaches
    with pytest.raises(InputError, match=r"connect 'tcp/127.0.0.1:99999': port above 65535"):
        zenoh_config(connect=["tcp/127.0.0.1:99999"])
    from truckd.runtime.telemetry import _port_out_of_range

    assert _port_out_of_range("tls/host:99999?x=y") and _port_out_of_range("tcp/[::1]:70000")
    assert not _port_out_of_range("unixsock-stream//tmp/run:99999")
    assert not _port_out_of_range("tcp/[::1]:7447")


@pytest.mark.parametrize(
    "argv",
    [
        ["monitor", "--connect", "notanendpoint", "--duration", "0"],
        ["run", "--config", "{cfg}", "--backend", "sim", "--duration", "1"],
    ],
)
def test_bad_endpoint_on_the_command_line_is_exit_2(tmp_path: Path, argv: list[str]) -> None:
    cfg = write_config(
        tmp_path / "truck.yaml",
        {"runtime": {"realtime": False, "telemetry": {"listen": ["nowhere"]},
                     "recorder": {"dir": str(tmp_path / "logs")}}},
    )  # fmt: skip
    r = subprocess.run(
        [sys.executable, "-m", "truckd.cli.main", *(a.format(cfg=cfg) for a in argv)],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    assert ("'notanendpoint'" if argv[0] == "monitor" else "runtime.telemetry.listen") in r.stderr

"""State messages built off the control loop: :class:`truckd.runtime.deferred.Deferred`.

The daemon hands the publisher and the recorder a deferred state message (the cycle's
frozen outputs); these tests check that what is built later, on another thread, is what
the cycle would have published at once, and that the loop's thread does not build it.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any

import zenoh
from runtime_support import endpoint, free_port, wait_for

from truckd.config.runtime import RecorderConfig, TelemetryConfig
from truckd.control.platoon import PlatoonDecision
from truckd.runtime.cycle import state_message
from truckd.runtime.daemon import _state_message
from truckd.runtime.deferred import Deferred, resolve
from truckd.runtime.mcap_log import McapLog, read_mcap
from truckd.runtime.recorder import Recorder
from truckd.runtime.replay import cycle_from_params
from truckd.runtime.rxlog import read_rx_log
from truckd.runtime.telemetry import Telemetry, zenoh_config

REPLAY_LOG = Path(__file__).parent / "data" / "replay" / "run.rx.jsonl"


def _wait(pred: Any, timeout: float = 10.0) -> bool:
    return wait_for(pred, timeout)


def test_builds_once_and_keeps_it() -> None:
    calls: list[tuple[int, int]] = []

    def build(a: int, b: int) -> dict[str, int]:
        calls.append((a, b))
        return {"sum": a + b}

    d = Deferred(build, 2, 3)
    assert calls == []  # nothing built on hand-over
    first = resolve(d)
    assert first == {"sum": 5} and d() is first
    assert calls == [(2, 3)]
    plain = {"x": 1}
    assert resolve(plain) is plain


def test_a_state_built_cycles_later_is_the_cycles_own() -> None:
    """Whatever the loop does after handing a cycle over, the message built later is the
    one built at once: the builder reads only that cycle's frozen outputs."""
    t0, params, cycles = read_rx_log(REPLAY_LOG)
    cyc = cycle_from_params(params, t0, str(REPLAY_LOG))
    decision = PlatoonDecision("CACC", 0.4, [0.5] * 3, 0.02)
    at_once: list[dict[str, Any]] = []
    later: list[Deferred] = []
    for k, inp in enumerate(cycles):
        out = cyc.step(inp)
        lateness = 1e-5 * (k % 7)
        at_once.append({**state_message(out, lateness), "platoon": "CACC", "headway": 0.4})
        later.append(Deferred(_state_message, out, lateness, decision))
    assert len(later) > 100
    built = [d() for d in later]
    assert built == at_once
    assert len({m["mode"] for m in built}) >= 1 and len({m["v"] for m in built}) > 10


def test_telemetry_builds_deferred_states_on_its_thread() -> None:
    port = free_port()
    tel = Telemetry("truckD", TelemetryConfig(listen=(endpoint(port),)), dict)
    tel.start()
    got: list[dict[str, Any]] = []
    s = zenoh.open(zenoh_config(listen=[], connect=[endpoint(port)]))
    threads: set[int] = set()

    def build(k: int) -> dict[str, Any]:
        threads.add(threading.get_ident())
        return {"seq": k, "mode": "ACTIVE"}

    try:
        s.declare_subscriber(
            "truckd/truckD/state", lambda m: got.append(json.loads(m.payload.to_bytes()))
        )
        assert _wait(lambda: tel._pubs["state"].matching_status.matching)
        for k in range(10):
            tel.publish_state(Deferred(build, k))
        assert _wait(lambda: len(got) >= 10)
    finally:
        tel.close()
        s.close()
    assert [m["seq"] for m in got] == list(range(10))
    assert threads and threading.get_ident() not in threads
    assert tel.errors == 0


def test_mcap_writes_deferred_states_built_by_the_writer(tmp_path: Path) -> None:
    mc = McapLog("t8", origin_ns=0)
    rec = Recorder(RecorderConfig(dir=str(tmp_path), flush_period_s=0.05), ("t",), sidecar=mc)
    threads: set[int] = set()
    shared = Deferred(lambda: (threads.add(threading.get_ident()), {"seq": 7})[1])
    rec.start()
    try:
        for k in range(50):
            rec.record((0.01 * k,))
            mc.record_state(0.01 * k, Deferred(lambda k=k: {"seq": k, "v": 0.5 * k}))
        mc.record_state(0.5, shared)
    finally:
        rec.stop()
    assert mc.path is not None
    c = read_mcap(mc.path)
    states = [json.loads(m.data) for m in c.messages if c.topic(m) == "/truckd/t8/state"]
    assert states == [{"seq": k, "v": 0.5 * k} for k in range(50)] + [{"seq": 7}]
    assert threads and threading.get_ident() not in threads
    assert mc.errors == 0 and mc.dropped == 0

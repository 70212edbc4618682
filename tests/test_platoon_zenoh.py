"""Platooning over Zenoh (loopback only): the shipped access control, a follower that
reads only its predecessor's plan, and a daemon that follows plans and falls back."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any

import pytest
import zenoh
from runtime_support import (
    endpoint,
    follower_config,
    free_port,
    run_daemon_beside,
    wait_for,
    watch_vehicle,
)

from truckd.config.runtime import TelemetryConfig
from truckd.config.truck import load_config
from truckd.control.platoon import encode_plan, kinematic_plan
from truckd.runtime.daemon import Daemon
from truckd.runtime.platoon_link import PlanReceiver
from truckd.runtime.telemetry import Telemetry, zenoh_config


def _wait(pred: Any, timeout: float = 10.0) -> bool:
    return wait_for(pred, timeout)


@pytest.mark.parametrize("acl", [True, False])
def test_shipped_access_control_passes_truckd_keys_only(acl: bool) -> None:
    port = free_port()
    a_conf = zenoh_config(listen=[endpoint(port)])
    b_conf = zenoh_config(listen=[], connect=[endpoint(port)])
    if not acl:  # the control experiment: without it the other key is delivered
        a_conf.insert_json5("access_control/enabled", "false")
        b_conf.insert_json5("access_control/enabled", "false")
    a, b = zenoh.open(a_conf), zenoh.open(b_conf)
    got: list[str] = []
    try:
        a.declare_subscriber("truckd/**", lambda s: got.append(str(s.key_expr)))
        a.declare_subscriber("other/**", lambda s: got.append(str(s.key_expr)))
        # until the subscription has reached b (a put before that is simply not routed)
        assert _wait(lambda: b.put("truckd/x/plan", "{}") or "truckd/x/plan" in got)
        b.put("other/secret", "1")
        b.put("truckd/x/state", "marker")  # same session, in order: after the other key
        assert _wait(lambda: "truckd/x/state" in got)
        assert ("other/secret" in got) is (not acl)
    finally:
        b.close()
        a.close()


def test_plan_receiver_refuses_other_senders_and_bad_payloads() -> None:
    r = PlanReceiver("truckA")
    for payload in (
        encode_plan(kinematic_plan(1.0, 5, 0.01, 1.0, 0.0, 10, "truckA")),
        encode_plan(kinematic_plan(1.1, 6, 0.01, 9.0, 0.0, 10, "truckC")),
        b"{not json",
        encode_plan(kinematic_plan(1.2, 4, 0.01, 7.0, 0.0, 10, "truckA")),  # older
    ):
        r.on_payload(payload)
        r.latest()  # one cycle per sample: each one decoded
    p = r.latest()
    assert p is not None and p.seq == 5 and p.v[0] == 1.0
    assert (r.accepted, r.refused) == (1, 3)
    r.on_payload(encode_plan(kinematic_plan(9.0, 0, 0.01, 2.0, 0.0, 10, "truckA")))  # restart
    p = r.latest()
    assert p is not None and p.seq == 0 and p.v[0] == 2.0


def test_a_plan_stamped_in_the_future_is_refused_and_locks_nothing_out() -> None:
    """One plan with a huge seq stamped 1e6 s ahead used to be held, and every genuine plan
    after it dropped as older, uncounted: the follower stayed in ACC for good."""
    now = [100.0]
    r = PlanReceiver("truckA", lambda: now[0], 0.05)
    r.on_payload(encode_plan(kinematic_plan(100.0, 5, 0.01, 1.0, 0.0, 10, "truckA")))
    r.latest()
    r.on_payload(encode_plan(kinematic_plan(1e6, 2**62, 0.01, 1.0, 0.0, 10, "truckA")))
    r.latest()
    assert r.refused == 1 and "future" in r.last_error
    now[0] = 100.01
    r.on_payload(encode_plan(kinematic_plan(100.01, 6, 0.01, 1.2, 0.0, 10, "truckA")))
    p = r.latest()
    assert p is not None and p.seq == 6 and r.accepted == 2
    r.on_payload(encode_plan(kinematic_plan(100.04, 7, 0.01, 1.2, 0.0, 10, "truckA")))
    r.latest()
    assert r.accepted == 3  # within the allowed skew


def test_follower_subscribes_to_its_predecessors_key_only() -> None:
    port = free_port()
    tel = Telemetry("truckB", TelemetryConfig(listen=(endpoint(port),)), dict)
    tel.start()
    r = PlanReceiver("truckA")
    seen: list[bytes] = []
    tel.subscribe_key(r.key, lambda p: (seen.append(p), r.on_payload(p)))
    s = zenoh.open(zenoh_config(listen=[], connect=[endpoint(port)]))
    try:
        pub_a = s.declare_publisher("truckd/truckA/plan")
        pub_c = s.declare_publisher("truckd/truckC/plan")
        assert _wait(lambda: pub_a.matching_status.matching)
        pub_c.put(encode_plan(kinematic_plan(1.0, 1, 0.01, 5.0, 0.0, 10, "truckC")))
        pub_a.put(encode_plan(kinematic_plan(1.0, 7, 0.01, 1.5, 0.0, 10, "truckA")))
        assert _wait(lambda: r.latest() is not None)
        p = r.latest()
        assert p is not None and p.vehicle_id == "truckA" and p.seq == 7
        assert len(seen) == 1  # truckC's plan never reached the follower's callback
    finally:
        s.close()
        tel.close()


@pytest.mark.parametrize("offset", [0.0, 2.0, -2.0])
def test_daemon_follows_its_predecessors_plan_then_falls_back_to_acc(
    tmp_path: Path, offset: float
) -> None:
    """``offset``: the lead's clock runs this far from the follower's (s); the follower
    estimates it from the plans (``platoon.clock_sync``) and follows all the same."""
    port = free_port()
    cfg_path = follower_config(tmp_path / "truck.yaml", "f1", {"predecessor": "lead"}, port)
    s = zenoh.open(zenoh_config(listen=[endpoint(port)]))
    got = watch_vehicle(s, "f1")
    states, plans, health = got["state"], got["plan"], got["health"]
    stopped_at: list[float] = []

    def lead(stop: threading.Event) -> None:
        pub = s.declare_publisher("truckd/lead/plan")
        seq = 0
        cacc_seen = None
        while not stop.is_set():
            if any(m.get("platoon") == "CACC" for m in states[-5:]):
                cacc_seen = cacc_seen or time.monotonic()
            if cacc_seen is not None and time.monotonic() - cacc_seen > 0.3:
                stopped_at.append(time.monotonic())
                return  # the link goes silent
            t = time.time() + offset
            pub.put(encode_plan(kinematic_plan(t, seq, 0.01, 0.9, 0.0, 40, "lead")))
            seq += 1
            time.sleep(0.01)

    d = Daemon(load_config(cfg_path), "sim", duration=4.0, env={})
    assert run_daemon_beside(d, s, lead) == 0
    modes = [m.get("platoon") for m in states]
    assert "CACC" in modes, modes[-20:]
    assert stopped_at, "the daemon never reached CACC"
    first_cacc = modes.index("CACC")
    assert "ACC" in modes[first_cacc:]  # fell back after the plans stopped
    assert all(m in ("CACC", "ACC") for m in modes)
    assert plans and {"t", "seq", "dt", "v", "a"} <= set(plans[-1])
    assert plans[-1]["vehicle_id"] == "f1" and plans[-1]["predecessor"] == "lead"
    assert len(plans[-1]["v"]) == d.controller.mpc.horizon + 1
    entries = [h["platoon"] for h in health if "platoon" in h]
    assert entries and entries[-1]["predecessor"] == "lead"
    assert entries[-1]["plans_accepted"] > 10 and entries[-1]["switches"] >= 2


def test_router_config_relays_truckd_keys_between_clients_only() -> None:
    defaults = Path(__file__).resolve().parent.parent / "truckd" / "defaults"
    port = free_port()
    router = zenoh.open(zenoh_config(defaults / "zenoh-router.json5", listen=[endpoint(port)]))
    client_file = defaults / "zenoh-client.json5"
    assert json.loads(zenoh_config(client_file).get_json("mode")) == "client"
    a = zenoh.open(zenoh_config(client_file, connect=[endpoint(port)]))
    b = zenoh.open(zenoh_config(client_file, connect=[endpoint(port)]))
    got: list[str] = []
    try:
        b.declare_subscriber("truckd/**", lambda s: got.append(str(s.key_expr)))
        b.declare_subscriber("other/**", lambda s: got.append(str(s.key_expr)))
        assert _wait(lambda: a.put("truckd/v1/plan", "{}") or "truckd/v1/plan" in got)
        a.put("other/secret", "1")
        a.put("truckd/v1/state", "marker")
        assert _wait(lambda: "truckd/v1/state" in got)
        assert "other/secret" not in got
    finally:
        a.close()
        b.close()
        router.close()

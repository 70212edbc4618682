"""Only trucks of the fleet speak: Zenoh over mutual TLS through a router whose access
control goes by certificate common name (truckd/runtime/fleet_tls.py); all on 127.0.0.1,
no scouting, no gossip."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from runtime_support import free_port, wait_for

from truckd.control.platoon import encode_plan, kinematic_plan
from truckd.errors import InputError
from truckd.runtime.fleet_tls import Fleet, client_config, make_fleet, router_config
from truckd.runtime.platoon_join import join_key
from truckd.runtime.platoon_link import PlanReceiver

REPO = Path(__file__).resolve().parent.parent


def _open(conf: dict[str, Any]) -> zenoh.Session:
    return zenoh.open(zenoh.Config.from_json5(json.dumps(conf)))


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Fleet:
    return make_fleet(tmp_path_factory.mktemp("fleet"), ["truck1", "truck2", "truck3"])


class _Net:
    def __init__(self, fleet: Fleet, acl: bool) -> None:
        self.endpoint = f"tls/127.0.0.1:{free_port()}"
        rc = router_config(fleet, self.endpoint)
        rc["access_control"]["enabled"] = acl
        self.sessions = [_open(rc)]
        self.fleet = fleet
        self.acl = acl

    def client(self, name: str) -> zenoh.Session:
        s = _open(client_config(self.fleet, name, self.endpoint))
        self.sessions.append(s)
        return s

    def close(self) -> None:
        for s in reversed(self.sessions):
            s.close()


@pytest.fixture(params=[True, False], ids=["acl", "no-acl"])
def net(fleet: Fleet, request: pytest.FixtureRequest) -> Iterator[_Net]:
    n = _Net(fleet, bool(request.param))
    try:
        yield n
    finally:
        n.close()


def _plan(t: float, seq: int, v: float, vid: str) -> bytes:
    return encode_plan(kinematic_plan(t, seq, 0.01, v, 0.0, 10, vid))


def test_a_spoofed_plan_and_a_trucks_fault_are_refused_by_the_router(net: _Net) -> None:
    """truck2 follows truck1: its plan receiver gets truck1's plans.  truck3 publishes a
    plan on truck1's key (claiming to be truck1), injects a fault into truck1 and tells
    it where to join: with the access control the router refuses all three; the
    operator's fault and join order pass.  Without
    it (the control experiment) the spoofed plan reaches the controller."""
    t1, t2, t3, op = (net.client(n) for n in ("truck1", "truck2", "truck3", "operator"))
    receiver = PlanReceiver("truck1")
    t2.declare_subscriber(receiver.key, lambda s: receiver.on_payload(s.payload.to_bytes()))
    faults: list[str] = []
    t1.declare_subscriber("truckd/truck1/inject", lambda s: faults.append(s.payload.to_string()))
    joins: list[str] = []
    t1.declare_subscriber(join_key("truck1"), lambda s: joins.append(s.payload.to_string()))
    seen: list[str] = []
    t2.declare_subscriber("truckd/truck3/state", lambda s: seen.append(s.payload.to_string()))
    seq = iter(range(1, 10_000))
    # until the subscriptions have reached the router (a put before is simply not routed)
    assert wait_for(lambda: t1.put(receiver.key, _plan(1.0, next(seq), 1.0, "truck1"))
                    or receiver.latest() is not None, 10.0)  # fmt: skip
    assert wait_for(lambda: op.put("truckd/truck1/inject", "op") or "op" in faults, 10.0)
    assert wait_for(lambda: op.put(join_key("truck1"), "op") or "op" in joins, 10.0)
    held = receiver.latest()
    assert held is not None and held.v[0] == 1.0
    t3.put(receiver.key, _plan(2.0, 10**6, 9.0, "truck1"))  # spoofed: truck3 as truck1
    t3.put("truckd/truck1/inject", "truck3")
    t3.put(join_key("truck1"), "truck3")  # a truck telling another where to drive
    # after those, in order from the same session: a marker on truck3's own key
    assert wait_for(lambda: t3.put("truckd/truck3/state", "marker") or "marker" in seen, 10.0)
    held = receiver.latest()
    assert held is not None
    assert (held.v[0] == 9.0) is (not net.acl)  # the spoofed plan (9 m/s) reached it
    assert ("truck3" in faults) is (not net.acl)
    assert ("truck3" in joins) is (not net.acl)


def test_only_an_operator_queries_parameters(fleet: Fleet) -> None:
    net = _Net(fleet, acl=True)
    try:
        t1, t2, op = (net.client(n) for n in ("truck1", "truck2", "operator"))
        t1.declare_queryable("truckd/truck1/params", lambda q: q.reply(q.key_expr, "{}"))

        def answers(s: zenoh.Session) -> int:
            return sum(1 for r in s.get("truckd/truck1/params", timeout=2.0) if r.ok)

        assert wait_for(lambda: answers(op) == 1, 10.0)  # the queryable is known
        assert answers(t2) == 0
    finally:
        net.close()


def test_strangers_cannot_connect(fleet: Fleet, tmp_path: Path) -> None:
    """Without a certificate, or with one from another authority, the TLS handshake is
    refused: the session does not open."""
    net = _Net(fleet, acl=True)
    other = make_fleet(tmp_path / "other", ["truck1"])
    try:
        no_cert = client_config(fleet, "truck1", net.endpoint)
        tls = no_cert["transport"]["link"]["tls"]
        for k in ("connect_certificate", "connect_private_key", "listen_certificate",
                  "listen_private_key"):  # fmt: skip
            del tls[k]
        foreign = client_config(other, "truck1", net.endpoint)
        foreign["transport"]["link"]["tls"]["root_ca_certificate"] = str(fleet.ca)
        for conf in (no_cert, foreign):
            with pytest.raises(zenoh.ZError):
                net.sessions.append(_open(conf))
        net.client("truck1")  # the same endpoint admits a member
    finally:
        net.close()


def test_fleet_files_and_configs(fleet: Fleet) -> None:
    from cryptography import x509

    for name in ("truck1", "truck2", "truck3", "operator", "router"):
        cert = x509.load_pem_x509_certificate(fleet.cert(name).read_bytes())
        cn = cert.subject.get_attributes_for_oid(x509.oid.NameOID.COMMON_NAME)[0].value
        assert cn == name
        assert fleet.key(name).stat().st_mode & 0o077 == 0
    rc = router_config(fleet)
    assert rc["scouting"] == {"multicast": {"enabled": False}, "gossip": {"enabled": False}}
    assert rc["listen"]["endpoints"] == ["tls/127.0.0.1:7449"]
    assert rc["transport"]["link"]["tls"]["enable_mtls"] is True
    subjects = {s["id"]: s["cert_common_names"] for s in rc["access_control"]["subjects"]}
    assert subjects == {n: [n] for n in ("truck1", "truck2", "truck3", "operator")}
    with pytest.raises(InputError):
        client_config(fleet, "stranger")
    for bad in (["truck*"], ["a/b"], ["x", "x"], ["router"]):
        with pytest.raises(InputError):
            make_fleet(fleet.directory / "bad", bad)


def test_fleet_script(tmp_path: Path) -> None:
    out = tmp_path / "f"
    script = [sys.executable, str(REPO / "tools" / "fleet_certs.py"), "--out", str(out)]
    ok = subprocess.run([*script, "--trucks", "t0,t1"], capture_output=True, text=True, check=False)
    assert ok.returncode == 0, ok.stderr
    for f in ("ca.pem", "t0.pem", "t1-key.pem", "operator.pem", "router.json5", "t1.json5"):
        assert (out / f).is_file()
    zenoh.Config.from_file(str(out / "router.json5"))  # zenoh reads what it wrote
    bad = subprocess.run([*script, "--trucks", "t*"], capture_output=True, text=True, check=False)
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1

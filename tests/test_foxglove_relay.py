"""``truckd monitor --foxglove``: a client speaking the Foxglove WebSocket protocol (the
``websockets`` package) against the relay process, with two vehicles publishing over Zenoh
on loopback: the channels are advertised with their JSON schemas and messages arrive for
both vehicles, and a vehicle that goes has its channels unadvertised.

The server accepts both names of the protocol, ``foxglove.websocket.v1`` (the reference
client ``@foxglove/ws-protocol``; tests/test_foxglove_readers.py runs it) and
``foxglove.sdk.v1`` (foxglove-sdk 0.30, recent Foxglove and Lichtblick): the same messages.
"""

from __future__ import annotations

import json
import os
import signal
import struct
import subprocess
import sys
import threading
import time
from typing import Any

import jsonschema
import pytest
from runtime_support import endpoint, free_port
from websockets.sync.client import connect

from truckd.cli.main import main
from truckd.config.runtime import TelemetryConfig
from truckd.runtime.foxglove_relay import clean_payload
from truckd.runtime.msg_schemas import SCHEMAS
from truckd.runtime.telemetry import Telemetry, open_session, zenoh_config

SUBPROTOCOLS = ("foxglove.websocket.v1", "foxglove.sdk.v1")
OP_MESSAGE_DATA = 0x01


def test_clean_payload() -> None:
    assert clean_payload(b'{"v": 1.0}') == b'{"v": 1.0}'  # passed through untouched
    assert json.loads(clean_payload(b'{"v": NaN, "w": [Infinity]}') or b"") == {
        "v": None,
        "w": [None],
    }
    assert clean_payload(b"[NaN]") is None and clean_payload(b"NaN garbage") is None
    # Not JSON objects, without a NaN to make them looked at: refused all the same (they
    # went to a JSON channel unchanged)
    for bad in (b"\xff\xfe not json", b"[1, 2, 3]", b"42", b'{"v": 1.0', b"[" * 100_000):
        assert clean_payload(bad) is None, bad[:20]


def _state(seq: int) -> dict[str, Any]:
    return {"seq": seq, "t": 0.01 * seq, "mode": "ACTIVE", "v": 0.8, "gap": 1.2,
            "gap_ref": 1.1, "v_lead": 0.8, "u": 2.5, "u_ff": 2.0, "solve_us": 250.0}  # fmt: skip


@pytest.mark.parametrize("subprotocol", SUBPROTOCOLS)
def test_relay_serves_two_vehicles_to_a_foxglove_client(subprotocol: str) -> None:
    port_a, port_b = free_port(), free_port()
    # vehicle A: the daemon's own publisher; vehicle B: plain Zenoh puts (state, health, plan)
    tel = Telemetry("fa", TelemetryConfig(listen=(endpoint(port_a),)), dict)
    tel.start()
    sess_b = open_session(zenoh_config(listen=[endpoint(port_b)], connect=[]), "test vehicle B")
    stop = threading.Event()

    def publish() -> None:
        seq = 0
        while not stop.is_set():
            tel.publish_state(_state(seq))
            sess_b.put("truckd/fb/state", json.dumps(_state(seq)))
            if seq % 10 == 0:
                tel.publish_health({"t": 0.01 * seq, "mode": "ACTIVE", "faults": []})
                plan = {"t": 0.01 * seq, "seq": seq, "dt": 0.01, "v": [0.8] * 5, "a": [0.0] * 5}
                sess_b.put("truckd/fb/plan", json.dumps(plan))
            seq += 1
            stop.wait(0.01)

    pub = threading.Thread(target=publish, daemon=True)
    pub.start()
    proc = subprocess.Popen(
        [sys.executable, "-m", "truckd.cli.main", "monitor", "--foxglove", "0",
         "--connect", endpoint(port_a), "--connect", endpoint(port_b), "--duration", "60"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()  # the relay prints its address once serving
        assert "ws://127.0.0.1:" in first, first + (proc.stderr.read() if proc.stderr else "")
        url = first.split()[3]
        with connect(url, subprotocols=[subprotocol], open_timeout=10) as ws:  # type: ignore[list-item]
            assert ws.subprotocol == subprotocol
            info = json.loads(ws.recv(timeout=10))
            assert info["op"] == "serverInfo" and info["name"] == "truckd"
            wanted = {"/truckd/fa/state", "/truckd/fa/health", "/truckd/fb/state",
                      "/truckd/fb/plan"}  # fmt: skip
            channels: dict[str, dict[str, Any]] = {}
            deadline = time.monotonic() + 20
            while not wanted <= channels.keys():
                assert time.monotonic() < deadline, f"advertised only {sorted(channels)}"
                msg = json.loads(ws.recv(timeout=max(0.1, deadline - time.monotonic())))
                if msg["op"] == "advertise":
                    channels.update({c["topic"]: c for c in msg["channels"]})
            for topic in wanted:
                c = channels[topic]
                kind = topic.rsplit("/", 1)[1]
                assert c["encoding"] == "json" and c["schemaEncoding"] == "jsonschema"
                assert json.loads(c["schema"]) == SCHEMAS[kind]
            subs = {i: topic for i, topic in enumerate(sorted(wanted), start=1)}
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": i, "channelId": channels[t]["id"]} for i, t in subs.items()]}))  # fmt: skip
            got: dict[str, int] = dict.fromkeys(wanted, 0)
            while min(got.values()) < 3:
                assert time.monotonic() < deadline + 20, f"messages so far {got}"
                frame = ws.recv(timeout=10)
                if isinstance(frame, str):
                    continue  # e.g. advertise of another channel
                op, sub_id, log_time = struct.unpack_from("<BIQ", frame)
                assert op == OP_MESSAGE_DATA
                topic = subs[sub_id]
                msg = json.loads(frame[13:])
                jsonschema.validate(msg, SCHEMAS[topic.rsplit("/", 1)[1]])
                assert abs(log_time * 1e-9 - time.time()) < 60
                got[topic] += 1
            # vehicle A goes (its liveliness token with it): its channels are unadvertised
            fa_ids = {channels[t]["id"] for t in wanted if t.startswith("/truckd/fa/")}
            tel.close()
            gone: set[int] = set()
            t_end = time.monotonic() + 20
            while not fa_ids <= gone:
                assert time.monotonic() < t_end, f"unadvertised only {gone} of {fa_ids}"
                frame = ws.recv(timeout=max(0.1, t_end - time.monotonic()))
                if isinstance(frame, str) and json.loads(frame)["op"] == "unadvertise":
                    gone |= set(json.loads(frame)["channelIds"])
            assert not gone & {channels[t]["id"] for t in wanted if t.startswith("/truckd/fb/")}
        stop.set()
        pub.join(timeout=5)
        os.kill(proc.pid, signal.SIGINT)
        assert proc.wait(timeout=20) == 130
    finally:
        stop.set()
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()
        for f in (proc.stdout, proc.stderr):
            if f is not None:
                f.close()
        tel.close()
        sess_b.close()  # type: ignore[no-untyped-call]


def test_relay_without_websockets_is_a_clear_error(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "websockets.sync.server", None)  # import -> ImportError
    assert main(["monitor", "--foxglove", "0", "--duration", "1"]) == 1
    err = capsys.readouterr().err
    assert "pip install 'truckd[foxglove]'" in err and err.count("\n") == 1


@pytest.mark.parametrize("port", ["70000", "-1"])
def test_bad_port_is_exit_2(port: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["monitor", "--foxglove", port]) == 2
    err = capsys.readouterr().err
    assert "--foxglove" in err and err.count("\n") == 1


def test_server_protocol_details() -> None:
    """The server alone: both subprotocol names accepted, any other refused at the
    handshake; channels open before a client connects are advertised to it; a request
    it does not serve, or a subscription to no channel, gets a status warning; message
    data goes only to a subscription, with its id and the log time; an unsubscribed or
    unadvertised channel sends nothing more."""
    from websockets.exceptions import InvalidHandshake

    from truckd.runtime.foxglove_ws import FoxgloveServer

    srv = FoxgloveServer(port=0)
    port = srv.start()
    try:
        url = f"ws://127.0.0.1:{port}"
        with pytest.raises(InvalidHandshake):
            connect(url, subprotocols=["foxglove.other.v9"], open_timeout=10).close()  # type: ignore[list-item]
        a = srv.add_channel("/a", "json", "truckd.state", b"{}", "jsonschema")
        with connect(url, subprotocols=["foxglove.websocket.v1"], open_timeout=10) as ws:  # type: ignore[list-item]
            assert json.loads(ws.recv(timeout=10))["op"] == "serverInfo"
            adv = json.loads(ws.recv(timeout=10))
            assert adv["op"] == "advertise" and [c["id"] for c in adv["channels"]] == [a]
            ws.send(json.dumps({"op": "publish"}))
            assert json.loads(ws.recv(timeout=10))["op"] == "status"
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": 99}]}))
            assert json.loads(ws.recv(timeout=10))["op"] == "status"
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 5, "channelId": a}]}))
            got = None
            for k in range(200):  # the subscription is taken on the server's thread
                srv.log(a, b'{"k": %d}' % k, 123456789)
                try:
                    got = ws.recv(timeout=0.05)
                    break
                except TimeoutError:
                    continue
            assert isinstance(got, bytes)
            op, sub, t = struct.unpack_from("<BIQ", got)
            assert (op, sub, t) == (OP_MESSAGE_DATA, 5, 123456789)
            assert "k" in json.loads(got[13:])
            srv.remove_channel(a)
            while True:  # the rest of the burst, then the unadvertise
                frame = ws.recv(timeout=10)
                if isinstance(frame, str):
                    assert json.loads(frame) == {"op": "unadvertise", "channelIds": [a]}
                    break
            srv.log(a, b"{}", 1)
            with pytest.raises(TimeoutError):
                ws.recv(timeout=0.3)
    finally:
        srv.stop()

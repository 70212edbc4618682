"""What truckd writes, read by readers that are not truckd's: the reference TypeScript
MCAP reader (``@mcap/core``, tests/js/mcap_read.mjs) and the reference Foxglove WebSocket
client (``@foxglove/ws-protocol`` with its default subprotocol ``foxglove.websocket.v1``,
tests/js/ws_client.mjs), under node.

Needs node and ``npm ci --prefix tests/js`` (``.ci/run`` does both); without them these
tests are skipped naming what is missing (tests/external_tools.py)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import jsonschema
import pytest
from external_tools import JS_DIR, ROOT, node_readers
from hil_support import end_process
from runtime_support import endpoint, free_port, write_config

from truckd.config.truck import load_config
from truckd.control.qp import ControlModel
from truckd.logfile import read_log
from truckd.runtime.msg_schemas import SCHEMAS
from truckd.sim.closed_loop import SimSetup, run_scenario
from truckd.sim.mcap_export import write_trace_mcap
from truckd.sim.scenarios import make_scenario

pytestmark = pytest.mark.needs_tool("node", install="apt-get install nodejs npm")

KIND_SCHEMA = {f"truckd.{k}": k for k in SCHEMAS}


def read_with_mcap_core(node: str, path: Path) -> dict[str, Any]:
    """The file as @mcap/core sees it (see tests/js/mcap_read.mjs)."""
    r = subprocess.run(
        [node, str(JS_DIR / "mcap_read.mjs"), str(path)],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    doc: dict[str, Any] = json.loads(r.stdout)
    return doc


def check_channels(doc: dict[str, Any], vehicle: str) -> None:
    """Three JSON channels with the JSON schemas of the contract, each message valid."""
    topics = {c["topic"]: c for c in doc["channels"].values()}
    assert set(topics) == {f"/truckd/{vehicle}/{k}" for k in ("state", "health", "plan")}
    for topic, c in topics.items():
        kind = topic.rsplit("/", 1)[1]
        schema = doc["schemas"][str(c["schemaId"])]
        assert c["messageEncoding"] == "json"
        assert schema["name"] == f"truckd.{kind}" and schema["encoding"] == "jsonschema"
        assert json.loads(schema["data"]) == SCHEMAS[kind]
        for m in doc["messages"][topic]:
            jsonschema.validate(m["data"], SCHEMAS[kind])
    counts = {
        doc["channels"][i]["topic"]: n for i, n in doc["statistics"]["channelMessageCounts"].items()
    }
    assert counts == {t: len(doc["messages"][t]) for t in topics}  # summary = what decodes
    assert doc["statistics"]["messageCount"] == sum(counts.values())


def test_sim_mcap_read_by_mcap_core(tmp_path: Path) -> None:
    """``truckd sim --mcap`` of a follow run: every cycle's state, the health every 0.5 s
    and every 10th plan (the daemon's default decimation), as sent, in order."""
    node = node_readers()
    cfg = load_config(None)
    setup = SimSetup(cfg.vehicle, cfg.plant, cfg.control, ControlModel(cfg.vehicle))
    _, tr = run_scenario(make_scenario("follow", cfg.vehicle, cfg.control), setup, 3.0)
    path = tmp_path / "follow.mcap"
    write_trace_mcap(path, "t3", "follow", tr, plan_every=10)
    doc = read_with_mcap_core(node, path)
    assert doc["library"] == "truckd"
    assert doc["metadata"]["truckd"]["source"] == "truckd sim"
    check_channels(doc, "t3")
    states = doc["messages"]["/truckd/t3/state"]
    assert [m["data"]["seq"] for m in states] == list(range(len(tr.t))) and len(tr.t) == 300
    assert [int(m["logTime"]) for m in states] == [round(t * 1e9) for t in tr.t]
    assert [m["data"]["v"] for m in states] == tr.v
    assert len(doc["messages"]["/truckd/t3/health"]) == 6
    sent = [p for p in tr.plans if p is not None][::10]
    plans = doc["messages"]["/truckd/t3/plan"]
    assert len(sent) >= 25 and len(plans) == len(sent)
    for m, p in zip(plans, sent, strict=True):
        assert m["data"]["seq"] == p.seq and m["data"]["v"] == list(p.v)
        assert m["data"]["vehicle_id"] == "t3" and int(m["logTime"]) == round(p.t * 1e9)


def _node_ws(node: str, url: str, n: int, topics: list[str]) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [node, str(JS_DIR / "ws_client.mjs"), url, str(n), "60", *topics],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip


def test_daemon_live_and_recorded_read_by_reference_clients(tmp_path: Path) -> None:
    """A daemon (simulated truck) publishes; ``truckd monitor --foxglove`` serves; the
    reference Foxglove client connects with its default subprotocol, subscribes to state
    and plan and decodes them.  Then the daemon's own MCAP, read by @mcap/core, holds as
    many states as its CSV has rows, and plans."""
    node = node_readers()
    port = free_port()
    cfg = write_config(
        tmp_path / "truck.yaml",
        {"vehicle_id": "fx1",
         "runtime": {"realtime": False, "telemetry": {"listen": [endpoint(port)]},
                     "recorder": {"dir": str(tmp_path / "logs")}}},
    )  # fmt: skip
    daemon = subprocess.Popen(
        [sys.executable, "-m", "truckd.cli.main", "run", "--config", str(cfg),
         "--backend", "sim", "--duration", "120"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT,
    )  # fmt: skip
    relay = subprocess.Popen(
        [sys.executable, "-m", "truckd.cli.main", "monitor", "--foxglove", "0",
         "--connect", endpoint(port), "--duration", "120"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
    )  # fmt: skip
    client: subprocess.Popen[str] | None = None
    try:
        assert relay.stdout is not None
        first = relay.stdout.readline()
        assert "ws://127.0.0.1:" in first, first + (relay.stderr.read() if relay.stderr else "")
        topics = ["/truckd/fx1/state", "/truckd/fx1/plan"]
        client = _node_ws(node, first.split()[3], 20, topics)
        out, err = client.communicate(timeout=90)
        assert client.returncode == 0, f"rc {client.returncode}: {err} {out[:2000]}"
        got = json.loads(out)
        assert got["requested"] == got["subprotocol"] == "foxglove.websocket.v1"
        assert got["serverInfo"]["name"] == "truckd"
        for topic in topics:
            c = got["channels"][topic]
            kind = topic.rsplit("/", 1)[1]
            assert c["encoding"] == "json" and c["schemaEncoding"] == "jsonschema"
            assert c["schemaName"] == f"truckd.{kind}"
            assert json.loads(c["schema"]) == SCHEMAS[kind]
            msgs = got["messages"][topic]
            assert len(msgs) >= 20
            for m in msgs:
                jsonschema.validate(m["data"], SCHEMAS[kind])
            seqs = [m["data"]["seq"] for m in msgs]
            assert seqs == sorted(set(seqs))  # in order, none twice
        assert all(len(m["data"]["v"]) > 10 for m in got["messages"]["/truckd/fx1/plan"])
        assert {m["data"]["vehicle_id"] for m in got["messages"]["/truckd/fx1/plan"]} == {"fx1"}
    finally:
        for p in (relay, daemon):
            if p.poll() is None:
                os.kill(p.pid, signal.SIGTERM)
        if client is not None:
            end_process(client)
        for p in (relay, daemon):
            try:
                p.wait(timeout=20)
            finally:
                end_process(p)
    assert daemon.returncode == 0
    (mcap,) = sorted((tmp_path / "logs").glob("*.mcap"))
    doc = read_with_mcap_core(node, mcap)
    check_channels(doc, "fx1")
    rows = len(read_log(mcap.with_suffix(".csv"))["t"])
    assert rows >= 20 and len(doc["messages"]["/truckd/fx1/state"]) == rows  # >= the client saw
    assert doc["messages"]["/truckd/fx1/plan"] and doc["messages"]["/truckd/fx1/health"]

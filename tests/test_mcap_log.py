"""MCAP beside the CSV (reference section 5): read back with the ``mcap`` reader,
counts per channel, every message validated against its channel's JSON schema (the
``jsonschema`` package), rotation with the CSV, a file cut by SIGKILL, ``truckd sim --mcap``.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jsonschema
import pytest
from runtime_support import write_config

from truckd.cli.main import main
from truckd.config.runtime import RecorderConfig
from truckd.config.truck import load_config
from truckd.logfile import read_log
from truckd.runtime.daemon import Daemon
from truckd.runtime.mcap_log import McapContent, McapLog, read_mcap
from truckd.runtime.msg_schemas import SCHEMAS
from truckd.runtime.realtime import unfreeze_gc
from truckd.runtime.recorder import Recorder

COLS = ("t", "u", "v")
ORIGIN = 1_700_000_000_000_000_000


def validate_all(c: McapContent) -> dict[str, list[dict[str, object]]]:
    """Every message against its channel's schema (as stored in the file); decoded
    messages by topic."""
    out: dict[str, list[dict[str, object]]] = {}
    validators = {}
    for ch in c.channels.values():
        sc = c.schemas[ch.schema_id]
        assert sc.encoding == "jsonschema" and ch.message_encoding == "json"
        validators[ch.id] = jsonschema.Draft202012Validator(json.loads(sc.data))
    for m in c.messages:
        msg = json.loads(m.data)  # strict: NaN would not parse back as null
        validators[m.channel_id].validate(msg)
        out.setdefault(c.topic(m), []).append(msg)
    return out


def state(k: int, t: float) -> dict[str, object]:
    return {
        "seq": k, "t": t, "mode": "ACTIVE", "v": 0.5, "gap": None if k % 5 else 1.0,
        "gap_ref": 0.9, "v_lead": math.nan, "u": 2.0, "u_ff": 1.0, "solve_us": 300.0,
    }  # fmt: skip


def test_schemas_are_valid_json_schemas() -> None:
    for s in SCHEMAS.values():
        jsonschema.Draft202012Validator.check_schema(s)


def test_counts_times_and_schemas(tmp_path: Path) -> None:
    mc = McapLog("t9", origin_ns=ORIGIN)
    rec = Recorder(RecorderConfig(dir=str(tmp_path), flush_period_s=0.05), COLS, sidecar=mc)
    rec.start()
    for k in range(1000):
        t = 0.01 * k
        rec.record((t, 1.0, 0.5))
        mc.record_state(t, state(k, t))
        if k % 50 == 0:
            mc.record_health(t, {"t": t, "mode": "ACTIVE", "faults": []}, lambda: {"loop": {}})
        if k % 10 == 0:
            mc.record_plan(t, {"t": t, "seq": k, "dt": 0.01, "v": [0.5] * 20, "a": [0.0] * 20})
    rec.stop()
    assert rec.path is not None and mc.path == rec.path.with_suffix(".mcap")
    c = read_mcap(mc.path)
    assert c.complete
    msgs = validate_all(c)
    assert {k: len(v) for k, v in msgs.items()} == {
        "/truckd/t9/state": 1000, "/truckd/t9/health": 20, "/truckd/t9/plan": 100,
    }  # fmt: skip
    assert mc.counts == {"state": 1000, "health": 20, "plan": 100}
    assert mc.dropped == 0 and mc.errors == 0
    states = [m for m in c.messages if c.topic(m) == "/truckd/t9/state"]
    assert [m.log_time for m in states] == [ORIGIN + round(0.01 * k * 1e9) for k in range(1000)]
    assert [m.sequence for m in states] == list(range(1000))
    assert msgs["/truckd/t9/state"][3]["v_lead"] is None  # NaN written as null
    assert "loop" in msgs["/truckd/t9/health"][0]  # the extra merged on the writer thread
    assert len(read_log(rec.path)) == 1000  # the CSV is untouched


def test_rotates_with_the_csv_and_keeps_as_many(tmp_path: Path) -> None:
    mc = McapLog("t9", keep=3, origin_ns=0)
    cfg = RecorderConfig(dir=str(tmp_path), max_bytes=4096, keep=3, flush_period_s=0.0)
    rec = Recorder(cfg, COLS, sidecar=mc)
    rec.start()
    for k in range(3000):
        t = 0.01 * k
        rec.record((t, 1.0, 0.5))
        mc.record_state(t, state(k, t))
        if k % 64 == 63:  # let the writer keep up so rotation interleaves with MCAP
            deadline = time.monotonic() + 10
            while rec._q and time.monotonic() < deadline:
                time.sleep(0.001)
    rec.stop()
    csvs, mcaps = sorted(tmp_path.glob("*.csv")), sorted(tmp_path.glob("*.mcap"))
    assert len(csvs) == 3 and [p.with_suffix(".mcap") for p in csvs] == mcaps == mc.files
    seqs = []
    for p in mcaps:
        c = read_mcap(p)
        assert c.complete
        seqs += [int(json.loads(m.data)["seq"]) for m in c.messages]
    assert seqs == list(range(seqs[0], 3000))  # the newest files, nothing lost between them
    assert seqs[0] > 1000


def test_plan_decimation_keeps_every_nth_from_the_first(tmp_path: Path) -> None:
    mc = McapLog("t9", plan_every=3, origin_ns=0)
    mc.open(tmp_path / "p.mcap")
    for k in range(10):
        mc.record_plan(0.01 * k, {"t": 0.01 * k, "seq": k, "dt": 0.01, "v": [], "a": []})
    mc.close()
    msgs = validate_all(read_mcap(tmp_path / "p.mcap"))
    assert [m["seq"] for m in msgs["/truckd/t9/plan"]] == [0, 3, 6, 9]


def test_bounded_queue_drops_oldest_and_counts(tmp_path: Path) -> None:
    mc = McapLog("t9", maxlen=16, origin_ns=0)
    for k in range(100):  # no writer running: the queue fills
        mc.record_state(0.01 * k, state(k, 0.01 * k))
    assert mc.dropped == 84
    mc.open(tmp_path / "x.mcap")
    mc.close()
    c = read_mcap(tmp_path / "x.mcap")
    assert [json.loads(m.data)["seq"] for m in c.messages] == list(range(84, 100))


def test_daemon_records_mcap_beside_the_csv_with_decimation(tmp_path: Path) -> None:
    cfg_path = write_config(
        tmp_path / "truck.yaml",
        {"runtime": {"realtime": False, "telemetry": {"enabled": False, "health_period_s": 0.5},
                     "recorder": {"dir": str(tmp_path / "logs"), "mcap_state_every": 2}}},
    )  # fmt: skip
    d = Daemon(load_config(cfg_path), "sim", duration=2.0, env={})
    try:
        assert d.run() == 0
    finally:
        unfreeze_gc()
    assert d.recorder is not None and d.recorder.path is not None and d.mcap is not None
    n = d.rk.cycles
    assert len(read_log(d.recorder.path)) == n
    c = read_mcap(d.recorder.path.with_suffix(".mcap"))
    assert c.complete  # finished on the stop path (the one SIGTERM takes)
    msgs = validate_all(c)
    states = msgs["/truckd/truck1/state"]
    assert [s["seq"] for s in states] == list(range(0, n, 2))
    t_last = states[-1]["t"]
    assert isinstance(t_last, float)
    assert len(msgs["/truckd/truck1/health"]) >= math.floor(t_last / 0.5)
    assert {s["mode"] for s in states} >= {"INIT", "ACTIVE"}
    # log time: the cycle's time on the wall clock, spaced as the loop's t
    st = [m for m in c.messages if c.topic(m) == "/truckd/truck1/state"]
    dt_log = (st[-1].log_time - st[0].log_time) * 1e-9
    assert dt_log == pytest.approx(t_last - float(states[0]["t"]), abs=1e-6)  # type: ignore[arg-type]
    assert abs(st[-1].log_time * 1e-9 - time.time()) < 60


def test_a_file_cut_by_sigkill_reads_up_to_its_last_chunk(tmp_path: Path) -> None:
    cfg_path = write_config(
        tmp_path / "truck.yaml",
        {"runtime": {"realtime": False, "telemetry": {"enabled": False},
                     "recorder": {"dir": str(tmp_path / "logs"), "flush_period_s": 0.2}}},
    )  # fmt: skip
    proc = subprocess.Popen(
        [sys.executable, "-m", "truckd.cli.main", "run", "--config", str(cfg_path),
         "--backend", "sim", "--duration", "60"],
        stderr=subprocess.DEVNULL,
    )  # fmt: skip
    logs = tmp_path / "logs"
    try:
        seen = 0
        deadline = time.monotonic() + 30
        while seen < 100 and time.monotonic() < deadline:  # chunks on disk
            mcaps = sorted(logs.glob("*.mcap"))
            seen = len(read_mcap(mcaps[0]).messages) if mcaps else 0
            time.sleep(0.05)
        assert seen >= 100, "no MCAP chunk was written"
        # ~400 states fill far less than the 256 kB that would close a chunk by size:
        # these chunks were closed by the flush period (0.2 s)
        rows = (logs / mcaps[0].with_suffix(".csv").name).read_text().count("\n") - 1
        assert rows < 400
        assert proc.poll() is None
        os.kill(proc.pid, signal.SIGKILL)
        assert proc.wait(timeout=10) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()
    (path,) = sorted(logs.glob("*.mcap"))
    c = read_mcap(path)
    assert not c.complete  # no footer: cut
    assert len(c.messages) >= seen  # everything flushed before the kill is still there
    msgs = validate_all(c)
    seqs = [s["seq"] for s in msgs["/truckd/truck1/state"]]
    assert seqs == list(range(len(seqs)))  # in order, no hole
    assert msgs["/truckd/truck1/health"]


def test_sim_writes_mcap_per_scenario(tmp_path: Path) -> None:
    argv = ["sim", "--scenario", "follow", "--duration", "3", "--mcap", str(tmp_path / "out"),
            "--json", str(tmp_path / "m.json")]  # fmt: skip
    assert main(argv) == 0
    cycles = json.loads((tmp_path / "m.json").read_text())["cycles"]
    c = read_mcap(tmp_path / "out" / "follow.mcap")
    assert c.complete
    msgs = validate_all(c)
    assert len(msgs["/truckd/truck1/state"]) == cycles == 300
    assert len(msgs["/truckd/truck1/health"]) == 6  # every 0.5 s of 3 s
    st = [m for m in c.messages if c.topic(m) == "/truckd/truck1/state"]
    assert [m.log_time for m in st] == [round(s["t"] * 1e9) for s in msgs["/truckd/truck1/state"]]  # type: ignore[operator]
    assert st[1].log_time == 10_000_000  # simulated time, 10 ms period
    assert not list((tmp_path / "out").glob(".*"))  # no temporary file left


def test_sim_mcap_file_needs_one_scenario(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["sim", "--mcap", str(tmp_path / "x.mcap")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "one scenario" in err
    assert not (tmp_path / "x.mcap").exists()


def test_sim_mcap_carries_the_supervisors_mode_and_enable(tmp_path: Path) -> None:
    """The sim runs the daemon's cycle: its MCAP shows the supervisor's mode
    and the driver enable of each cycle, as the --trace log records them, not a constant."""
    argv = ["sim", "--scenario", "cruise", "--duration", "1", "--mcap", str(tmp_path / "m"),
            "--trace", str(tmp_path / "tr")]  # fmt: skip
    assert main(argv) == 0
    log = read_log(tmp_path / "tr" / "cruise.csv")
    names = {0: "INIT", 1: "ACTIVE", 2: "DEGRADED", 3: "SAFE_STOP", 4: "FAULT"}
    want_mode = [names[int(x)] for x in log["mode"]]
    assert set(want_mode) != {"ACTIVE"}  # cruise without a lead is not ACTIVE throughout
    msgs = validate_all(read_mcap(tmp_path / "m" / "cruise.mcap"))
    states = msgs["/truckd/truck1/state"]
    assert [s["mode"] for s in states] == want_mode
    assert [s["enable"] for s in states] == [bool(x) for x in log["enable"]]
    health = msgs["/truckd/truck1/health"]
    assert health[0]["mode"] == want_mode[0]


def test_sim_mcap_empty_name_is_exit_2_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["sim", "--scenario", "cruise", "--duration", "0.2", "--mcap", ""]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--mcap" in err
    assert list(tmp_path.iterdir()) == []


def test_sim_mcap_mistyped_file_name_is_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--mcap run.txt`` is a mistyped file name, not a new directory called run.txt."""
    assert main(["sim", "--scenario", "cruise", "--duration", "0.2", "--mcap",
                 str(tmp_path / "run.txt")]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--mcap" in err
    assert not (tmp_path / "run.txt").exists()


def test_sim_mcap_records_the_plan_like_the_daemon(tmp_path: Path) -> None:
    """``sim --mcap`` records the MPC's plan on ``/plan``, every ``mcap_plan_every``-th
    offered from the first (the daemon's decimation), each one at the log time of the
    cycle that made it, with the configured vehicle id and a horizon of predicted speeds."""
    runs = {}
    for every in (1, 3):
        over = {"vehicle_id": "t7", "runtime": {"recorder": {"mcap_plan_every": every}}}
        cfg = write_config(tmp_path / f"truck{every}.yaml", over)
        out = tmp_path / f"f{every}.mcap"
        argv = ["sim", "--config", str(cfg), "--scenario", "follow", "--duration", "2",
                "--mcap", str(out)]  # fmt: skip
        assert main(argv) == 0
        runs[every] = read_mcap(out)
    msgs = validate_all(runs[1])
    states, plans = msgs["/truckd/t7/state"], msgs["/truckd/t7/plan"]
    assert len(states) == 200
    assert len(plans) > 150  # the follow scenario runs the MPC nearly throughout
    assert validate_all(runs[3])["/truckd/t7/plan"] == plans[::3]
    t_of = {s["seq"]: s["t"] for s in states}
    for p in plans:
        assert p["vehicle_id"] == "t7" and p["t"] == t_of[p["seq"]]
        assert len(p["v"]) == len(p["a"]) > 10 and p["dt"] == pytest.approx(0.01)
        assert all(v >= 0.0 for v in p["v"])
    c = runs[1]
    msg = [m for m in c.messages if c.topic(m) == "/truckd/t7/plan"]
    assert [m.log_time for m in msg] == [round(p["t"] * 1e9) for p in plans]

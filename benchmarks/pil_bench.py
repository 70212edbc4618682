"""Processor in the loop, measured: the firmware's ARM image on QEMU's emulated STM32F405
(``make -C firmware_protocol/firmware pil``), the simulated plant on the host
(:class:`truckd.sim.pil.EmulatedBoard`), ``truckd run`` driving it over its serial
backend on a pty; ``truckd monitor --foxglove`` serving the daemon's telemetry.

    python benchmarks/pil_bench.py [--json FILE [--key NAME]] [--seconds S] [--runs N]

Figures (``pil``): ``boot_s`` (QEMU started -> the board's boot line, wall),
``frames_per_s`` (frames the board sent per second of its clock), ``collision``,
``gap_error_rms_m`` (true gap minus ``d_0 + h v`` over the last half of the drive),
``command_timeouts`` and ``crc_errors`` (the board's and the daemon's receive counters)
over ``S`` s of follow (default 10) from the daemon's first ACTIVE state; plus the
frames both ways counted by the link relay and the daemon.  With ``--runs N`` each run
boots a fresh board; ``median`` holds the median of each figure over the runs (the
shared machine is noisy: its load average is written before and after).

Message counts seen by the independent readers against what was sent (``readers``,
when node and ``npm ci --prefix tests/js`` are there): the reference Foxglove client
(``@foxglove/ws-protocol``) subscribed to state and plan during the drive, its messages
against the span of ``seq`` it saw (the daemon numbers its cycles and publishes a state
every cycle; a plan only after a cycle whose MPC solved or that holds); ``@mcap/core``
reading the daemon's MCAP against the rows of its CSV; and ``truckd sim --mcap`` of a
follow run of the same length against the run's cycles and plans.  Every process is
ended by its pid.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import yaml
import zenoh
from results import write_json
from scratch import scratch_dir

from truckd.config.truck import default_config_path, load_config
from truckd.logfile import read_log
from truckd.runtime.telemetry import zenoh_config
from truckd.sim.closed_loop import SimSetup, run_scenario
from truckd.sim.firmware import CuedLead
from truckd.sim.mcap_export import write_trace_mcap
from truckd.sim.pil import build_pil_elf
from truckd.sim.scenarios import make_scenario
from truckd.sim.truck import emulated_board, truck_spec

PY = sys.executable
ROOT = Path(__file__).resolve().parent.parent
JS = ROOT / "tests" / "js"
LEAD_GAP, LEAD_SPEED = 1.5, 0.8
RX_ERRORS = ("checksum_errors", "crc_errors", "cobs_errors", "length_errors")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _config(tmp: Path, pty: Path, port: int) -> Path:
    cfg = yaml.safe_load(default_config_path().read_text())
    cfg["link"].update({"serial_device": str(pty), "reconnect_interval": 0.1})
    cfg["control"]["on_lead_lost"] = "stop"
    rt = cfg["runtime"]
    rt.update({"backend": "serial", "realtime": False})
    rt["telemetry"].update({"listen": [f"tcp/127.0.0.1:{port}"]})
    rt["recorder"].update({"dir": str(tmp / "logs")})
    path = tmp / "truck.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


class _Watch:
    """The daemon's state and health over Zenoh (loopback)."""

    def __init__(self, port: int) -> None:
        self.lock = threading.Lock()
        self.state: dict[str, Any] = {}
        self.health: dict[str, Any] = {}
        self.session = zenoh.open(zenoh_config(listen=[], connect=[f"tcp/127.0.0.1:{port}"]))
        self.session.declare_subscriber("truckd/truck1/state", self._on("state"))
        self.session.declare_subscriber("truckd/truck1/health", self._on("health"))

    def _on(self, kind: str) -> Any:
        def cb(s: zenoh.Sample) -> None:
            with self.lock:
                setattr(self, kind, json.loads(s.payload.to_bytes()))

        return cb

    def get(self, kind: str) -> dict[str, Any]:
        with self.lock:
            return dict(getattr(self, kind))

    def close(self) -> None:
        self.session.close()  # type: ignore[no-untyped-call]


def _wait(pred: Any, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.02)
    return bool(pred())


def _end(p: subprocess.Popen[Any], sig: int = signal.SIGTERM) -> int:
    if p.poll() is None:
        os.kill(p.pid, sig)
        try:
            p.wait(20)
        except subprocess.TimeoutExpired:
            os.kill(p.pid, signal.SIGKILL)
            p.wait(10)
    return int(p.returncode)


def _seq_ratio(msgs: list[dict[str, Any]]) -> dict[str, Any]:
    seqs = [m["data"]["seq"] for m in msgs]
    if not seqs:
        return {"received": 0}
    return {"received": len(seqs), "seq_span": seqs[-1] - seqs[0] + 1}


def _mcap_core(node: str, path: Path) -> dict[str, Any]:
    r = subprocess.run(
        [node, str(JS / "mcap_read.mjs"), str(path)], capture_output=True, text=True, check=True
    )
    doc: dict[str, Any] = json.loads(r.stdout)
    return doc


def run(seconds: float, work_dir: str | None = None) -> dict[str, Any]:
    res: dict[str, Any] = {
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "machine": f"{platform.machine()} {os.cpu_count()} cpus, {platform.system()}",
        "qemu": subprocess.run(
            ["qemu-system-arm", "--version"], capture_output=True, text=True, check=True
        ).stdout.splitlines()[0],
        "load_average_start": os.getloadavg(),
    }
    node = shutil.which("node")
    readers = node is not None and (JS / "node_modules" / "@mcap" / "core").exists()
    elf = build_pil_elf()
    cfg = load_config(None)
    tmp = scratch_dir("pil-bench-", work_dir)
    lead = CuedLead(LEAD_GAP, LEAD_SPEED)  # sets off once the daemon publishes
    board = emulated_board(truck_spec(cfg), lead, tmp / "ttyPIL", elf=elf)
    plant = board.plant
    port = _free_port()
    board.start()
    daemon = subprocess.Popen(
        [PY, "-m", "truckd.cli.main", "run", "--config", str(_config(tmp, tmp / "ttyPIL", port))],
        stdout=subprocess.DEVNULL,
        stderr=open(tmp / "daemon.err", "w"),  # noqa: SIM115 - the child owns it
        cwd=ROOT,
    )
    watch = _Watch(port)
    relay = client = None
    try:
        if not _wait(lambda: board.boot_s() is not None, 60):
            raise RuntimeError("the emulated board never reported its boot")
        res["boot_s"] = board.boot_s()
        if not _wait(lambda: bool(watch.get("state")), 60):
            raise RuntimeError("the daemon never published: " + (tmp / "daemon.err").read_text())
        lead.go(plant.t)
        if not _wait(lambda: watch.get("state").get("mode") == "ACTIVE", 60):
            raise RuntimeError("the daemon never went ACTIVE: " + (tmp / "daemon.err").read_text())
        if readers:
            assert node is not None
            relay = subprocess.Popen(
                [PY, "-m", "truckd.cli.main", "monitor", "--foxglove", "0", "--connect",
                 f"tcp/127.0.0.1:{port}"],
                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, cwd=ROOT,
            )  # fmt: skip
            assert relay.stdout is not None
            url = relay.stdout.readline().split()[3]
            client = subprocess.Popen(
                [node, str(JS / "ws_client.mjs"), url, "1000000000", str(seconds),
                 "/truckd/truck1/state", "/truckd/truck1/plan"],
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            )  # fmt: skip
        s0, h0, t0 = board.last_stats(), watch.get("health"), plant.t
        r0 = (board.relay.to_board_frames, board.relay.to_daemon_frames)
        time.sleep(seconds)
        s1, h1, t1 = board.last_stats(), watch.get("health"), plant.t
        r1 = (board.relay.to_board_frames, board.relay.to_daemon_frames)
        c = cfg.control
        half = [(g, v) for t, g, v in board.gaps if t >= t0 + (t1 - t0) / 2 and t <= t1]
        err = [g - (c.d_0 + c.time_headway * v) for g, v in half]
        l0, l1 = h0.get("link", {}), h1.get("link", {})
        res["pil"] = {
            "seconds_board": (s1["ms"] - s0["ms"]) / 1000.0,
            "frames_per_s": (s1["frames_sent"] - s0["frames_sent"]) / ((s1["ms"] - s0["ms"]) / 1e3),
            "collision": board.min_gap <= 0.0,
            "min_gap_m": board.min_gap,
            "gap_error_rms_m": math.sqrt(math.fsum(e * e for e in err) / len(err)),
            "command_timeouts": s1["cmd_timeouts"] - s0["cmd_timeouts"],
            "crc_errors": (s1["crc_errors"] - s0["crc_errors"])
            + (l1.get("framing_crc_errors", 0) - l0.get("framing_crc_errors", 0)),
            "board_rx_errors": sum(s1[k] - s0[k] for k in RX_ERRORS),
            "commands_applied": s1["commands_applied"] - s0["commands_applied"],
            "relay_frames_to_board": r1[0] - r0[0],
            "relay_frames_to_daemon": r1[1] - r0[1],
            "daemon_rx_frames_ok": l1.get("rx_frames_ok", 0) - l0.get("rx_frames_ok", 0),
            "skipped_snapshots": board.skipped_snapshots,
            "final_speed_m_s": plant.v,
        }
        if client is not None:
            out, _ = client.communicate(timeout=seconds + 60)
            got = json.loads(out)
            res["readers"] = {
                "foxglove_client": {
                    "subprotocol": got["subprotocol"],
                    "state": _seq_ratio(got["messages"]["/truckd/truck1/state"]),
                    # a plan goes out only after a cycle whose MPC solved (or that holds):
                    # fewer than the cycles its seq spans
                    "plan": _seq_ratio(got["messages"]["/truckd/truck1/plan"]),
                }
            }
    finally:
        watch.close()
        for p in (client, relay):
            if p is not None:
                _end(p, signal.SIGKILL)
        rc = _end(daemon)
        board.stop()
    res["daemon_exit"] = rc
    if readers:
        assert node is not None
        (mcap,) = sorted((tmp / "logs").glob("*.mcap"))
        doc = _mcap_core(node, mcap)
        rows = len(read_log(mcap.with_suffix(".csv"))["t"])
        counts = {t.rsplit("/", 1)[1]: len(m) for t, m in doc["messages"].items()}
        res["readers"]["daemon_mcap"] = {"csv_rows": rows, "mcap_core_counts": counts}
        setup = SimSetup.from_config(cfg)
        _, tr = run_scenario(make_scenario("follow", cfg.vehicle, cfg.control), setup, seconds)
        every = cfg.runtime.recorder.mcap_plan_every
        write_trace_mcap(tmp / "sim.mcap", cfg.vehicle_id, "follow", tr, every)
        doc = _mcap_core(node, tmp / "sim.mcap")
        counts = {t.rsplit("/", 1)[1]: len(m) for t, m in doc["messages"].items()}
        plans = sum(p is not None for p in tr.plans)
        res["readers"]["sim_mcap"] = {
            "sent": {"state": len(tr.t), "plan": math.ceil(plans / every)},
            "mcap_core_counts": counts,
        }
    else:
        res["readers"] = "skipped: node or tests/js/node_modules missing (npm ci --prefix tests/js)"
    res["load_average_end"] = os.getloadavg()
    shutil.rmtree(tmp, ignore_errors=True)
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", default=None, help="write the figures to this file")
    ap.add_argument(
        "--work-dir",
        metavar="DIR",
        help="keep the runs' configurations and logs, one directory each, in DIR "
        "(default: a temporary directory, removed at the end)",
    )
    ap.add_argument(
        "--key",
        metavar="NAME",
        help="store the run under NAME in --json's file (what_YYYY-MM-DD), not at its top level",
    )
    ap.add_argument("--seconds", type=float, default=10.0, help="length of the follow drive")
    ap.add_argument("--runs", type=int, default=1, help="boots of a fresh board (1..20)")
    args = ap.parse_args()
    if not 1.0 <= args.seconds <= 600.0:
        print("pil_bench: --seconds must be in [1, 600]", file=sys.stderr)
        return 2
    if not 1 <= args.runs <= 20:
        print("pil_bench: --runs must be in [1, 20]", file=sys.stderr)
        return 2
    for tool in ("qemu-system-arm", "arm-none-eabi-gcc"):
        if shutil.which(tool) is None:
            print(f"pil_bench: {tool} not found (apt-get install -y qemu-system-arm "
                  "gcc-arm-none-eabi libnewlib-arm-none-eabi)", file=sys.stderr)  # fmt: skip
            return 2
    runs = [
        run(args.seconds, f"{args.work_dir}/run{k}" if args.work_dir else None)
        for k in range(args.runs)
    ]
    keys = ["boot_s", *(f"pil.{k}" for k in runs[0]["pil"])]

    def value(r: dict[str, Any], key: str) -> Any:
        return r["pil"][key[4:]] if key.startswith("pil.") else r[key]

    median = {
        k: statistics.median(float(value(r, k)) for r in runs)
        for k in keys
        if not isinstance(value(runs[0], k), bool)
    }
    median["collision_any"] = any(r["pil"]["collision"] for r in runs)
    res = {"median": median, "runs": runs}
    text = json.dumps(res, indent=2) + "\n"
    if args.json:
        write_json(args.json, res, args.key)
    print(text, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())

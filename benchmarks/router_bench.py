"""Load test: 20 simulated vehicles publish state and plans at 100 Hz through a Zenoh router
on loopback; a monitor receives everything.  Reports the delivery ratio and the latency
(send to receive, ``time.monotonic`` on one machine) per message kind.

Three processes: the router (``config/zenoh-router.json5``, on a free loopback port), the
vehicles (one client session each, all in one process, absolute 10 ms deadlines), and the
monitor (this process, a client).  Publishing starts once every publisher sees the
monitor's subscription, so the start-up is not counted as loss.

    python benchmarks/router_bench.py --json benchmarks/router_bench.json [--vehicles 20]

``--tls on`` runs the same through a router with the fleet's mutual TLS and access control
(truckd/runtime/fleet_tls.py: a certificate per vehicle, the monitor an operator);
``--tls both`` runs without and with, one after the other, and writes both
(``benchmarks/platoon_router.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

ROOT = Path(__file__).resolve().parent.parent
ROUTER_CONF = ROOT / "truckd" / "defaults" / "zenoh-router.json5"
CLIENT_CONF = ROOT / "truckd" / "defaults" / "zenoh-client.json5"
HORIZON = 40


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _conf(path: Path, listen: list[str] | None, connect: list[str] | None) -> zenoh.Config:
    c = zenoh.Config.from_file(str(path))
    if listen is not None:
        c.insert_json5("listen/endpoints", json.dumps(listen))
    if connect is not None:
        c.insert_json5("connect/endpoints", json.dumps(connect))
    return c


def _fleet(fleet_dir: str) -> Any:
    from truckd.runtime.fleet_tls import Fleet

    names = json.loads((Path(fleet_dir) / "names.json").read_text())
    return Fleet(Path(fleet_dir), tuple(names["trucks"]), tuple(names["operators"]))


def _client(port: int, fleet_dir: str, name: str) -> zenoh.Config:
    if not fleet_dir:
        return _conf(CLIENT_CONF, None, [f"tcp/127.0.0.1:{port}"])
    from truckd.runtime.fleet_tls import client_config

    conf = client_config(_fleet(fleet_dir), name, f"tls/127.0.0.1:{port}")
    return zenoh.Config.from_json5(json.dumps(conf))


def router(port: int, fleet_dir: str = "") -> int:
    """Run the router until stdin closes."""
    if fleet_dir:
        from truckd.runtime.fleet_tls import router_config

        conf = router_config(_fleet(fleet_dir), f"tls/127.0.0.1:{port}")
        s = zenoh.open(zenoh.Config.from_json5(json.dumps(conf)))
    else:
        s = zenoh.open(_conf(ROUTER_CONF, [f"tcp/127.0.0.1:{port}"], None))
    print("ready", flush=True)
    sys.stdin.read()
    s.close()  # type: ignore[no-untyped-call]
    return 0


def vehicles(port: int, n: int, duration: float, rate: float, fleet_dir: str = "") -> int:
    """n client sessions, each publishing state and plan at ``rate`` Hz for ``duration``."""
    sessions, pubs = [], []
    for i in range(n):
        s = zenoh.open(_client(port, fleet_dir, f"v{i}"))
        sessions.append(s)
        for kind in ("state", "plan"):
            pubs.append((i, kind, s.declare_publisher(f"truckd/v{i}/{kind}")))
    t_end = time.monotonic() + 20.0
    while not all(p.matching_status.matching for _, _, p in pubs):
        if time.monotonic() > t_end:
            print(json.dumps({"error": "monitor never matched"}), flush=True)
            return 1
        time.sleep(0.01)
    period = 1.0 / rate
    # full-precision floats, as the MPC's plan has them (about 1.7 kB of JSON)
    v = [1.2 - 0.0123456789 * k / 7.0 for k in range(HORIZON + 1)]
    a = [-0.0123456789 / 7.0 / 0.01 * (1.0 + 1e-9 * k) for k in range(HORIZON + 1)]
    sent = 0
    late = 0
    t0 = time.monotonic()
    k = 0
    while True:
        deadline = t0 + k * period
        now = time.monotonic()
        if now - t0 >= duration:
            break
        if deadline > now:
            time.sleep(deadline - now)
        else:
            late += 1
        for i, kind, p in pubs:
            ts = time.monotonic()
            if kind == "state":
                msg: dict[str, Any] = {
                    "seq": k, "t": ts, "mode": "ACTIVE", "v": 1.2, "gap": 0.96,
                    "gap_ref": 0.95, "v_lead": 1.2, "u": 4.1, "u_ff": 0.4, "solve_us": 150.0,
                    "enable": True, "ctrl": "follow", "fallback": None, "lead_valid": True,
                    "lateness_us": 40.0, "faults": [], "platoon": "CACC", "headway": 0.5,
                    "ages_ms": {"link": 1.0, "encoder": 1.0, "range": 8.0},
                }  # fmt: skip
            else:
                msg = {"t": ts, "seq": k, "dt": 0.01, "v": v, "a": a, "vehicle_id": f"v{i}"}
            p.put(json.dumps(msg))
            sent += 1
        k += 1
    time.sleep(0.5)  # let the last messages drain before the sessions close
    print(json.dumps({"sent": sent, "ticks": k, "late_ticks": late}), flush=True)
    for s in sessions:
        s.close()  # type: ignore[no-untyped-call]
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=int, default=20)
    ap.add_argument("--rate", type=float, default=100.0, help="Hz per vehicle and kind")
    ap.add_argument("--duration", type=float, default=10.0, help="s of publishing")
    ap.add_argument("--json", help="write the figures here")
    ap.add_argument("--tls", choices=("off", "on", "both"), default="off")
    ap.add_argument("--role", choices=("router", "vehicles"), help=argparse.SUPPRESS)
    ap.add_argument("--port", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--fleet", default="", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.role == "router":
        return router(args.port, args.fleet)
    if args.role == "vehicles":
        return vehicles(args.port, args.vehicles, args.duration, args.rate, args.fleet)
    if args.tls == "both":
        return _both(args)
    fleet_dir = ""
    tmp = None
    if args.tls == "on":
        import tempfile

        from truckd.runtime.fleet_tls import make_fleet

        tmp = tempfile.TemporaryDirectory()
        fleet_dir = tmp.name
        trucks = [f"v{i}" for i in range(args.vehicles)]
        make_fleet(fleet_dir, trucks, ["monitor"])
        names = {"trucks": trucks, "operators": ["monitor"]}
        (Path(fleet_dir) / "names.json").write_text(json.dumps(names))
    port = _free_port()
    me = [sys.executable, str(Path(__file__).resolve())]
    rproc = subprocess.Popen(
        [*me, "--role", "router", "--port", str(port), "--fleet", fleet_dir],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert rproc.stdout is not None and rproc.stdin is not None
    vproc = None
    try:
        if rproc.stdout.readline().strip() != "ready":
            print("router_bench: the router did not start", file=sys.stderr)
            return 1
        lat: dict[str, list[float]] = {"state": [], "plan": []}
        lock = threading.Lock()

        def on_sample(s: zenoh.Sample) -> None:
            now = time.monotonic()
            kind = str(s.key_expr).rsplit("/", 1)[1]
            msg = json.loads(s.payload.to_bytes())
            with lock:
                lat[kind].append(now - msg["t"])

        mon = zenoh.open(_client(port, fleet_dir, "monitor"))
        subs = [mon.declare_subscriber(f"truckd/*/{k}", on_sample) for k in ("state", "plan")]
        vproc = subprocess.Popen(
            [*me, "--role", "vehicles", "--port", str(port), "--vehicles", str(args.vehicles),
             "--rate", str(args.rate), "--duration", str(args.duration), "--fleet", fleet_dir],
            stdout=subprocess.PIPE, text=True,
        )  # fmt: skip
        out, _ = vproc.communicate(timeout=args.duration + 120)
        report = json.loads(out.strip().splitlines()[-1])
        for s in subs:
            s.undeclare()  # type: ignore[no-untyped-call]
        mon.close()  # type: ignore[no-untyped-call]
    finally:
        if vproc is not None and vproc.poll() is None:
            vproc.kill()
        rproc.stdin.close()
        try:
            rproc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            rproc.kill()
    if "error" in report:
        print(f"router_bench: {report['error']}", file=sys.stderr)
        return 1
    received = sum(len(v) for v in lat.values())
    if tmp is not None:
        tmp.cleanup()
    doc: dict[str, Any] = {
        "tls": args.tls == "on",
        "vehicles": args.vehicles,
        "rate_hz": args.rate,
        "duration_s": args.duration,
        "sent": report["sent"],
        "received": received,
        "delivery_ratio": received / report["sent"] if report["sent"] else None,
        "publisher_late_ticks": report["late_ticks"],
        "publisher_ticks": report["ticks"],
        "load_average": os.getloadavg(),
    }
    for kind, xs in lat.items():
        a = np.asarray(xs) * 1e3
        doc[f"{kind}_latency_ms"] = {
            "p50": float(np.percentile(a, 50)) if a.size else None,
            "p99": float(np.percentile(a, 99)) if a.size else None,
            "max": float(a.max()) if a.size else None,
            "count": int(a.size),
        }
    print(json.dumps(doc, indent=2))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(doc, f, indent=2)
            f.write("\n")
    return 0


def _both(args: argparse.Namespace) -> int:
    """Without TLS, then with: one JSON with both runs."""
    import datetime
    import platform
    import tempfile

    me = [sys.executable, str(Path(__file__).resolve())]
    runs: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as d:
        for tls in ("off", "on"):
            out = Path(d) / f"{tls}.json"
            cmd = [*me, "--tls", tls, "--vehicles", str(args.vehicles), "--rate", str(args.rate),
                   "--duration", str(args.duration), "--json", str(out)]  # fmt: skip
            if subprocess.run(cmd, stdout=subprocess.DEVNULL, check=False).returncode != 0:
                print(f"router_bench: the run with TLS {tls} failed", file=sys.stderr)
                return 1
            runs[f"tls_{tls}"] = json.loads(out.read_text())
    doc = {
        "what": "state and plan messages through one router, TLS (mutual, access control by "
        "certificate name) off and on",
        "date": datetime.date.today().isoformat(),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        **runs,
    }
    print(json.dumps(doc, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps(doc, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

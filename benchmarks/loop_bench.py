"""Loop timing of `truckd run` at the configured rate (100 Hz) with Zenoh publishing and
recording on: wake lateness p50/p99/max, compute p50/p99/max, deadline misses.

    .venv/bin/python benchmarks/loop_bench.py [--duration 60] [--backend serial|sim] [--json FILE]
        [--stages] [--cpu-latency-us US] [--rate HZ] [--busy] [--mpc compiled|python]

``serial`` (default) runs the daemon against the simulated firmware in its own process on
a pty, as in the HIL tests (the loop's work is what it is on the car); ``sim`` steps the
simulated truck inside the loop (more work per cycle).  A Zenoh subscriber in a process of
its own receives every state message, so publishing really goes over TCP.

``--stages`` adds wall-clock timers around each stage of ``Daemon.cycle`` (p50/p99 per
stage; about 1 us of overhead per timer): in the serial backend the whole cycle is the
car's work, in the sim backend ``backend.tick`` is the simulated truck's.

``--rate HZ`` runs the loop at that rate (``control.rate_hz``, default the shipped 100 Hz;
the MPC's step is the period, its horizon stays 40 steps; the solve's time budget
``time_budget_s`` at most half the period, as the configuration requires it below).
``--busy`` starts a CPU-bound process beside the daemon for the whole run (a Python busy
loop, as a recorder compressing or a second truck's process would keep one of the cores
busy), ended by its pid after.
The result names the MPC's path (``mpc_backend``: compiled or python and why);
``--mpc python`` runs the Python path although the compiled one is built (A/B runs).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import host_steal
import numpy as np
import yaml
import zenoh
from results import write_json
from scratch import scratch_dir

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from truckd.config.truck import default_config_path, load_config  # noqa: E402
from truckd.control import ccycle  # noqa: E402
from truckd.logfile import read_log  # noqa: E402
from truckd.runtime.daemon import Daemon  # noqa: E402
from truckd.runtime.realtime import unfreeze_gc  # noqa: E402
from truckd.runtime.telemetry import zenoh_config  # noqa: E402


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _config(
    tmp: Path,
    backend: str,
    pty: str,
    port: int,
    cpu_latency_us: int | None = None,
    rate_hz: float | None = None,
) -> Path:
    data = yaml.safe_load(default_config_path().read_text())
    if rate_hz is not None:
        data["control"]["rate_hz"] = rate_hz
        # The configuration refuses a solve budget that is not below the period: at a rate
        # where the shipped one is not, half the period.
        budget = float(data["control"]["time_budget_s"])
        data["control"]["time_budget_s"] = min(budget, 0.5 / rate_hz)
    data["link"]["serial_device"] = pty
    rt = data["runtime"]
    rt["backend"] = backend
    if cpu_latency_us is not None:
        rt["cpu_latency_us"] = cpu_latency_us
    rt["telemetry"]["listen"] = [f"tcp/127.0.0.1:{port}"]
    rt["recorder"]["dir"] = str(tmp / "logs")
    p = tmp / "truck.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def _pct(a: np.ndarray, q: float) -> float:
    return float(np.percentile(a, q)) if a.size else float("nan")


STAGES = (
    ("port", "poll", "poll"),
    ("sensors", "update", "sensors.update"),
    ("controller", "step", "controller.step"),
    ("mpc", "solve", "mpc.solve"),
    ("supervisor", "decide", "supervisor.update"),  # (the cycle calls update's decide)
    ("companion", "step", "companion.step"),
    ("daemon", "send_command", "send_command"),
    ("backend", "tick", "backend.tick"),
    ("daemon", "publish", "publish"),
    ("daemon", "record", "record"),
)


def _instrument(daemon: Daemon) -> dict[str, list[float]]:
    """Time each stage of every cycle (s): the methods are wrapped on the first cycle,
    when the port and the backend exist."""
    times: dict[str, list[float]] = {}
    pc = time.perf_counter
    cycle = daemon.cycle

    def timed(f: Any, acc: list[float]) -> Any:
        def g(*a: Any, **k: Any) -> Any:
            t = pc()
            r = f(*a, **k)
            acc.append(pc() - t)
            return r

        return g

    def first_cycle() -> None:
        c = daemon.companion
        owners = {"port": daemon.port, "sensors": c.sensors, "controller": c.controller,
                  "mpc": c.controller.mpc, "supervisor": c.supervisor, "companion": c,
                  "daemon": daemon, "backend": daemon.backend}  # fmt: skip
        for owner, meth, key in STAGES:
            obj = owners[owner]
            setattr(obj, meth, timed(getattr(obj, meth), times.setdefault(key, [])))
        whole = timed(cycle, times.setdefault("whole cycle", []))
        daemon.cycle = whole  # type: ignore[method-assign]
        whole()

    daemon.cycle = first_cycle  # type: ignore[method-assign]
    return times


def run(
    duration: float,
    backend: str,
    stages: bool = False,
    cpu_latency_us: int | None = None,
    rate_hz: float | None = None,
    busy: bool = False,
    work_dir: str | None = None,
) -> dict[str, Any]:
    tmp = scratch_dir("loop_bench_", work_dir)
    pty = str(tmp / "ttyTRUCK")
    port = _free_port()
    cfg_path = _config(tmp, backend, pty, port, cpu_latency_us, rate_hz)
    fw = None
    burner = None
    if busy:  # a CPU-bound process beside the loop for the whole run
        burner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    if backend == "serial":
        fw = subprocess.Popen(
            [sys.executable, "-m", "truckd.sim.firmware_main", "--pty", pty, "--config",
             str(cfg_path), "--lead-gap", "1.2", "--lead-speed", "0.8"],
            stdout=subprocess.PIPE, text=True, cwd=ROOT,
        )  # fmt: skip
        assert fw.stdout is not None
        json.loads(fw.stdout.readline())
    # the host's steal time, sampled beside the run (benchmarks/host_steal.py)
    steal_probe = subprocess.Popen(
        [sys.executable, str(Path(__file__).with_name("host_steal.py")), "0.002"],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert steal_probe.stdout is not None
    steal_probe.stdout.readline()  # sampling from here on
    # the monitoring side in a process of its own, as on the car (opening a Zenoh session
    # holds this interpreter's GIL for some 20 ms: in the daemon's process it was a miss)
    sub = subprocess.Popen(
        [sys.executable, __file__, "--subscriber", str(port)], stdout=subprocess.PIPE, text=True
    )
    try:
        daemon = Daemon(load_config(cfg_path), backend, duration=duration)
        times = _instrument(daemon) if stages else None
        daemon.run()
        unfreeze_gc()
    finally:
        if burner is not None:
            burner.kill()
            burner.wait(10)
        os.kill(steal_probe.pid, signal.SIGTERM)
        steal_out, _ = steal_probe.communicate(timeout=10)
        os.kill(sub.pid, signal.SIGTERM)
        sub_out, _ = sub.communicate(timeout=30)
        received = int(sub_out.split()[-1]) if sub_out.split() else 0
        if fw is not None:
            os.kill(fw.pid, signal.SIGTERM)
            fw.wait(10)
            if fw.stdout is not None:
                fw.stdout.close()
    assert daemon.recorder is not None
    logs = sorted((tmp / "logs").glob("*.csv"))
    cols: dict[str, list[np.ndarray]] = {"lateness_us": [], "compute_us": [], "solve_us": []}
    period = 1.0 / daemon.control_cfg.rate_hz
    miss_starts: list[float] = []
    miss_ends: list[float] = []
    miss_rows: list[dict[str, float]] = []  # the first 50: what each missed cycle spent
    for f in logs:
        log = read_log(f)
        for k in cols:
            cols[k].append(log[k])
        # a row holds its cycle's wake lateness and the previous cycle's compute
        t, lat, comp_prev = log["t"], log["lateness_us"] * 1e-6, log["compute_us"] * 1e-6
        for j in np.flatnonzero(lat[:-1] + comp_prev[1:] > period):
            start = daemon.t0 + float(t[j] - lat[j])
            miss_starts.append(start)
            miss_ends.append(start + float(lat[j] + comp_prev[j + 1]))
            if len(miss_rows) < 50:
                miss_rows.append({
                    "t_s": round(float(t[j]), 4),
                    "lateness_us": round(float(lat[j]) * 1e6),
                    "compute_us": round(float(comp_prev[j + 1]) * 1e6),
                    "cpu_us": round(float(log["cpu_us"][j + 1])),
                })  # fmt: skip
    steal_t, steal_s = host_steal.steal_times(steal_out.splitlines()[1:])
    host = host_steal.misses_explained(miss_starts, miss_ends, steal_t, 0.015, duration)
    host["steal_s"] = round(float(steal_s.sum()), 3)
    host["missed_cycles"] = miss_rows
    late = np.concatenate(cols["lateness_us"])
    comp = np.concatenate(cols["compute_us"])[1:]  # the first row has no previous cycle
    solve = np.concatenate(cols["solve_us"])
    solve = solve[np.isfinite(solve)]
    rk = daemon.rk
    tel = daemon.telemetry
    result: dict[str, Any] = {
        "backend": backend,
        "rate_hz": daemon.control_cfg.rate_hz,
        "busy_process_beside": busy,
        "mpc_backend": daemon.controller.mpc.backend,
        "duration_s": duration,
        "cycles": rk.cycles,
        "deadline_misses": rk.misses,
        "skipped_periods": rk.skipped_periods,
        "misses_and_host_steal": host,
        "lateness_us_p50": _pct(late, 50),
        "lateness_us_p99": _pct(late, 99),
        "lateness_us_max": float(late.max()),
        "compute_us_p50": _pct(comp, 50),
        "compute_us_p99": _pct(comp, 99),
        "compute_us_max": float(comp.max()),
        "solve_us_p50": _pct(solve, 50),
        "solve_us_p99": _pct(solve, 99),
        "zenoh_messages_sent": tel.sent if tel is not None else 0,
        "zenoh_messages_dropped": tel.dropped if tel is not None else 0,
        "states_received": received,
        "rows_recorded": daemon.recorder.rows,
        "realtime": daemon.realtime.as_dict(),
        "machine": {
            "cpus": os.cpu_count(),
            "kernel": platform.release(),
            "python": platform.python_version(),
            "processor": platform.processor() or platform.machine(),
            "loadavg_1_5_15": list(os.getloadavg()),
        },
    }
    if times is not None:
        result["stages_us_p50_p99"] = {
            k: [_pct(np.array(v[1:]) * 1e6, 50), _pct(np.array(v[1:]) * 1e6, 99)]
            for k, v in times.items()
        }
        # the stages' longest calls: where a missed cycle's time went
        result["stages_us_max"] = {k: float(np.max(v[1:]) * 1e6) for k, v in times.items()}
    return result


def subscriber(port: int) -> None:
    """The monitoring side (``--subscriber PORT``): connect to the daemon's session once it
    listens, count its state messages, print the count on SIGTERM."""
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_a: stop.set())
    received = 0
    lock = threading.Lock()

    def on_state(_s: zenoh.Sample) -> None:
        nonlocal received
        with lock:
            received += 1

    time.sleep(1.0)  # the daemon's session is listening by then
    session = zenoh.open(zenoh_config(listen=[], connect=[f"tcp/127.0.0.1:{port}"]))
    session.declare_subscriber("truckd/truck1/state", on_state)
    stop.wait()
    session.close()
    with lock:
        print(received, flush=True)


def main() -> int:
    if sys.argv[1:2] == ["--subscriber"]:
        subscriber(int(sys.argv[2]))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--backend", choices=("serial", "sim"), default="serial")
    ap.add_argument("--json", metavar="FILE")
    ap.add_argument(
        "--work-dir",
        metavar="DIR",
        help="keep the run's configuration and logs in DIR "
        "(default: a temporary directory, removed at the end)",
    )
    ap.add_argument(
        "--key",
        metavar="NAME",
        help="store the run under NAME in --json's file (what_YYYY-MM-DD), not at its top level",
    )
    ap.add_argument("--stages", action="store_true", help="time each stage of the cycle")
    ap.add_argument(
        "--cpu-latency-us",
        type=int,
        metavar="US",
        help="runtime.cpu_latency_us for the daemon (default: the shipped configuration's; "
        "-1 leaves the CPU idle states alone)",
    )
    ap.add_argument("--rate", type=float, metavar="HZ", help="loop rate (default: configured)")
    ap.add_argument("--busy", action="store_true", help="a CPU-bound process beside the loop")
    ap.add_argument("--mpc", choices=("compiled", "python"), default="compiled",
                    help="the MPC's path (compiled: when built, the default)")  # fmt: skip
    args = ap.parse_args()
    if args.mpc == "python":  # the loader's answer, as if the library were not built
        ccycle._state.update(lib=None, why="loop_bench --mpc python")
    if args.rate is not None and not 1.0 <= args.rate <= 2000.0:
        print("loop_bench: --rate must be in [1, 2000] Hz", file=sys.stderr)
        return 2
    r = run(
        args.duration, args.backend, args.stages, args.cpu_latency_us, args.rate, args.busy,
        args.work_dir,
    )  # fmt: skip
    h = r["misses_and_host_steal"]
    rows = [
        ("cycles", f"{r['cycles']}"),
        ("deadline misses", f"{r['deadline_misses']} ({r['skipped_periods']} periods skipped)"),
        ("misses during host steal (by chance) / steal", "{} ({}) of {} / {:.2f} s".format(
            h["with_host_steal"], h["expected_by_chance"], h["misses"], h["steal_s"])),
        ("wake lateness p50 / p99 / max", "{:.0f} / {:.0f} / {:.0f} us".format(
            r["lateness_us_p50"], r["lateness_us_p99"], r["lateness_us_max"])),
        ("compute p50 / p99 / max",
         f"{r['compute_us_p50']:.0f} / {r['compute_us_p99']:.0f} / {r['compute_us_max']:.0f} us"),
        ("MPC solve p50 / p99", f"{r['solve_us_p50']:.0f} / {r['solve_us_p99']:.0f} us"),
        ("zenoh sent (state+health) / states received / dropped",
         f"{r['zenoh_messages_sent']} / {r['states_received']} / {r['zenoh_messages_dropped']}"),
        ("rows recorded", f"{r['rows_recorded']}"),
        ("MPC path / busy process beside", f"{r['mpc_backend']} / {r['busy_process_beside']}"),
        ("SCHED_FIFO / mlockall", f"{r['realtime']['sched_fifo']} / {r['realtime']['mlock']}"),
        ("CPU wake-up latency held", f"{r['realtime'].get('cpu_latency_us')} us"),
    ]  # fmt: skip
    print(f"loop_bench: {r['rate_hz']:.0f} Hz for {r['duration_s']:.0f} s, backend {r['backend']},"
          f" {r['machine']['cpus']} CPUs, kernel {r['machine']['kernel']}")  # fmt: skip
    w = max(len(k) for k, _ in rows)
    for k, v in rows:
        print(f"  {k.ljust(w)}  {v}")
    for k, (p50, p99) in r.get("stages_us_p50_p99", {}).items():
        top = r["stages_us_max"][k]
        print(f"  stage {k.ljust(w - 6)}  {p50:.0f} / {p99:.0f} / {top:.0f} us (p50 / p99 / max)")
    if args.json:
        write_json(args.json, r, args.key)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

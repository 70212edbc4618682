"""What recording costs the control loop: CSV alone vs CSV + MCAP (docs/foxglove.md).

    .venv/bin/python benchmarks/recorder_bench.py [--seconds 20] [--repeats 5] [--json FILE]

A loop paced like the daemon's (absolute deadlines at ``--rate``, 100 Hz) spins 1.5 ms of
Python per cycle (the controller's share of the GIL) and does what the daemon's outputs
do: one CSV row (``Recorder.record``), one state message (the daemon's keys), a 40-step
plan offered every cycle (every 10th kept: ``mcap_plan_every``) and a health message every
0.5 s into the MCAP log (``McapLog``); the recorder's writer thread writes them as in
``truckd run``.  Three modes, nothing / CSV / CSV + MCAP, run in interleaved segments so a
drifting load on a shared machine touches them alike.  Per mode:

- loop-side cost of recording per cycle (the calls the loop makes), median/p99/max;
- wake lateness and cycle busy time median/p99/max (the writer thread competes for the
  GIL: this is where its work would show in the loop);
- writer-thread CPU per cycle (process CPU minus the loop thread's);
- bytes written, scaled to one minute.

Also why the writer releases the GIL every 0.2 ms (a thread encoding JSON in 4 ms bursts
beside the loop, with and without that yield), and the writer's own cost per cycle (JSON
encode + add to the chunk, chunks closed every second), measured synchronously, for state
alone and state + a plan every cycle.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from truckd.config.runtime import RecorderConfig  # noqa: E402
from truckd.runtime.daemon import LOG_COLUMNS  # noqa: E402
from truckd.runtime.mcap_log import McapFile, McapLog, to_json  # noqa: E402
from truckd.runtime.recorder import Recorder  # noqa: E402

HORIZON = 40


def state_msg(k: int, t: float) -> dict[str, Any]:
    """A state message with the daemon's keys and realistic values."""
    return {
        "seq": k, "t": t, "mode": "ACTIVE", "v": 0.8 + 1e-3 * math.sin(t), "gap": 1.234567,
        "gap_ref": 1.2, "v_lead": 0.81, "u": 2.345678, "u_ff": 2.1, "solve_us": 281.5,
        "enable": True, "ctrl": "follow", "fallback": None, "lead_valid": True,
        "lateness_us": 85.3, "faults": [],
        "ages_ms": {"link": 1.2, "encoder": 3.4, "range": 12.5},
    }  # fmt: skip


def plan_msg(k: int, t: float) -> dict[str, Any]:
    v = [0.8 + 0.001 * i + 1e-4 * math.sin(t) for i in range(HORIZON)]
    return {"t": t, "seq": k, "dt": 0.01, "v": v, "a": [0.1 - 0.002 * i for i in range(HORIZON)]}


def health_msg(t: float) -> dict[str, Any]:
    return {
        "t": t, "mode": "ACTIVE", "faults": [], "transitions": [],
        "ages_s": {"link": 0.001, "encoder": 0.003, "range": 0.012},
        "link": {"connected": True, "tx_frames": 12345, "rx_frames": 45678, "rx_checksum_errors": 0,
                 "rx_counter_errors": 0, "rx_timeouts": 0, "framing_bytes_discarded": 0},
        "firmware": {"state": "ACTIVE", "faults": 0, "invalid_messages": 0,
                     "repeated_samples": 0, "range_faults": 0},
        "controller": {"solver_failures": 0, "fallback_cycles": 3, "braking_cycles": 0,
                       "errors": 0},
        "telemetry": {"dropped": 0, "sent": 4567, "errors": 0},
        "recorder": {"rows": 4567, "dropped": 0, "errors": 0, "file": "logs/x.csv"},
        "realtime": {"gc_frozen": True, "sched_fifo": False, "mlock": False, "notes": []},
        "state_rate_hz": 100.0, "pid": 1234,
    }  # fmt: skip


def loop_stats() -> dict[str, float]:
    return {"cycles": 1000, "misses": 0, "lateness_us_p50": 85.0, "lateness_us_p99": 230.0}


def spin(us: float) -> None:
    """Busy Python work for ``us`` microseconds of wall time."""
    end = time.perf_counter() + us * 1e-6
    x = 0
    while time.perf_counter() < end:
        x += 1


def pct(xs: list[float]) -> dict[str, float]:
    a = np.asarray(xs)
    return {
        "p50": round(float(np.percentile(a, 50)), 2),
        "p99": round(float(np.percentile(a, 99)), 2),
        "max": round(float(a.max()), 2),
    }


def paced(mode: str, seconds: float, rate: float, compute_us: float, d: Path) -> dict[str, Any]:
    """One paced segment; ``mode`` none | csv | csv+mcap.  Each cycle also spins in Python
    for ``compute_us`` (the controller's share: it needs the GIL as the writer does).
    Returns raw samples."""
    cfg = RecorderConfig(dir=str(d), flush_period_s=1.0)
    mc = McapLog("bench", flush_period_s=1.0, plan_every=10) if mode == "csv+mcap" else None
    rec = Recorder(cfg, LOG_COLUMNS, sidecar=mc) if mode != "none" else None
    if rec is not None:
        rec.start()
    period = 1.0 / rate
    n = round(seconds * rate)
    cost_us: list[float] = []
    late_us: list[float] = []
    busy_us: list[float] = []
    row = tuple(0.1 * i for i in range(len(LOG_COLUMNS)))
    cpu0, main0 = time.process_time(), time.thread_time()
    start = time.monotonic() + 0.05
    for k in range(n):
        deadline = start + k * period
        delay = deadline - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        wake = time.perf_counter()
        late_us.append((time.monotonic() - deadline) * 1e6)
        spin(compute_us)
        t = k * period
        msg, plan = state_msg(k, t), plan_msg(k, t)  # built by the daemon anyway (telemetry)
        c0 = time.perf_counter_ns()
        if rec is not None:
            rec.record(row)
        if mc is not None:
            mc.record_state(t, msg)
            mc.record_plan(t, plan)  # every 10th kept (runtime.recorder.mcap_plan_every)
            if k % round(0.5 * rate) == 0:
                mc.record_health(t, health_msg(t), loop_stats)
        cost_us.append((time.perf_counter_ns() - c0) * 1e-3)
        busy_us.append((time.perf_counter() - wake) * 1e6)
    if rec is not None:
        rec.stop()
    cpu, main = time.process_time() - cpu0, time.thread_time() - main0
    return {
        "cycles": n,
        "cost": cost_us,
        "late": late_us,
        "busy": busy_us,
        "writer_cpu_s": max(0.0, cpu - main),
        "csv_bytes": sum(p.stat().st_size for p in rec.files) if rec is not None else 0,
        "mcap_bytes": sum(p.stat().st_size for p in mc.files) if mc is not None else 0,
        "mcap_counts": dict(mc.counts) if mc is not None else {},
        "mcap_dropped": mc.dropped if mc is not None else 0,
    }


def interleaved(
    seconds: float, rate: float, compute_us: float, repeats: int, tmp: Path
) -> dict[str, Any]:
    """``repeats`` rounds of none, csv, csv+mcap segments (so a load that drifts on a
    shared machine affects the three alike), aggregated per mode."""
    modes = ("none", "csv", "csv+mcap")
    segs: dict[str, list[dict[str, Any]]] = {m: [] for m in modes}
    for r in range(repeats):
        for m in modes:
            d = tmp / f"{m.replace('+', '_')}-{r}"
            segs[m].append(paced(m, seconds / repeats, rate, compute_us, d))
    out: dict[str, Any] = {}
    for m in modes:
        ss = segs[m]
        n = sum(s["cycles"] for s in ss)
        per_min = 60.0 * rate / n
        counts: dict[str, int] = {}
        for s in ss:
            for k, v in s["mcap_counts"].items():
                counts[k] = counts.get(k, 0) + v
        out[m] = {
            "cycles": n,
            "record_cost_us": pct([x for s in ss for x in s["cost"]]),
            "lateness_us": pct([x for s in ss for x in s["late"]]),
            "cycle_busy_us": pct([x for s in ss for x in s["busy"]]),
            "writer_cpu_us_per_cycle": round(sum(s["writer_cpu_s"] for s in ss) / n * 1e6, 1),
            "csv_mb_per_min": round(sum(s["csv_bytes"] for s in ss) * per_min / 1e6, 3),
            "mcap_mb_per_min": round(sum(s["mcap_bytes"] for s in ss) * per_min / 1e6, 3),
            "mcap_messages": counts,
            "mcap_dropped": sum(s["mcap_dropped"] for s in ss),
        }
    return out


def gil_yield_demo(seconds: float, yield_s: float | None) -> dict[str, Any]:
    """Why the MCAP writer yields: a thread encoding JSON in 4 ms bursts beside a 100 Hz
    paced loop, releasing the GIL every ``yield_s`` (None: never).  The loop's wake
    lateness."""
    import threading

    stop = threading.Event()
    plan = plan_msg(0, 0.0)

    def burst() -> None:
        while not stop.is_set():
            last = time.perf_counter()
            end = last + 0.004
            while time.perf_counter() < end:
                to_json(plan)
                if yield_s is not None and time.perf_counter() - last > yield_s:
                    time.sleep(0)
                    last = time.perf_counter()
            time.sleep(0.0037)  # out of phase with the loop's 10 ms

    th = threading.Thread(target=burst, daemon=True)
    th.start()
    late: list[float] = []
    start = time.monotonic() + 0.05
    for k in range(round(seconds * 100)):
        deadline = start + k * 0.01
        delay = deadline - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        late.append((time.monotonic() - deadline) * 1e6)
    stop.set()
    th.join()
    return {"yield_s": yield_s, "lateness_us": pct(late)}


def writer_cost(tmp: Path, n: int = 6000, with_plan: bool = True) -> dict[str, Any]:
    """Encode + write per message on one thread, chunks closed every 100 messages (1 s)."""
    f = McapFile(tmp / f"sync{int(with_plan)}.mcap", "bench")
    per: list[float] = []
    for k in range(n):
        t = 0.01 * k
        c0 = time.perf_counter_ns()
        f.write("state", k * 10_000_000, to_json(state_msg(k, t)))
        if with_plan:
            f.write("plan", k * 10_000_000, to_json(plan_msg(k, t)))
        if k % 100 == 99:
            f.flush()
        per.append((time.perf_counter_ns() - c0) * 1e-3)
    f.close()
    size = f.path.stat().st_size
    return {
        "cycles": n,
        "us_per_cycle": pct(per),
        "mb_per_min_at_100hz": round(size / (n / 100.0) * 60.0 / 1e6, 3),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="per mode (default 20)")
    ap.add_argument("--repeats", type=int, default=5, help="interleaved rounds (default 5)")
    ap.add_argument("--rate", type=float, default=100.0, help="loop rate, Hz")
    ap.add_argument(
        "--compute-us", type=float, default=1500.0, help="Python work per cycle (default 1500)"
    )
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()
    res: dict[str, Any] = {
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, "
        f"Python {platform.python_version()}",
        "load_avg_before": [round(x, 2) for x in os.getloadavg()],
        "rate_hz": args.rate,
        "seconds_per_mode": args.seconds,
        "repeats": args.repeats,
        "compute_us": args.compute_us,
    }
    with tempfile.TemporaryDirectory(prefix="recorder-bench-") as td:
        tmp = Path(td)
        res["writer_state_only"] = writer_cost(tmp, with_plan=False)
        res["writer_state_and_plan"] = writer_cost(tmp, with_plan=True)
        res["gil_no_yield"] = gil_yield_demo(3.0, None)
        res["gil_yield_200us"] = gil_yield_demo(3.0, 200e-6)
        res.update(interleaved(args.seconds, args.rate, args.compute_us, args.repeats, tmp))
    res["load_avg_after"] = [round(x, 2) for x in os.getloadavg()]
    print(
        f"recorder cost at {args.rate:.0f} Hz, {args.seconds:.0f} s per mode in "
        f"{args.repeats} interleaved rounds ({res['machine']})"
    )
    print(f"load average before {res['load_avg_before']}, after {res['load_avg_after']}")
    hdr = ("run", "record us p50/p99/max", "lateness us p50/p99/max", "cycle busy us "
           "p50/p99/max", "writer CPU us/cycle", "CSV MB/min", "MCAP MB/min")  # fmt: skip
    print("  ".join(hdr))
    for mode in ("none", "csv", "csv+mcap"):
        r = res[mode]
        c, lt, b = r["record_cost_us"], r["lateness_us"], r["cycle_busy_us"]
        print(
            f"{mode:8s}  {c['p50']:.1f}/{c['p99']:.1f}/{c['max']:.0f}  "
            f"{lt['p50']:.0f}/{lt['p99']:.0f}/{lt['max']:.0f}  "
            f"{b['p50']:.0f}/{b['p99']:.0f}/{b['max']:.0f}  {r['writer_cpu_us_per_cycle']:.0f}  "
            f"{r.get('csv_mb_per_min', 0):.2f}  {r.get('mcap_mb_per_min', 0):.2f}"
        )
    for key in ("writer_state_only", "writer_state_and_plan"):
        w = res[key]
        print(
            f"{key}: {w['us_per_cycle']['p50']:.0f} us/cycle median "
            f"(p99 {w['us_per_cycle']['p99']:.0f}), {w['mb_per_min_at_100hz']:.2f} MB/min"
        )
    for key in ("gil_no_yield", "gil_yield_200us"):
        lt = res[key]["lateness_us"]
        print(f"{key}: 4 ms JSON bursts beside the loop: lateness p50/p99 "
              f"{lt['p50']:.0f}/{lt['p99']:.0f} us")  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

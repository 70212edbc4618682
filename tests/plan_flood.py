"""A hostile peer for the HIL tests: floods one plan key as fast as this process can.

python tests/plan_flood.py --connect ENDPOINT --key truckd/<vehicle>/plan --duration S
    [--rate N]

Publishes, in turn, garbage bytes, a NaN plan, a plan naming another sender and JSON
nested deeper than a parser's stack, N per second (default 100 000; as many as the
process can send when it cannot reach N), at a low CPU priority.  Prints "flooding" once
a subscriber matches the key, then about every second, and at the end (after S seconds, or
on SIGINT), one JSON line {"sent": N, "seconds": S} of what it sent so far (a caller that
cannot wait for its end reads the last line and ends it).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import zenoh


def payloads() -> list[bytes]:
    nan_plan = b'{"t": 1.0, "seq": 1, "dt": 0.01, "v": [NaN, 1.0], "a": [0.0, 0.0]}'
    other = json.dumps(
        {"t": 1.0, "seq": 2**40, "dt": 0.01, "v": [9.0, 9.0], "a": [0.0, 0.0], "vehicle_id": "x"}
    ).encode()
    return [b"\x00garbage\xff", nan_plan, other, b"[" * 5000 + b"]" * 5000]


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--connect", required=True)
    ap.add_argument("--key", required=True)
    ap.add_argument("--duration", type=float, required=True)
    ap.add_argument("--rate", type=float, default=100_000.0, help="puts per second at most")
    args = ap.parse_args()
    # A low CPU priority: a hostile peer is another computer; here it shares the cores
    # with the simulated firmware, which must not be the one starved.  Not the lowest: at
    # nice 19 other work on a loaded machine left it too little to flood at all.
    os.nice(10)
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", json.dumps([args.connect]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    with zenoh.open(conf) as session:
        pub = session.declare_publisher(args.key, congestion_control=zenoh.CongestionControl.DROP)
        t_end = time.monotonic() + 30.0
        while not pub.matching_status.matching and time.monotonic() < t_end:
            time.sleep(0.01)
        print("flooding", flush=True)
        data = payloads()
        n = 0
        t0 = time.monotonic()
        t_end = t0 + args.duration
        t_report = t0 + 1.0
        try:
            while True:
                for p in data:  # 100 puts between clock reads
                    for _ in range(25):
                        pub.put(p)
                n += 25 * len(data)
                now = time.monotonic()
                if now >= t_end:
                    break
                if now >= t_report:
                    print(json.dumps({"sent": n, "seconds": now - t0}), flush=True)
                    t_report = now + 1.0
                ahead = t0 + n / args.rate - now  # paced at --rate, never above it
                if ahead > 0:
                    time.sleep(ahead)
        except KeyboardInterrupt:  # SIGINT: stop early, still report
            pass
        print(json.dumps({"sent": n, "seconds": time.monotonic() - t0}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

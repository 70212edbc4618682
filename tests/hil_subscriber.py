"""An independent Zenoh subscriber process for the HIL tests.

python tests/hil_subscriber.py --connect ENDPOINT --vehicle ID --out FILE --duration S

Writes one JSON line per state sample: {"rx": local monotonic time, "msg": state}, and at
the end {"stalls": [[start, end], ...]}: this process's own scheduling stalls (monotonic s,
see stall_probe.py), so the test can tell samples lost to a starved subscriber from
samples the daemon did not publish.
Prints "ready" once subscribed and "receiving" when the first sample arrives (so the
caller knows the subscription reached the publisher).  Exits after S seconds.
"""

from __future__ import annotations

import argparse
import json
import threading
import time

import zenoh
from stall_probe import StallProbe


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--connect", required=True)
    ap.add_argument("--vehicle", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--duration", type=float, required=True)
    args = ap.parse_args()
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", json.dumps([args.connect]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    lock = threading.Lock()
    first = True
    probe = StallProbe()
    with open(args.out, "w", encoding="utf-8") as fh, zenoh.open(conf) as session:

        def on_state(sample: zenoh.Sample) -> None:
            nonlocal first
            line = json.dumps(
                {"rx": time.monotonic(), "msg": json.loads(sample.payload.to_bytes())}
            )
            with lock:
                fh.write(line + "\n")
                if first:
                    first = False
                    print("receiving", flush=True)

        sub = session.declare_subscriber(f"truckd/{args.vehicle}/state", on_state)
        print("ready", flush=True)
        time.sleep(args.duration)
        sub.undeclare()
        probe.stop()
        with lock:
            fh.write(json.dumps({"stalls": probe.stalls}) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

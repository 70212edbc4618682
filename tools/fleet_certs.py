#!/usr/bin/env python3
"""Make a fleet's certificates and Zenoh configurations (mutual TLS, access control by
certificate common name): see truckd/runtime/fleet_tls.py and docs/platoon.md.

    python tools/fleet_certs.py --out fleet --trucks truck0,truck1,truck2 \
        [--operators operator] [--endpoint tls/127.0.0.1:7449] [--days 365]

Writes into DIR: ca.pem; <name>.pem and <name>-key.pem for every truck, operator and the
router; router.json5 (``zenohd -c DIR/router.json5``, or a Python router) and one
<name>.json5 per truck and operator (``runtime.telemetry.zenoh_config`` of that truck,
``truckd monitor --zenoh-config``).  Needs the cryptography package (``pip install
'truckd[tls]'``).  Exit 2 on bad input.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from truckd.errors import InputError
from truckd.runtime.fleet_tls import client_config, make_fleet, router_config


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="directory to write")
    p.add_argument("--trucks", required=True, help="vehicle ids, comma-separated")
    p.add_argument("--operators", default="operator", help="operator names (default operator)")
    p.add_argument("--endpoint", default="tls/127.0.0.1:7449", help="the router's endpoint")
    p.add_argument("--days", type=int, default=365, help="validity (days)")
    a = p.parse_args(argv)
    try:
        if not a.endpoint.startswith("tls/"):
            raise InputError(f"--endpoint {a.endpoint!r}: expected tls/<host>:<port>")
        if not 1 <= a.days <= 3650:
            raise InputError(f"--days: expected 1 to 3650, got {a.days}")
        trucks = [t for t in a.trucks.split(",") if t]
        ops = [o for o in a.operators.split(",") if o]
        fleet = make_fleet(a.out, trucks, ops, a.days)
        out = Path(a.out)
        (out / "router.json5").write_text(json.dumps(router_config(fleet, a.endpoint), indent=2))
        for name in (*fleet.trucks, *fleet.operators):
            conf = client_config(fleet, name, a.endpoint)
            (out / f"{name}.json5").write_text(json.dumps(conf, indent=2))
    except InputError as exc:
        print(f"fleet_certs: {exc}", file=sys.stderr)
        return 2
    trucks, ops = len(fleet.trucks), len(fleet.operators)
    plural = {True: "s", False: ""}
    print(
        f"fleet of {trucks} truck{plural[trucks != 1]} and {ops} "
        f"operator{plural[ops != 1]} in {out}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The C firmware core on the host: how fast the simulated truck runs with it.

``python benchmarks/firmware_bench.py [--json FILE]``:
- one 10 ms control cycle of the simulated truck (command, firmware step with plant and
  messages, companion receive with checks), frames (CAN) and serial bytes;
- the bare core: polls per second over a simulated second with a trivial Python HAL
  (every message due is packed, sealed and handed to the HAL).
Wall-clock figures: run on a quiet machine; the load average is recorded with them.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from protocol_bench import _sim_cycle_us

from firmware_protocol.fwcore import CoreConfig, FirmwareCore


class _Hal:
    def read_encoders(self) -> tuple[int, int, int]:
        return 1, 2, 0

    def read_power(self) -> tuple[int, int, int]:
        return 1000, 7200, 3000

    def read_range(self) -> tuple[int, int]:
        return 0, 1500

    def set_motor(self, voltage_mv: int, enable: bool) -> None:
        pass

    def send_bytes(self, data: bytes) -> bool:
        return True

    def send_frame(self, can_id: int, data: bytes) -> bool:
        return True


def _core_polls_per_s(link: str, seconds: int = 20) -> float:
    core = FirmwareCore(_Hal(), CoreConfig(link=link))  # type: ignore[arg-type]
    t0 = time.perf_counter()
    for ms in range(seconds * 1000):
        core.now_ms = ms
        core.poll()
    return seconds * 1000 / (time.perf_counter() - t0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", default=None, help="write the figures to this file")
    args = ap.parse_args()
    res = {
        "load_average_1min": os.getloadavg()[0],
        "sim_cycle_us_frames": _sim_cycle_us("frames"),
        "sim_cycle_us_bytes": _sim_cycle_us("bytes"),
        "core_polls_per_s_can": _core_polls_per_s("can"),
        "core_polls_per_s_serial": _core_polls_per_s("serial"),
    }
    for k, v in res.items():
        print(f"{k:28s} {v:12.1f}")
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

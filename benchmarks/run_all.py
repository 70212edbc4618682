"""Run every benchmark in turn, each writing ``benchmarks/<name>.json`` beside its script.

``python benchmarks/run_all.py [NAME ...]``: all of them (about 30 minutes on 2 cores), or
only the named ones (the names in ``ORDER`` below).  Run them on a quiet machine: every
figure is a wall-clock measurement.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ORDER = (
    "plant_bench",
    "protocol_bench",
    "firmware_bench",
    "mpc_bench",
    "loop_bench",
    "wakeup_floor",
    "cycle_work",
    "mpc_settings",
    "recorder_bench",
    "diagnose_bench",
    "diagnose_work",  # the swerve log under callgrind: about 4 minutes
    "closed_loop_gain",
    "platoon_figures",
    "platoon_frequency",
    "router_bench",
    "platoon_hil",
    "platoon_order_bench",
    "pil_bench",  # needs qemu-system-arm and arm-none-eabi-gcc (node for its readers part)
)


def main() -> int:
    names = sys.argv[1:] or list(ORDER)
    unknown = [n for n in names if n not in ORDER]
    if unknown:
        print(
            f"run_all: unknown benchmark(s) {', '.join(unknown)}; known: {', '.join(ORDER)}",
            file=sys.stderr,
        )
        return 2
    failed = []
    for name in names:
        print(f"== {name}", flush=True)
        cmd = [sys.executable, str(HERE / f"{name}.py"), "--json", str(HERE / f"{name}.json")]
        if subprocess.run(cmd, check=False).returncode != 0:
            failed.append(name)
    if failed:
        print(f"run_all: failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

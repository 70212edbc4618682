"""Makes tests/data/replay/: a short recorded daemon run for the replay regression test.

``truckd run --backend sim`` (in-process, real time, the shipped configuration with the
received-message log on, telemetry off) for ``--duration`` seconds; the recorder's CSV log
and its received-message sidecar are copied to ``tests/data/replay/run.csv`` and
``run.rx.jsonl``.  The run is then replayed; the script fails (exit 1, nothing written)
when the replay does not reproduce the commands, e.g. because a solve overran its time
budget on a loaded machine (run it again then).

    .venv/bin/python tests/data/make_replay_log.py [--duration 3]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from runtime_support import write_config  # noqa: E402

from truckd.config.truck import load_config  # noqa: E402
from truckd.logfile import read_log  # noqa: E402
from truckd.runtime.daemon import Daemon  # noqa: E402
from truckd.runtime.realtime import unfreeze_gc  # noqa: E402
from truckd.runtime.replay import compare, replay  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=3.0)
    ap.add_argument("--out", type=Path, default=HERE / "replay")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        cfg = write_config(
            Path(tmp) / "truck.yaml",
            {"runtime": {"realtime": False, "telemetry": {"enabled": False},
                         "recorder": {"dir": str(Path(tmp) / "logs"), "messages": True}}},
        )  # fmt: skip
        d = Daemon(load_config(cfg), "sim", duration=args.duration, env={})
        try:
            d.run()
        finally:
            unfreeze_gc()
        assert d.recorder is not None and d.rxlog is not None and d.recorder.path is not None
        csv, rx = d.recorder.path, d.rxlog.path
        c = compare(read_log(csv), replay(rx))
        print(c)
        if c.max_abs_du > 1e-6 or c.enable_mismatches or c.mode_mismatches:
            print("replay does not reproduce the run: not written", file=sys.stderr)
            return 1
        args.out.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(csv, args.out / "run.csv")
        shutil.copyfile(rx, args.out / "run.rx.jsonl")
    return 0


if __name__ == "__main__":
    sys.exit(main())

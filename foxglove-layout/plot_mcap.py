"""Plot one vehicle's channels of a truckd MCAP file with matplotlib, panel for panel as
the vehicle's tab in foxglove-layout/truckd-layout.json (a stand-in picture where Foxglove is not
at hand; it is NOT a Foxglove screenshot and says so on the figure).

    python foxglove-layout/plot_mcap.py FILE.mcap OUT.png [--vehicle truck1]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from truckd.runtime.mcap_log import read_mcap

MODES = ["INIT", "ACTIVE", "DEGRADED", "SAFE_STOP", "FAULT"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mcap")
    ap.add_argument("out")
    ap.add_argument("--vehicle", default="truck1")
    args = ap.parse_args()
    c = read_mcap(args.mcap)
    by = c.by_topic()
    st = by.get(f"/truckd/{args.vehicle}/state", [])
    if not st:
        print(f"{args.mcap}: no /truckd/{args.vehicle}/state messages", file=sys.stderr)
        return 2
    t0 = st[0].log_time
    t = [(m.log_time - t0) * 1e-9 for m in st]
    msgs = [json.loads(m.data) for m in st]

    def col(key: str) -> list[float]:
        return [float("nan") if m.get(key) is None else float(m[key]) for m in msgs]

    hl = by.get(f"/truckd/{args.vehicle}/health", [])
    th = [(m.log_time - t0) * 1e-9 for m in hl]
    loop = [json.loads(m.data).get("loop") or {} for m in hl]

    fig, ax = plt.subplots(5, 1, figsize=(10, 11), sharex=True)
    ax[0].plot(t, col("gap"), label="gap")
    ax[0].plot(t, col("gap_ref"), "--", label="gap_ref")
    ax[0].set_ylabel("m")
    ax[0].set_title(f"{args.vehicle}: gap and reference")
    ax[1].plot(t, col("v"), label="v")
    ax[1].plot(t, col("v_lead"), "--", label="v_lead")
    ax[1].set_ylabel("m/s")
    ax[1].set_title("speed and lead speed")
    ax[2].plot(t, col("u"), label="u")
    ax[2].plot(t, col("u_ff"), "--", label="u_ff")
    ax[2].set_ylabel("V")
    ax[2].set_title("voltage command and feedforward")
    ax[3].step(t, [MODES.index(m["mode"]) for m in msgs], where="post", label="mode")
    ax[3].set_yticks(range(len(MODES)), MODES)
    ax[3].set_title("supervisor mode")
    ax[4].plot(t, col("lateness_us"), lw=0.6, label="wake lateness")
    ax[4].plot(t, col("solve_us"), lw=0.6, label="MPC solve")
    if loop:
        ax[4].plot(th, [x.get("lateness_us_p99") for x in loop], "o-", label="lateness p99")
        ax[4].plot(th, [x.get("compute_us_p99") for x in loop], "s-", label="compute p99")
    ax[4].set_yscale("log")
    ax[4].set_ylabel("us")
    ax[4].set_title("loop timing")
    ax[4].set_xlabel("s since the first state message (MCAP log time)")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(loc="upper right", fontsize=8)
    fig.suptitle(
        f"matplotlib plot of the MCAP channels in {Path(args.mcap).name}\n"
        "(the panels of foxglove-layout/truckd-layout.json; not a Foxglove screenshot)",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(args.out, dpi=90)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""String stability over frequency: how a lead speed oscillation travels down the platoon.

For a lead speed ``1.2 + A sin(2 pi f t)`` m/s (A at most 0.3 m/s and at most 0.5 m/s^2 of
acceleration) and each frequency f, the speed amplitude of every truck in the steady
oscillation (the last two periods); the ratio of consecutive followers' amplitudes is the
magnitude of the string-stability transfer |Gamma(j 2 pi f)| (Ploeg, van de Wouw, Nijmeijer
2014: string stable when it is <= 1 at every frequency).  CACC (the predecessor's plan) and
ACC alone (every plan lost, the range sensor only) at the same headways, 4 trucks, the
platoon scenarios' 0.15 s dead time.  Simulated time: the figures do not depend on the
machine's load.  Prints a table, writes JSON (``--json``) and a figure (``--png``).

    python benchmarks/platoon_frequency.py --json benchmarks/platoon_frequency.json \
        --png docs/img/platoon-frequency.png
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from truckd.config.truck import load_config
from truckd.control.platoon import PlatoonConfig
from truckd.sim.closed_loop import SimSetup
from truckd.sim.platoon import ACTUATION_DELAY_S, PlatoonScenario, run_platoon

FREQS_HZ = (0.05, 0.1, 0.2, 0.3, 0.5, 0.8, 1.2)
HEADWAYS_S = (0.3, 0.5)
START_S = 3.0


def _sine(f: float, amp: float) -> tuple[Callable[[float], float], Callable[[float], float]]:
    w = 2.0 * math.pi * f

    def v(t: float) -> float:
        return 1.2 + amp * math.sin(w * (t - START_S)) if t >= START_S else 1.2

    def a(t: float) -> float:
        return amp * w * math.cos(w * (t - START_S)) if t >= START_S else 0.0

    return v, a


def speed_ratios(setup: SimSetup, f: float, h: float, policy: str, n: int) -> list[float]:
    """Follower-to-predecessor speed amplitude ratios (pairs 1/0, 2/1, ...) at f (Hz)."""
    amp = min(0.3, 0.5 / (2.0 * math.pi * f))
    v, a = _sine(f, amp)
    dur = START_S + max(4.0 / f, 8.0)
    sc = PlatoonScenario("frequency", f"lead sine {f} Hz", dur, 1.2, v, a)
    pcfg = PlatoonConfig(cacc_headway=h, acc_headway=max(h, 1.1))
    loss = 0.0
    if policy == "ACC":
        pcfg, loss = replace(pcfg, acc_headway=h), 1.0
    _m, tr = run_platoon(sc, setup, pcfg, n, loss=loss)
    t = np.asarray(tr.t)
    speeds = np.asarray(tr.v, dtype=float)[t >= dur - 2.0 / f]
    amps = (speeds.max(axis=0) - speeds.min(axis=0)) / 2.0
    return [float(amps[i] / amps[i - 1]) for i in range(1, len(amps))]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the figures here")
    ap.add_argument("--png", help="write the figure here")
    ap.add_argument("--trucks", type=int, default=4)
    args = ap.parse_args()
    cfg = load_config()
    setup = SimSetup.from_config(cfg)
    t0 = time.monotonic()
    rows: list[dict[str, Any]] = []
    for h in HEADWAYS_S:
        for policy in ("CACC", "ACC"):
            for f in FREQS_HZ:
                r = speed_ratios(setup, f, h, policy, args.trucks)
                rows.append({"headway_s": h, "policy": policy, "f_hz": f, "ratios": r})
                # the first ratio is follower 1 against the scripted lead
                print(
                    f"h {h:.1f} s  {policy:4s}  f {f:4.2f} Hz  speed amplitude ratios "
                    f"{' '.join(f'{x:.3f}' for x in r)}",
                    flush=True,
                )
    doc = {
        "trucks": args.trucks,
        "dead_time_s": ACTUATION_DELAY_S,
        "rows": rows,
        "run_time_s": round(time.monotonic() - t0, 1),
        "load_average": os.getloadavg(),
    }
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(doc, fh, indent=2)
            fh.write("\n")
    if args.png:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, len(HEADWAYS_S), figsize=(10, 4), sharey=True)
        for ax, h in zip(np.atleast_1d(axes), HEADWAYS_S, strict=True):
            for policy, style in (("CACC", "o-"), ("ACC", "s--")):
                sel = [r for r in rows if r["headway_s"] == h and r["policy"] == policy]
                worst = [max(r["ratios"][1:]) for r in sel]  # followers behind followers
                ax.semilogx([r["f_hz"] for r in sel], worst, style, label=policy)
            ax.axhline(1.0, color="k", lw=0.8)
            ax.set_title(f"headway {h} s, dead time {ACTUATION_DELAY_S} s")
            ax.set_xlabel("lead speed oscillation (Hz)")
            ax.grid(True, which="both", alpha=0.3)
        np.atleast_1d(axes)[0].set_ylabel("largest speed amplitude ratio, follower pairs")
        np.atleast_1d(axes)[0].legend()
        fig.tight_layout()
        fig.savefig(args.png, dpi=100)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

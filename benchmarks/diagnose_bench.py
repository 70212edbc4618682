"""Diagnosis benchmark: hit rate over many random seeds per effect, and speed.

For each effect: ``--seeds`` plant logs (random magnitude in
labkit.synth.EFFECT_RANGES, random excitation, 0.01 m/s and 0.3 A noise, 50 s at
100 Hz).  A *hit* names exactly that effect, recovers its parameter within the tests'
tolerance and improves the fit.  Also: logs without effect (hit = nothing named, not
unexplained), two effects at once (hit = both named), a periodic disturbance outside
the candidates (hit = unexplained and nothing named).  Speed: diagnose on 10 000 and 60 000
samples at 100 Hz, median of 3, with the load average (``--speed-only``).

``--trucks drawn``: the wider draw.  Every log comes from a different truck with 0.1x..10x
the default motor constant and inertia (log-uniform), logged at 50-200 Hz with jittered
timing, dropped rows and coarse speed steps, without current (with current for
viscous friction, which needs it) (:func:`labkit.synth.draw_truck`); the effect
magnitudes scale with the motor constant (:func:`labkit.synth.scaled_effect`).
Diagnosis is always started from the *default* configuration.  Also reported: false
causes per 100 logs (named effects that were not hidden, over every log of the run).
Terrain cases ``hill`` (a load on 5 m of road, crossed repeatedly) and ``rolling`` (a
sinusoid in position): the hidden cause is ``load_force`` with that profile, located.
The hill is placed without regard to how far the truck drives, so an edge may lie
beyond the driven range (it cannot be located) or the hill may cover all of it (then it
is a constant load); ``hit_rate_observable`` scores the hill the log can show (edges
clipped to the driven range; a constant ``load_force`` when it covers all of it),
``hit_rate`` the hill as placed.  ``pair``: a new cause and a second one hidden together;
observable when each moves the log by ``VISIBLE`` noise units beside the other.

    nice .venv/bin/python benchmarks/diagnose_bench.py [--seeds N] [--trucks default|drawn]
        [--speed-only | --no-speed] [--sizes N,M] [--speed-logs F,G] [--jobs N]
        [--json FILE [--key NAME]]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from collections.abc import Sequence
from typing import Any

import lab_path  # noqa: F401 - tests/ on sys.path, for labkit
import numpy as np
from labkit.synth import (
    draw_truck,
    drawn_log,
    hill_effects,
    hill_force_for,
    plant_log,
    random_effect,
    random_effects,
    rolling_effects,
    visibility,
    with_effect,
)
from results import write_json

from truckd.config.truck import load_config
from truckd.ident import ckernel
from truckd.ident.api import diagnose_log, read_logs
from truckd.logfile import Log
from truckd.model.effects import COMPANIONS, EFFECT_NAMES, Effects

TOLERANCE: dict[str, tuple[float, float]] = {
    "viscous_friction": (0.10, 0.0),
    "aero_drag": (0.10, 0.0),
    "load_force": (0.05, 0.2),
    "input_delay": (0.0, 0.003),
    "dead_zone": (0.0, 0.3),
    "dead_zone_offset": (0.0, 0.3),
    "voltage_saturation": (0.0, 0.1),
    "battery_sag": (0.10, 0.0),
    "sensor_lag": (0.10, 0.0),
    "current_limit": (0.05, 0.0),
    "backlash": (0.20, 0.0),
    "stribeck": (0.25, 0.0),
    "resistance_drift": (0.25, 0.0),
}
N = 5000

NEW_CAUSES = ("current_limit", "backlash", "stribeck", "resistance_drift")
"""Causes real drivetrains have beyond the contract's first eight."""
PAIR_PARTNERS = (*NEW_CAUSES, "load_force", "input_delay", "sensor_lag")
"""The ``pair`` case hides one new cause with another cause from this list."""
VISIBLE = 2.0
"""A new cause is observable in a log when it moves it by this many noise units
(:func:`labkit.synth.visibility`, as ``tests/test_diagnose_causes.py``)."""
WITH_CURRENT = ("viscous_friction", "resistance_drift")
"""Drawn logs with a current column (what shows these causes)."""


def _one_effect(p: Any, name: str, seed: int) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    eff = random_effects(name, rng)
    value = float(getattr(eff, name))
    t0 = time.perf_counter()
    d = diagnose_log(plant_log(p, eff, seed=seed, n=N), p)
    dt = time.perf_counter() - t0
    names = [f.name for f in d.effects]
    found = next(iter(d.effects[0].params.values())) if d.effects else float("nan")
    rel, ab = TOLERANCE[name]
    named = names == [name]
    within = named and abs(found - value) <= max(rel * abs(value), ab)
    gain = d.extended.fit_percent - d.baseline.fit_percent
    return {
        "case": name,
        "seed": seed,
        "value": value,
        "found": found,
        "named": names,
        "hit": bool(within and gain > 0.0),
        "name_hit": name in names,
        "unexplained": d.unexplained,
        "ambiguous": d.ambiguous,
        "gain": gain,
        "time_s": dt,
    }


def _drawn(p: Any, name: str, seed: int) -> dict[str, Any]:
    """One log of a drawn truck with ``name`` hidden ("none": clean)."""
    rng = np.random.default_rng(seed)
    truck = draw_truck(p, rng)
    value = 0.0
    eff = Effects()
    if name != "none":
        eff = random_effects(name, rng, truck.k_scale)
        value = float(getattr(eff, name))
    log_seed = int(rng.integers(1 << 30))
    log = drawn_log(truck, eff, log_seed, with_current=name in WITH_CURRENT)
    with_i = name in WITH_CURRENT
    shown = visibility(truck, eff, log_seed, with_current=with_i) if name in NEW_CAUSES else 0.0
    t0 = time.perf_counter()
    d = diagnose_log(log, p)
    dt = time.perf_counter() - t0
    names = [f.name for f in d.effects]
    kv_rel = float(d.vehicle.K_v / truck.params.K_v - 1.0) if d.vehicle is not None else 1.0
    row: dict[str, Any] = {
        "case": name,
        "seed": seed,
        "k_scale": truck.k_scale,
        "j_scale": truck.j_scale,
        "rate_hz": truck.rate_hz,
        "value": value,
        "named": names,
        "false_causes": len([n for n in names if n != name]),
        "unexplained": d.unexplained,
        "K_v_relerr": kv_rel,
        "baseline_fit": d.baseline.fit_percent,
        "extended_fit": d.extended.fit_percent,
        "rejected": [r.name for r in d.rejected],
        "time_s": dt,
        "visibility": shown,
    }
    if name == "none":
        row["hit"] = not names and abs(kv_rel) < 0.1
        return row
    found = next(iter(d.effects[0].params.values())) if d.effects else float("nan")
    rel, ab = TOLERANCE[name]
    if name == "load_force":
        ab *= truck.k_scale
    row["found"] = found
    row["name_hit"] = name in names
    row["hit"] = bool(
        names == [name]
        and abs(found - value) <= max(rel * abs(value), ab)
        and d.extended.fit_percent > d.baseline.fit_percent
    )
    return row


def _pair(p: Any, seed: int) -> dict[str, Any]:
    """One log of a drawn truck with a new cause and a second cause hidden (current
    logged): a hit names both and nothing else."""
    rng = np.random.default_rng(seed)
    truck = draw_truck(p, rng)
    a = str(rng.choice(np.array(NEW_CAUSES)))
    b = str(rng.choice(np.array([n for n in PAIR_PARTNERS if n != a])))
    own: dict[str, dict[str, float]] = {}
    for n in (a, b):
        e = random_effects(n, rng, truck.k_scale)
        own[n] = {k: float(getattr(e, k)) for k in (*e.active(), *COMPANIONS.get(n, ()))}
    eff = Effects(**own[a], **own[b])
    log_seed = int(rng.integers(1 << 30))
    log = drawn_log(truck, eff, log_seed, with_current=True)
    shown = {
        n: visibility(truck, eff, log_seed, base=Effects(**own[m])) for n, m in ((a, b), (b, a))
    }
    t0 = time.perf_counter()
    d = diagnose_log(log, p)
    dt = time.perf_counter() - t0
    names = sorted(f.name for f in d.effects)
    return {
        "case": "pair",
        "seed": seed,
        "k_scale": truck.k_scale,
        "j_scale": truck.j_scale,
        "rate_hz": truck.rate_hz,
        "hidden": sorted([a, b]),
        "named": names,
        "false_causes": len([n for n in names if n not in (a, b)]),
        "hit": names == sorted([a, b]),
        "name_hit": a in names and b in names,
        "unexplained": d.unexplained,
        "time_s": dt,
        "visibility": shown,
        "observable": min(shown.values()) >= VISIBLE,
    }


TERRAIN = ("hill", "rolling")
"""Position-dependent load cases of the drawn run (named ``load_force`` with a profile)."""


def _terrain(p: Any, name: str, seed: int) -> dict[str, Any]:
    """A drawn truck on a hill (load on 5 m of road, crossed repeatedly) or on rolling
    terrain (a quarter of the driven range per wave); hit: ``load_force`` alone, with the
    right profile, located (hill edges within 30 % of its length; wavelength within
    10 %) and its force within 25 %, the extended fit above the seed's."""
    rng = np.random.default_rng(seed)
    truck = draw_truck(p, rng)
    log_seed = int(rng.integers(1 << 30))
    force = hill_force_for(truck, p) * (1.0 if rng.random() < 0.5 else -1.0)
    if name == "hill":
        eff = hill_effects(truck, log_seed, force)
        value = eff.hill_force
    else:
        eff = rolling_effects(truck, log_seed, abs(force))
        value = eff.load_force_amplitude
    log = drawn_log(truck, eff, log_seed)
    t0 = time.perf_counter()
    d = diagnose_log(log, p)
    dt = time.perf_counter() - t0
    names = [f.name for f in d.effects]
    out = next((f.to_json() for f in d.effects if f.name == "load_force"), {})
    observable = None
    if name == "hill":
        tol = 0.3 * eff.hill_length
        located = (
            out.get("profile") == "hill"
            and abs(out["x_start_m"] - eff.hill_start) < tol
            and abs(out["x_end_m"] - eff.hill_start - eff.hill_length) < tol
        )
        found = out.get("value", out.get("params", {}).get("load_force", float("nan")))
        observable = _observable_hit(log, eff, out, names, found)
    else:
        located = (
            out.get("profile") == "rolling"
            and abs(out["wavelength_m"] - eff.load_force_wavelength)
            < 0.1 * eff.load_force_wavelength
        )
        found = out.get("amplitude_n", float("nan"))
    return {
        "case": name,
        "seed": seed,
        "k_scale": truck.k_scale,
        "j_scale": truck.j_scale,
        "rate_hz": truck.rate_hz,
        "value": value,
        "found": found,
        "profile": out,
        "named": names,
        "name_hit": out.get("profile") == name,
        "false_causes": len([n for n in names if n != "load_force"]),
        "unexplained": d.unexplained,
        "baseline_fit": d.baseline.fit_percent,
        "extended_fit": d.extended.fit_percent,
        "rejected": [r.name for r in d.rejected],
        "hit": bool(
            names == ["load_force"]
            and located
            and abs(found - value) <= 0.25 * abs(value)
            and d.extended.fit_percent > d.baseline.fit_percent
        ),
        "hit_observable": bool(
            (observable if observable is not None else names == ["load_force"] and located)
            and abs(found - value) <= 0.25 * abs(value)
            and d.extended.fit_percent > d.baseline.fit_percent
        ),
        "time_s": dt,
    }


def _observable_hit(
    log: Log, eff: Effects, out: dict[str, Any], names: list[str], found: float
) -> bool:
    """The hill as the log can show it: its edges clipped to the driven range (position
    integrated from the logged speed, as :func:`hill_effects` places it).  A hill that
    covers the whole range is a constant load (``load_force`` without profile, ``found``
    is then its value); otherwise ``load_force`` with profile hill, each edge inside the
    range within 30 % of the hill's length."""
    t, v = log["t"], log["v"]
    x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))])
    lo, hi = float(np.min(x)), float(np.max(x))
    start, end = eff.hill_start, eff.hill_start + eff.hill_length
    if names != ["load_force"]:
        return False
    if start <= lo and end >= hi:
        return "profile" not in out
    tol = 0.3 * eff.hill_length
    return bool(
        out.get("profile") == "hill"
        and abs(out["x_start_m"] - max(start, lo)) < tol
        and abs(out["x_end_m"] - min(end, hi)) < tol
    )


def _observable(row: dict[str, Any]) -> bool:
    """Whether a drawn run's hidden cause (a pair: both) could show in its log."""
    if "observable" in row:
        return bool(row["observable"])
    return bool(row.get("visibility", 0.0) >= VISIBLE)


def _run_drawn(p: Any, seeds: list[int], cases: list[str]) -> list[dict[str, Any]]:
    """Every case once per seed (``cases``), clean logs twice per seed."""
    jobs = [(name, s) for name in cases if name != "none" for s in seeds]
    if "none" in cases:
        jobs += [("none", s + k) for s in seeds for k in (1, 2)]
    rows = []
    for name, s in jobs:
        if name in TERRAIN:
            rows.append(_terrain(p, name, s))
        elif name == "pair":
            rows.append(_pair(p, s))
        else:
            rows.append(_drawn(p, name, s))
        r = rows[-1]
        print(
            f"  {name} seed {s} k={r['k_scale']:.3g} J={r['j_scale']:.3g}: "
            f"{r['named']} hit={r['hit']} ({r['time_s']:.1f} s)",
            file=sys.stderr,
            flush=True,
        )
    return rows


def _none(p: Any, seed: int) -> dict[str, Any]:
    d = diagnose_log(plant_log(p, Effects(), seed=seed, n=N), p)
    return {
        "case": "none",
        "seed": seed,
        "named": [f.name for f in d.effects],
        "hit": not d.effects and not d.unexplained,
        "unexplained": d.unexplained,
    }


def _two(p: Any, seed: int) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    a, b = rng.choice(np.array(EFFECT_NAMES), size=2, replace=False)
    eff = Effects(**{str(a): random_effect(str(a), rng), str(b): random_effect(str(b), rng)})
    d = diagnose_log(plant_log(p, eff, seed=seed, n=N), p)
    names = sorted(f.name for f in d.effects)
    return {
        "case": "two",
        "seed": seed,
        "hidden": sorted([str(a), str(b)]),
        "named": names,
        "hit": names == sorted([str(a), str(b)]),
        "ambiguous": d.ambiguous,
    }


def _wobble(p: Any, seed: int) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    log = plant_log(p, Effects(), seed=seed, n=N)
    cols = dict(log.columns)
    freq, amp = rng.uniform(0.2, 1.0), rng.uniform(0.03, 0.08)
    cols["v"] = log["v"] + amp * np.sin(2 * np.pi * freq * log["t"] + rng.uniform(0, 6))
    d = diagnose_log(Log(cols, "wobble"), p)
    return {
        "case": "unexplained",
        "seed": seed,
        "named": [f.name for f in d.effects],
        "hit": d.unexplained and not d.effects,
        "unexplained": d.unexplained,
    }


SPEED_SAMPLES = (10000, 60000)
"""Log lengths of the speed figure (100 Hz: 100 s and 10 min)."""
SPEED_REPEATS = 3


def _cpu_s() -> float:
    """CPU seconds of this process and of its children that ended (the diagnosis's
    workers), user and system."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def _timed_rows(p: Any, cases: list[tuple[str, int, list[Log]]], jobs: int) -> list[dict[str, Any]]:
    """Diagnose time of each ``(name, samples, logs)``: median of :data:`SPEED_REPEATS`,
    with the 1-minute load average before each run and the CPU time (the workers'
    included), on ``jobs`` processes (``truckd diagnose --jobs``)."""
    rows = []
    for name, n, logs in cases:
        secs, cpu, loads = [], [], []
        named: list[str] = []
        for _ in range(SPEED_REPEATS):
            loads.append(os.getloadavg()[0])
            t0, c0 = time.perf_counter(), _cpu_s()
            d = diagnose_log(logs, p, workers=jobs)
            secs.append(time.perf_counter() - t0)
            cpu.append(_cpu_s() - c0)
            named = [f.name for f in d.effects]
        rows.append(
            {
                "log": name,
                "samples": n,
                "jobs": jobs,
                "seconds": secs,
                "median_s": float(np.median(secs)),
                "cpu_seconds": cpu,
                "median_cpu_s": float(np.median(cpu)),
                "loadavg_1min": [round(x, 2) for x in loads],
                "named": named,
            }
        )
        print(f"  speed {name} ({n} samples, jobs {jobs}): {secs}", file=sys.stderr, flush=True)
    return rows


def _speed(
    p: Any, sizes: tuple[int, ...] = SPEED_SAMPLES, jobs: int = 1, files: Sequence[str] = ()
) -> dict[str, Any]:
    """Diagnose time of a log with a hidden sensor lag at each of ``sizes``, and of
    each real log in ``files`` (diagnosed whole, as ``truckd diagnose FILE`` does)."""
    cases: list[tuple[str, int, list[Log]]] = []
    for n in sizes:
        cases.append(
            (
                f"plant_sensor_lag_{n}",
                n,
                [plant_log(p, with_effect("sensor_lag", 0.06), seed=3, n=n)],
            )
        )
    for f in files:
        logs = read_logs([f])
        cases.append((f, sum(len(lg.columns["t"]) for lg in logs), logs))
    return {"c_kernel": ckernel.available(), "rows": _timed_rows(p, cases, jobs)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10, help="seeds per case")
    ap.add_argument("--json", metavar="FILE", help="write the results as JSON")
    ap.add_argument("--no-speed", action="store_true", help="skip the speed runs")
    ap.add_argument(
        "--speed-only", action="store_true", help="only the speed runs (10 000, 60 000 samples)"
    )
    ap.add_argument(
        "--trucks", choices=("default", "drawn"), default="default", help="which trucks"
    )
    ap.add_argument(
        "--sizes",
        metavar="N,M",
        help="log lengths of the speed runs (default: 10000,60000)",
    )
    ap.add_argument(
        "--jobs", type=int, default=1, help="worker processes of each diagnosis (default 1)"
    )
    ap.add_argument(
        "--speed-logs",
        metavar="F,G",
        help="real logs (CSV or SysId JSON) timed whole beside the plant logs",
    )
    ap.add_argument("--key", help="with --json: store the run under this name (results.py)")
    ap.add_argument(
        "--cases",
        metavar="A,B",
        help="only these cases (effect names, none, two, unexplained; drawn: hill, rolling, "
        "pair; 'new' = the causes beyond the contract's first eight, none and pair)",
    )
    args = ap.parse_args()
    p = load_config().vehicle
    load_before = os.getloadavg()
    seeds = [int(s) for s in np.random.SeedSequence(20261122).generate_state(args.seeds)]
    rows: list[dict[str, Any]] = []
    wanted = None
    if args.cases:
        wanted = args.cases.split(",")
        if wanted == ["new"]:
            wanted = [*NEW_CAUSES, "none", "pair"]
    if args.speed_only:
        cases = []
    elif args.trucks == "drawn":
        cases = wanted or [*EFFECT_NAMES, *TERRAIN, "none", "pair"]
        rows = _run_drawn(p, seeds, cases)
    else:
        cases = [
            c for c in (wanted or [*EFFECT_NAMES, "none", "two", "unexplained"]) if c != "pair"
        ]
        for name in [c for c in cases if c in EFFECT_NAMES]:
            for s in seeds:
                rows.append(_one_effect(p, name, s))
                print(
                    f"  {name} seed {s}: {rows[-1]['named']} hit={rows[-1]['hit']}",
                    file=sys.stderr,
                    flush=True,
                )
        extra = {"none": _none, "two": _two, "unexplained": _wobble}
        for s in seeds:
            for case in [c for c in cases if c in extra]:
                rows.append(extra[case](p, s))
                print(f"  {case} seed {s}: {rows[-1]['hit']}", file=sys.stderr, flush=True)
    table: dict[str, dict[str, float]] = {}
    for case in cases:
        rs = [r for r in rows if r["case"] == case]
        table[case] = {"runs": len(rs), "hit_rate": float(np.mean([r["hit"] for r in rs]))}
        shown = [r for r in rs if _observable(r)]
        if (case in NEW_CAUSES or case == "pair") and shown:
            table[case]["hit_rate_observable"] = float(np.mean([r["hit"] for r in shown]))
            table[case]["observable_runs"] = len(shown)
        if case in TERRAIN:
            table[case]["hit_rate_observable"] = float(np.mean([r["hit_observable"] for r in rs]))
        if case in EFFECT_NAMES or case in TERRAIN or case == "pair":
            table[case]["named_rate"] = float(np.mean([r["name_hit"] for r in rs]))
            table[case]["median_time_s"] = float(np.median([r["time_s"] for r in rs]))
    false_per_100 = None
    if args.trucks == "drawn" and rows:
        false_per_100 = 100.0 * sum(r["false_causes"] for r in rows) / len(rows)
    speed: dict[str, Any] = {}
    if not args.no_speed:
        sizes = tuple(int(x) for x in args.sizes.split(",")) if args.sizes else SPEED_SAMPLES
        files = args.speed_logs.split(",") if args.speed_logs else []
        speed = _speed(p, sizes, args.jobs, files)
    print(f"\n{'case':20s} {'runs':>5s} {'hit rate':>9s} {'named':>7s} {'median s':>9s}")
    for case, r in table.items():
        named = f"{r['named_rate']:.2f}" if "named_rate" in r else ""
        med = f"{r['median_time_s']:.1f}" if "median_time_s" in r else ""
        obs = (
            f"  (observable: {r['hit_rate_observable']:.2f})" if "hit_rate_observable" in r else ""
        )
        print(f"{case:20s} {r['runs']:5d} {r['hit_rate']:9.2f} {named:>7s} {med:>9s}{obs}")
    if false_per_100 is not None:
        print(f"\nfalse causes per 100 logs: {false_per_100:.1f} ({len(rows)} logs)")
    for row in speed.get("rows", []):
        print(
            f"\ndiagnose {row['log']} ({row['jobs']} jobs) on {row['samples']} samples: "
            f"median {row['median_s']:.2f} s of "
            f"{[round(x, 2) for x in row['seconds']]}, CPU {row['median_cpu_s']:.2f} s "
            f"(load {row['loadavg_1min']})"
        )
    machine = {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpus": os.cpu_count(),
        "loadavg_before": load_before,
        "loadavg_after": os.getloadavg(),
    }
    print(f"machine: {machine}")
    if args.json:
        write_json(
            args.json,
            {
                "trucks": args.trucks,
                "table": table,
                "false_causes_per_100_logs": false_per_100,
                "speed": speed,
                "machine": machine,
                "runs": rows,
            },
            args.key,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

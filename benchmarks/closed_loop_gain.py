"""Closing the loop: the controller with the seed model against the controller with the
model ``diagnose`` extracted from a log of the same truck, for every effect the diagnosis
can name.

For each effect and value: the simulated truck (plant) has the effect switched on; an
open-loop log of it (random excitation, noise) goes through ``truckd diagnose --out
MODEL.yaml``; then ``truckd sim`` runs each scenario twice on that plant, the controller
using the configured (seed) model, then ``--model MODEL.yaml``.  A clean row per scenario
(no effect, seed model) gives what the controller achieves without the effect.  Reported
per row: gap error RMS (after the first 5 s) clean / seed / extended, the minimum gaps,
collisions, ``found`` (the diagnosis named the effect), ``recovered = (seed - extended)
/ (seed - clean)`` (null when the effect costs under 2 mm) and the goal's verdict
(``judged``, ``meets_goal``, see :func:`judge`).

    .venv/bin/python benchmarks/closed_loop_gain.py [--json FILE [--key NAME]]
        [--scenarios a,b] [--effects NAME[,NAME]] [--value NAME=VALUE ...] [--true]
        [--companion FIELD=V1[,V2...]] [--models DIR] [--note TEXT]

``--json FILE`` writes ``{date, machine, argv, rows}`` (``--key NAME``: under that key,
keeping the file's other measurements; see ``results.py``).  ``--true`` skips the diagnosis
and gives the controller the plant's true effects (fast, for development; rows say
``"diagnosed": false``).  ``--models DIR`` keeps the diagnosed model files in DIR and
reuses those already there (the diagnosis does not depend on the controller).  ``--value
NAME=VALUE`` replaces an effect's values by one.  ``--companion FIELD=V1[,V2...]`` sets
one of the effect's other parameters (``load_force_phase``: where the rolling road's
slopes fall), a row per value (e.g. a terrain at eight phases).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime
import io
import json
import math
import sys
import tempfile
from pathlib import Path
from typing import Any

import lab_path  # noqa: F401 - tests/ on sys.path, for labkit
import yaml
from labkit.synth import plant_log
from results import machine, write_json

from truckd.cli.main import main as truckd
from truckd.config.truck import default_config_path, load_config
from truckd.logfile import write_log
from truckd.model.effects import Effects
from truckd.modelfile import ModelFile, write_model

CASES: dict[str, tuple[float, ...]] = {
    # name: (a value a user meets, a larger one)
    "viscous_friction": (2e-5, 6e-5),  # N m s/rad at the motor shaft
    "aero_drag": (0.5, 2.0),  # N/(m/s)^2
    "load_force": (2.0, 5.0),  # N: a 6 % / 15 % grade for a 3.5 kg truck, or a trailer
    "load_force_amplitude": (2.0, 4.0),  # N, rolling terrain (wavelength 3.6 m)
    "hill_force": (3.0, 5.0),  # N on a 5 m stretch from 7 m
    "input_delay": (0.03, 0.06),  # s
    "dead_zone": (0.6, 1.2),  # V, threshold
    "dead_zone_offset": (0.6, 1.2),  # V, offset
    "voltage_saturation": (5.0, 3.5),  # V (the battery is 7.4 V)
    "battery_sag": (0.2, 0.3),  # ohm (0.5: the firmware cuts out at 5.5 V on a start)
    "sensor_lag": (0.05, 0.15),  # s
    "current_limit": (30.0, 20.0),  # A (the stall current at 7.2 V is 85 A)
    "backlash": (1.0, 3.0),  # rad at the motor shaft: 2 / 6 degrees at the wheel
    "stribeck": (0.006, 0.015),  # N m above K_coulomb (0.015 N m) at rest, v_s 0.1 m/s
    "resistance_drift": (1.0, 2.0),  # K/W, tau 20 s (2.5: 200 K over the diagnosis log)
}

COMPANIONS: dict[str, dict[str, float]] = {
    "load_force_amplitude": {"load_force_wavelength": 3.6},
    "hill_force": {"hill_start": 7.0, "hill_length": 5.0},
    "stribeck": {"stribeck_speed": 0.1},
    "resistance_drift": {"winding_time_constant": 20.0},
}
"""The other parameters of an effect: a position-dependent effect's (m: the diagnosis log,
seed 2026, drives over 0 .. 14.4 m, most of its time near 9.3 m; the scenarios start at
0 m), the Stribeck speed (m/s), the winding's thermal time constant (s)."""

COST_MIN_M = 0.002
"""An effect that costs less RMS gap error than this has nothing to recover."""

WORSE_MAX = 0.05
"""The extended model may be this much (relative) worse than its bar, no more."""


def judge(clean: float, seed: float, ext: float, collision: bool) -> tuple[str, bool]:
    """The goal's verdict on one row (gap error RMS clean / seed / extended, m): how it
    is judged and whether it meets the goal (never with a collision).

    The extended model is never more than :data:`WORSE_MAX` worse than its bar: the seed,
    or the clean truck where the seed is better than that (the effect itself helps the
    seed's controller there: a rolling road whose downhill falls where the truck stops
    pushes it nearer the standstill gap; with the slopes elsewhere the same seed is worse
    than clean, see the terrain phase rows of ``closed_loop_gain.json``; a model's
    knowledge cannot earn that gain, only keep the controller's own).  The row is judged

    * ``recovery`` where the effect costs more than :data:`COST_MIN_M` (seed - clean): the
      extended model also recovers half of it;
    * ``helped`` where the seed is better than the clean truck by more than
      :data:`COST_MIN_M`;
    * ``no cost`` otherwise.
    """
    cost = seed - clean
    ok = ext <= (1.0 + WORSE_MAX) * max(seed, clean) and not collision
    if cost > COST_MIN_M:
        return "recovery", ok and (seed - ext) >= 0.5 * cost
    return ("helped" if cost < -COST_MIN_M else "no cost"), ok


def plant_effects(name: str, value: float, companions: dict[str, float]) -> Effects:
    return dataclasses.replace(Effects(), **{name: value}, **companions)


def _sim(cfg: Path, scenario: str, out: Path, model: Path | None) -> dict[str, Any]:
    argv = ["sim", "--config", str(cfg), "--scenario", scenario, "--json", str(out)]
    if model is not None:
        argv += ["--model", str(model)]
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        code = truckd(argv)
    if code != 0:
        raise SystemExit(f"truckd {' '.join(argv)} exited {code}")
    data = json.loads(out.read_text())
    return data[0] if isinstance(data, list) else data  # type: ignore[no-any-return]


def _diagnose(eff: Effects, tag: str, d: Path, models: Path | None) -> tuple[Path, list[Any]]:
    """The diagnosed model file of a log of the plant with ``eff`` and what was found."""
    where = models if models is not None else d
    model, report = where / f"{tag}_model.yaml", where / f"{tag}.json"
    if not (model.exists() and report.exists()):
        p = load_config().vehicle
        log = plant_log(p, eff, seed=2026, n=6000)
        write_log(d / f"{tag}.csv", log.columns)
        argv = ["diagnose", str(d / f"{tag}.csv"), "--out", str(model), "--json", str(report)]
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            code = truckd(argv)
        if code != 0:
            raise SystemExit(f"diagnose failed on {tag}")
    found = json.loads(report.read_text())["effects"]
    return model, list(found)


def _parse_values(items: list[str]) -> dict[str, float]:
    out = {}
    for item in items:
        name, _, val = item.partition("=")
        if name not in CASES or not val:
            raise SystemExit(f"--value wants NAME=VALUE with NAME one of {', '.join(CASES)}")
        out[name] = float(val)
    return out


def _parse_companions(items: list[str]) -> list[dict[str, float]]:
    """``--companion FIELD=V1[,V2...]``: one dict of the fields set per combination."""
    fields = {f.name for f in dataclasses.fields(Effects)}
    combos: list[dict[str, float]] = [{}]
    for item in items:
        name, _, vals = item.partition("=")
        if name not in fields or not vals:
            raise SystemExit(
                f"--companion wants FIELD=V1[,V2...] with FIELD of Effects, not {item!r}"
            )
        combos = [{**c, name: float(v)} for c in combos for v in vals.split(",")]
    return combos


def main() -> int:
    ap = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    ap.add_argument("--json", metavar="FILE")
    ap.add_argument("--key", help="store the run under this key (what_YYYY-MM-DD)")
    ap.add_argument("--note", help="a note stored with the run")
    ap.add_argument("--scenarios", default="follow,stop-and-go,lead-brake")
    ap.add_argument("--effects", default=",".join(CASES), help="NAME[,NAME]")
    ap.add_argument("--value", action="append", default=[], metavar="NAME=VALUE")
    ap.add_argument("--companion", action="append", default=[], metavar="FIELD=V1[,V2...]")
    ap.add_argument("--true", action="store_true", help="the true effects, no diagnosis")
    ap.add_argument("--models", metavar="DIR", help="keep and reuse diagnosed model files")
    ap.add_argument("--no-clean", action="store_true", help="skip the clean rows")
    ap.add_argument(
        "--diagnose-only", action="store_true", help="fill --models DIR, run no scenario"
    )
    args = ap.parse_args()
    names = [n for n in args.effects.split(",") if n]
    bad = [n for n in names if n not in CASES]
    if bad:
        raise SystemExit(f"unknown effect {bad[0]!r}; one of {', '.join(CASES)}")
    values = _parse_values(args.value)
    combos = _parse_companions(args.companion)
    scenarios = args.scenarios.split(",")
    base = yaml.safe_load(default_config_path().read_text())
    vehicle = load_config().vehicle
    models = Path(args.models) if args.models else None
    if models is not None:
        models.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        clean: dict[str, dict[str, Any]] = {}
        (d / "clean.yaml").write_text(yaml.safe_dump(base))
        if not (args.no_clean or args.diagnose_only):
            for sc in scenarios:
                m = _sim(d / "clean.yaml", sc, d / "a.json", None)
                clean[sc] = m
                rows.append(
                    {
                        "effect": "clean",
                        "value": 0.0,
                        "scenario": sc,
                        "gap_rms_clean_m": m["gap_error_rms_m"],
                        "min_gap_clean_m": m["min_gap_m"],
                        "collision_clean": m["collision"],
                    }
                )
                print(f"clean {sc:12s} gap RMS {m['gap_error_rms_m']:.4f} m", flush=True)
        runs = [
            (name, value, {**COMPANIONS.get(name, {}), **combo})
            for name in names
            for value in ((values[name],) if name in values else CASES[name])
            for combo in combos
        ]
        for name, value, companions in runs:
            eff = plant_effects(name, value, companions)
            tag = "_".join(
                [name, f"{value:g}"]
                + [f"{v:g}" for k, v in companions.items() if k in COMPANIONS.get(name, {})]
                + [f"{k}{v:g}" for k, v in companions.items() if k not in COMPANIONS.get(name, {})]
            )
            cfg = dict(base)
            cfg["plant"] = dict(base["plant"])
            off = Effects()
            plain = {k: v for k, v in dataclasses.asdict(eff).items() if v != getattr(off, k)}
            cfg["plant"]["effects"] = dict(base["plant"]["effects"], **plain)
            cfg_path = d / f"{tag}.yaml"
            cfg_path.write_text(yaml.safe_dump(cfg))
            if args.true:
                model = d / f"{tag}_true.yaml"
                write_model(model, ModelFile(vehicle, eff, "true effects"))
                found: list[Any] = [{"name": name, "params": plain}]
            else:
                model, found = _diagnose(eff, tag, d, models)
            if args.diagnose_only:
                print(f"{tag}: found {[f['name'] for f in found]}", flush=True)
                continue
            # A terrain is reported under its family's name with its own parameters.
            named = list(dict.fromkeys(n for f in found for n in (f["name"], *f.get("params", {}))))
            for sc in scenarios:
                seed_m = _sim(cfg_path, sc, d / "a.json", None)
                ext_m = _sim(cfg_path, sc, d / "b.json", model)
                if sc not in clean:
                    clean[sc] = _sim(d / "clean.yaml", sc, d / "c.json", None)
                c, s, e = (
                    clean[sc]["gap_error_rms_m"],
                    seed_m["gap_error_rms_m"],
                    ext_m["gap_error_rms_m"],
                )
                ok = None not in (c, s, e)
                cost = s - c if ok else math.nan
                how, meets = judge(c, s, e, bool(ext_m["collision"])) if ok else ("no gap", False)
                rows.append(
                    {
                        "effect": name,
                        "value": value,
                        "companions": companions,
                        "scenario": sc,
                        "diagnosed": not args.true,
                        "found": name in named,
                        "found_effects": found,
                        "gap_rms_clean_m": c,
                        "gap_rms_seed_m": s,
                        "gap_rms_extended_m": e,
                        "cost_m": cost,
                        "recovered": (s - e) / cost if ok and cost > COST_MIN_M else None,
                        "extended_vs_seed": e / s - 1.0 if ok and s > 0 else None,
                        "min_gap_seed_m": seed_m["min_gap_m"],
                        "min_gap_extended_m": ext_m["min_gap_m"],
                        "collision_seed": seed_m["collision"],
                        "collision_extended": ext_m["collision"],
                        "judged": how,
                        "meets_goal": meets,
                    }
                )
                r = rows[-1]
                rec = "-" if r["recovered"] is None else f"{r['recovered']:.2f}"
                mm = [f"{1e3 * g:6.1f}" if g is not None else "  none" for g in (c, s, e)]
                print(
                    f"{tag:24s} {sc:12s} clean {mm[0]} seed "
                    f"{mm[1]} extended {mm[2]} mm  recovered {rec:>5s}  "
                    f"min gap {ext_m['min_gap_m']:.3f} m  {how}: "
                    f"{'met' if meets else 'MISSED'}  found {named}",
                    flush=True,
                )
    if args.json:
        doc: dict[str, Any] = {
            "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d"),
            "machine": machine(),  # the load average at the end of the run
            "argv": sys.argv[1:],
            "rows": rows,
        }
        if args.note:
            doc["note"] = args.note
        write_json(args.json, doc, args.key)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""``truckd sim --platoon N``: the platoon scenarios (reference section 1)."""

from __future__ import annotations

import argparse
import json
import math
import re
from pathlib import Path
from typing import Any

from truckd.cli.args import MAX_PLATOON_TRUCK_S
from truckd.config.truck import load_config
from truckd.control.qp import ControlModel
from truckd.errors import InputError, TruckdError
from truckd.modelfile import read_controller_model
from truckd.outputs import check_output_dir, ensure_dir, write_set
from truckd.sim.closed_loop import SimSetup, Trace
from truckd.sim.platoon import (
    MAX_TRUCKS,
    MIN_TRUCKS,
    PLATOON_SCENARIOS,
    PREROLL_S,
    make_platoon_scenario,
    run_platoon,
)
from truckd.sim.report import json_safe, trace_text

JOINS_LEAVES = ("platoon-join", "platoon-leave")
"""Scenarios in which trucks join or leave: their ratios pair trucks by index."""

# the shortest platoon run whose spacing errors the string ratios can compare (s)
MIN_PLATOON_DURATION_S = 1.0


def add_platoon_arguments(p: argparse.ArgumentParser) -> None:
    """The platoon options of ``truckd sim``."""
    p.add_argument(
        "--platoon", type=int, metavar="N", help=f"N trucks (2..{MAX_TRUCKS}), truck 0 leads"
    )
    p.add_argument(
        "--plan-delay",
        metavar="LO[-HI]",
        help="plan delivery delay (s, default 0.02); a range LO-HI: each plan's delay drawn "
        "in it (plans overtake each other)",
    )
    p.add_argument(
        "--plan-loss", type=float, metavar="P", help="share of plans lost (0..1, default 0)"
    )
    p.add_argument(
        "--burst-loss", action="store_const", const=True, help="plans lost in runs (same share)"
    )
    p.add_argument(
        "--clock-offset",
        type=float,
        metavar="S",
        help="each truck's clock offset drawn in +-S (s, default 0)",
    )
    p.add_argument(
        "--clock-drift",
        type=float,
        metavar="PPM",
        help="each truck's clock drift drawn in +-PPM (default 0)",
    )
    p.add_argument(
        "--mixed",
        action="store_const",
        const=True,
        help="each truck drawn: mass, motor, one effect; its controller on the model its "
        "own identification drive diagnoses",
    )
    p.add_argument(
        "--true-models",
        action="store_const",
        const=True,
        help="with --mixed: the controllers on the drawn trucks' true parameters (no "
        "identification drive and diagnosis per truck)",
    )
    p.add_argument(
        "--diagnosis-cache",
        metavar="DIR",
        help="with --mixed: keep the trucks' diagnosed models in DIR (keyed by the drawn "
        "truck, the configuration and truckd's code) and reuse them",
    )
    p.add_argument(
        "--steady-start",
        action="store_const",
        const=True,
        help="a scenario that starts at speed starts in the steady state of that speed, "
        f"after an unrecorded {PREROLL_S:g} s pre-roll (not platoon-join: its trucks approach "
        "from 0 s)",
    )
    p.add_argument(
        "--seed", type=int, help="random seed of the plan loss, clocks and trucks (default 0)"
    )


PLATOON_ONLY: dict[str, object] = {
    "plan_delay": "0.02",
    "plan_loss": 0.0,
    "burst_loss": False,
    "clock_offset": 0.0,
    "clock_drift": 0.0,
    "mixed": False,
    "true_models": False,
    "diagnosis_cache": None,
    "steady_start": False,
    "seed": 0,
}
"""Options of a platoon run and their defaults: given without ``--platoon``, refused."""


def check_platoon_only(args: argparse.Namespace) -> None:
    """A single-truck run refuses the platoon's options (they would be ignored)."""
    for name in PLATOON_ONLY:
        if getattr(args, name) is not None:
            opt = "--" + name.replace("_", "-")
            raise InputError(f"{opt}: applies to a platoon run only (--platoon N)")


def _check(args: argparse.Namespace) -> None:
    for name, default in PLATOON_ONLY.items():
        if getattr(args, name) is None:
            setattr(args, name, default)
    if args.platoon is None:
        raise InputError(f"--scenario {args.scenario}: a platoon scenario needs --platoon N")
    if not 2 <= args.platoon <= MAX_TRUCKS:
        raise InputError(f"--platoon: expected 2 to {MAX_TRUCKS} trucks, got {args.platoon}")
    if args.scenario not in (*PLATOON_SCENARIOS, "all"):
        raise InputError(
            f"--scenario {args.scenario}: with --platoon expected one of "
            f"{', '.join(PLATOON_SCENARIOS)}"
        )
    for opt in ("true_models", "diagnosis_cache"):
        if getattr(args, opt) and not args.mixed:
            raise InputError(f"--{opt.replace('_', '-')}: applies to drawn trucks only (--mixed)")
    args.plan_delay = parse_delay(str(args.plan_delay))
    if not (math.isfinite(args.clock_offset) and 0.0 <= args.clock_offset <= 3600.0):
        raise InputError(f"--clock-offset: expected 0 to 3600 s, got {args.clock_offset}")
    if not (math.isfinite(args.clock_drift) and 0.0 <= args.clock_drift <= 1000.0):
        raise InputError(f"--clock-drift: expected 0 to 1000 ppm, got {args.clock_drift}")
    if not (math.isfinite(args.plan_loss) and 0.0 <= args.plan_loss <= 1.0):
        raise InputError(f"--plan-loss: expected a share from 0 to 1, got {args.plan_loss}")
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise InputError(f"--duration: expected a positive number of seconds, got {args.duration}")
    if args.seed < 0:  # numpy's seeds are 0 or more: -1 drew the run of seed 1
        raise InputError(f"--seed: expected 0 or more, got {args.seed}")
    trucks = args.platoon
    if args.duration is not None and args.duration * trucks > MAX_PLATOON_TRUCK_S:
        raise InputError(
            f"--duration: {args.duration:g} s of {trucks} trucks is "
            f"{args.duration * trucks:g} truck-seconds; expected at most "
            f"{MAX_PLATOON_TRUCK_S:g} (each is kept in memory for the figures, about "
            "0.13 MB)"
        )
    if args.duration is not None and args.duration < MIN_PLATOON_DURATION_S:
        raise InputError(
            f"--duration: a platoon run needs at least {MIN_PLATOON_DURATION_S:g} s to measure"
            f" string ratios, got {args.duration:g}"
        )
    for opt in ("realtime", "plot", "mcap"):  # --mcap was silently ignored
        if getattr(args, opt, None):
            raise InputError(f"--{opt}: not available with --platoon")


def parse_delay(text: str) -> tuple[float, float]:
    """``--plan-delay``: ``S`` or ``LO-HI`` (s, 0 to 10); InputError otherwise."""
    # the range's dash, not an exponent's (1e-2) nor a leading sign
    parts = [text] if text.startswith("-") else re.split(r"(?<![eE])-", text, maxsplit=1)
    try:
        if "_" in text:  # float() takes 1_0; a delay written so is a typo
            raise ValueError(text)
        lo, hi = (float(parts[0]), float(parts[-1]))
    except ValueError:
        raise InputError(f"--plan-delay: expected S or LO-HI in seconds, got {text!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo <= hi <= 10.0):
        raise InputError(f"--plan-delay: expected 0 <= LO <= HI <= 10 s, got {text!r}")
    return lo, hi


def _fmt(xs: list[float | None]) -> str:
    return " ".join("-" if x is None else f"{x:.2f}" for x in xs)


def run_platoon_cli(args: argparse.Namespace) -> int:
    _check(args)
    cfg = load_config(args.config)
    model = ControlModel(cfg.vehicle)
    if args.model:
        mf = read_controller_model(cfg, args.model)
        model = ControlModel(mf.vehicle, mf.effects)
    setup = SimSetup.from_config(cfg, model)
    names = PLATOON_SCENARIOS if args.scenario == "all" else (args.scenario,)
    needs = {n: MIN_TRUCKS.get(make_platoon_scenario(n).kind, 2) for n in names}
    short = [f"{n} needs at least {k} trucks" for n, k in needs.items() if args.platoon < k]
    if short:
        every = " (or run another --scenario)" if args.scenario == "all" else ""
        raise InputError(f"--platoon {args.platoon}: {'; '.join(short)}{every}")
    # checked now, created when the traces are written (a run that fails leaves none)
    trace = getattr(args, "trace", None)
    trace_dir = check_output_dir(trace, "trace directory") if trace else None
    results: list[dict[str, Any]] = []
    files: list[tuple[str | Path, str | bytes]] = []
    controllers = None
    if args.mixed and not args.true_models:
        # here: the diagnosis stack (scipy) only for the runs that diagnose
        from truckd.cli.platoon_diagnosis import (
            DIAGNOSIS_JOBS_MAX,
            DiagnosedControllers,
            stderr_progress,
        )
        from truckd.workers import usable_cpus

        cache = None
        if args.diagnosis_cache:
            cache = ensure_dir(args.diagnosis_cache, "diagnosis cache directory")
        jobs = min(usable_cpus(), DIAGNOSIS_JOBS_MAX)  # the drawn trucks on forked workers
        controllers = DiagnosedControllers(cfg, stderr_progress, cache, jobs)
    for name in names:
        m, tr = run_platoon(
            make_platoon_scenario(name),
            setup,
            cfg.platoon,
            args.platoon,
            delay_s=args.plan_delay,
            loss=args.plan_loss,
            burst_loss=args.burst_loss,
            seed=args.seed,
            duration=args.duration,
            clock_offset_s=args.clock_offset,
            clock_drift_ppm=args.clock_drift,
            mixed=args.mixed,
            steady_start=args.steady_start,
            controllers=controllers,
        )
        results.append(json_safe(m))
        if trace_dir is not None:  # one log per truck, the lead (truck 0) included
            for i, rows in enumerate(tr.rows):
                files.append((trace_dir / f"{name}-truck{i}.csv", trace_text(Trace(rows=rows))))
        # With joins and leaves the ratios pair trucks by index, not road neighbours.
        by_index = " (pairs by truck index, not road order)" if name in JOINS_LEAVES else ""
        print(
            f"{name}: {args.platoon} trucks, collision {m['collision']}, "
            f"min gap {m['min_gap_m']:.3f} m, string ratio l2 [{_fmt(m['string_ratio_l2'])}] "
            f"max [{_fmt(m['string_ratio_max'])}]{by_index}, "
            f"CACC share [{_fmt(m['cacc_fraction'])}]"
        )
    if args.json:
        doc: object = results if args.scenario == "all" else results[0]
        files.append((args.json, json.dumps(doc, indent=2, allow_nan=False) + "\n"))
    if trace_dir is not None:
        ensure_dir(trace_dir, "trace directory")
    write_set(files)  # all or nothing: JSON and traces
    crashed = [r["scenario"] for r in results if r["collision"]]
    if crashed:
        raise TruckdError(f"collision in: {', '.join(crashed)}")
    return 0

"""``truckd characterize --config FILE [--backend sim|serial|can] [--out DIR]
[--drive-only]``: the truck identifies itself, safely, in one command;
``truckd characterize --config FILE --analyse DIR``: the analysis of a drive already made.

The daemon runs as ``truckd run`` does (its loop, link, supervisor, recorder, telemetry);
the routine (:mod:`truckd.runtime.characterize`) is its command source.  Then the
experiment log goes through the diagnosis (:mod:`truckd.ident.api`) and DIR holds
``log.csv``, ``model.yaml``, ``diagnosis.json``, ``report.html``, ``summary.json`` (and
the daemon's own recording under ``raw/``).  Exit 0 completed, 3 a bring-up check failed,
4 stopped (stop request, SIGTERM, supervisor); 2 bad input, 1 other failures.

``--drive-only`` stops after ``log.csv`` and ``summary.json`` (``"analysed": false``): a
companion computer too slow or too busy for the analysis leaves it to another machine,
which runs ``--analyse DIR`` on the directory (the same configuration file: its vehicle is
the diagnosis's starting point).  ``--analyse`` also analyses a drive again, e.g. with a
newer truckd: it replaces ``model.yaml``, ``diagnosis.json``, ``report.html`` and the
summary's analysis keys.
"""

from __future__ import annotations

import argparse
import base64
import dataclasses
import html
import json
import math
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from truckd.config.truck import TruckConfig, load_config
from truckd.errors import InputError, TruckdError
from truckd.io.backends import BACKEND_NAMES
from truckd.jsonsafe import json_number
from truckd.logfile import Log, read_log, write_log
from truckd.runtime.backend import Backend
from truckd.runtime.characterize import Routine
from truckd.runtime.characterize_plan import EXIT_DONE, Check, Experiment, Result, TruckFacts
from truckd.runtime.daemon import Daemon
from truckd.runtime.ratekeeper import SteppedClock
from truckd.workers import usable_cpus

LOG_COLUMNS = ("t", "u", "v", "vbat", "x", "range_raw")
"""The daemon log's columns copied into DIR/log.csv (plus ``experiment``, its index, and
``stopped``)."""

T_TOL = 1e-6
"""s: times from the routine and from the recorded log agree to within this."""

SIM_WALL_BEYOND_M = 0.5
"""With ``--backend sim`` the simulated track ends at a wall this far beyond
``characterize.track_length_m`` (the range sensor sees it, as on a real track)."""

Prepare = Callable[[Backend], None]


def add_subparser(sub: Any) -> None:
    p = sub.add_parser(
        "characterize", help="bring-up checks, identification experiments, diagnosed model"
    )
    p.add_argument("--config", help="configuration file (default: the shipped one)")
    p.add_argument("--backend", choices=BACKEND_NAMES, help="default: runtime.backend")
    p.add_argument(
        "--out",
        metavar="DIR",
        help="output directory (default: characterize-<UTC time>); created, must be empty",
    )
    p.add_argument(
        "--drive-only",
        action="store_true",
        help="drive and write log.csv and summary.json, leave the analysis to --analyse",
    )
    p.add_argument(
        "--analyse",
        metavar="DIR",
        help="analyse the drive in DIR (a finished run's log.csv and summary.json); no driving",
    )
    p.set_defaults(run=run)


def _console(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    if args.analyse is not None:
        if args.out or args.backend or args.drive_only:
            raise InputError("--analyse drives nothing: no --out, --backend or --drive-only")
        return analyse_dir(cfg, Path(args.analyse), _console)
    out = Path(args.out or time.strftime("characterize-%Y%m%dT%H%M%SZ", time.gmtime()))
    return characterize(cfg, args.backend, out, _console, drive_only=args.drive_only)


def out_dir(path: Path) -> Path:
    """Create DIR (an existing one must be empty: nothing of another run is mixed in)."""
    if path.exists() and (not path.is_dir() or any(path.iterdir())):
        raise InputError(
            f"{path}: --out exists and is not an empty directory; name a new one (nothing of "
            "another run is mixed in)"
        )
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise TruckdError(f"{path}: cannot create the output directory: {exc.strerror}") from None
    return path


class CharacterizeDaemon(Daemon):
    """The daemon with the routine as its command source: the first SIGTERM/SIGINT stops
    the routine (0 V, wait at rest, end); a second ends the loop at once."""

    def __init__(
        self,
        cfg: TruckConfig,
        backend: str | None,
        prepare: Prepare | None = None,
        clock: SteppedClock | None = None,
    ) -> None:
        if clock is None:
            super().__init__(cfg, backend)
        else:
            super().__init__(cfg, backend, clock=clock, sleep=clock.sleep)
        self.prepare = prepare
        self.routine: Routine | None = None
        self._signalled = False

    def start(self) -> None:
        super().start()
        assert self.routine is not None and self.backend is not None
        routine = self.routine
        if self.telemetry is not None:
            self.telemetry.declare("characterize")
            self.telemetry.subscribe(
                "stop", lambda _payload: routine.request_stop("stop request over Zenoh")
            )
        if self.backend.name == "sim":  # the simulated track: a wall beyond its end
            from truckd.sim.backend import SimBackend

            assert isinstance(self.backend, SimBackend)
            wall = self.cfg.characterize.track_length_m + SIM_WALL_BEYOND_M
            self.backend.firmware.range_fn = lambda _t, x: wall - x
        if self.prepare is not None:
            self.prepare(self.backend)
        self.companion.command_source = routine

    def request_stop(self, signum: int = 0, _frame: object = None) -> None:
        if self.routine is None or self.routine.finished or self._signalled:
            self.stop_requested = True
            return
        self._signalled = True
        name = signal.Signals(signum).name if signum else "stop"
        self.routine.request_stop(name)


def _daemon_config(cfg: TruckConfig, raw: Path) -> TruckConfig:
    """The daemon's configuration for the routine: no lead to follow (a target ahead is
    free space, not a lead: lead lost drives on), the recorder on, into DIR/raw."""
    rt = cfg.runtime
    recorder = dataclasses.replace(rt.recorder, enabled=True, dir=str(raw), messages=False)
    return dataclasses.replace(
        cfg,
        control=dataclasses.replace(cfg.control, on_lead_lost="cruise"),
        runtime=dataclasses.replace(rt, recorder=recorder),
    )


def drive(
    cfg: TruckConfig,
    backend: str | None,
    out: Path,
    console: Callable[[str], None] = _console,
    prepare: Prepare | None = None,
    clock: SteppedClock | None = None,
) -> tuple[Result, CharacterizeDaemon]:
    """Run the daemon with the routine until it ends; (result, daemon).  With ``clock``
    the loop runs in simulated time (the ``sim`` backend only: a real truck's messages
    come in real time)."""
    from firmware_protocol.codec import specs

    name = backend or cfg.runtime.backend
    if clock is not None and name != "sim":
        raise ValueError(f"simulated time needs the sim backend, not {name!r}")
    d = CharacterizeDaemon(_daemon_config(cfg, out / "raw"), backend, prepare, clock)
    printed: list[tuple[str, str]] = []

    def progress(msg: dict[str, Any]) -> None:
        key = (str(msg["stage"]), str(msg["experiment"]))
        if not printed or printed[-1] != key:
            printed.append(key)
            what = f" {msg['experiment']}" if msg["experiment"] else ""
            console(f"characterize: {msg['stage']}{what} ({msg['percent']:.0f} %)")
        if d.telemetry is not None:
            d.telemetry.publish("characterize", msg)

    def done() -> None:
        d.stop_requested = True

    d.routine = Routine(
        cfg.characterize,
        TruckFacts(
            period=d.period,
            range_max=cfg.control.estimator.range_max,
            encoder_period=specs()["WHEEL_ENCODERS"].period,
            ticks_per_rev=d.ticks_per_rev,
            r_w=cfg.vehicle.r_w,
        ),
        decision=lambda: d.decision,
        link_stats=lambda: d.port.stats() if d.port is not None else {},
        on_progress=progress,
        on_done=done,
    )
    d.run()
    return d.routine.result, d


def experiment_log(
    files: list[Path], experiments: list[Experiment], stop_t: float = math.nan
) -> Log | None:
    """The experiments' rows of the daemon's recording (one run each, the pauses between
    them cut out), with their index in ``experiment`` and ``stopped`` (1 from the stop at
    ``stop_t`` on: the partial log marks itself); None when nothing was driven."""
    parts = [read_log(f) for f in files if f.exists()]
    parts = [p for p in parts if len(p) > 0]
    if not parts:
        return None
    cols = {c: np.concatenate([p[c] for p in parts]) for c in LOG_COLUMNS}
    t = cols["t"]
    index = np.full(len(t), -1.0)
    for k, e in enumerate(experiments):
        if math.isfinite(e.t_start) and math.isfinite(e.t_end):
            # the recorder writes t with 10 significant digits: compare to within 1 us
            index[(t >= e.t_start - T_TOL) & (t <= e.t_end + T_TOL)] = k
    keep = index >= 0
    if not keep.any():
        return None
    columns = {c: a[keep] for c, a in cols.items()}
    columns["experiment"] = index[keep]
    columns["stopped"] = (t[keep] >= stop_t - T_TOL).astype(float)  # NaN stop_t: all 0
    return Log(columns, source="log.csv")


def _select(log: Log, keep: Any, source: str) -> Log:
    return Log({c: a[keep] for c, a in log.columns.items()}, source=source)


def _loop_counts(d: Daemon) -> dict[str, int]:
    """The drive's loop counters: cycles run, cycles past their deadline, and whole
    periods skipped after overruns (the log has no row for a skipped period)."""
    s = d.rk.stats()
    return {"cycles": s.cycles, "misses": s.misses, "skipped_periods": s.skipped_periods}


def characterize(
    cfg: TruckConfig,
    backend: str | None,
    out: Path,
    console: Callable[[str], None] = _console,
    prepare: Prepare | None = None,
    clock: SteppedClock | None = None,
    drive_only: bool = False,
) -> int:
    """The whole command: drive, then analyse (not ``drive_only``); the exit code.
    ``clock``: see :func:`drive`."""
    out = out_dir(out)
    result, d = drive(cfg, backend, out, console, prepare, clock)
    files = list(d.recorder.files) if d.recorder is not None else []
    log = experiment_log(files, result.experiments, result.stop_t)
    if log is not None:
        write_log(out / "log.csv", log.columns)
    summary: dict[str, Any] = {
        "completed": result.code == EXIT_DONE,
        "exit_code": result.code,
        "checks": [c.as_dict() for c in result.checks],
        "experiments": [e.as_dict() for e in result.experiments],
        "distance_m": round(result.distance_m, 4),
        "duration_s": round(result.duration_s, 3),
        "end_speed_m_s": json_number(result.end_speed_m_s),
        "stopped": {"reason": result.stop_reason, "t": result.stop_t}
        if result.stop_reason
        else None,
        "log_rows": len(log) if log is not None else 0,
        "loop": _loop_counts(d),
        "raw_logs": [str(f.relative_to(out)) for f in files if f.exists()],
    }
    failed = [c for c in result.checks if not c.ok]
    if result.code != EXIT_DONE or log is None:
        for c in failed:
            console(f"characterize: check {c.name} failed: {c.detail}")
        if result.stop_reason:
            console(f"characterize: stopped ({result.stop_reason}); partial log in {out}")
        _write_json(out / "summary.json", summary)
        return result.code if result.code != EXIT_DONE else 1
    summary["analysed"] = False
    if drive_only:
        _write_json(out / "summary.json", summary)
        console(f"characterize: driven; analyse with truckd characterize --analyse {out}")
        return EXIT_DONE
    return _analyse_into(cfg, log, result, out, summary, console)


def _analyse_into(
    cfg: TruckConfig,
    log: Log,
    result: Result,
    out: Path,
    summary: dict[str, Any],
    console: Callable[[str], None],
    workers: int = 1,
) -> int:
    """Analyse ``log`` into ``out`` and write ``summary`` with the analysis keys and
    ``analysed``; exit 0, or 1 when the log cannot be analysed (it is kept, and the summary
    says why: the files the analysis wrote before it failed are not a set).  ``workers``:
    the diagnosis's (1 after a drive: the process that held the truck forks nothing)."""
    try:
        summary.update(analyse(cfg, log, result, out, console, workers))
    except (TruckdError, InputError) as exc:
        summary.update(analysed=False, analysis_error=str(exc))
        _write_json(out / "summary.json", summary)
        console(f"characterize: analysis failed: {exc}; the log is in {out / 'log.csv'}")
        return 1
    summary.pop("analysis_error", None)
    summary["analysed"] = True
    _write_json(out / "summary.json", summary)
    _print_summary(summary, console)
    return EXIT_DONE


SUMMARY_MAX_BYTES = 1 << 20
"""The largest summary.json ``--analyse`` reads (one holds some 20 experiments: a few kB)."""


def analyse_dir(cfg: TruckConfig, d: Path, console: Callable[[str], None] = _console) -> int:
    """``--analyse DIR``: the analysis of the completed drive in ``d`` (its ``log.csv`` and
    ``summary.json``), written into ``d``; the exit code (0, 1 the analysis failed).
    InputError (exit 2) when ``d`` holds no completed drive."""
    from truckd.inputs import read_text

    try:
        summary = json.loads(
            read_text(d / "summary.json", "characterize summary", SUMMARY_MAX_BYTES)
        )
        if not isinstance(summary, dict) or not summary.get("completed"):
            code = summary.get("exit_code") if isinstance(summary, dict) else None
            raise InputError(f"{d}: the drive did not complete (exit {code}): nothing to analyse")
        result = Result(
            checks=[
                Check(str(c["name"]), bool(c["ok"]), str(c["detail"])) for c in summary["checks"]
            ],
            experiments=[_experiment(e) for e in summary["experiments"]],
        )
        log = read_log(d / "log.csv", require=("t", "u", "v"))
        if "experiment" not in log.columns:
            raise InputError(f"{d / 'log.csv'}: no 'experiment' column: not a characterize log")
    except (ValueError, KeyError, TypeError) as exc:  # JSONDecodeError is a ValueError
        # one line, `truckd characterize: error: ...`, exit 2 (reference section 1)
        raise InputError(f"{d / 'summary.json'}: not a characterize summary ({exc})") from None
    # no link to a truck here: the diagnosis's fits may go to forked workers
    return _analyse_into(cfg, log, result, d, summary, console, min(usable_cpus(), 4))


def _experiment(e: dict[str, Any]) -> Experiment:
    """An experiment as summary.json keeps it (what the analysis and the report read)."""
    t0, t1 = (math.nan if e[k] is None else float(e[k]) for k in ("t_start", "t_end"))
    ended = str(e.get("ended") or "")
    return Experiment(
        name=str(e["name"]),
        kind=str(e["kind"]),
        direction=0,
        duration_s=t1 - t0,
        t_start=t0,
        t_end=t1,
        ended="" if ended == "done" else ended,
        skipped=str(e.get("skipped") or ""),
        distance_m=float(e.get("distance_m") or 0.0),
    )


def split_validation(log: Log, result: Result) -> tuple[Log, Log | None]:
    """The experiment log as the diagnosis takes it: the ramps and steps to fit, the
    validation chirp (None when it was not driven) to validate."""
    val_k = [k for k, e in enumerate(result.experiments) if e.kind == "validation"]
    is_val = np.isin(log["experiment"], val_k)
    fit = _select(log, ~is_val, "log.csv (ramps and steps)")
    val = _select(log, is_val, "log.csv (validation)") if is_val.any() else None
    return fit, val


def analyse(
    cfg: TruckConfig,
    log: Log,
    result: Result,
    out: Path,
    console: Callable[[str], None],
    workers: int = 1,
) -> dict[str, Any]:
    """Diagnose the experiment log (the chirp validates; its fits on ``workers``
    processes), write model.yaml, diagnosis.json and report.html; the summary's analysis
    keys."""
    from truckd.ident.api import diagnose_log, model_of, require_physical
    from truckd.modelfile import write_model

    fit, val = split_validation(log, result)
    console("characterize: analysis")
    diag = diagnose_log(fit, cfg.vehicle, val, lambda m: console(f"  {m}"), workers=workers)
    model = require_physical(model_of(diag, "truckd characterize"), "log.csv", "diagnosed model")
    write_model(out / "model.yaml", model)
    dj = diag.to_json()
    _write_json(out / "diagnosis.json", dj)
    closed = closed_loop(cfg, model.vehicle, model.effects)
    ext = dj.get("extended", {})
    keys = {
        "feedforward": ext.get("feedforward"),
        "params": ext.get("params"),
        "effects": dj.get("effects", []),
        "fit_percent": ext.get("fit_percent"),
        "closed_loop": closed,
    }
    _write_report(diag, out, keys, result)
    return keys


def closed_loop(cfg: TruckConfig, vehicle: Any, effects: Any) -> list[dict[str, Any]]:
    """Gap RMS per scenario with the configured and with the identified model driving
    the truck as identified (a short ``truckd sim`` of each)."""
    from truckd.control.qp import ControlModel
    from truckd.model.plant_config import PlantConfig
    from truckd.sim.closed_loop import SimSetup, run_scenario
    from truckd.sim.scenarios import make_scenario

    plant = PlantConfig(effects=effects)
    rows = []
    for name in cfg.characterize.closed_loop_scenarios:
        row: dict[str, Any] = {"scenario": name}
        for label, model in (
            ("configured", ControlModel(cfg.vehicle)),
            ("identified", ControlModel(vehicle, effects)),
        ):
            setup = SimSetup(
                vehicle, plant, cfg.control, model,
                ticks_per_rev=cfg.link.encoder_ticks_per_rev,
                supervisor=cfg.runtime.supervisor,
                stop_ramp_v_per_s=cfg.runtime.stop_ramp_v_per_s,
            )  # fmt: skip
            metrics, _ = run_scenario(make_scenario(name, vehicle, cfg.control), setup)
            row[f"gap_rms_{label}_m"] = metrics["gap_error_rms_m"]
            row[f"collision_{label}"] = metrics["collision"]
        rows.append(row)
    return rows


def _write_json(path: Path, doc: Any) -> None:
    from truckd.outputs import write_text

    write_text(path, json.dumps(doc, indent=2, allow_nan=False, default=_json_default) + "\n")


def _json_default(x: Any) -> Any:
    if isinstance(x, np.generic):
        return x.item()
    raise TypeError(f"not JSON: {type(x).__name__}")


def _write_report(diag: Any, out: Path, keys: dict[str, Any], result: Result) -> None:
    """report.html: the summary and the diagnosis's plots, images inline (one file)."""
    import tempfile

    from truckd.ident.report import write_report
    from truckd.outputs import write_text

    with tempfile.TemporaryDirectory(dir=out) as tmp:
        write_report(diag, tmp, "truckd characterize")
        images = sorted(Path(tmp).glob("*.png"))
        imgs = "".join(
            f'<h3>{html.escape(p.stem)}</h3><img alt="{html.escape(p.stem)}" '
            f'src="data:image/png;base64,{base64.b64encode(p.read_bytes()).decode()}">'
            for p in images
        )
    rows = "".join(
        f"<tr><td>{html.escape(c.name)}</td><td>{'ok' if c.ok else 'FAILED'}</td>"
        f"<td>{html.escape(c.detail)}</td></tr>"
        for c in result.checks
    )
    exps = "".join(
        f"<tr><td>{html.escape(e.name)}</td><td>{e.distance_m:.2f}</td>"
        f"<td>{html.escape(e.skipped or e.ended or 'done')}</td></tr>"
        for e in result.experiments
    )
    ff = keys.get("feedforward") or {}
    effects = ", ".join(str(e["name"]) for e in keys["effects"]) or "none"
    cl = "".join(
        f"<tr><td>{html.escape(r['scenario'])}</td><td>{_fmt(r['gap_rms_configured_m'])}</td>"
        f"<td>{_fmt(r['gap_rms_identified_m'])}</td></tr>"
        for r in keys["closed_loop"]
    )
    page = f"""<!doctype html><html><head><meta charset="utf-8">
<title>truckd characterize</title></head><body>
<h1>truckd characterize</h1>
<p>Feedforward (SysId form): kS {_fmt(ff.get("kS"))} V, kV {_fmt(ff.get("kV"))} V s/m,
kA {_fmt(ff.get("kA"))} V s^2/m. Effects named: {html.escape(effects)}.
Validation fit {_fmt(keys.get("fit_percent"))} %.</p>
<h2>Bring-up checks</h2><table border="1"><tr><th>check</th><th></th><th>detail</th></tr>
{rows}</table>
<h2>Experiments</h2><table border="1"><tr><th>experiment</th><th>distance (m)</th>
<th>ended</th></tr>{exps}</table>
<h2>Closed loop (gap RMS, m)</h2><table border="1"><tr><th>scenario</th><th>configured
model</th><th>identified model</th></tr>{cl}</table>
<h2>Diagnosis</h2>{imgs}
</body></html>
"""
    write_text(out / "report.html", page)


def _fmt(x: Any) -> str:
    return f"{x:.4g}" if isinstance(x, int | float) else "-"


def _print_summary(s: dict[str, Any], console: Callable[[str], None]) -> None:
    ff = s.get("feedforward") or {}
    console(
        f"feedforward: kS={_fmt(ff.get('kS'))} V, kV={_fmt(ff.get('kV'))} V s/m, "
        f"kA={_fmt(ff.get('kA'))} V s^2/m"
    )
    effects = ", ".join(str(e["name"]) for e in s["effects"]) or "none"
    console(f"effects: {effects}; validation fit {_fmt(s.get('fit_percent'))} %")
    for r in s["closed_loop"]:
        console(
            f"closed loop {r['scenario']}: gap RMS {_fmt(r['gap_rms_configured_m'])} m "
            f"(configured) -> {_fmt(r['gap_rms_identified_m'])} m (identified)"
        )
    console(f"distance {s['distance_m']:.2f} m in {s['duration_s']:.1f} s")

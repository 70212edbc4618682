"""Replay by default: the recorder keeps what replay needs (the received-message log, on by
default, rotated and deleted with the CSV), a run recorded with the default configuration
replays to its commands, and a solve that failed on the car (over its time budget) fails
in the replay too."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from runtime_support import write_config

from truckd.cli.main import main
from truckd.config.runtime import RecorderConfig
from truckd.config.truck import load_config
from truckd.control.mpc import MpcResult
from truckd.errors import InputError
from truckd.logfile import read_log
from truckd.runtime.cycle import LOG_COLUMNS, CompanionCycle, CycleInputs, CycleOutputs
from truckd.runtime.recorder import Recorder
from truckd.runtime.replay import compare, cycle_from_params, replay
from truckd.runtime.rxlog import FORMAT, RxLog, encode_cycle, read_rx_log, solver_failure

DATA = Path(__file__).resolve().parent / "data" / "replay"


def stored_run() -> tuple[float, dict[str, Any], list[CycleInputs]]:
    """3 s of `truckd run --backend sim` (tests/data/replay, made by make_replay_log.py)."""
    t0, params, cycles = read_rx_log(DATA / "run.rx.jsonl")
    return t0, params, list(cycles)


def car(params: dict[str, Any], t0: float, fail: dict[int, bool]) -> CompanionCycle:
    """The stored run's cycle as on a loaded car: the solves of the cycles in ``fail`` go
    over their time budget, after finishing (True: the car keeps the solution as its warm
    start, as on a late solve) or before (False: stopped early, its warm start not the
    converged one: here, the previous one)."""
    cyc = cycle_from_params(params, t0, "car")
    mpc = cyc.controller.mpc
    solve = mpc.solve

    def on_the_car(*args: Any, **kwargs: Any) -> MpcResult:
        finished = fail.get(cyc.seq)
        if finished is None:
            return solve(*args, **kwargs)
        if finished:
            res = solve(*args, **kwargs)
            return MpcResult(False, math.nan, "overrun", res.iterations, 0.005)
        return MpcResult(False, math.nan, "run time limit reached", 3, 0.004)

    mpc.solve = on_the_car  # type: ignore[method-assign]
    return cyc


def record(
    path: Path,
    t0: float,
    params: dict[str, Any],
    cycles: list[CycleInputs],
    cyc: CompanionCycle,
    keep_failures: bool = True,
) -> list[CycleOutputs]:
    outs = []
    lines = [json.dumps({"format": FORMAT, "t0": t0, "seq0": 0, "params": params})]
    for inp in cycles:
        out = cyc.step(inp)
        outs.append(out)
        lines.append(encode_cycle(inp, solver_failure(out) if keep_failures else None))
    path.write_text("\n".join(lines) + "\n")
    return outs  # fmt: skip


def differences(a: list[CycleOutputs], b: list[CycleOutputs]) -> tuple[float, int]:
    assert [o.seq for o in a] == [o.seq for o in b]
    du = max(abs(x.command.voltage - y.command.voltage) for x, y in zip(a, b, strict=True))
    modes = sum(
        x.mode != y.mode or x.command.enable != y.command.enable for x, y in zip(a, b, strict=True)
    )
    return du, modes


def test_a_solve_that_failed_on_the_car_fails_in_the_replay(tmp_path: Path) -> None:
    t0, params, cycles = stored_run()
    late = {k: True for k in (60, 61, 62, 140)}  # two in a row: DEGRADED on the car
    on_car = record(tmp_path / "late.rx.jsonl", t0, params, cycles, car(params, t0, late))
    assert sum(solver_failure(o) is not None for o in on_car) == 4
    again = replay(tmp_path / "late.rx.jsonl")
    assert differences(on_car, again) == (0.0, 0)  # finished late: the same warm start
    # stopped early on the car: the warm start differs, the commands agree within the
    # solver's tolerance, the modes exactly
    early = {k: False for k in late}
    on_car = record(tmp_path / "early.rx.jsonl", t0, params, cycles, car(params, t0, early))
    du, modes = differences(on_car, replay(tmp_path / "early.rx.jsonl"))
    assert modes == 0 and du < 2e-3
    # the check can fail: without the failures recorded the replay drives on where the car
    # fell back
    record(tmp_path / "bare.rx.jsonl", t0, params, cycles, car(params, t0, late), False)
    du, modes = differences(on_car, replay(tmp_path / "bare.rx.jsonl"))
    assert modes > 0 or du > 1e-2


def test_a_run_recorded_with_the_default_configuration_replays(tmp_path: Path) -> None:
    """`truckd run --backend sim` for 2 s, in this process; the recorder's settings are the
    shipped ones (its directory aside): the received-message log is there and replays to
    the logged commands."""
    from truckd.runtime.daemon import Daemon
    from truckd.runtime.realtime import unfreeze_gc

    shipped = load_config()
    assert shipped.runtime.recorder.messages  # on by default
    cfg = write_config(
        tmp_path / "truck.yaml",
        {"runtime": {"realtime": False, "telemetry": {"enabled": False},
                     "recorder": {"dir": str(tmp_path / "logs")}}},
    )  # fmt: skip
    d = Daemon(load_config(cfg), "sim", duration=2.0, env={})
    try:
        assert d.run() == 0
    finally:
        unfreeze_gc()
    assert d.recorder is not None and d.recorder.path is not None
    csv = d.recorder.path
    rx = csv.with_suffix(".rx.jsonl")
    assert rx.exists()
    log = read_log(csv)
    outs = replay(rx)
    c = compare(log, outs)
    late = [(o.seq, solver_failure(o)) for o in outs if solver_failure(o) is not None]
    assert c.cycles == len(log) == len(outs) > 0, (c, late)  # (fewer than 200 under load)
    assert c.enable_mismatches == 0 and c.mode_mismatches == 0, (c, late)
    assert log["u"].max() > 1.0  # the run drove: the comparison covers solved cycles
    # exact to the CSV's 10 digits; within the solver's tolerance after a solve the car
    # stopped early (over its time budget on a loaded machine: its warm start differs)
    assert c.max_abs_du <= (1e-8 if not late else 2e-3), (c, late)
    # the comparison's JSON never replaces the log or its received-message log
    before = csv.read_bytes(), rx.read_bytes()
    assert main(["replay", str(csv), "--json", str(csv)]) == 2
    assert main(["replay", str(csv), "--json", str(rx)]) == 2
    assert (csv.read_bytes(), rx.read_bytes()) == before


def test_the_received_message_log_rotates_and_is_deleted_with_the_csv(tmp_path: Path) -> None:
    """Bounded: one received-message log per CSV file, the oldest deleted with it; the
    files of a run replay in order as one run."""
    t0, params, cycles = stored_run()
    cfg = RecorderConfig(dir=str(tmp_path), max_bytes=4096, keep=3, flush_period_s=0.01)
    rx = RxLog(params, keep=cfg.keep)
    rx.t0 = t0
    rec = Recorder(cfg, LOG_COLUMNS, sidecars=(rx,))
    rec.start()
    cyc = cycle_from_params(params, t0, "run")
    rows = []
    for inp in cycles:
        out = cyc.step(inp)
        rx.record(inp, out)
        rows.append(cyc.log_row(out))
    # the received messages queued well ahead of the CSV rows, and the writer's turn (as
    # the recorder's thread takes it): it must not run ahead of the CSV
    rx.write_pending(rec.rows)
    assert rx.rows == 0
    for row in rows:
        rec.record(row)
    rec.stop()
    csvs = sorted(tmp_path.glob("*.csv"))
    rxs = sorted(tmp_path.glob("*.rx.jsonl"))
    assert len(csvs) == 3 and rec.files == csvs  # rotated, the oldest deleted
    assert rxs == [p.with_suffix(".rx.jsonl") for p in csvs]
    assert len(rx.files) == 3 and rx.dropped == 0
    heads = [json.loads(p.read_text().splitlines()[0]) for p in rxs]
    assert all(h["format"] == FORMAT for h in heads)
    assert heads[0]["seq0"] > 0 and heads[0]["seq0"] < heads[1]["seq0"] < heads[2]["seq0"]
    # the last two files as one run from the second's first cycle: a fresh state, so only
    # the cycle numbers are checked here; in order or refused
    # each CSV's cycles are in the received-message log beside it
    for c, r, h in zip(csvs, rxs, heads, strict=True):
        seqs = read_log(c)["seq"].astype(int)
        n = len(r.read_text().splitlines()) - 1
        assert seqs.tolist() == list(range(h["seq0"], h["seq0"] + n))
    tail = replay(rxs[1:])
    assert [o.seq for o in tail] == list(range(heads[1]["seq0"], len(cycles)))
    with pytest.raises(InputError, match="expected"):
        replay([rxs[2], rxs[1]])
    # every file of a run, in order: the cycles as they ran
    with pytest.raises(InputError):
        replay([])
    assert np.isfinite([o.command.voltage for o in tail]).all()


def test_truckd_replay_compares_a_log_with_its_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`truckd replay LOG.csv`: the run's received-message logs kept up to LOG's, in order;
    a log without one is bad input (exit 2, one line)."""
    from cli_support import bad_input, cli

    t0, params, cycles = stored_run()
    cfg = RecorderConfig(dir=str(tmp_path), max_bytes=8192, keep=20, flush_period_s=0.01)
    rx = RxLog(params, keep=cfg.keep)
    rx.t0 = t0
    rec = Recorder(cfg, LOG_COLUMNS, sidecars=(rx,))
    rec.start()
    cyc = cycle_from_params(params, t0, "run")
    for inp in cycles:
        out = cyc.step(inp)
        rx.record(inp, out)
        rec.record(cyc.log_row(out))
    rec.stop()
    assert len(rec.files) >= 3
    middle = rec.files[1]
    code, out, _err = cli(["replay", str(middle), "--json", str(tmp_path / "r.json")], capsys)
    assert code == 0
    doc = json.loads((tmp_path / "r.json").read_text())
    assert doc["rx_logs"] == [str(p.with_suffix(".rx.jsonl")) for p in rec.files[:2]]
    assert doc["first_cycle"] == 0 and doc["cycles"] == len(read_log(middle))
    assert doc["max_abs_du_v"] <= 1e-8 and doc["mode_mismatches"] == 0
    assert f"{doc['cycles']} cycles compared" in out
    # the same log with another controller's commands: the comparison says so
    other = tmp_path / "other.csv"
    text = middle.read_text().splitlines()
    cols = text[0].split(",")
    k = cols.index("u")
    rows = [r.split(",") for r in text[1:]]
    for r in rows:
        r[k] = str(float(r[k]) + 0.5)
    other.write_text("\n".join([text[0], *(",".join(r) for r in rows)]) + "\n")
    other.with_suffix(".rx.jsonl").write_text(middle.with_suffix(".rx.jsonl").read_text())
    # (renamed: only its own received-message log, which starts past cycle 0)
    code, out, _err = cli(["replay", str(other), "--json", str(tmp_path / "o.json")], capsys)
    doc = json.loads((tmp_path / "o.json").read_text())
    assert code == 0 and "fresh state" in out
    assert doc["first_cycle"] > 0 and doc["max_abs_du_v"] >= 0.5
    middle.with_suffix(".rx.jsonl").unlink()
    line = bad_input(["replay", str(middle)], capsys)
    assert "no received-message log beside it" in line


def test_a_loop_stall_on_the_car_is_replayed(tmp_path: Path) -> None:
    """The car's loop stalled (no cycle for 0.12 s): its control state was re-initialised
    (runtime.stall_limit_s), and so it is in the replay, from the recorded parameters."""
    t0, params, cycles = stored_run()
    params = {**params, "runtime": {**params["runtime"], "stall_limit_s": 0.05}}
    stalled = cycles[:150] + cycles[162:]
    on_the_car = car(params, t0, {})
    on_the_car.stall_limit_s = 0.05  # as the daemon builds it
    on_car = record(tmp_path / "stall.rx.jsonl", t0, params, stalled, on_the_car)
    assert sum(o.stall_s > 0 for o in on_car) == 1
    again = replay(tmp_path / "stall.rx.jsonl")
    assert differences(on_car, again) == (0.0, 0)
    assert sum(o.stall_s > 0 for o in again) == 1

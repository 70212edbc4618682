"""The simulated firmware as its own real-time process, for the daemon's HIL tests.

Usage::

    python -m truckd.sim.firmware_main --pty PATH [--link serial|slcan] [--config FILE]
        [--scenario NAME] [--lead-gap M] [--lead-speed M/S]
        [--lead MODULE:FACTORY [--lead-arg STR]] [--no-lead] [--control-port N]
        [--duration S] [--tick S]

It creates a pty whose slave is reachable at PATH (a symlink; the daemon opens it as its
serial device; with ``--link slcan`` it is a simulated CANable-style slcan adapter that
the daemon opens with python-can ``interface="slcan"``, and the C firmware core speaks
CAN frames instead of COBS serial frames), prints one JSON line ``{"ready": true,
"device": PATH, "control_port": N, "pid": P}`` on stdout, then runs the plant and
firmware in real time.  The lead is the built-in constant-speed lead (``--lead-gap``,
``--lead-speed``) or a scenario of :mod:`truckd.sim.scenarios` (``--scenario NAME``: its
lead, sensor view and initial ego speed, with t = 0 at process start), or
``FACTORY(arg: str) -> range_fn`` imported from MODULE (any other hook).

Faults are switched at run time with JSON datagrams to ``127.0.0.1:control_port`` (UDP):
any :meth:`SimulatedFirmware.apply_fault` command, ``{"cmd": "lead", "gap": M,
"speed": M/S}`` (a new constant-speed lead, gap measured from now; the reply carries
``t`` and ``x``, the time and the truck's position it is measured from), ``{"cmd":
"status"}`` (replies with a JSON status datagram: time, state, speed, position, voltage
applied, the last valid command, counters) and ``{"cmd": "stop"}``.  Every
datagram gets a JSON reply: ``{"ok": true, ...}`` or ``{"ok": false, "error": ...}``.
SIGTERM/SIGINT stop it cleanly (the symlink is removed).
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import signal
import socket
import sys
import time
from collections import deque
from collections.abc import Sequence
from typing import Any

from truckd.config.truck import TruckConfig, load_config
from truckd.errors import InputError
from truckd.sim.firmware import RangeFn, SimulatedFirmware, constant_speed_lead
from truckd.sim.pty_link import PtyDevice
from truckd.sim.slcan_peer import SlcanDevice
from truckd.sim.truck import build_truck, truck_spec


def _no_lead(t: float, x: float) -> float | None:
    return None


def _load_lead(spec: str, arg: str) -> RangeFn:
    module, _, attr = spec.partition(":")
    if not module or not attr:
        raise InputError(f"--lead {spec!r}: expected MODULE:FACTORY")
    try:
        factory = getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        raise InputError(f"--lead {spec!r}: {exc}") from None
    fn = factory(arg)
    if not callable(fn):
        raise InputError(f"--lead {spec!r}: factory did not return a callable")
    return fn  # type: ignore[no-any-return]


def _scenario_lead(name: str, cfg: TruckConfig) -> tuple[RangeFn, float]:
    """The scenario's range_fn and the ego's initial speed (m/s)."""
    from truckd.sim.scenarios import World, make_scenario

    try:
        sc = make_scenario(name, cfg.vehicle, cfg.control)
    except ValueError as exc:
        raise InputError(f"--scenario: {exc}") from None
    return World(sc).range_fn, sc.v0


class _Shifted:
    """A constant-speed lead that starts ``gap`` ahead of the ego at time ``t0``."""

    def __init__(self, t0: float, x0: float, gap: float, speed: float) -> None:
        self.t0, self.x0, self.gap, self.speed = t0, x0, gap, speed

    def __call__(self, t: float, x: float) -> float | None:
        return self.x0 + self.gap + self.speed * (t - self.t0) - x


RIG_STALL_S = 0.02
"""A pass of the firmware's loop that starts this much later than due (wall clock) is
recorded as a stall of the rig."""


def _handle(
    fw: SimulatedFirmware, cmd: Any, stalls: Sequence[tuple[float, float]] = ()
) -> tuple[dict[str, Any], bool]:
    """Apply one control command; (reply, stop).  ``stalls``: the rig's own recent stalls
    (reported by ``status``)."""
    if not isinstance(cmd, dict):
        return {"ok": False, "error": "expected a JSON object"}, False
    what = cmd.get("cmd")
    if what == "stop":
        return {"ok": True}, True
    if what == "status":
        st = fw.link_stats()
        last = fw.last_command
        return {
            "ok": True,
            "t": fw.t,
            "state": fw.state.name,
            "v": fw.plant.v,
            "x": fw.plant.x,
            "voltage": fw.voltage,
            # before the first command: what the firmware holds (0 V, motor disabled)
            "last_command": {"voltage": 0.0, "enable": False}
            if last is None
            else {"voltage": last.voltage, "enable": last.enable},
            "firmware": vars(fw.stats),
            "rx": st,
            # This process's own stalls (start, end on the shared monotonic clock): passes
            # of its loop that began over RIG_STALL_S late, e.g. after a read of the pty
            # waited for the kernel's normal-priority tty worker on a busy host.  Tests
            # use them to tell a late rig from a daemon that stopped sending.
            "rig_stalls": [list(x) for x in stalls],
        }, False
    if what == "lead":
        gap, speed = cmd.get("gap"), cmd.get("speed", 0.0)
        if gap is None:
            fw.range_fn = _no_lead
        elif isinstance(gap, int | float) and isinstance(speed, int | float):
            fw.range_fn = _Shifted(fw.t, fw.plant.x, float(gap), float(speed))
        else:
            return {"ok": False, "error": "lead: gap and speed must be numbers"}, False
        return {"ok": True, "t": fw.t, "x": fw.plant.x}, False  # where the lead starts
    try:
        fw.apply_fault(cmd)
    except ValueError as exc:
        return {"ok": False, "error": str(exc)}, False
    return {"ok": True}, False


def serve_truck(
    cfg: TruckConfig, range_fn: RangeFn, link: str, pty: str, v0: float = 0.0
) -> SimulatedFirmware:
    """The configuration's simulated truck (:func:`truckd.sim.truck.truck_spec`) serving
    a pty at ``pty``: COBS frames (``link`` ``serial``) or a simulated slcan adapter."""
    kind = SlcanDevice if link == "slcan" else PtyDevice
    truck = build_truck(
        truck_spec(cfg), range_fn, device=lambda clock: kind(pty, clock=clock), v0=v0
    )
    return truck.firmware


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m truckd.sim.firmware_main", description=__doc__.split("\n")[0]
    )
    ap.add_argument("--pty", required=True, help="path of the symlink to the pty slave")
    ap.add_argument(
        "--link",
        choices=("serial", "slcan"),
        default="serial",
        help="serial: COBS frames on the pty; slcan: CAN frames through a simulated adapter",
    )
    ap.add_argument("--config", default=None, help="truck.yaml (default: the shipped one)")
    ap.add_argument("--scenario", default=None, help="lead of a truckd sim scenario")
    ap.add_argument("--lead-gap", type=float, default=2.0, help="built-in lead: start gap, m")
    ap.add_argument("--lead-speed", type=float, default=1.0, help="built-in lead speed, m/s")
    ap.add_argument("--lead", default=None, help="MODULE:FACTORY; FACTORY(arg) -> range_fn")
    ap.add_argument("--lead-arg", default="", help="argument passed to the --lead factory")
    ap.add_argument("--no-lead", action="store_true", help="no target in range")
    ap.add_argument("--control-port", type=int, default=0, help="UDP port on 127.0.0.1 (0: any)")
    ap.add_argument("--duration", type=float, default=0.0, help="stop after S s (0: run on)")
    ap.add_argument("--tick", type=float, default=0.001, help="simulation step, s")
    args = ap.parse_args(argv)
    v0 = 0.0
    try:
        cfg = load_config(args.config)
        if args.no_lead:
            range_fn: RangeFn = _no_lead
        elif args.scenario:
            range_fn, v0 = _scenario_lead(args.scenario, cfg)
        elif args.lead:
            range_fn = _load_lead(args.lead, args.lead_arg)
        else:
            range_fn = constant_speed_lead(args.lead_gap, args.lead_speed)
    except InputError as exc:
        print(f"firmware_main: {exc}", file=sys.stderr)
        return 2
    if not 1e-4 <= args.tick <= 0.05:
        print("firmware_main: --tick must be in [0.0001, 0.05] s", file=sys.stderr)
        return 2
    fw = serve_truck(cfg, range_fn, args.link, args.pty, v0)
    dev = fw.link
    ctl = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ctl.bind(("127.0.0.1", args.control_port))
    ctl.setblocking(False)
    stop = False

    def _term(signum: int, frame: object) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGTERM, _term)
    signal.signal(signal.SIGINT, _term)
    ready = {"ready": True, "device": args.pty, "control_port": ctl.getsockname()[1]}
    print(json.dumps(ready | {"pid": os.getpid()}), flush=True)
    try:
        stop = _run(fw, ctl, args.tick, args.duration, lambda: stop)
    finally:
        dev.close()
        ctl.close()
    return 0


def _run(
    fw: SimulatedFirmware, ctl: socket.socket, tick: float, duration: float, stopped: Any
) -> bool:
    start = time.monotonic()
    t_sim = 0.0
    stalls: deque[tuple[float, float]] = deque(maxlen=64)
    top = start

    def mark() -> float:
        # Called at the start of each pass and before each control command: more than
        # RIG_STALL_S past due (the last mark plus a tick) means the process was held up
        # somewhere in between (a slow read of the pty, a late wake-up, the process
        # stopped): a stall of the rig, wherever it happened.
        nonlocal top
        t = time.monotonic()
        if t - top > tick + RIG_STALL_S:
            stalls.append((top + tick, t))
        top = t
        return t

    while not stopped():
        now = mark() - start
        if duration and now >= duration:
            return True
        while True:
            try:
                data, addr = ctl.recvfrom(65536)
            except BlockingIOError:
                break
            mark()  # a status reports a stall that ended just now
            try:
                cmd = json.loads(data)
            except ValueError:
                reply, halt = {"ok": False, "error": "not JSON"}, False
            else:
                reply, halt = _handle(fw, cmd, stalls)
            ctl.sendto(json.dumps(reply).encode(), addr)
            if halt:
                return True
        dt = now - t_sim
        if dt > 0.0:
            fw.step(min(dt, 0.05))  # after a stall, catch up in bounded steps
            t_sim += min(dt, 0.05)
        nxt = start + t_sim + tick
        pause = nxt - time.monotonic()
        if pause > 0:
            time.sleep(pause)
    return True


if __name__ == "__main__":
    raise SystemExit(main())

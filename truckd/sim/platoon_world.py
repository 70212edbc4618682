"""N simulated trucks in one real-time process, each with its firmware on its own pty,
for the platoon's HIL run (separate ``truckd run`` daemons on the serial backend).

Usage::

    python -m truckd.sim.platoon_world --pty-dir DIR --trucks N [--config FILE]
        [--gap M] [--parked K] [--control-port N] [--tick S]

Truck i's firmware is on ``DIR/tty<i>`` (a symlink to the pty slave).  Every truck starts
at rest in lane 0, ``--gap`` behind the one ahead, truck 0 ``--gap`` behind a virtual lead
standing until told to drive; with ``--parked K`` the last K trucks start parked off the
road (lane 2: they see nothing and nothing sees them).  A truck's range sensor sees the
nearest vehicle ahead of it in lane 0 (the lead included); a truck in lane 1 sees the
truck it was put beside to join behind, else nothing (it left).  Prints one JSON line
``{"ready": true, "devices": [...], "control_port": N, "pid": P}``, then runs in real time.

Control: JSON datagrams to ``127.0.0.1:control_port`` (UDP), each answered:
``{"cmd": "status"}`` (time, positions, speeds, lanes, the lead's, the firmware states),
``{"cmd": "lead", "speed": S, "accel": A}`` (the virtual lead changes speed towards S
m/s at |A| m/s^2), ``{"cmd": "leave", "truck": I}`` (truck I moves to lane 1: the truck
behind it now sees the next one ahead), ``{"cmd": "beside", "truck": I, "behind": J,
"gap": G}`` (truck I is put in lane 1, G m behind truck J, at J's speed: a truck about to
join behind J; its range sensor sees J), ``{"cmd": "merge", "truck": I}`` (truck I moves
to lane 0, where it is), ``{"cmd": "stop"}``.  SIGTERM/SIGINT stop it cleanly.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import socket
import sys
import time
from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import Any

from truckd.config.truck import load_config
from truckd.errors import InputError
from truckd.sim.firmware import SimulatedFirmware
from truckd.sim.plant import Plant
from truckd.sim.pty_link import PtyDevice
from truckd.sim.truck import build_truck, truck_spec


class VirtualLead:
    """A lead vehicle in front of truck 0: speed ramps towards a target (m/s, m/s^2)."""

    def __init__(self, x: float) -> None:
        self.x, self.v, self.target, self.accel = x, 0.0, 0.0, 0.0

    def step(self, dt: float) -> None:
        dv = self.target - self.v
        step = abs(self.accel) * dt
        v_new = self.target if abs(dv) <= step else self.v + math.copysign(step, dv)
        self.x += 0.5 * (self.v + v_new) * dt
        self.v = v_new


class World:
    """The trucks, their firmware and the lead (see module docstring)."""

    def __init__(
        self, pty_dir: Path, n: int, gap: float, config: str | None, parked: int = 0
    ) -> None:
        spec = truck_spec(load_config(config))
        self.lead = VirtualLead(gap)
        self.plants: list[Plant] = []
        self.fws: list[SimulatedFirmware] = []
        self.devices: list[PtyDevice] = []
        self.lanes = [0] * (n - parked) + [2] * parked
        self.behind: dict[int, int] = {}
        """Trucks in lane 1 about to join: truck -> the truck it joins behind."""
        for i in range(n):
            device = partial(PtyDevice, str(pty_dir / f"tty{i}"))
            truck = build_truck(spec, self._range_fn(i), device=device, x0=-i * gap)
            assert isinstance(truck.firmware.link, PtyDevice)
            self.plants.append(truck.plant)
            self.devices.append(truck.firmware.link)
            self.fws.append(truck.firmware)

    def _range_fn(self, i: int) -> Any:
        def fn(t: float, x: float) -> float | None:
            if self.lanes[i] != 0:
                j = self.behind.get(i) if self.lanes[i] == 1 else None
                return max(self.plants[j].x - x, 0.0) if j is not None else None
            ahead = [
                p.x for j, p in enumerate(self.plants) if j != i and self.lanes[j] == 0 and p.x > x
            ]
            return max(min([*ahead, self.lead.x]) - x, 0.0)

        return fn

    def step(self, dt: float) -> None:
        """Advance everything by dt (s): the lead first, then the trucks front to back."""
        self.lead.step(dt)
        for fw in self.fws:
            fw.step(dt)

    def status(self) -> dict[str, Any]:
        return {
            "ok": True,
            "t": self.fws[0].t,
            "x": [p.x for p in self.plants],
            "v": [p.v for p in self.plants],
            "lanes": list(self.lanes),
            "lead_x": self.lead.x,
            "lead_v": self.lead.v,
            "states": [fw.state.name for fw in self.fws],
        }

    def handle(self, cmd: Any) -> tuple[dict[str, Any], bool]:
        if not isinstance(cmd, dict):
            return {"ok": False, "error": "expected a JSON object"}, False
        what = cmd.get("cmd")
        if what == "stop":
            return {"ok": True}, True
        if what == "status":
            return self.status(), False
        if what == "lead":
            speed, accel = cmd.get("speed"), cmd.get("accel", 1.0)
            if not (
                isinstance(speed, int | float)
                and isinstance(accel, int | float)
                and math.isfinite(speed)
                and math.isfinite(accel)
            ):
                return {"ok": False, "error": "lead: speed and accel must be numbers"}, False
            self.lead.target, self.lead.accel = max(float(speed), 0.0), float(accel)
            return {"ok": True}, False
        if what == "leave":
            i = cmd.get("truck")
            if not (isinstance(i, int) and 0 <= i < len(self.lanes)):
                return {
                    "ok": False,
                    "error": f"leave: truck must be 0..{len(self.lanes) - 1}",
                }, False
            self.lanes[i] = 1
            self.behind.pop(i, None)
            return {"ok": True}, False
        if what == "beside":
            return self._beside(cmd), False
        if what == "merge":
            i = cmd.get("truck")
            if not (isinstance(i, int) and i in self.behind):
                return {"ok": False, "error": "merge: not a truck put beside"}, False
            self.lanes[i] = 0
            del self.behind[i]
            return {"ok": True}, False
        return {"ok": False, "error": f"unknown command {what!r}"}, False

    def _beside(self, cmd: dict[str, Any]) -> dict[str, Any]:
        i, j, gap = cmd.get("truck"), cmd.get("behind"), cmd.get("gap")
        n = len(self.lanes)
        if not (
            isinstance(i, int)
            and isinstance(j, int)
            and 0 <= i < n
            and 0 <= j < n
            and i != j
            and isinstance(gap, int | float)
            and 0.0 < gap < 100.0
        ):
            return {"ok": False, "error": "beside: truck, behind (0..n-1, apart) and gap (m)"}
        ahead = self.plants[j]
        self.plants[i].hold(ahead.v, ahead.x - float(gap))
        self.lanes[i], self.behind[i] = 1, j
        return {"ok": True}

    def close(self) -> None:
        for d in self.devices:
            d.close()


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m truckd.sim.platoon_world", description=__doc__.split("\n")[0]
    )
    ap.add_argument("--pty-dir", required=True, help="directory for the tty<i> symlinks")
    ap.add_argument("--trucks", type=int, default=3)
    ap.add_argument("--config", default=None, help="truck.yaml (default: the shipped one)")
    ap.add_argument("--gap", type=float, default=0.8, help="start gap between trucks, m")
    ap.add_argument(
        "--parked", type=int, default=0, help="the last K trucks start parked off the road"
    )
    ap.add_argument("--control-port", type=int, default=0, help="UDP port on 127.0.0.1")
    ap.add_argument("--tick", type=float, default=0.001, help="simulation step, s")
    args = ap.parse_args(argv)
    if not 1 <= args.trucks <= 10 or not 0.1 <= args.gap <= 4.0 or not 1e-4 <= args.tick <= 0.05:
        print("platoon_world: --trucks 1..10, --gap 0.1..4 m, --tick 1e-4..0.05 s", file=sys.stderr)
        return 2
    if not 0 <= args.parked < args.trucks:
        print("platoon_world: --parked 0..trucks-1", file=sys.stderr)
        return 2
    try:
        world = World(Path(args.pty_dir), args.trucks, args.gap, args.config, args.parked)
    except InputError as exc:
        print(f"platoon_world: {exc}", file=sys.stderr)
        return 2
    ctl = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ctl.bind(("127.0.0.1", args.control_port))
    ctl.setblocking(False)
    stop = False

    def _term(signum: int, frame: object) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGTERM, _term)
    signal.signal(signal.SIGINT, _term)
    devices = [str(Path(args.pty_dir) / f"tty{i}") for i in range(args.trucks)]
    ready = {"ready": True, "devices": devices, "control_port": ctl.getsockname()[1]}
    print(json.dumps(ready | {"pid": os.getpid()}), flush=True)
    start = time.monotonic()
    t_sim = 0.0
    try:
        while not stop:
            while True:
                try:
                    data, addr = ctl.recvfrom(65536)
                except BlockingIOError:
                    break
                try:
                    reply, halt = world.handle(json.loads(data))
                except ValueError:
                    reply, halt = {"ok": False, "error": "not JSON"}, False
                ctl.sendto(json.dumps(reply).encode(), addr)
                stop = stop or halt
            dt = min(time.monotonic() - start - t_sim, 0.05)  # after a stall: bounded steps
            if dt > 0.0:
                world.step(dt)
                t_sim += dt
            pause = start + t_sim + args.tick - time.monotonic()
            if pause > 0:
                time.sleep(pause)
    finally:
        world.close()
        ctl.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

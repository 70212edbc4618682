"""Protocol figures: decode/encode throughput against the 500 kbit/s bus maximum, bus and
serial load, and the 10^6-mutation fuzz of both decoders.

    python benchmarks/protocol_bench.py [--fuzz N] [--json FILE]

Prints a table; ``--json FILE`` writes the figures.  Single process, one core.
"""

from __future__ import annotations

import argparse
import json
import platform
import random
import time
from collections.abc import Callable

import lab_path  # noqa: F401 - tests/ on sys.path, for labkit
from labkit.fuzz import fuzz_codec, fuzz_deframer

from firmware_protocol.busload import can_bus_load, can_frame_bits, loads, serial_load
from firmware_protocol.checks import RxChecker
from firmware_protocol.codec import decode, encode
from firmware_protocol.framing import Deframer, frame_to_bytes
from firmware_protocol.messages import (
    FirmwareFault,
    FirmwareHeartbeat,
    FirmwareState,
    MotorCommand,
    MotorFeedback,
    RangeReading,
    RangeStatus,
    WheelEncoders,
)


def _rate(fn: Callable[[], int], min_time: float = 0.5) -> float:
    """Items per second of ``fn`` (returns the items it processed), best of 3."""
    best = 0.0
    for _ in range(3):
        n = 0
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < min_time:
            n += fn()
        best = max(best, n / (time.perf_counter() - t0))
    return best


def _sim_cycle_us(mode: str, cycles: int = 2000) -> float:
    """Wall time (us) of one 10 ms control cycle of the simulated truck: command, firmware
    step (plant + messages), companion receive with checks."""
    from truckd.config.truck import load_config
    from truckd.io.port import companion_port
    from truckd.sim.firmware import constant_speed_lead
    from truckd.sim.truck import build_truck, truck_spec

    truck = build_truck(truck_spec(load_config()), constant_speed_lead(2.0, 1.0), mode=mode)  # type: ignore[arg-type]
    fw, link = truck.firmware, truck.link
    assert link is not None
    port = companion_port(link, clock=lambda: fw.t)
    t0 = time.perf_counter()
    for _ in range(cycles):
        port.send(MotorCommand(3.0, True))
        fw.step(0.01)
        port.poll()
    return (time.perf_counter() - t0) / cycles * 1e6


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--fuzz", type=int, default=1_000_000, help="mutations per decoder")
    ap.add_argument("--json", default=None, help="write the figures to this file")
    args = ap.parse_args()

    r = random.Random(0)
    msgs = [WheelEncoders(r.randrange(65536), r.randrange(65536), 1.0, 0) for _ in range(50)] + [
        MotorFeedback(r.uniform(-20, 20), 7.2, r.uniform(-7, 7), 1) for _ in range(50)
    ]
    msgs += [RangeReading(r.uniform(0, 4), RangeStatus.VALID, 0.5) for _ in range(25)]
    msgs += [FirmwareHeartbeat(FirmwareState.ACTIVE, FirmwareFault.NONE, 0) for _ in range(5)]
    frames = [encode(m, k) for k, m in enumerate(msgs)]
    wire = b"".join(frame_to_bytes(f) for f in frames)

    def dec() -> int:
        for f in frames:
            decode(f)
        return len(frames)

    def enc() -> int:
        for k in range(100):
            encode(MotorCommand(0.01 * k, True), k)
        return 100

    checker = RxChecker(expect=["WHEEL_ENCODERS", "MOTOR_FEEDBACK", "RANGE", "FIRMWARE_HEARTBEAT"])
    clock = [0.0]

    def chk() -> int:
        clock[0] += 0.01
        for f in frames:
            checker.accept(f, clock[0])
        return len(frames)

    deframer = Deframer()

    def dfr() -> int:
        return len(deframer.feed(wire))

    sim_us = {mode: _sim_cycle_us(mode) for mode in ("frames", "bytes")}
    bus_max = 500_000 / can_frame_bits(8)  # 8-byte frames/s, worst-case stuffing
    bus_max_nostuff = 500_000 / can_frame_bits(8, worst_case_stuffing=False)
    rates = {
        "decode (codec)": _rate(dec),
        "decode + receive checks": _rate(chk),
        "deframe (serial bytes -> frames)": _rate(dfr),
        "encode MOTOR_CMD": _rate(enc),
    }
    print(f"machine: {platform.processor() or platform.machine()}, {platform.python_version()}")
    print(f"\n{'operation':36s} {'frames/s':>12s} {'x bus max':>10s}")
    for k, v in rates.items():
        print(f"{k:36s} {v:12.0f} {v / bus_max:10.1f}")
    print(
        f"500 kbit/s bus maximum: {bus_max:.0f} frames/s (8-byte, worst-case stuffing), "
        f"{bus_max_nostuff:.0f} without stuffing"
    )

    for mode, us in sim_us.items():
        print(
            f"simulated firmware + companion port ({mode}): {us:.0f} us per 10 ms cycle "
            f"({1e4 / us:.0f}x real time)"
        )
    print(
        f"\n{'message':22s} {'bytes':>5s} {'period ms':>9s} {'CAN bit/s':>10s} {'serial B/s':>10s}"
    )
    for ld in loads():
        print(
            f"{ld.name:22s} {ld.length:5d} {ld.period * 1e3:9.0f} {ld.can_bits_per_s:10.0f} "
            f"{ld.serial_bytes_per_s:10.0f}"
        )
    load = can_bus_load(500_000)
    up, down = serial_load(115_200)
    print(f"CAN bus load at 500 kbit/s (worst-case stuffing): {100 * load:.2f} %")
    print(
        f"serial load at 115200 baud: MCU->companion {100 * up:.1f} %, "
        f"companion->MCU {100 * down:.1f} %"
    )

    print(f"\nfuzz: {args.fuzz} mutations per decoder")
    t0 = time.perf_counter()
    fc = fuzz_codec(args.fuzz, seed=100)
    t1 = time.perf_counter()
    fd = fuzz_deframer(args.fuzz, seed=101)
    t2 = time.perf_counter()
    print(
        f"{'decoder':10s} {'mutated':>9s} {'escaped':>7s} {'accepted':>8s} {'rate':>10s} "
        f"{'bound':>8s} {'intact lost':>11s} {'s':>6s}"
    )
    for name, fr, dt in (("codec", fc, t1 - t0), ("deframer", fd, t2 - t1)):
        print(
            f"{name:10s} {fr.mutated:9d} {fr.escaped:7d} {fr.accepted_corrupt:8d} "
            f"{fr.accept_rate:10.2e} {fr.bound():8.0f} {fr.intact_lost:11d} {dt:6.1f}"
        )
    print(
        f"  (random-acceptance bound: 2^-8 = {2**-8:.2e} for CHECKSUM, "
        f"2^-16 = {2**-16:.2e} for the frame CRC)"
    )
    ok = all(
        x.escaped == 0 and x.accepted_corrupt <= x.bound() and x.intact_lost == 0 for x in (fc, fd)
    )
    print("fuzz verdict:", "PASS" if ok else "FAIL")

    if args.json:
        out = {
            "machine": platform.processor() or platform.machine(),
            "python": platform.python_version(),
            "frames_per_s": rates,
            "sim_firmware_us_per_10ms_cycle": sim_us,
            "bus_max_frames_per_s": bus_max,
            "bus_max_frames_per_s_no_stuffing": bus_max_nostuff,
            "can_bus_load_500k": load,
            "serial_load_115200": {"mcu_to_companion": up, "companion_to_mcu": down},
            "messages": [vars(ld) for ld in loads()],
            "fuzz": {"codec": fc.as_dict(), "deframer": fd.as_dict()},
            "fuzz_pass": ok,
        }
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(out, f, indent=2)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())

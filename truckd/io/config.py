"""The ``link`` section of the configuration file: which transport, and its settings."""

from __future__ import annotations

from dataclasses import dataclass

from truckd.schema import spec

ENCODER_TICKS_PER_REV = 512
"""The default of ``link.encoder_ticks_per_rev`` (the firmware's encoder).  Everything else
takes the configured value (``TruckConfig.ticks_per_rev``); the simulator's own defaults
take this one."""


@dataclass(frozen=True)
class LinkConfig:
    """Transport to the microcontroller and the receive-check settings."""

    serial_device: str = spec(
        "serial device path or pyserial URL of the microcontroller", default="/dev/ttyACM0"
    )
    serial_baudrate: int = spec(
        "serial baud rate", unit="bit/s", lo=9600, hi=12_000_000, default=115200
    )
    can_interface: str = spec("python-can interface name", default="socketcan")
    can_channel: str = spec("python-can channel", default="can0")
    can_bitrate: int = spec("CAN bit rate", unit="bit/s", lo=10_000, hi=1_000_000, default=500_000)
    reconnect_interval: float = spec(
        "pause between reopen attempts of a vanished device",
        unit="s",
        lo=0.0,
        hi=60.0,
        default=0.5,
    )
    timeout_periods: float = spec(
        "freshness timeout of each received message, in multiples of its period",
        lo=1.0,
        hi=100.0,
        default=5.0,
    )
    encoder_ticks_per_rev: int = spec(
        "encoder ticks per wheel revolution the firmware counts (the simulated firmware "
        "uses plant.encoder_ticks_per_rev instead when that is > 0)",
        lo=1,
        hi=65535,
        default=ENCODER_TICKS_PER_REV,
    )

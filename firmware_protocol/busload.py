"""Bus and line load of the protocol (pure arithmetic on the DBC's lengths and periods).

CAN 2.0A data frame with n payload bytes: 47 + 8n bits including the 3-bit interframe
space; bit stuffing can add up to floor((34 + 8n - 1) / 4) bits (worst case).  Serial:
10 bits per byte (8N1), wire bytes per frame = 2 delimiters + COBS(2 + n + 2).
"""

from __future__ import annotations

from dataclasses import dataclass

from firmware_protocol.codec import specs


def can_frame_bits(n: int, worst_case_stuffing: bool = True) -> int:
    """Bits on the bus for one standard-id data frame with ``n`` payload bytes."""
    bits = 47 + 8 * n
    return bits + ((34 + 8 * n - 1) // 4 if worst_case_stuffing else 0)


def serial_frame_bytes(n: int) -> int:
    """Wire bytes of one serial frame with ``n`` payload bytes (no 254-byte blocks)."""
    return 2 + 1 + 2 + n + 2


@dataclass(frozen=True)
class Load:
    """Load of one message at its period."""

    name: str
    length: int
    period: float
    rate_hz: float
    can_bits_per_s: float
    serial_bytes_per_s: float


def loads() -> list[Load]:
    """Every periodic message of truck.dbc."""
    out = []
    for s in specs().values():
        rate = 1.0 / s.period
        out.append(
            Load(
                s.name,
                s.length,
                s.period,
                rate,
                rate * can_frame_bits(s.length),
                rate * serial_frame_bytes(s.length),
            )
        )
    return out


def can_bus_load(bitrate: float = 500_000.0) -> float:
    """Fraction of a CAN bus the protocol uses (worst-case stuffing)."""
    return sum(ld.can_bits_per_s for ld in loads()) / bitrate


def serial_load(baudrate: float = 115_200.0) -> tuple[float, float]:
    """Fraction of each serial direction used: (MCU -> companion, companion -> MCU)."""
    from_mcu = sum(
        ld.serial_bytes_per_s for ld in loads() if specs()[ld.name].dbc.senders == ["MCU"]
    )
    to_mcu = sum(ld.serial_bytes_per_s for ld in loads()) - from_mcu
    return from_mcu * 10 / baudrate, to_mcu * 10 / baudrate

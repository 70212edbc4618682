"""The two checksums of the protocol (pure functions on bytes).

- CRC-8/SAE-J1850 (poly 0x1D, init 0xFF, xorout 0xFF): the ``CHECKSUM`` signal of every
  message, computed over the 11-bit id as 2 bytes little-endian and the payload bytes
  before the checksum byte (the checksum is always the last payload byte).
- CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, xorout 0): the serial frame check.

Check values (the catalogue's "123456789" test): CRC-8 0x4B, CRC-16 0x29B1.
"""

from __future__ import annotations

import binascii


def _table8(poly: int) -> tuple[int, ...]:
    out = []
    for b in range(256):
        c = b
        for _ in range(8):
            c = ((c << 1) ^ poly) & 0xFF if c & 0x80 else (c << 1) & 0xFF
        out.append(c)
    return tuple(out)


def _table16(poly: int) -> tuple[int, ...]:
    out = []
    for b in range(256):
        c = b << 8
        for _ in range(8):
            c = ((c << 1) ^ poly) & 0xFFFF if c & 0x8000 else (c << 1) & 0xFFFF
        out.append(c)
    return tuple(out)


_T8 = _table8(0x1D)
_T16 = _table16(0x1021)


def crc8_j1850(data: bytes | bytearray | memoryview) -> int:
    """CRC-8/SAE-J1850 of ``data``."""
    c = 0xFF
    t = _T8
    for b in bytes(data):
        c = t[c ^ b]
    return c ^ 0xFF


def crc16_ccitt(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (the standard library's C ``crc_hqx`` with init
    0xFFFF: the same polynomial, no reflection; the serial framing's per-byte cost)."""
    return binascii.crc_hqx(data, 0xFFFF)


def crc16_ccitt_table(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE by table in Python (the reference :func:`crc16_ccitt` is tested
    against)."""
    c = 0xFFFF
    t = _T16
    for b in bytes(data):
        c = ((c << 8) & 0xFFFF) ^ t[(c >> 8) ^ b]
    return c


_ID_STATE: dict[int, int] = {}
"""The CRC-8 register after the 2 id bytes, per CAN id (the id prefix is constant)."""


def _id_state(can_id: int) -> int:
    c = 0xFF
    for b in (can_id & 0xFF, (can_id >> 8) & 0xFF):
        c = _T8[c ^ b]
    _ID_STATE[can_id] = c
    return c


def message_checksum(can_id: int, payload_without_checksum: bytes | bytearray) -> int:
    """The ``CHECKSUM`` signal value of a message: CRC-8 over id (2 bytes LE) + payload
    (the register after the id is cached per id: the same value, fewer steps)."""
    c = _ID_STATE.get(can_id)
    if c is None:
        c = _id_state(can_id)
    t = _T8
    for b in payload_without_checksum:
        c = t[c ^ b]
    return c ^ 0xFF

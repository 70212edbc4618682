"""Receive checks: checksum, counter continuity, freshness, statistics."""

from __future__ import annotations

import pytest

from firmware_protocol.checks import RxChecker
from firmware_protocol.codec import Frame, encode
from firmware_protocol.messages import MotorCommand, RangeReading, RangeStatus


def rng(c: int, d: float = 1.0) -> Frame:
    return encode(RangeReading(d, RangeStatus.VALID, 0.0), c)


def test_in_sequence_frames_pass() -> None:
    ch = RxChecker(expect=["RANGE"])
    for k in range(40):
        assert ch.accept(rng(k), 0.02 * k) is not None
    assert ch.stats.frames_ok == 40
    assert ch.stats.counter_gaps == ch.stats.counter_errors == ch.stats.timeouts == 0


def test_repeated_counter_rejected() -> None:
    ch = RxChecker(expect=["RANGE"])
    assert ch.accept(rng(3), 0.0) is not None
    assert ch.accept(rng(3, 2.0), 0.02) is None
    assert ch.stats.counter_errors == 1
    assert ch.accept(rng(4), 0.04) is not None


def test_gap_counted_and_accepted() -> None:
    ch = RxChecker(expect=["RANGE"])
    ch.accept(rng(0), 0.0)
    assert ch.accept(rng(4), 0.1) is not None  # 1, 2, 3 lost
    assert ch.stats.counter_gaps == 3


def test_broken_counter_rejected_until_it_recovers() -> None:
    ch = RxChecker(expect=["RANGE"], max_wrong_counters=3, timeout_periods=100)
    ch.accept(rng(0), 0.0)
    accepted = [ch.accept(rng(2 * k), 0.02 * k) is not None for k in range(1, 10)]
    assert accepted[:3] == [True] * 3 and not any(accepted[3:])
    # the score is capped at 2 x 3 = 6; in-sequence frames bring it to 5, 4 (rejected),
    # then 3 (accepted again)
    c = 18 % 16
    results = [ch.accept(rng(c + k), 0.2 + 0.02 * k) is not None for k in range(1, 6)]
    assert results == [False, False, True, True, True]


def test_checksum_and_length_and_unexpected() -> None:
    ch = RxChecker(expect=["RANGE"])
    f = rng(0)
    assert ch.accept(Frame(f.can_id, f.data[:-1] + bytes((f.data[-1] ^ 0xFF,))), 0.0) is None
    assert ch.accept(Frame(f.can_id, f.data[:-1]), 0.0) is None
    assert ch.accept(Frame(0x555, f.data), 0.0) is None
    assert ch.accept(encode(MotorCommand(1.0, True), 0), 0.0) is None
    s = ch.stats
    assert (s.checksum_errors, s.length_errors, s.unknown_ids, s.unexpected) == (1, 1, 1, 1)
    assert s.frames_ok == 0


def test_freshness_timeout_counted_once() -> None:
    ch = RxChecker(expect=["RANGE"], timeout_periods=5)  # 5 x 20 ms
    assert not ch.fresh("RANGE", 0.0)  # never received
    ch.accept(rng(0), 1.0)
    assert ch.fresh("RANGE", 1.099)
    assert not ch.fresh("RANGE", 1.101)
    assert not ch.fresh("RANGE", 2.0)
    assert ch.stats.timeouts == 1
    assert ch.age("RANGE", 2.0) == pytest.approx(1.0)
    # after a timeout any counter is accepted (no gap counted across the outage)
    assert ch.accept(rng(9), 2.0) is not None
    assert ch.stats.counter_gaps == 0
    assert ch.freshness(2.01) == {"RANGE": True}


def test_unknown_expected_name() -> None:
    with pytest.raises(ValueError, match="unknown message"):
        RxChecker(expect=["NOPE"])

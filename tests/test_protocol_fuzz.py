"""10^5 mutated frames per decoder (the benchmark runs 10^6): nothing escapes but the
documented error, corrupt acceptances stay within the check width's bound, and no intact
frame is lost after garbage."""

from __future__ import annotations

from labkit.fuzz import fuzz_codec, fuzz_deframer

N = 100_000


def test_codec_fuzz() -> None:
    r = fuzz_codec(N, seed=11)
    assert r.mutated == N
    assert r.escaped == 0
    assert r.single_bit_accepted == 0  # a CRC detects every single-bit error
    assert r.accepted_corrupt <= r.bound()  # 2^-8 for the 8-bit CHECKSUM
    assert r.rejected + r.accepted_corrupt + r.escaped == N


def test_deframer_fuzz() -> None:
    r = fuzz_deframer(N, seed=12)
    assert r.mutated == N and r.intact == N
    assert r.escaped == 0
    assert r.intact_lost == 0
    assert r.accepted_corrupt <= r.bound()  # 2^-16 for the frame CRC-16

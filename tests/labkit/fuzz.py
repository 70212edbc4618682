"""Mutation fuzzing of the two decoders (pure, seeded; used by tests and benchmarks).

- :func:`fuzz_codec`: valid CAN frames of every message, mutated (bit flips, byte
  changes, truncation/extension, id changes), through :func:`codec.decode`.
- :func:`fuzz_deframer`: a serial stream of intact frames, mutated frames and garbage
  bursts, fed in random chunks through :class:`framing.Deframer`.

Both report exceptions other than the documented ones (must be 0), corrupt frames that
were accepted (bounded by the check's width: 2^-8 for CHECKSUM, 2^-16 for the frame
CRC), and for the deframer the intact frames lost (must be 0).
"""

from __future__ import annotations

import math
import random
from dataclasses import asdict, dataclass

from firmware_protocol.codec import DecodeError, Frame, decode, encode_raw, specs
from firmware_protocol.framing import MAX_PAYLOAD, Deframer, frame_to_bytes


@dataclass
class FuzzResult:
    """Outcome of one fuzz run."""

    mutated: int
    """Corrupt inputs presented."""
    rejected: int
    accepted_corrupt: int
    escaped: int
    """Exceptions other than the documented decode error."""
    single_bit_accepted: int = 0
    intact: int = 0
    intact_lost: int = 0
    check_bits: int = 8

    @property
    def accept_rate(self) -> float:
        """Accepted corrupt / presented corrupt."""
        return self.accepted_corrupt / self.mutated if self.mutated else 0.0

    def bound(self, sigmas: float = 6.0) -> float:
        """Upper limit for ``accepted_corrupt``: a random check of ``check_bits`` passes
        with probability 2^-bits; mean + ``sigmas`` standard deviations + 1."""
        p = 2.0**-self.check_bits
        mean = self.mutated * p
        return mean + sigmas * math.sqrt(mean * (1 - p)) + 1

    def as_dict(self) -> dict[str, float]:
        """JSON-ready figures."""
        d: dict[str, float] = dict(asdict(self))
        d["accept_rate"] = self.accept_rate
        d["bound"] = self.bound()
        return d


def _valid_frames(r: random.Random, per_message: int) -> list[Frame]:
    out = []
    for name, sp in specs().items():
        for _ in range(per_message):
            raw = {
                k: r.randint(*sp.raw_range[k])
                for k in sp.raw_range
                if k not in ("COUNTER", "CHECKSUM")
            }
            # enums decode only for defined values: keep states/status small
            for k in ("STATE", "STATUS"):
                if k in raw:
                    raw[k] = r.randint(0, 2)
            out.append(encode_raw(name, raw, r.randint(0, 15)))
    return out


def _mutate_payload(r: random.Random, f: Frame) -> tuple[Frame, bool]:
    """A different frame; True when exactly one bit was flipped."""
    data = bytearray(f.data)
    k = r.random()
    if k < 0.35:
        i = r.randrange(len(data) * 8)
        data[i // 8] ^= 1 << (i % 8)
        return Frame(f.can_id, bytes(data)), True
    if k < 0.6:
        for i in r.sample(range(len(data) * 8), r.randint(2, 6)):
            data[i // 8] ^= 1 << (i % 8)
    elif k < 0.8:
        i = r.randrange(len(data))
        data[i] = (data[i] + r.randint(1, 255)) & 0xFF
    elif k < 0.9:
        data = bytearray(r.randbytes(len(data)))
    elif k < 0.95:
        n = r.randint(0, MAX_PAYLOAD)
        data = data[:n] if n < len(data) else data + bytearray(r.randbytes(n - len(data)))
    else:
        return Frame(r.randrange(0x800), bytes(data)), False
    return Frame(f.can_id, bytes(data)), False


def fuzz_codec(n: int, seed: int = 0) -> FuzzResult:
    """``n`` mutated frames through :func:`codec.decode`."""
    r = random.Random(seed)
    pool = _valid_frames(r, 200)
    res = FuzzResult(0, 0, 0, 0, check_bits=8)
    while res.mutated < n:
        f = pool[r.randrange(len(pool))]
        m, single = _mutate_payload(r, f)
        if m == f:
            continue
        res.mutated += 1
        try:
            decode(m)
        except DecodeError:
            res.rejected += 1
            continue
        except Exception:
            res.escaped += 1
            continue
        res.accepted_corrupt += 1
        res.single_bit_accepted += single
    return res


def fuzz_deframer(n: int, seed: int = 0, garbage_every: int = 4) -> FuzzResult:
    """A stream with ``n`` mutated frames, as many intact ones and garbage bursts."""
    r = random.Random(seed)
    pool = _valid_frames(r, 50)
    res = FuzzResult(0, 0, 0, 0, check_bits=16)
    d = Deframer()
    batch = 2000
    while res.mutated < n:
        stream = bytearray()
        intact: list[Frame] = []
        for _ in range(min(batch, n - res.mutated)):
            f = pool[r.randrange(len(pool))]
            wire = frame_to_bytes(f)
            stream += wire
            intact.append(f)
            res.intact += 1
            if r.randrange(garbage_every) == 0:
                stream += r.randbytes(r.randint(1, 80))  # garbage burst
            g = pool[r.randrange(len(pool))]
            body = bytearray(frame_to_bytes(g)[1:-1])
            k = r.random()
            if k < 0.5:
                i = r.randrange(len(body) * 8)
                body[i // 8] ^= 1 << (i % 8)
            elif k < 0.8:
                for i in r.sample(range(len(body) * 8), r.randint(2, 6)):  # distinct bits
                    body[i // 8] ^= 1 << (i % 8)
            elif k < 0.9:
                del body[r.randrange(len(body))]
            else:
                b = r.randrange(256)
                # a 0x00 at either end is only an extra delimiter: keep it inside
                at = r.randrange(1, len(body)) if b == 0 else r.randrange(len(body) + 1)
                body.insert(at, b)
            stream += b"\x00" + bytes(body) + b"\x00"
            res.mutated += 1
        got: list[Frame] = []
        pos = 0
        try:
            while pos < len(stream):
                step = r.randint(1, 64)
                got += d.feed(bytes(stream[pos : pos + step]))
                pos += step
        except Exception:
            res.escaped += 1
            continue
        # intact frames must appear in order; anything else was corrupt and accepted
        j = 0
        for g in got:
            if j < len(intact) and g == intact[j]:
                j += 1
            else:
                res.accepted_corrupt += 1
        res.intact_lost += len(intact) - j
    res.rejected = res.mutated - res.accepted_corrupt
    return res

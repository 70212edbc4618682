"""The link relay of the processor-in-the-loop rig counts whole frames however the bytes
are split into reads (``truckd.sim.pil.count_frames``); no emulator needed."""

from __future__ import annotations

import random

from firmware_protocol.codec import Frame
from firmware_protocol.framing import frame_to_bytes
from truckd.sim.pil import count_frames


def test_count_frames_any_split() -> None:
    rng = random.Random(7)
    for _ in range(200):
        frames = [
            frame_to_bytes(
                Frame(
                    rng.randrange(0x800), bytes(rng.randrange(256) for _ in range(rng.randrange(9)))
                )
            )
            for _ in range(rng.randrange(1, 20))
        ]
        wire = b"".join(frames)
        cuts = sorted(rng.sample(range(1, len(wire)), k=min(len(wire) - 1, rng.randrange(10))))
        total, open_ = 0, False
        for a, b in zip([0, *cuts], [*cuts, len(wire)], strict=True):
            n, open_ = count_frames(wire[a:b], open_)
            total += n
        assert total == len(frames) and not open_

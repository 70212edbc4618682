"""Serial framing: the CAN frames of truck.dbc over a byte stream.

Wire format of one frame::

    0x00 | COBS( id_lo id_hi payload... crc_lo crc_hi ) | 0x00

``crc`` is CRC-16/CCITT-FALSE over id (2 bytes LE) and payload.  COBS removes every 0x00
from the body, so 0x00 only ever delimits.  The receiver (:class:`Deframer`) splits the
stream at 0x00, so after any burst of garbage it resynchronises on the next delimiter
and loses no intact frame.  Bodies longer than :data:`MAX_BODY` are discarded as they
arrive (bounded memory).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from firmware_protocol.codec import Frame
from firmware_protocol.crc import crc16_ccitt

MAX_PAYLOAD = 8
MAX_DECODED = 2 + MAX_PAYLOAD + 2
MAX_BODY = MAX_DECODED + 1
"""Longest COBS body of a valid frame (bytes)."""


class FramingError(ValueError):
    """A COBS body that is not a frame (``reason``: cobs, length, crc)."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing of ``data`` (no 0x00 in the result)."""
    if len(data) < 254:
        # No zero-free run can reach 254 bytes: each run is its length + 1, then the run
        # (the zero it ended at is implied).  Every frame takes this path.
        return b"".join([bytes((len(run) + 1,)) + run for run in bytes(data).split(b"\x00")])
    out = bytearray(b"\x01")
    code_idx = 0
    code = 1
    for b in data:
        if b == 0:
            out[code_idx] = code
            code_idx = len(out)
            out.append(1)
            code = 1
        else:
            out.append(b)
            code += 1
            if code == 0xFF:
                out[code_idx] = code
                code_idx = len(out)
                out.append(1)
                code = 1
    out[code_idx] = code
    return bytes(out)


def cobs_decode(body: bytes) -> bytes:
    """Inverse of :func:`cobs_encode`; raises FramingError('cobs') on a malformed body."""
    out = bytearray()
    i = 0
    n = len(body)
    if n == 0:
        raise FramingError("cobs", "empty body")
    while i < n:
        code = body[i]
        if code == 0:
            raise FramingError("cobs", "zero byte inside body")
        end = i + code
        if end > n:
            raise FramingError("cobs", "block runs past the end")
        block = body[i + 1 : end]
        if 0 in block:
            raise FramingError("cobs", "zero byte inside body")
        out += block
        i = end
        if code < 255 and i < n:
            out.append(0)
    return bytes(out)


def frame_to_bytes(frame: Frame) -> bytes:
    """The wire bytes of one frame, delimiters included."""
    if not 0 <= frame.can_id < 0x800:
        raise ValueError(f"CAN id must be 11-bit, got {frame.can_id:#x}")
    if len(frame.data) > MAX_PAYLOAD:
        raise ValueError(f"payload is {len(frame.data)} bytes, at most {MAX_PAYLOAD}")
    raw = bytes((frame.can_id & 0xFF, frame.can_id >> 8)) + frame.data
    c = crc16_ccitt(raw)
    return b"\x00" + cobs_encode(raw + bytes((c & 0xFF, c >> 8))) + b"\x00"


def body_to_frame(body: bytes) -> Frame:
    """The frame in one COBS body (between delimiters); raises FramingError."""
    if len(body) > MAX_BODY:
        raise FramingError("length", f"{len(body)}-byte body, at most {MAX_BODY}")
    raw = cobs_decode(body)
    if len(raw) < 4:
        raise FramingError("length", f"{len(raw)} decoded bytes, at least 4")
    c = crc16_ccitt(raw[:-2])
    if c != raw[-2] | (raw[-1] << 8):
        raise FramingError("crc", "CRC-16 mismatch")
    can_id = raw[0] | (raw[1] << 8)
    if can_id >= 0x800:
        raise FramingError("length", f"id {can_id:#x} is not 11-bit")
    return Frame(can_id, bytes(raw[2:-2]))


@dataclass
class FramingStats:
    """Serial receive statistics (counts since start)."""

    frames_ok: int = 0
    crc_errors: int = 0
    cobs_errors: int = 0
    length_errors: int = 0
    resyncs: int = 0
    """Bodies thrown away (each bad body or garbage run costs one resync)."""
    bytes_discarded: int = 0

    def as_dict(self) -> dict[str, int]:
        """The counters as a JSON-ready dict."""
        return asdict(self)


@dataclass
class Deframer:
    """Streaming receiver: feed bytes, get the intact frames.  Never raises on input."""

    stats: FramingStats = field(default_factory=FramingStats)

    def __post_init__(self) -> None:
        self._buf = bytearray()
        self._overflow = False

    def reset(self) -> None:
        """Forget a partial body (after a reconnect); the statistics are kept."""
        self._buf.clear()
        self._overflow = False

    def feed(self, data: bytes) -> list[Frame]:
        """All frames completed by ``data``, in order."""
        out: list[Frame] = []
        st = self.stats
        start = 0
        n = len(data)
        while start < n:
            z = data.find(0, start)
            if z < 0:
                chunk = data[start:]
                start = n
                self._append(chunk)
                break
            self._append(data[start:z])
            start = z + 1
            if self._overflow:
                st.resyncs += 1
                self._overflow = False
                self._buf.clear()
                continue
            if not self._buf:
                continue
            body = bytes(self._buf)
            self._buf.clear()
            try:
                out.append(body_to_frame(body))
                st.frames_ok += 1
            except FramingError as exc:
                st.resyncs += 1
                st.bytes_discarded += len(body)
                if exc.reason == "crc":
                    st.crc_errors += 1
                elif exc.reason == "cobs":
                    st.cobs_errors += 1
                else:
                    st.length_errors += 1
        return out

    def _append(self, chunk: bytes) -> None:
        if self._overflow:
            self.stats.bytes_discarded += len(chunk)
            return
        self._buf += chunk
        if len(self._buf) > MAX_BODY:
            self.stats.bytes_discarded += len(self._buf)
            self.stats.length_errors += 1
            self._buf.clear()
            self._overflow = True

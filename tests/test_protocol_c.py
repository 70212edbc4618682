"""The microcontroller's C code: in sync with the DBC, compiles, and produces the same
bytes as Python on shared vectors, both directions (pack/unpack, checksum, framing,
deframing with statistics).

The test writes a small C harness (one command per stdin line: ``P_<MSG> raw...`` packs
and seals, ``U_<MSG> hex`` unpacks, ``C8``/``C16`` checksums, ``F id hex`` frames, ``D
hex`` deframes a stream), compiles it with the generated and framing C, and compares
every answer with Python's."""

from __future__ import annotations

import random
import shutil
import subprocess
from pathlib import Path

import pytest

from firmware_protocol import generate
from firmware_protocol.codec import Frame, database, encode_raw, specs
from firmware_protocol.crc import crc8_j1850, crc16_ccitt, message_checksum
from firmware_protocol.framing import Deframer, frame_to_bytes

C_DIR = generate.C_DIR
GCC = shutil.which("gcc")


@pytest.fixture(autouse=True)
def _gcc_required() -> None:
    """The byte-identity proof is part of the suite: a missing compiler fails, never skips."""
    assert GCC is not None, "gcc is required by the C/Python byte-identity tests"


def test_generated_c_in_sync_with_dbc() -> None:
    assert generate.out_of_sync() == []


def _harness() -> str:
    """C main() reading commands on stdin (see module docstring of this test)."""
    lines = [
        "#include <stdio.h>",
        "#include <string.h>",
        "#include <stdlib.h>",
        '#include "truck.h"',
        '#include "truck_framing.h"',
        "static size_t unhex(const char *s, uint8_t *out) {",
        "  size_t n = 0; while (s[0] && s[1] && s[0] != '\\n') {",
        '    unsigned v; sscanf(s, "%2x", &v); out[n++] = (uint8_t)v; s += 2; } return n; }',
        "static void hex(const uint8_t *d, size_t n) {",
        '  for (size_t i = 0; i < n; i++) printf("%02x", d[i]); }',
        "static char line[70000]; static uint8_t buf[40000];",
        "int main(void) {",
        "  struct truck_deframer_t dfr;",
        "  while (fgets(line, sizeof line, stdin)) {",
        '    char cmd[32]; int off = 0; sscanf(line, "%31s %n", cmd, &off);',
        "    const char *rest = line + off;",
        '    if (!strcmp(cmd, "C8")) { size_t n = unhex(rest, buf);',
        '      printf("%02x\\n", truck_crc8_j1850(buf, n)); continue; }',
        '    if (!strcmp(cmd, "C16")) { size_t n = unhex(rest, buf);',
        '      printf("%04x\\n", truck_crc16_ccitt(buf, n)); continue; }',
        '    if (!strcmp(cmd, "F")) { unsigned id; int o2 = 0; sscanf(rest, "%x %n", &id, &o2);',
        "      size_t n = unhex(rest + o2, buf); uint8_t out[TRUCK_MAX_WIRE];",
        "      int w = truck_frame_encode((uint16_t)id, buf, n, out);",
        '      if (w < 0) printf("ERR"); else hex(out, (size_t)w); printf("\\n"); continue; }',
        '    if (!strcmp(cmd, "D")) { size_t n = unhex(rest, buf); truck_deframer_init(&dfr);',
        "      for (size_t i = 0; i < n; i++) { uint16_t id; uint8_t d[8]; size_t len;",
        "        if (truck_deframer_feed(&dfr, buf[i], &id, d, &len)) {",
        '          printf("%03x:", id); hex(d, len); printf(" "); } }',
        "      struct truck_framing_stats_t *s = &dfr.stats;",
        '      printf("| %u %u %u %u %u %u\\n", s->frames_ok, s->crc_errors, s->cobs_errors,',
        "        s->length_errors, s->resyncs, s->bytes_discarded); continue; }",
    ]
    for m in database().messages:
        low = m.name.lower()
        sigs = [s.name for s in m.signals]
        fields = " ".join("%lld" for _ in sigs)
        # pack: raw values in DBC order, checksum sealed by truck_seal
        lines += [
            f'    if (!strcmp(cmd, "P_{m.name}")) {{ long long v[{len(sigs)}];',
            f'      sscanf(rest, "{fields}", '
            + ", ".join(f"&v[{k}]" for k in range(len(sigs)))
            + ");",
            f"      struct truck_{low}_t msg; truck_{low}_init(&msg);",
        ]
        lines += [f"      msg.{s.lower()} = v[{k}];" for k, s in enumerate(sigs)]
        lines += [
            f"      uint8_t out[8]; int n = truck_{low}_pack(out, &msg, sizeof out);",
            f"      truck_seal(TRUCK_{m.name}_FRAME_ID, out, (size_t)n);",
            '      hex(out, (size_t)n); printf("\\n"); continue; }',
            f'    if (!strcmp(cmd, "U_{m.name}")) {{ size_t n = unhex(rest, buf);',
            f"      struct truck_{low}_t msg; int rc = truck_{low}_unpack(&msg, buf, n);",
            '      if (rc != 0) { printf("ERR\\n"); continue; }',
            f'      printf("%d", truck_checksum_ok(TRUCK_{m.name}_FRAME_ID, buf, n));',
        ]
        lines += [f'      printf(" %lld", (long long)msg.{s.lower()});' for s in sigs]
        lines += ['      printf("\\n"); continue; }']
    lines += ['    printf("?\\n");', "  }", "  return 0;", "}"]
    return "\n".join(lines) + "\n"


@pytest.fixture(scope="module")
def harness(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("c")
    (d / "main.c").write_text(_harness())
    exe = d / "harness"
    subprocess.run(
        [
            str(GCC),
            "-std=c99",
            "-O1",
            "-Wall",
            "-Wextra",
            "-Werror",
            "-Wno-unused-parameter",
            f"-I{C_DIR}",
            str(C_DIR / "truck.c"),
            str(C_DIR / "truck_framing.c"),
            str(d / "main.c"),
            "-o",
            str(exe),
            "-lm",
        ],
        check=True,
        capture_output=True,
        timeout=120,
    )
    return exe


def run(exe: Path, lines: list[str]) -> list[str]:
    out = subprocess.run(
        [str(exe)],
        input="\n".join(lines) + "\n",
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    ).stdout
    return out.splitlines()


def _random_raw(r: random.Random, name: str) -> dict[str, int]:
    sp = specs()[name]
    return {
        k: r.randint(*sp.raw_range[k]) for k in sp.raw_range if k not in ("COUNTER", "CHECKSUM")
    }


def test_framing_library_compiles_pedantic() -> None:
    for src in ("truck.c", "truck_framing.c"):
        subprocess.run(
            [
                str(GCC),
                "-std=c99",
                "-Wall",
                "-Wextra",
                "-Werror",
                "-pedantic",
                "-fsyntax-only",
                str(C_DIR / src),
            ],
            check=True,
            capture_output=True,
            timeout=60,
        )


def test_pack_python_to_c_identical(harness: Path) -> None:
    r = random.Random(1)
    cases: list[tuple[str, dict[str, int], int]] = []
    for name in specs():
        sp = specs()[name]
        # the extremes of every signal, then random values
        lo = {k: sp.raw_range[k][0] for k in sp.raw_range if k not in ("COUNTER", "CHECKSUM")}
        hi = {k: sp.raw_range[k][1] for k in lo}
        cases += [(name, lo, 0), (name, hi, 15)]
        cases += [(name, _random_raw(r, name), r.randint(0, 15)) for _ in range(150)]
    lines = []
    for name, raw, c in cases:
        order = [s.name for s in specs()[name].dbc.signals]
        vals = {**raw, "COUNTER": c, "CHECKSUM": 0}
        lines.append(f"P_{name} " + " ".join(str(vals[s]) for s in order))
    out = run(harness, lines)
    expected = [encode_raw(name, raw, c).data.hex() for name, raw, c in cases]
    assert out == expected


def test_unpack_python_bytes_in_c(harness: Path) -> None:
    """Python-encoded frames (and random payloads) decode to the same raw values in C."""
    r = random.Random(2)
    frames: list[Frame] = []
    for name in specs():
        sp = specs()[name]
        frames += [encode_raw(name, _random_raw(r, name), r.randint(0, 15)) for _ in range(100)]
        frames += [Frame(sp.can_id, r.randbytes(sp.length)) for _ in range(50)]
    lines = [f"U_{specs_by_id(f.can_id)} {f.data.hex()}" for f in frames]
    out = run(harness, lines)
    for f, line in zip(frames, out, strict=True):
        sp = specs()[specs_by_id(f.can_id)]
        raw = sp.dbc.decode(f.data, decode_choices=False, scaling=False)
        ok = int(message_checksum(f.can_id, f.data[:-1]) == f.data[-1])
        assert line == " ".join([str(ok)] + [str(int(raw[s.name])) for s in sp.dbc.signals])


def specs_by_id(can_id: int) -> str:
    return next(n for n, s in specs().items() if s.can_id == can_id)


def test_checksums_identical(harness: Path) -> None:
    r = random.Random(3)
    blobs = [b"123456789", b""] + [r.randbytes(r.randint(1, 40)) for _ in range(200)]
    out = run(harness, [f"C8 {b.hex()}" for b in blobs] + [f"C16 {b.hex()}" for b in blobs])
    assert out == [f"{crc8_j1850(b):02x}" for b in blobs] + [f"{crc16_ccitt(b):04x}" for b in blobs]


def test_frame_encode_identical(harness: Path) -> None:
    r = random.Random(4)
    frames = [Frame(r.randrange(0x800), r.randbytes(r.randint(0, 8))) for _ in range(300)]
    frames += [Frame(0, bytes(8)), Frame(0x7FF, b"\xff" * 8), Frame(0x100, b"")]
    out = run(harness, [f"F {f.can_id:x} {f.data.hex()}" for f in frames])
    assert out == [frame_to_bytes(f).hex() for f in frames]


def test_deframer_identical_on_noisy_streams(harness: Path) -> None:
    """C and Python extract the same frames and count the same errors."""
    r = random.Random(5)
    streams = []
    for _ in range(60):
        s = bytearray()
        for _ in range(r.randint(1, 25)):
            k = r.random()
            if k < 0.6:
                s += frame_to_bytes(Frame(r.randrange(0x800), r.randbytes(r.randint(0, 8))))
            elif k < 0.8:
                s += r.randbytes(r.randint(1, 60))  # garbage burst
            else:
                w = bytearray(frame_to_bytes(Frame(r.randrange(0x800), r.randbytes(8))))
                w[r.randrange(len(w))] ^= 1 << r.randrange(8)  # one flipped bit
                s += w
        streams.append(bytes(s))
    out = run(harness, [f"D {s.hex()}" for s in streams])
    for s, line in zip(streams, out, strict=True):
        d = Deframer()
        frames = d.feed(s)
        st = d.stats
        expect = "".join(f"{f.can_id:03x}:{f.data.hex()} " for f in frames)
        expect += (
            f"| {st.frames_ok} {st.crc_errors} {st.cobs_errors} {st.length_errors} "
            f"{st.resyncs} {st.bytes_discarded}"
        )
        assert line == expect

"""Byte mutations of a file, and of MCAP records and chunks (CRC fixed, so the records inside
reach the parsers).
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

from recorder.fuzz.cases import _pick

_INTERESTING = (0, 1, 2, 3, 7, 255, 256, 65535, 2**31 - 1, 2**31, 2**32 - 1, 2**32, 2**53,
                2**62, 2**63 - 1, 2**63, 2**64 - 1)
_BYTE_OPS = ("truncate", "flip", "overwrite", "insert", "delete", "duplicate", "zero",
             "splice", "ints")


def mutate_bytes(rng: np.random.Generator, data: bytes, other: bytes | None = None,
                 op: str | None = None) -> tuple[bytes, str]:
    """One random byte-level mutation of ``data``; returns ``(mutated, op)``."""
    op = op or str(_pick(rng, _BYTE_OPS))
    n = len(data)
    if n == 0:
        return bytes(rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8)), "random"
    b = bytearray(data)
    at = int(rng.integers(0, n))
    span = min(n - at, int(rng.integers(1, 1 + max(1, min(4096, n // 4)))))
    if op == "truncate":
        # Anywhere, but often near the end (inside the summary) or near the start.
        where = rng.random()
        cut = (int(rng.integers(max(0, n - 4096), n)) if where < 0.3 else
               int(rng.integers(0, min(n, 256))) if where < 0.4 else at)
        return bytes(b[:cut]), op
    if op == "flip":
        for _ in range(int(rng.integers(1, 17))):
            i = int(rng.integers(0, n))
            b[i] ^= 1 << int(rng.integers(0, 8))
        return bytes(b), op
    if op == "overwrite":
        b[at:at + span] = rng.integers(0, 256, span, dtype=np.uint8).tobytes()
        return bytes(b), op
    if op == "insert":
        k = int(rng.integers(1, 512))
        return bytes(b[:at]) + rng.integers(0, 256, k, dtype=np.uint8).tobytes() + bytes(
            b[at:]), op
    if op == "delete":
        del b[at:at + span]
        return bytes(b), op
    if op == "duplicate":
        seg = bytes(b[at:at + span])
        j = int(rng.integers(0, n))
        return bytes(b[:j]) + seg + bytes(b[j:]), op
    if op == "zero":
        b[at:at + span] = bytes(span)
        return bytes(b), op
    if op == "splice" and other:
        j = int(rng.integers(0, len(other)))
        return bytes(b[:at]) + other[j:], op
    # "ints" (and splice without a partner): an interesting integer over 1-8 bytes
    width = int(_pick(rng, [1, 2, 4, 8]))
    v = int(_pick(rng, _INTERESTING)) & ((1 << (8 * width)) - 1)
    b[at:at + width] = v.to_bytes(width, "little")[: n - at]
    return bytes(b[:n]), "ints"


def _records(data: bytes) -> list[tuple[int, int, int]]:
    """Top-level MCAP record framing ``(offset, opcode, length)`` after the magic."""
    out = []
    off = 8
    while off + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, off)
        if off + 9 + length > len(data):
            break
        out.append((off, opcode, length))
        off += 9 + length
    return out


def _mutate_record_frame(rng: np.random.Generator, data: bytes) -> tuple[bytes, str]:
    recs = _records(data)
    if not recs:
        return mutate_bytes(rng, data, op="flip")
    off, opcode, length = recs[int(rng.integers(0, len(recs)))]
    b = bytearray(data)
    u = rng.random()
    if u < 0.3:
        return data[:off] + _random_record(rng) + data[off:], "record-insert"
    if u < 0.7:
        choices = [0, 1, 8, max(0, length - 1), length + 1, len(data), 2 * len(data),
                   *_INTERESTING]
        new = int(_pick(rng, choices)) & (2**64 - 1)
        b[off + 1:off + 9] = struct.pack("<Q", new)
        return bytes(b), "record-length"
    b[off] = int(_pick(rng, [0x00, 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08, 0x09, 0x0A,
                             0x0B, 0x0C, 0x0D, 0x0E, 0x0F, 0x10, 0x7F, 0xFF]))
    return bytes(b), "record-opcode"


def _random_record(rng: np.random.Generator) -> bytes:
    """A record of a random (mostly known) opcode with a short random body: it parses as
    far as the body goes."""
    op = int(_pick(rng, [0x01, 0x02, 0x03, 0x04, 0x05, 0x05, 0x05, 0x06, 0x07, 0x08, 0x09,
                         0x0A, 0x0B, 0x0C, 0x0D, 0x0E, 0x0F, 0x80]))
    body = rng.integers(0, 256, int(rng.integers(0, 48)), dtype=np.uint8).tobytes()
    if rng.random() < 0.3:  # plausible small length prefixes inside
        body = bytes(8) + body
    return struct.pack("<BQ", op, len(body)) + body


def _mutate_chunk_content(rng: np.random.Generator, data: bytes) -> tuple[bytes, str]:
    """Mutate the records inside a chunk, then fix its CRC and sizes, so that the damage
    passes the CRC check and reaches the record parsers."""
    import zstandard

    chunks = [r for r in _records(data) if r[1] == 0x06]
    if not chunks:
        return mutate_bytes(rng, data, op="flip")
    off, _, length = chunks[int(rng.integers(0, len(chunks)))]
    body = data[off + 9:off + 9 + length]
    try:
        t0, t1, _usize, _crc = struct.unpack_from("<QQQI", body, 0)
        (clen,) = struct.unpack_from("<I", body, 28)
        comp = body[32:32 + clen]
        (dlen,) = struct.unpack_from("<Q", body, 32 + clen)
        payload = body[40 + clen:40 + clen + dlen]
        inner = zstandard.decompress(payload) if comp == b"zstd" else payload
    except (struct.error, zstandard.ZstdError):
        return mutate_bytes(rng, data, op="flip")
    if rng.random() < 0.4:
        new_inner, what = _mutate_inner_frame(rng, inner)
    else:
        new_inner, what = mutate_bytes(rng, inner)
    packed = zstandard.compress(new_inner) if comp == b"zstd" else new_inner
    new_body = (struct.pack("<QQQI", t0, t1, len(new_inner), zlib.crc32(new_inner))
                + struct.pack("<I", len(comp)) + comp + struct.pack("<Q", len(packed))
                + packed)
    rec = struct.pack("<BQ", 0x06, len(new_body)) + new_body
    return data[:off] + rec + data[off + 9 + length:], f"chunk-{what}"


def _mutate_inner_frame(rng: np.random.Generator, inner: bytes) -> tuple[bytes, str]:
    """Change the opcode or length of one record inside decompressed chunk data."""
    recs = []
    off = 0
    while off + 9 <= len(inner):
        opcode, length = struct.unpack_from("<BQ", inner, off)
        recs.append((off, opcode, length))
        if off + 9 + length > len(inner):
            break
        off += 9 + length
    if not recs:
        return mutate_bytes(rng, inner)
    off, _, length = recs[int(rng.integers(0, len(recs)))]
    b = bytearray(inner)
    u = rng.random()
    if u < 0.3:
        return inner[:off] + _random_record(rng) + inner[off:], "inner-insert"
    if u < 0.65:
        new = int(_pick(rng, [0, 1, 4, 21, 22, max(0, length - 1), length + 1,
                              *_INTERESTING])) & (2**64 - 1)
        b[off + 1:off + 9] = struct.pack("<Q", new)
        return bytes(b), "inner-length"
    b[off] = int(_pick(rng, [0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x09, 0x0F, 0xFF]))
    return bytes(b), "inner-opcode"

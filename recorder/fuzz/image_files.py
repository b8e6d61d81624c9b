"""The ``image`` cases: PNG/TIFF depth images with adversarial content, headers claiming
huge sizes, other formats under a depth-image name, and byte mutations.
"""

from __future__ import annotations

import contextlib
import struct
import warnings
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from recorder.fuzz.cases import Job, _pick
from recorder.fuzz.mutate import mutate_bytes
from recorder.fuzz.scan_files import _file_job, _intrinsics_kw, _storm


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return (struct.pack(">I", len(data)) + kind + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))


def _crafted_image(rng: np.random.Generator) -> tuple[bytes, str, str]:
    """Headers that claim huge (or zero) images, and other formats under a depth-image
    name: (bytes, suffix, what)."""
    dims = [0, 1, 4096, 5000, 65535, 100_000, 2**31 - 1, 2**32 - 1]
    w, h = int(_pick(rng, dims)), int(_pick(rng, dims))
    what = str(_pick(rng, ["png", "tiff", "bigtiff", "ppm", "bmp", "pfm"]))
    if what == "png":
        ihdr = struct.pack(">IIBBBBB", w, h, 16, 0, 0, 0, 0)
        data = (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr)
                + _png_chunk(b"IDAT", zlib.compress(bytes(64))) + _png_chunk(b"IEND", b""))
        return data, ".png", f"png-{w}x{h}"
    if what == "tiff":
        typ = int(_pick(rng, [3, 4, 16, 1]))
        fmt = {3: "H", 4: "I", 16: "I", 1: "B"}[typ]
        ents = [(256, typ, 1, w), (257, typ, 1, h), (258, 3, 1, 32), (259, 3, 1, 1),
                (262, 3, 1, 1), (273, 4, 1, 8), (277, 3, 1, 1), (278, 4, 1, h), (279, 4, 1, 64),
                (339, 3, 1, 3)]
        ifd = struct.pack("<H", len(ents))
        for tag, t, c, v in ents:
            val = struct.pack("<" + fmt, v & (2 ** (8 * struct.calcsize(fmt)) - 1))
            ifd += struct.pack("<HHI", tag, t, c) + val.ljust(4, b"\0")
        ifd += struct.pack("<I", 0)
        off = int(_pick(rng, [8, 8, 8, 2**31, 7]))
        return b"II*\x00" + struct.pack("<I", off) + ifd + bytes(64), ".tiff", \
            f"tiff-t{typ}-{w}x{h}"
    if what == "bigtiff":
        ents = [(256, 16, 1, w), (257, 16, 1, h), (258, 3, 1, 32), (259, 3, 1, 1),
                (262, 3, 1, 1), (273, 16, 1, 16), (277, 3, 1, 1), (278, 16, 1, h),
                (279, 16, 1, 64), (339, 3, 1, 3)]
        ifd = struct.pack("<Q", len(ents))
        for tag, t, c, v in ents:
            ifd += struct.pack("<HHQQ", tag, t, c, v)
        ifd += struct.pack("<Q", 0)
        return b"II+\x00" + struct.pack("<HHQ", 8, 0, 16) + ifd + bytes(64), ".tif", \
            f"bigtiff-{w}x{h}"
    if what == "ppm":
        return f"P5\n{w} {h}\n65535\n".encode() + bytes(64), ".png", f"ppm-{w}x{h}"
    if what == "pfm":
        return f"Pf\n{w} {h}\n-1.0\n".encode() + bytes(64), ".tiff", f"pfm-{w}x{h}"
    hdr = struct.pack("<2sIHHI", b"BM", 54 + 64, 0, 0, 54) + struct.pack(
        "<IiiHHIIiiII", 40, w % 2**31, h % 2**31, 1, 24, 0, 0, 2835, 2835, 0, 0)
    return hdr + bytes(64), ".png", f"bmp-{w}x{h}"


def _scale_kw(rng: np.random.Generator, default: float | None) -> float | None:
    u = rng.random()
    if u < 0.8:
        return default
    return float(_pick(rng, [0.0, -1.0, float("nan"), float("inf"), 1e-300, 1e300, 1.0]))


def _gen_image(rng: np.random.Generator, corpus: dict[str, Any], d: Path) -> Job:
    import cv2

    intr = corpus["intrinsics"] if rng.random() < 0.85 else _intrinsics_kw(rng, corpus)
    u = rng.random()
    if u < 0.3:
        src = Path(corpus["images"][int(rng.integers(0, len(corpus["images"])))])
        data, op = mutate_bytes(rng, src.read_bytes())
        p = d / f"fuzzed{src.suffix}"
        p.write_bytes(data)
        scale = _scale_kw(rng, 0.001 if src.suffix == ".png" else None)
        return _file_job(f"mutate-{op}", p, {"intrinsics": intr, "depth_scale": scale}, d)
    if u < 0.55:
        data, suffix, what = _crafted_image(rng)
        p = d / f"fuzzed{suffix}"
        p.write_bytes(data)
        return _file_job(f"header-{what}", p, {"intrinsics": intr, "depth_scale": 0.001}, d)
    dt = str(_pick(rng, ["uint16", "uint16", "uint8", "float32", "float32", "float64", "int16",
                         "int32"]))
    ch = int(_pick(rng, [1, 1, 1, 3, 4]))
    H, W = (int(_pick(rng, [1, 2, 7, 36])), int(_pick(rng, [1, 3, 48])))
    shape = (H, W) if ch == 1 else (H, W, ch)
    a, kind = _storm(rng, shape, np.float64)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if dt.startswith(("uint", "int")):
            info = np.iinfo(dt)
            a = np.clip(np.nan_to_num(a * 1000, nan=0, posinf=info.max, neginf=info.min),
                        info.min, info.max).astype(dt)
        else:
            a = a.astype(dt)
    suffix = ".png" if dt in ("uint8", "uint16") and rng.random() < 0.6 else str(
        rng.choice([".tiff", ".tif"]))
    p = d / f"fuzzed{suffix}"
    ok = False
    with contextlib.suppress(cv2.error):
        ok = bool(cv2.imwrite(str(p), a))
    if not ok:
        p.write_bytes(b"")
    scale = _scale_kw(rng, 0.001 if dt.startswith("uint") else None)
    return _file_job(f"write-{dt}x{ch}:{kind}", p, {"intrinsics": intr, "depth_scale": scale},
                     d)

"""PCD headers (ascii, binary, binary_compressed): parse, check the data length, undo VIEWPOINT.

The organization is the header's ``WIDTH``/``HEIGHT``; a ``VIEWPOINT`` other than the
identity is undone, so the points are in the sensor frame.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from boxloc.errors import InputError
from boxloc.io.common import _check_size, _one_line

_PCD_TYPES = {("F", 4), ("F", 8), ("U", 1), ("U", 2), ("U", 4), ("U", 8),
              ("I", 1), ("I", 2), ("I", 4), ("I", 8)}


@dataclass(frozen=True)
class _PcdHeader:
    fields: list[str]
    sizes: list[int]
    types: list[str]
    counts: list[int]
    width: int
    height: int
    points: int
    viewpoint: tuple[float, ...]
    data: str
    data_offset: int

    @property
    def point_size(self) -> int:
        return sum(s * c for s, c in zip(self.sizes, self.counts))


def _parse_pcd_header(p: Path) -> _PcdHeader:
    with open(p, "rb") as f:
        raw = f.read(65536)
    kv: dict[str, list[str]] = {}
    offset = 0
    for line in raw.splitlines(keepends=True):
        offset += len(line)
        text = line.decode("ascii", errors="replace").strip()
        if not text or text.startswith("#"):
            continue
        key, *vals = text.split()
        kv[key.upper()] = vals
        if key.upper() == "DATA":
            break
    else:
        raise InputError(f"{p}: not a PCD file (no DATA line in the header)")
    try:
        fields = kv["FIELDS"]
        sizes = [int(s) for s in kv["SIZE"]]
        types = [t.upper() for t in kv["TYPE"]]
        counts = [int(c) for c in kv.get("COUNT", ["1"] * len(fields))]
        width, height = int(kv["WIDTH"][0]), int(kv["HEIGHT"][0])
        npts = int(kv.get("POINTS", [str(width * height)])[0])
        vp = tuple(float(v) for v in kv.get("VIEWPOINT", "0 0 0 1 0 0 0".split()))
        data = kv["DATA"][0].lower()
    except (KeyError, IndexError, ValueError) as e:
        raise InputError(f"{p}: malformed PCD header ({_one_line(e)})") from None
    if not (len(fields) == len(sizes) == len(types) == len(counts)):
        raise InputError(f"{p}: malformed PCD header (FIELDS, SIZE, TYPE, COUNT differ in "
                         "length)")
    if any((t, s) not in _PCD_TYPES for t, s in zip(types, sizes)) or min(counts) < 1:
        raise InputError(f"{p}: malformed PCD header (bad TYPE/SIZE/COUNT)")
    if len(vp) != 7 or not all(math.isfinite(v) for v in vp):
        raise InputError(f"{p}: malformed PCD header (VIEWPOINT must be 7 numbers)")
    if data not in ("ascii", "binary", "binary_compressed"):
        raise InputError(f"{p}: unknown PCD DATA type {data!r}")
    for c in "xyz":
        if c not in fields:
            raise InputError(f"{p}: PCD has no '{c}' field (fields: {' '.join(fields)})")
        i = fields.index(c)
        if types[i] != "F" or counts[i] != 1:
            raise InputError(f"{p}: PCD field '{c}' must be a float scalar")
    if width < 0 or height < 0 or npts != width * height:
        raise InputError(f"{p}: malformed PCD header (POINTS {npts} != WIDTH {width} x "
                         f"HEIGHT {height})")
    return _PcdHeader(fields, sizes, types, counts, width, height, npts, vp, data, offset)


def _pcd_layout(p: Path, max_pixels: int) -> _PcdHeader:
    """The header of an organized PCD of at most ``max_pixels`` points whose data are all
    there, checked before Open3D reads the file."""
    h = _parse_pcd_header(p)
    if h.height <= 1:
        raise InputError(f"{p}: PCD is unorganized (HEIGHT={h.height}, WIDTH={h.width}): "
                         "a range image needs an organized cloud")
    _check_size(p, h.height, h.width, max_pixels)
    _check_pcd_data(p, h)
    return h


def _check_pcd_data(p: Path, h: _PcdHeader) -> None:
    """Refuse truncated binary data before Open3D sees it (it only warns)."""
    size = p.stat().st_size
    need = h.points * h.point_size
    if h.data == "ascii":
        with open(p, "rb") as f:
            f.seek(h.data_offset)
            lines = sum(1 for line in f if line.strip())
        if lines < h.points:
            raise InputError(f"{p}: truncated PCD (ascii data has {lines} of {h.points} "
                             "points)")
    if h.data == "binary" and size - h.data_offset < need:
        raise InputError(f"{p}: truncated PCD (binary data has {size - h.data_offset} of "
                         f"{need} bytes)")
    if h.data == "binary_compressed":
        with open(p, "rb") as f:
            f.seek(h.data_offset)
            raw = f.read(8)
        if len(raw) < 8:
            raise InputError(f"{p}: truncated PCD (no compressed data)")
        comp, uncomp = struct.unpack("<II", raw)
        if uncomp != need:
            raise InputError(f"{p}: corrupt PCD (compressed block holds {uncomp} bytes, "
                             f"header says {need})")
        if size - h.data_offset - 8 < comp:
            raise InputError(f"{p}: truncated PCD (compressed data has "
                             f"{size - h.data_offset - 8} of {comp} bytes)")


def _undo_viewpoint(P: np.ndarray, vp: tuple[float, ...], meta: dict[str, Any]) -> np.ndarray:
    """Express PCD points in the sensor frame given by VIEWPOINT (tx ty tz qw qx qy qz)."""
    t = np.asarray(vp[:3])
    q = np.asarray(vp[3:])
    if np.array_equal(t, 0) and np.array_equal(q, [1, 0, 0, 0]):
        return P
    n = np.linalg.norm(q)
    if n == 0:
        return P
    w, x, y, z = q / n
    R = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    meta["pcd_viewpoint"] = T
    return (P - t) @ R  # R^T (p - t), row-vector form

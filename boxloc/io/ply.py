"""PLY headers: parse, check, and find the organization of a range-grid PLY.

The organization is ``obj_info num_cols``/``num_rows`` (Stanford range-grid convention,
with or without a ``range_grid`` element) or a PCL ``camera`` element's
``viewportx``/``viewporty``. Vertex properties that Open3D would misread are refused.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from boxloc.errors import InputError
from boxloc.io.common import _check_size, _one_line


@dataclass(frozen=True)
class _PlyElement:
    name: str
    count: int
    props: list[tuple[str, ...]]  # ("scalar", type, name) or ("list", ctype, itype, name)


@dataclass(frozen=True)
class _PlyHeader:
    fmt: str
    elements: list[_PlyElement]
    obj_info: dict[str, str]
    data_offset: int


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _parse_ply_header(p: Path) -> _PlyHeader:
    with open(p, "rb") as f:
        raw = f.read(65536)
    if not raw.startswith(b"ply"):
        raise InputError(f"{p}: not a PLY file (no 'ply' magic)")
    end = raw.find(b"end_header")
    if end < 0:
        raise InputError(f"{p}: not a PLY file (no end_header)")
    nl = raw.find(b"\n", end)
    if nl < 0:
        raise InputError(f"{p}: truncated PLY header")
    fmt = ""
    elements: list[_PlyElement] = []
    info: dict[str, str] = {}
    try:
        for line in raw[:end].decode("ascii", errors="replace").splitlines()[1:]:
            tok = line.split()
            if not tok:
                continue
            if tok[0] == "format":
                fmt = tok[1]
            elif tok[0] == "obj_info" and len(tok) >= 3:
                info[tok[1]] = tok[2]
            elif tok[0] == "element":
                elements.append(_PlyElement(tok[1], int(tok[2]), []))
            elif tok[0] == "property":
                if tok[1] == "list":
                    elements[-1].props.append(("list", _PLY_TYPES[tok[2]],
                                               _PLY_TYPES[tok[3]], tok[4]))
                else:
                    elements[-1].props.append(("scalar", _PLY_TYPES[tok[1]], tok[2]))
    except (IndexError, KeyError, ValueError) as e:
        raise InputError(f"{p}: malformed PLY header ({_one_line(e)})") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(f"{p}: unknown PLY format {fmt!r}")
    if not any(e.name == "vertex" for e in elements):
        raise InputError(f"{p}: PLY has no vertex element")
    names = [e.name for e in elements]
    if len(set(names)) != len(names):
        raise InputError(f"{p}: PLY repeats an element ({' '.join(names)})")
    size = p.stat().st_size
    for el in elements:
        # Every entry takes at least a byte (a line in ascii), so a larger count is corrupt;
        # Open3D would otherwise loop over it (even over entries without properties).
        if el.count < 0 or el.count > size:
            raise InputError(f"{p}: PLY element {el.name!r} claims {el.count} entries in a "
                             f"file of {size} bytes")
    return _PlyHeader(fmt, elements, info, nl + 1)


#: Vertex properties Open3D reads into one array: their types must agree (Open3D writes
#: past its buffer when, say, ``x`` is float and ``z`` double).
_PLY_GROUPS = (("x", "y", "z"), ("nx", "ny", "nz"), ("red", "green", "blue"))


def _ply_layout(p: Path, max_pixels: int) -> tuple[int, int, int, np.ndarray | None]:
    """``(height, width, n_vertices, grid)`` of an organized PLY of at most ``max_pixels``
    pixels, checked before Open3D reads the file; ``grid`` maps pixels to vertices (-1 =
    none) for a PLY with a ``range_grid`` element, else None (one vertex per pixel)."""
    ph = _parse_ply_header(p)
    _ply_check_vertex(p, ph)
    n_expected = next(e.count for e in ph.elements if e.name == "vertex")
    H, W, grid = _ply_organization(p, ph, n_expected)
    if H <= 1:
        raise InputError(f"{p}: PLY is unorganized (num_rows={H}): a range image needs an "
                         "organized cloud")
    _check_size(p, H, W, max_pixels)
    if grid is None and n_expected != H * W:
        raise InputError(f"{p}: PLY has {n_expected} vertices, organization says "
                         f"{W}x{H} = {H * W}")
    _ply_check_data(p, ph)
    return H, W, n_expected, grid


def _ply_check_vertex(p: Path, h: _PlyHeader) -> None:
    """Refuse vertex properties that Open3D would misread: positions that are not float
    scalars, repeated names, and groups (x y z, nx ny nz, red green blue) of mixed types."""
    e = next(e for e in h.elements if e.name == "vertex")
    names = [pr[-1] for pr in e.props]
    if len(set(names)) != len(names):
        raise InputError(f"{p}: PLY vertex element repeats a property ({' '.join(names)})")
    kinds = {pr[-1]: pr[:-1] for pr in e.props}
    for c in "xyz":
        if kinds.get(c) not in (("scalar", "f4"), ("scalar", "f8")):
            raise InputError(f"{p}: PLY vertex property '{c}' must be a float or double scalar")
    for group in _PLY_GROUPS:
        found = {kinds[n] for n in group if n in kinds}
        if len(found) > 1:
            raise InputError(f"{p}: PLY vertex properties {' '.join(group)} must have one type, "
                             f"got {', '.join(sorted(' '.join(k) for k in found))}")


def _ply_element_dtype(h: _PlyHeader, e: _PlyElement) -> np.dtype[Any] | None:
    """Structured dtype of a binary element with only scalar properties; else None."""
    if any(pr[0] == "list" for pr in e.props):
        return None
    bo = "<" if h.fmt == "binary_little_endian" else ">"
    return np.dtype([(pr[2], bo + pr[1]) for pr in e.props])


def _ply_seek_element(p: Path, h: _PlyHeader, name: str) -> tuple[int, _PlyElement]:
    """Byte offset (binary) or line number after the header (ascii) of an element's data."""
    pos = h.data_offset if h.fmt != "ascii" else 0
    for e in h.elements:
        if e.name == name:
            return pos, e
        if h.fmt == "ascii":
            pos += e.count
            continue
        dt = _ply_element_dtype(h, e)
        if dt is None:
            if e.count:
                raise InputError(f"{p}: cannot locate PLY element {name!r} after the "
                                 f"variable-size element {e.name!r}")
            continue
        pos += e.count * dt.itemsize
    raise InputError(f"{p}: PLY has no element {name!r}")


def _ply_check_data(p: Path, h: _PlyHeader) -> None:
    """Refuse truncated binary vertex data before Open3D sees it (it only warns)."""
    if h.fmt == "ascii":
        with open(p, "rb") as f:
            f.seek(h.data_offset)
            nlines = f.read().count(b"\n")
        need = sum(e.count for e in h.elements)
        if nlines < need:
            raise InputError(f"{p}: truncated PLY (ascii data has {nlines} of {need} lines)")
        return
    off, e = _ply_seek_element(p, h, "vertex")
    dt = _ply_element_dtype(h, e)
    if dt is not None and p.stat().st_size < off + e.count * dt.itemsize:
        raise InputError(f"{p}: truncated PLY (vertex data ends early)")


def _ply_organization(
    p: Path, h: _PlyHeader, n_vertices: int
) -> tuple[int, int, np.ndarray | None]:
    """(height, width, grid) of an organized PLY; grid maps pixels to vertices (-1 = none)."""
    names = {e.name: e for e in h.elements}
    if "num_cols" in h.obj_info and "num_rows" in h.obj_info:
        try:
            W, H = int(h.obj_info["num_cols"]), int(h.obj_info["num_rows"])
        except ValueError:
            raise InputError(f"{p}: PLY obj_info num_cols/num_rows must be integers") from None
        if "range_grid" in names:
            return H, W, _ply_range_grid(p, h, H * W, n_vertices)
        return H, W, None
    if "camera" in names:
        cam = _ply_camera(p, h)
        if cam is not None:
            return cam[1], cam[0], None
    raise InputError(
        f"{p}: PLY is unorganized (no obj_info num_cols/num_rows, range_grid or camera "
        "viewport): a range image needs an organized cloud"
    )


def _ply_camera(p: Path, h: _PlyHeader) -> tuple[int, int] | None:
    """(viewportx, viewporty) of a PCL-style camera element."""
    pos, e = _ply_seek_element(p, h, "camera")
    prop_names = [pr[-1] for pr in e.props]
    if "viewportx" not in prop_names or "viewporty" not in prop_names or e.count < 1:
        return None
    if h.fmt == "ascii":
        with open(p, "rb") as f:
            f.seek(h.data_offset)
            lines = f.read().splitlines()
        if len(lines) <= pos:
            raise InputError(f"{p}: truncated PLY (no camera data)")
        vals = lines[pos].split()
        try:
            return (int(float(vals[prop_names.index("viewportx")])),
                    int(float(vals[prop_names.index("viewporty")])))
        except (IndexError, ValueError):
            raise InputError(f"{p}: corrupt PLY camera element") from None
    dt = _ply_element_dtype(h, e)
    if dt is None:
        return None
    with open(p, "rb") as f:
        f.seek(pos)
        raw = f.read(dt.itemsize)
    if len(raw) < dt.itemsize:
        raise InputError(f"{p}: truncated PLY (no camera data)")
    rec = np.frombuffer(raw, dtype=dt)[0]
    return int(rec["viewportx"]), int(rec["viewporty"])


def _ply_range_grid(p: Path, h: _PlyHeader, n_pixels: int, n_vertices: int) -> np.ndarray:
    """The range_grid element: for each pixel the index of its vertex, or -1."""
    pos, e = _ply_seek_element(p, h, "range_grid")
    if e.count != n_pixels or len(e.props) != 1 or e.props[0][0] != "list":
        raise InputError(f"{p}: PLY range_grid must have num_cols*num_rows = {n_pixels} "
                         "entries of one list property")
    grid = np.full(n_pixels, -1, dtype=np.int64)
    if h.fmt == "ascii":
        with open(p, "rb") as f:
            f.seek(h.data_offset)
            lines = f.read().splitlines()[pos : pos + n_pixels]
        if len(lines) < n_pixels:
            raise InputError(f"{p}: truncated PLY (range_grid data ends early)")
        for i, line in enumerate(lines):
            tok = line.split()
            if tok and tok[0] != b"0":
                if len(tok) < 2:
                    raise InputError(f"{p}: corrupt PLY range_grid entry {i}")
                grid[i] = int(tok[1])
    else:
        bo = "<" if h.fmt == "binary_little_endian" else ">"
        ct, it = np.dtype(bo + e.props[0][1]), np.dtype(bo + e.props[0][2])
        with open(p, "rb") as f:
            f.seek(pos)
            buf = f.read()
        off = 0
        try:
            for i in range(n_pixels):  # variable-size records: a sequential walk
                (c,) = np.frombuffer(buf, ct, 1, off)
                off += ct.itemsize
                if c:
                    grid[i] = int(np.frombuffer(buf, it, 1, off)[0])
                    off += int(c) * it.itemsize
        except ValueError:
            raise InputError(f"{p}: truncated PLY (range_grid data ends early)") from None
    if (grid >= n_vertices).any():
        raise InputError(f"{p}: corrupt PLY range_grid (vertex index out of range)")
    return grid

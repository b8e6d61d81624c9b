"""Depth images: 16-bit PNG, 8/16-bit or float TIFF (and BigTIFF).

*z* depth along the optical axis (not range), ``depth * depth_scale`` metres; 0 (and, for
float images, NaN or negative) means no return. Intrinsics are required; ``depth_scale``
is required for integer images (0.001 for millimetres) and defaults to 1.0 for float ones.
The image size is read from the file header and checked before OpenCV decodes anything.
"""

from __future__ import annotations

import contextlib
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import numpy.typing as npt

from boxloc.errors import InputError
from boxloc.io.common import _check_size, _one_line
from boxloc.scan import PinholeModel, Scan


def _image_size_from_header(p: Path) -> tuple[int, int]:
    """(height, width) of a PNG, TIFF or BigTIFF from its header.

    The size is checked before OpenCV decodes anything (it would allocate whatever a header
    claims), so a file whose size cannot be read here, or that is another format under a
    depth-image name (OpenCV goes by content, not by suffix), is refused.
    """
    with open(p, "rb") as f:
        head = f.read(32)
        if head[:8] == b"\x89PNG\r\n\x1a\n":
            if len(head) < 24 or head[12:16] != b"IHDR":
                raise InputError(f"{p}: corrupt PNG header")
            w, h = struct.unpack(">II", head[16:24])
            return int(h), int(w)
        if head[:4] in (b"II*\x00", b"MM\x00*"):
            return _tiff_size(f, "<" if head[:2] == b"II" else ">", p, big=False)
        if head[:4] in (b"II+\x00", b"MM\x00+"):
            return _tiff_size(f, "<" if head[:2] == b"II" else ">", p, big=True)
    raise InputError(f"{p}: not a PNG or TIFF image")


def _tiff_size(f: BinaryIO, bo: str, p: Path, *, big: bool) -> tuple[int, int]:
    """Image width and length tags of the first IFD of a classic TIFF or a BigTIFF."""
    f.seek(4)
    if big:
        off_size, _ = struct.unpack(bo + "HH", f.read(4))
        if off_size != 8:
            raise InputError(f"{p}: corrupt BigTIFF header")
        (ifd,) = struct.unpack(bo + "Q", f.read(8))
        cfmt, elen, voff = "Q", 20, 12
    else:
        (ifd,) = struct.unpack(bo + "I", f.read(4))
        cfmt, elen, voff = "H", 12, 8
    f.seek(ifd)
    raw = f.read(struct.calcsize(cfmt))
    if len(raw) < struct.calcsize(cfmt):
        raise InputError(f"{p}: truncated TIFF (no image directory)")
    (n,) = struct.unpack(bo + cfmt, raw)
    if n > 4096:  # real directories hold a few dozen tags
        raise InputError(f"{p}: corrupt TIFF (image directory of {n} entries)")
    entries = f.read(elen * n)
    if len(entries) < elen * n:
        raise InputError(f"{p}: truncated TIFF (short image directory)")
    size: dict[int, int] = {}
    for i in range(n):
        e = entries[elen * i : elen * (i + 1)]
        tag, typ = struct.unpack(bo + "HH", e[:4])
        if tag in (256, 257):
            fmt = {3: "H", 4: "I", 16: "Q"}.get(typ)
            if fmt is None:
                raise InputError(f"{p}: TIFF image size has an unsupported type {typ}")
            (size[tag],) = struct.unpack(bo + fmt, e[voff : voff + struct.calcsize(fmt)])
    if 256 not in size or 257 not in size:
        raise InputError(f"{p}: TIFF has no image width and length in its first directory")
    return size[257], size[256]


@contextlib.contextmanager
def _quiet_cv2() -> Iterator[Any]:
    """OpenCV logs decoder errors to stderr; the CLI promises one line, so silence it."""
    import cv2

    try:
        old = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    except AttributeError:  # very old OpenCV
        old = None
    try:
        yield cv2
    finally:
        if old is not None:
            cv2.utils.logging.setLogLevel(old)


def _read_depth_image(
    p: Path, intr: tuple[float, float, float, float] | None, scale: float | None,
    max_pixels: int, index: int,
) -> Scan:
    if intr is None:
        raise InputError(f"depth image {p} needs intrinsics: pass --intrinsics FX,FY,CX,CY")
    try:
        hw = _image_size_from_header(p)
    except struct.error:
        raise InputError(f"{p}: corrupt or truncated image header") from None
    _check_size(p, hw[0], hw[1], max_pixels)
    with _quiet_cv2() as cv2:
        try:
            img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
        except cv2.error as e:
            raise InputError(f"{p}: cannot decode image: {_one_line(e)}") from None
    if img is None:
        raise InputError(f"{p}: cannot decode image (corrupt, truncated or not an image)")
    if img.ndim != 2:
        raise InputError(f"{p}: depth image must have one channel, got shape {img.shape}")
    H, W = img.shape
    _check_size(p, H, W, max_pixels)
    if img.dtype.kind == "u":
        if scale is None:
            raise InputError(
                f"{p}: {img.dtype.itemsize * 8}-bit depth image needs --depth-scale "
                "(metres per unit, e.g. 0.001 for millimetres)"
            )
    elif img.dtype.kind == "f":
        scale = 1.0 if scale is None else scale
    else:
        raise InputError(f"{p}: depth image must be unsigned integer or float, "
                         f"got dtype {img.dtype}")
    z = img.astype(np.float64) * scale
    z[~(z > 0) | ~np.isfinite(z)] = np.nan  # 0, negative and NaN depths are "no return"
    try:
        sensor = PinholeModel(*intr, width=W, height=H)
    except InputError as e:
        raise InputError(f"{p}: {e}") from None
    return Scan(range=range_from_depth(z, sensor), sensor=sensor, index=index, source=str(p))


def range_from_depth(z: npt.ArrayLike, sensor: PinholeModel) -> np.ndarray:
    """Convert z depth (along the optical axis) to range along each pixel's ray.

    Parameters
    ----------
    z : ndarray, shape (H, W), metres
        Depth along the optical axis; NaN for no return.
    sensor : PinholeModel

    Returns
    -------
    ndarray, shape (H, W), float32, metres
        ``z * |((u - cx)/fx, (v - cy)/fy, 1)|``.
    """
    v, u = np.mgrid[0 : sensor.height, 0 : sensor.width].astype(np.float64)
    stretch = np.sqrt(((u - sensor.cx) / sensor.fx) ** 2 + ((v - sensor.cy) / sensor.fy) ** 2
                      + 1.0)
    return (np.asarray(z, dtype=np.float64) * stretch).astype(np.float32)

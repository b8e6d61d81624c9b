"""Scan readers and the ``.npz`` writer.

Every reader returns a :class:`boxloc.scan.Scan`. Every problem with the user's file raises
:class:`boxloc.errors.InputError` with one line that names the file and the problem; library
exceptions (zip, zlib, OpenCV, Open3D) never escape.

Formats
-------
``.npz`` (the public, stable layout; see :func:`write_npz`)
    ``range`` (H, W) float32 metres along each pixel's unit ray, NaN (or 0) for no return,
    ``intrinsics`` (3, 3) pinhole matrix, ``points`` (H, W, 3) float32 metres in the sensor
    frame (x right, y down, z forward), NaN for no return. Optional ``sensor_to_base`` (4, 4)
    and ``capture_time_ns`` (0-d integer). A file needs ``range`` + ``intrinsics`` (lossless,
    preferred), or ``points`` (the sensor model is then fitted, see
    :meth:`boxloc.scan.Scan.from_points`), or ``range`` + ``--intrinsics``. Unknown keys (e.g.
    the simulator's ``truth/...``) are ignored. Files are loaded with ``allow_pickle=False``.
16-bit PNG, 8/16-bit or float TIFF depth images
    *z* depth along the optical axis (not range), ``depth * depth_scale`` metres; 0 (and, for
    float images, NaN or negative) means no return. Intrinsics are required; ``depth_scale``
    is required for integer images (0.001 for millimetres) and defaults to 1.0 for float ones.
Organized PCD (ascii, binary, binary_compressed) and PLY
    Decoded by Open3D (NaN points are kept in place); the organization comes from our own
    header parse: PCD ``WIDTH``/``HEIGHT``; PLY ``obj_info num_cols``/``num_rows`` (Stanford
    range-grid convention, with or without a ``range_grid`` element) or a PCL ``camera``
    element's ``viewportx``/``viewporty``. An unorganized cloud is refused. A PCD
    ``VIEWPOINT`` other than the identity is undone, so the points are in the sensor frame.

An all-NaN scan is accepted by the readers (it is a valid recording of nothing); the pipeline's
``check_scan`` refuses it.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import struct
import zipfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, overload

import numpy as np
import numpy.typing as npt

from boxloc.errors import InputError
from boxloc.scan import PinholeModel, RayTableModel, Scan

__all__ = [
    "SUPPORTED_SUFFIXES",
    "DEFAULT_MAX_PIXELS",
    "parse_intrinsics",
    "read_scan",
    "read_scans",
    "read_labels",
    "write_npz",
]

SUPPORTED_SUFFIXES: tuple[str, ...] = (".npz", ".png", ".tif", ".tiff", ".pcd", ".ply")
DEFAULT_MAX_PIXELS = 16_777_216  # 4096^2, same as Config.max_pixels

# The keys of the public .npz layout; anything else in a file is ignored.
_NPZ_KEYS = ("range", "points", "intrinsics", "sensor_to_base", "capture_time_ns")

PathLike = str | os.PathLike[str]
IntrinsicsLike = str | Sequence[float] | npt.NDArray[Any] | None


# --- common checks ------------------------------------------------------------------------


@overload
def parse_intrinsics(value: None) -> None: ...


@overload
def parse_intrinsics(value: str | Sequence[float] | npt.NDArray[Any]
                     ) -> tuple[float, float, float, float]: ...


def parse_intrinsics(value: IntrinsicsLike) -> tuple[float, float, float, float] | None:
    """Normalize intrinsics given as ``"fx,fy,cx,cy"``, four numbers or a 3x3 matrix.

    Parameters
    ----------
    value : str, sequence of 4 floats, ndarray (3, 3) or (4,), or None
        Focal lengths and principal point, pixels.

    Returns
    -------
    tuple of 4 floats or None
        ``(fx, fy, cx, cy)``; None when ``value`` is None.

    Raises
    ------
    InputError
        If the string does not hold four numbers, the array has another shape, or a value is
        not finite or a focal length is not positive.
    """
    if value is None:
        return None
    if isinstance(value, str):
        parts = [p for p in re.split(r"[,\s]+", value.strip()) if p]
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            vals = []
        if len(vals) != 4:
            raise InputError(f"intrinsics must be FX,FY,CX,CY (four numbers), got {value!r}")
    else:
        try:
            a = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            msg = f"intrinsics must be four numbers or a 3x3 matrix, got {value!r}"
            raise InputError(msg) from None
        if a.shape == (3, 3):
            vals = [a[0, 0], a[1, 1], a[0, 2], a[1, 2]]
        elif a.shape == (4,):
            vals = list(a)
        else:
            raise InputError(
                f"intrinsics must be four numbers or a 3x3 matrix, got shape {a.shape}"
            )
    fx, fy, cx, cy = (float(v) for v in vals)
    if not all(math.isfinite(v) for v in (fx, fy, cx, cy)):
        raise InputError(f"intrinsics must be finite, got fx,fy,cx,cy = {fx}, {fy}, {cx}, {cy}")
    if fx <= 0 or fy <= 0:
        raise InputError(f"intrinsics focal lengths must be positive, got fx={fx}, fy={fy}")
    return fx, fy, cx, cy


def _K(intr: tuple[float, float, float, float]) -> np.ndarray:
    fx, fy, cx, cy = intr
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _check_depth_scale(depth_scale: float | None) -> float | None:
    if depth_scale is None:
        return None
    try:
        s = float(depth_scale)
    except (TypeError, ValueError):
        raise InputError(f"depth scale must be a number, got {depth_scale!r}") from None
    if not math.isfinite(s) or s <= 0:
        raise InputError(f"depth scale must be finite and > 0 (metres per unit), got {s}")
    return s


def _check_size(path: Path, height: int, width: int, max_pixels: int) -> None:
    if height <= 0 or width <= 0:
        raise InputError(f"{path}: image size must be positive, got {height}x{width}")
    if height * width > max_pixels:
        raise InputError(
            f"{path}: scan of {height}x{width} = {height * width} pixels exceeds "
            f"max_pixels = {max_pixels}"
        )


def _check_path(path: PathLike) -> Path:
    p = Path(path)
    if not p.exists():
        raise InputError(f"scan file not found: {p}")
    if p.is_dir():
        raise InputError(f"expected a scan file, got a directory: {p}")
    if p.suffix.lower() not in SUPPORTED_SUFFIXES:
        raise InputError(
            f"unsupported scan file type {p.suffix or '(none)'!r}: {p} "
            f"(supported: {', '.join(SUPPORTED_SUFFIXES)})"
        )
    if not os.access(p, os.R_OK):
        raise InputError(f"cannot read {p}: permission denied")
    return p


def _one_line(e: BaseException) -> str:
    s = str(e).strip().splitlines()
    return s[0] if s else type(e).__name__


# --- public readers -----------------------------------------------------------------------


def read_scan(
    path: PathLike,
    *,
    intrinsics: IntrinsicsLike = None,
    depth_scale: float | None = None,
    index: int = 0,
    max_pixels: int = DEFAULT_MAX_PIXELS,
) -> Scan:
    """Read one scan from a ``.npz``, depth PNG/TIFF, or organized PCD/PLY file.

    Parameters
    ----------
    path : str or Path
        The file; the format is chosen by its suffix (see ``SUPPORTED_SUFFIXES``).
    intrinsics : str, sequence of 4 floats or ndarray (3, 3), optional
        Pinhole ``fx, fy, cx, cy`` in pixels (the ``--intrinsics`` option). Required for depth
        images and for an ``.npz`` with ``range`` but no ``intrinsics``. For a point cloud it
        sets the pinhole model instead of fitting one. It must agree with intrinsics stored in
        an ``.npz``.
    depth_scale : float, optional
        Metres per depth unit for PNG/TIFF depth images (0.001 for millimetres). Required for
        integer images; float images default to 1.0 (metres). Checked, but not used, for
        other formats (so one option set can serve a directory of mixed files).
    index : int
        Sequence number stored in ``Scan.index``.
    max_pixels : int
        Largest scan accepted, pixels; the size is checked from the file header before the
        data are loaded whenever the format allows.

    Returns
    -------
    Scan
        ``range`` (H, W) float32 metres, NaN for no return, with a pinhole or ray-table sensor.

    Raises
    ------
    InputError
        Missing file, directory, unknown suffix, unreadable, truncated or corrupt file, wrong
        shape or dtype, missing or invalid intrinsics, invalid depth scale, organization
        missing, or a scan larger than ``max_pixels``.
    """
    p = _check_path(path)
    intr = parse_intrinsics(intrinsics)
    scale = _check_depth_scale(depth_scale)
    if not isinstance(max_pixels, int) or max_pixels <= 0:
        raise InputError(f"max_pixels must be a positive integer, got {max_pixels!r}")
    suffix = p.suffix.lower()
    try:
        if suffix == ".npz":
            scan = _read_npz(p, intr, max_pixels, index)
        elif suffix in (".png", ".tif", ".tiff"):
            scan = _read_depth_image(p, intr, scale, max_pixels, index)
        else:
            cloud = _read_cloud(p, max_pixels, want_labels=False)
            scan = _scan_from_cloud(p, cloud, intr, index)
    except InputError:
        raise
    except MemoryError:
        raise InputError(f"{p}: not enough memory to read this scan") from None
    except OSError as e:
        raise InputError(f"cannot read {p}: {e.strerror or _one_line(e)}") from None
    return scan


def read_scans(path_or_dir: PathLike, **same: Any) -> Iterator[Scan]:
    """Read one scan file, or every supported file in a directory sorted by name, or the
    depth frames of a ROS 2 bag (:func:`boxloc.io.rosbag.open_bag`).

    Parameters
    ----------
    path_or_dir : str or Path
        A scan file, or a directory of them (not recursive; other files are skipped), or a
        ROS 2 bag (a rosbag2 directory, an ``.mcap`` file of profile ``ros2``, a ``.db3``).
    **same
        Keyword arguments of :func:`read_scan`, the same for every file. In a directory
        ``index`` counts from its value (default 0) in name order. ``depth_topic``,
        ``info_topic`` and ``base_frame`` are for bags (ignored for other inputs).

    Yields
    ------
    Scan

    Raises
    ------
    InputError
        As :func:`read_scan`; also for a directory without any scan file.
    """
    p = Path(path_or_dir)
    # ROS 2 bags (boxloc.io.rosbag, its reader imported only for a bag): their own options.
    bag_kw: dict[str, Any] = {k: same.pop(k) for k in ("depth_topic", "info_topic",
                                                        "base_frame") if k in same}
    from boxloc.io.rosbag import is_rosbag

    if is_rosbag(p):
        yield from _read_bag(p, bag_kw, same)
        return
    if not p.is_dir():
        yield read_scan(p, **same)
        return
    files = sorted(f for f in p.iterdir()
                   if f.is_file() and f.suffix.lower() in SUPPORTED_SUFFIXES)
    if not files:
        raise InputError(f"no scan files ({', '.join(SUPPORTED_SUFFIXES)}) in directory {p}")
    start = int(same.pop("index", 0))
    for i, f in enumerate(files):
        yield read_scan(f, index=start + i, **same)


def _read_bag(p: Path, bag_kw: dict[str, Any], same: dict[str, Any]) -> Iterator[Scan]:
    from boxloc.io.rosbag import open_bag

    yield from open_bag(p, **bag_kw, **same)


def read_labels(path: PathLike, *, max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """Read the ``label`` field of an organized PCD (or PLY) as an image.

    Parameters
    ----------
    path : str or Path
        A PCD/PLY file with an integer ``label`` field, e.g. an mOSD frame (0 = no return,
        1-9 = table, 10*k + j = part j of object k).
    max_pixels : int
        Largest cloud accepted, pixels.

    Returns
    -------
    ndarray, shape (H, W), int64
        The label of each pixel, in the same layout as :func:`read_scan`'s range.

    Raises
    ------
    InputError
        As :func:`read_scan`, or when the file has no ``label`` field.
    """
    p = _check_path(path)
    if p.suffix.lower() not in (".pcd", ".ply"):
        raise InputError(f"labels can only be read from .pcd or .ply files, got {p}")
    try:
        cloud = _read_cloud(p, max_pixels, want_labels=True)
    except OSError as e:
        raise InputError(f"cannot read {p}: {e.strerror or _one_line(e)}") from None
    assert cloud.labels is not None
    return cloud.labels


# --- .npz -------------------------------------------------------------------------------


@dataclass(frozen=True)
class _NpyHeader:
    shape: tuple[int, ...]
    dtype: np.dtype[Any]


def _npy_header(zf: zipfile.ZipFile, member: str) -> _NpyHeader:
    """Shape and dtype of an ``.npy`` member, from its header alone (no data read)."""
    with zf.open(member) as f:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, _fortran, dtype = np.lib.format.read_array_header_1_0(f)
        elif version == (2, 0):
            shape, _fortran, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise ValueError(f"unsupported .npy format version {version}")
    return _NpyHeader(tuple(int(s) for s in shape), np.dtype(dtype))


def _npz_member(zf: zipfile.ZipFile, member: str) -> np.ndarray:
    with zf.open(member) as f:
        # allow_pickle=False always: the file is untrusted.
        return np.asarray(np.lib.format.read_array(f, allow_pickle=False))


def _read_npz(
    p: Path, intr: tuple[float, float, float, float] | None, max_pixels: int, index: int
) -> Scan:
    try:
        zf = zipfile.ZipFile(p)
    except (zipfile.BadZipFile, zipfile.LargeZipFile, ValueError, EOFError) as e:
        raise InputError(f"{p}: not a valid .npz file (corrupt or truncated): "
                         f"{_one_line(e)}") from None
    with zf:
        members = {n[:-4]: n for n in zf.namelist() if n.endswith(".npy")}
        keys = [k for k in _NPZ_KEYS if k in members]
        try:
            heads = {k: _npy_header(zf, members[k]) for k in keys}
        except MemoryError:
            raise
        except Exception as e:  # zip, zlib and numpy's header parser raise many kinds
            raise InputError(f"{p}: corrupt .npz member: {_one_line(e)}") from None
        _check_npz_headers(p, heads, max_pixels)
        if "range" not in heads and "points" not in heads:
            found = ", ".join(sorted(members)) or "none"
            raise InputError(f"{p}: .npz needs key 'range' or 'points' (found keys: {found})")
        use = [k for k in keys if not (k == "points" and "range" in heads
                                        and ("intrinsics" in heads or intr is not None))]
        try:
            arrs = {k: _npz_member(zf, members[k]) for k in use}
        except MemoryError:
            raise
        except Exception as e:  # as above
            raise InputError(f"{p}: corrupt or truncated .npz member: {_one_line(e)}") from None
    return _scan_from_npz(p, arrs, intr, index)


def _check_npz_headers(p: Path, heads: dict[str, _NpyHeader], max_pixels: int) -> None:
    """Shapes and dtypes of the layout's keys, checked before any data is loaded."""

    def bad(key: str, want: str) -> InputError:
        h = heads[key]
        return InputError(f"{p}: .npz '{key}' must be {want}, got shape {h.shape} "
                          f"dtype {h.dtype}")

    hw: tuple[int, int] | None = None
    if "range" in heads:
        h = heads["range"]
        if len(h.shape) != 2 or h.dtype.kind != "f":
            raise bad("range", "an (H, W) float array")
        hw = (h.shape[0], h.shape[1])
    if "points" in heads:
        h = heads["points"]
        if len(h.shape) != 3 or h.shape[2] != 3 or h.dtype.kind != "f":
            raise bad("points", "an (H, W, 3) float array")
        if hw is not None and (h.shape[0], h.shape[1]) != hw:
            raise InputError(f"{p}: .npz 'points' shape {h.shape} does not match "
                             f"'range' shape {hw}")
        hw = hw or (h.shape[0], h.shape[1])
    if hw is not None:
        _check_size(p, hw[0], hw[1], max_pixels)
    if "intrinsics" in heads:
        h = heads["intrinsics"]
        if h.shape != (3, 3) or h.dtype.kind not in "fiu":
            raise bad("intrinsics", "a (3, 3) numeric matrix")
    if "sensor_to_base" in heads:
        h = heads["sensor_to_base"]
        if h.shape != (4, 4) or h.dtype.kind not in "fiu":
            raise bad("sensor_to_base", "a (4, 4) numeric matrix")
    if "capture_time_ns" in heads:
        h = heads["capture_time_ns"]
        if h.shape not in ((), (1,)) or h.dtype.kind not in "iu":
            raise bad("capture_time_ns", "a 0-d integer (nanoseconds)")


def _scan_from_npz(
    p: Path, arrs: dict[str, np.ndarray], intr: tuple[float, float, float, float] | None,
    index: int,
) -> Scan:
    kw: dict[str, Any] = {"index": index, "source": str(p)}
    if "sensor_to_base" in arrs:
        kw["sensor_to_base"] = arrs["sensor_to_base"].astype(np.float64)
    if "capture_time_ns" in arrs:
        t = int(arrs["capture_time_ns"].reshape(()))
        if t < 0:
            raise InputError(f"{p}: .npz 'capture_time_ns' must be >= 0, got {t}")
        kw["capture_time_ns"] = t
    stored = None
    if "intrinsics" in arrs:
        K = arrs["intrinsics"].astype(np.float64)
        try:
            stored = parse_intrinsics(K)
        except InputError as e:
            raise InputError(f"{p}: .npz 'intrinsics': {e}") from None
        if not np.array_equal(K, _K(stored)):
            raise InputError(f"{p}: .npz 'intrinsics' is not a pinhole matrix "
                             f"[[fx,0,cx],[0,fy,cy],[0,0,1]]: {K.tolist()}")
        if intr is not None and not np.allclose(intr, stored, rtol=1e-9, atol=1e-9):
            raise InputError(f"{p}: --intrinsics {intr} conflicts with the intrinsics "
                             f"stored in the file {stored}")
    pin = stored or intr
    try:
        if "range" in arrs and pin is not None:
            H, W = arrs["range"].shape
            sensor: PinholeModel | RayTableModel = PinholeModel(*pin, width=W, height=H)
            return Scan(range=arrs["range"], sensor=sensor, **kw)
        if "points" in arrs:
            P = arrs["points"]
            if "range" not in arrs:
                if pin is None:
                    return Scan.from_points(P, **kw)
                _check_points_fit_intrinsics(P.astype(np.float64), pin)
                return Scan.from_points(P, _K(pin), **kw)
            # range + points without intrinsics: the rays come from the points, the range
            # (lossless) from the file.
            sensor = Scan.from_points(P).sensor
            return Scan(range=arrs["range"], sensor=sensor, **kw)
    except InputError as e:
        raise InputError(f"{p}: {e}") from None
    raise InputError(f"{p}: .npz has 'range' but no 'intrinsics' (or 'points'); "
                     "pass --intrinsics FX,FY,CX,CY")


def write_npz(scan: Scan, path: PathLike) -> None:
    """Write a scan in the public ``.npz`` layout, atomically.

    Keys: ``range`` (H, W) float32 metres (NaN = no return; lossless), ``points`` (H, W, 3)
    float32 metres, sensor frame, ``intrinsics`` (3, 3) float64 when the sensor is pinhole,
    ``capture_time_ns`` 0-d int64, and ``sensor_to_base`` (4, 4) float64 when known.

    Parameters
    ----------
    scan : Scan
    path : str or Path
        Destination, written exactly as given (no suffix is added).

    Notes
    -----
    Zip entries carry a fixed timestamp, so the same scan always gives the same bytes.
    A ray-table sensor is stored only through ``points``; reading it back refits the rays
    from those float32 points (the range stays bit-exact).
    """
    if not isinstance(scan, Scan):
        raise TypeError(f"scan must be a boxloc.scan.Scan, got {type(scan).__name__}")
    arrays: dict[str, np.ndarray] = {
        "range": np.ascontiguousarray(scan.range, dtype=np.float32),
        "points": np.ascontiguousarray(scan.points, dtype=np.float32),
        "capture_time_ns": np.asarray(scan.capture_time_ns, dtype=np.int64),
    }
    if isinstance(scan.sensor, PinholeModel):
        arrays["intrinsics"] = scan.sensor.K
    if scan.sensor_to_base is not None:
        arrays["sensor_to_base"] = np.asarray(scan.sensor_to_base, dtype=np.float64)
    write_arrays_npz(path, arrays)


def write_arrays_npz(path: str | os.PathLike[str], arrays: dict[str, np.ndarray]) -> None:
    """Write arrays as an ``.npz``, deterministically and atomically.

    Zip entries carry a fixed timestamp (same arrays, same bytes); the file appears under
    its name only when complete (temporary file + rename); nothing is pickled.
    """
    p = Path(path)
    tmp = p.with_name(f".{p.name}.tmp{os.getpid()}")
    try:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
            for name, a in arrays.items():
                info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_DEFLATED
                with zf.open(info, "w", force_zip64=True) as f:
                    np.lib.format.write_array(f, np.asarray(a, order="C"), allow_pickle=False)
        os.replace(tmp, p)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


# --- depth images -----------------------------------------------------------------------


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


# --- point clouds (PCD, PLY) ------------------------------------------------------------


@dataclass
class _Cloud:
    """An organized cloud decoded from a PCD/PLY file."""

    points: np.ndarray  # (H, W, 3) float64, sensor frame, NaN = no return
    labels: np.ndarray | None = None  # (H, W) int64
    meta: dict[str, Any] = field(default_factory=dict)


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


def _o3d_read(p: Path) -> Any:
    import open3d as o3d

    # Open3D reports failures as warnings on stdout; keep them off the CLI's streams and
    # check the result ourselves.
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        try:
            return o3d.t.io.read_point_cloud(
                p, remove_nan_points=False, remove_infinite_points=False
            )
        except RuntimeError as e:
            raise InputError(f"{p}: cannot decode point cloud: {_one_line(e)}") from None


def _read_cloud(p: Path, max_pixels: int, *, want_labels: bool) -> _Cloud:
    suffix = p.suffix.lower()
    meta: dict[str, Any] = {}
    grid = None
    if suffix == ".pcd":
        h = _parse_pcd_header(p)
        if h.height <= 1:
            raise InputError(f"{p}: PCD is unorganized (HEIGHT={h.height}, WIDTH={h.width}): "
                             "a range image needs an organized cloud")
        _check_size(p, h.height, h.width, max_pixels)
        _check_pcd_data(p, h)
        H, W, n_expected = h.height, h.width, h.points
    else:
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
    pc = _o3d_read(p)
    if "positions" not in pc.point:
        raise InputError(f"{p}: cannot decode point cloud (corrupt or truncated)")
    pos = pc.point.positions.numpy()
    if pos.shape != (n_expected, 3):
        raise InputError(f"{p}: corrupt or truncated point cloud ({pos.shape[0]} of "
                         f"{n_expected} points decoded)")
    labels = None
    if want_labels:
        if "label" not in pc.point:
            raise InputError(f"{p}: point cloud has no 'label' field")
        lab = pc.point["label"].numpy()
        if lab.dtype.kind not in "iu" or lab.shape[0] != n_expected:
            raise InputError(f"{p}: 'label' field must be an integer scalar per point")
        labels = lab.reshape(-1).astype(np.int64)
    if pos.dtype.kind != "f":
        raise InputError(f"{p}: point positions decode as {pos.dtype}, not floats (corrupt?)")
    with np.errstate(invalid="ignore"):  # signalling NaNs from the file become quiet ones
        pts = pos.astype(np.float64)
    if grid is not None:
        full = np.full((H * W, 3), np.nan)
        ok = grid >= 0
        full[ok] = pts[grid[ok]]
        pts = full
        if labels is not None:
            lab_full = np.zeros(H * W, dtype=np.int64)
            lab_full[ok] = labels[grid[ok]]
            labels = lab_full
    pts = pts.reshape(H, W, 3)
    if suffix == ".pcd":
        pts = _undo_viewpoint(pts, h.viewpoint, meta)
    return _Cloud(pts, None if labels is None else labels.reshape(H, W), meta)


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


def _check_points_fit_intrinsics(
    P: np.ndarray, intr: tuple[float, float, float, float], tol_px: float = 0.5
) -> None:
    """Refuse intrinsics that do not reproject the points onto their own pixels.

    ``Scan.from_points`` with intrinsics keeps only each point's distance and takes the ray
    from the intrinsics, so intrinsics that do not fit would silently move every point.
    """
    H, W = P.shape[:2]
    sensor = PinholeModel(*intr, width=W, height=H)
    ok = np.isfinite(P).all(-1) & (P[..., 2] > 0)
    if not ok.any():
        return
    v, u = np.nonzero(ok)
    uv = sensor.project(P[ok])
    err = float(np.median(np.hypot(uv[:, 0] - u, uv[:, 1] - v)))
    if not err <= tol_px:
        raise InputError(f"intrinsics {intr} do not fit the points (median reprojection "
                         f"error {err:.2f} px)")


def _scan_from_cloud(
    p: Path, cloud: _Cloud, intr: tuple[float, float, float, float] | None, index: int
) -> Scan:
    P = cloud.points
    if np.isinf(P).any():
        P = np.where(np.isfinite(P), P, np.nan)  # PCL writes inf for some invalid points
    try:
        if intr is not None:
            _check_points_fit_intrinsics(P, intr)
        scan = Scan.from_points(P, None if intr is None else _K(intr), index=index,
                                source=str(p), meta=cloud.meta)
    except InputError as e:
        raise InputError(f"{p}: {e}") from None
    if isinstance(scan.sensor, RayTableModel):
        scan.meta["sensor_fit"] = "raytable"
    return scan

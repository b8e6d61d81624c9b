"""The ``.npz`` scan layout: reading (headers checked before any data is loaded) and writing.

``range`` (H, W) float32 metres along each pixel's unit ray, NaN (or 0) for no return,
``intrinsics`` (3, 3) pinhole matrix, ``points`` (H, W, 3) float32 metres in the sensor
frame (x right, y down, z forward), NaN for no return. Optional ``sensor_to_base`` (4, 4)
and ``capture_time_ns`` (0-d integer). A file needs ``range`` + ``intrinsics`` (lossless,
preferred), or ``points`` (the sensor model is then fitted, see
:meth:`boxloc.scan.Scan.from_points`), or ``range`` + ``--intrinsics``. Unknown keys (e.g.
the simulator's ``truth/...``) are ignored. Files are loaded with ``allow_pickle=False``.
"""

from __future__ import annotations

import contextlib
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from boxloc.errors import InputError
from boxloc.io.common import (
    _K,
    PathLike,
    _check_points_fit_intrinsics,
    _check_size,
    _one_line,
    parse_intrinsics,
)
from boxloc.scan import PinholeModel, RayTableModel, Scan

# The keys of the public .npz layout; anything else in a file is ignored.
_NPZ_KEYS = ("range", "points", "intrinsics", "sensor_to_base", "capture_time_ns")


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

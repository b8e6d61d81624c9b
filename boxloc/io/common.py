"""Checks shared by every scan reader: paths, sizes, intrinsics, depth scale.

Every problem with the user's input raises :class:`boxloc.errors.InputError` with one line
that names the file and the problem.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any, overload

import numpy as np
import numpy.typing as npt

from boxloc.errors import InputError
from boxloc.scan import PinholeModel

SUPPORTED_SUFFIXES: tuple[str, ...] = (".npz", ".png", ".tif", ".tiff", ".pcd", ".ply")
DEFAULT_MAX_PIXELS = 16_777_216  # 4096^2, same as Config.max_pixels


PathLike = str | os.PathLike[str]
IntrinsicsLike = str | Sequence[float] | npt.NDArray[Any] | None


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

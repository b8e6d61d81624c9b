"""Organized point clouds (PCD, PLY) to scans: Open3D decodes, our header parse organizes.

The points are decoded by Open3D (NaN points kept in place); the organization (H, W) and
the checks that keep Open3D from misreading a file come from :mod:`boxloc.io.pcd` and
:mod:`boxloc.io.ply`. An unorganized cloud is refused.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from boxloc.errors import InputError
from boxloc.io.common import _K, _check_points_fit_intrinsics, _one_line
from boxloc.io.pcd import _pcd_layout, _undo_viewpoint
from boxloc.io.ply import _ply_layout
from boxloc.scan import RayTableModel, Scan


@dataclass
class _Cloud:
    """An organized cloud decoded from a PCD/PLY file."""

    points: np.ndarray  # (H, W, 3) float64, sensor frame, NaN = no return
    labels: np.ndarray | None = None  # (H, W) int64
    meta: dict[str, Any] = field(default_factory=dict)


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
    h = None
    if suffix == ".pcd":
        h = _pcd_layout(p, max_pixels)
        H, W, n_expected = h.height, h.width, h.points
    else:
        H, W, n_expected, grid = _ply_layout(p, max_pixels)
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
    if h is not None:  # a PCD
        pts = _undo_viewpoint(pts, h.viewpoint, meta)
    return _Cloud(pts, None if labels is None else labels.reshape(H, W), meta)


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

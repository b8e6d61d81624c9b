"""The sensor model of a ``sensor_msgs/msg/CameraInfo``: pinhole, or a ray table for
``plumb_bob`` distortion; ``binning`` and ``roi`` applied.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from boxloc.errors import InputError
from boxloc.scan import PinholeModel, RayTableModel, SensorModel

#: Distortion models read as they are when every coefficient is zero; plumb_bob also with
#: non-zero coefficients (a ray table).
_PINHOLE_MODELS = ("", "none", "plumb_bob")


@dataclass(frozen=True)
class _Camera:
    """The sensor model of a CameraInfo for one image size."""

    sensor: SensorModel
    stretch: np.ndarray | None  # range / z per pixel for a ray table (None: pinhole)
    description: dict[str, Any]


def _camera(info: Any, H: int, W: int, where: str) -> _Camera:
    """The sensor model of a CameraInfo for an (H, W) image.

    Raises
    ------
    InputError
        Uncalibrated K, a size that does not match, or a distortion model other than
        plumb_bob/none with non-zero coefficients.
    """
    K = np.asarray(info.k, dtype=np.float64).reshape(-1)
    D = np.asarray(info.d, dtype=np.float64).reshape(-1)
    model = str(info.distortion_model).strip().lower()
    if K.size != 9 or not np.isfinite(K).all() or K[0] <= 0 or K[4] <= 0:
        raise InputError(f"{where}: CameraInfo K is not a calibrated camera matrix "
                         f"(fx={K[0] if K.size else None}); the camera was not calibrated")
    if not np.isfinite(D).all():
        raise InputError(f"{where}: CameraInfo distortion coefficients are not finite")
    distorted = bool(np.any(D != 0))
    if distorted and model not in _PINHOLE_MODELS:
        raise InputError(f"{where}: distortion model {info.distortion_model!r} with non-zero "
                         "coefficients is not supported (only plumb_bob or none); rectify the "
                         "depth image first")
    fx, fy, cx, cy = K[0], K[4], K[2], K[5]
    bx, by = max(int(info.binning_x), 1), max(int(info.binning_y), 1)
    roi = info.roi
    x0, y0 = int(roi.x_offset), int(roi.y_offset)
    full_w = int(roi.width) or int(info.width)
    full_h = int(roi.height) or int(info.height)
    want = (full_h // by, full_w // bx)
    if (full_w or full_h) and want != (H, W):
        raise InputError(f"{where}: CameraInfo is for {want[0]}x{want[1]} images (after roi "
                         f"and binning), the depth image is {H}x{W}")
    fx, fy, cx, cy = fx / bx, fy / by, (cx - x0) / bx, (cy - y0) / by
    desc = {"fx": float(fx), "fy": float(fy), "cx": float(cx), "cy": float(cy),
            "distortion_model": str(
        info.distortion_model), "d": [float(x) for x in D], "binning": [bx, by],
        "roi": [x0, y0, int(roi.width), int(roi.height)]}
    try:
        pin = PinholeModel(float(fx), float(fy), float(cx), float(cy), W, H)
    except InputError as e:
        raise InputError(f"{where}: {e}") from None
    if not distorted:
        return _Camera(pin, None, desc)
    import cv2

    # Pixel centres of the image (binned/ROI coordinates) in the calibrated image, undistorted
    # to normalized coordinates: every pixel's ray.
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    pts = np.stack([u * bx + x0 + (bx - 1) / 2, v * by + y0 + (by - 1) / 2], -1)
    Kfull = np.array([[K[0], 0, K[2]], [0, K[4], K[5]], [0, 0, 1]], dtype=np.float64)
    xy = cv2.undistortPoints(pts.reshape(-1, 1, 2), Kfull, D).reshape(H, W, 2)
    d = np.concatenate([xy, np.ones((H, W, 1))], -1)
    stretch = np.linalg.norm(d, axis=-1)
    return _Camera(RayTableModel(d / stretch[..., None]), stretch, desc)

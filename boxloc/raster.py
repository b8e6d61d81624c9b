"""Rasterization of a projected polygon (the paper's ref [10]; here ``cv2.fillPoly``)."""

from __future__ import annotations

import cv2
import numpy as np

#: Sub-pixel precision of the polygon's vertices for fillPoly, bits.
SHIFT = 4


def fill_polygon(uv: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Pixels inside a polygon given in image coordinates, clipped to the image.

    Parameters
    ----------
    uv : (k, 2) float64
        Vertices in pixels (column, row), finite, in order around the polygon.
    shape : (H, W)

    Returns
    -------
    rows, cols : (n,) int64
    """
    H, W = shape
    # keep cv2's fixed-point coordinates in range for vertices far outside the image
    uv = np.clip(uv, -4.0 * max(H, W), 4.0 * max(H, W))
    x0, y0 = np.floor(uv.min(0)).astype(int)
    x1, y1 = np.ceil(uv.max(0)).astype(int)
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, W - 1), min(y1, H - 1)
    if x1 < x0 or y1 < y0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    mask = np.zeros((y1 - y0 + 1, x1 - x0 + 1), np.uint8)
    pts = np.round((uv - [x0, y0]) * (1 << SHIFT)).astype(np.int32)
    cv2.fillPoly(mask, [pts], 1, lineType=cv2.LINE_8, shift=SHIFT)
    rr, cc = np.nonzero(mask)
    return rr + y0, cc + x0


__all__ = ["fill_polygon"]

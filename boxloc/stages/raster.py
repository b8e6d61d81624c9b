"""Rasterization of a projected polygon (the paper's ref [10]; here ``cv2.fillPoly``)."""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

#: Sub-pixel precision of the polygon's vertices for fillPoly, bits.
SHIFT = 4


def _polygon_mask(uv: np.ndarray, shape: tuple[int, int]
                  ) -> tuple[np.ndarray, int, int] | None:
    """The polygon's pixels as a uint8 mask over its bounding box clipped to the image,
    and the box's first column and row; None when the box misses the image."""
    H, W = shape
    # keep cv2's fixed-point coordinates in range for vertices far outside the image
    uv = np.clip(uv, -4.0 * max(H, W), 4.0 * max(H, W))
    x0, y0 = np.floor(uv.min(0)).astype(int)
    x1, y1 = np.ceil(uv.max(0)).astype(int)
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, W - 1), min(y1, H - 1)
    if x1 < x0 or y1 < y0:
        return None
    mask = np.zeros((y1 - y0 + 1, x1 - x0 + 1), np.uint8)
    pts = np.round((uv - [x0, y0]) * (1 << SHIFT)).astype(np.int32)
    cv2.fillPoly(mask, [pts], 1, lineType=cv2.LINE_8, shift=SHIFT)
    return mask, int(x0), int(y0)


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
    box = _polygon_mask(uv, shape)
    if box is None:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    mask, x0, y0 = box
    rr, cc = np.nonzero(mask)
    return rr + y0, cc + x0


def rectangle_pixels(
    project: Callable[[np.ndarray], np.ndarray], valid: np.ndarray, origin: np.ndarray,
    x_axis: np.ndarray, y_axis: np.ndarray, u_range: tuple[float, float],
    v_range: tuple[float, float],
) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Valid pixels of a rectangle in 3D, projected into the image and clipped to it.

    Parameters
    ----------
    project : callable
        The sensor's projection, (n, 3) -> (n, 2) pixels (column, row).
    valid : (H, W) bool
        Pixels with a return.
    origin, x_axis, y_axis : (3,) float64
        The rectangle's frame.
    u_range, v_range : (float, float)
        Its extent along x_axis and y_axis, metres from origin.

    Returns
    -------
    rows, cols : (n,) int64
        Its valid pixels, row by row.
    inside : float
        Fraction of its projected area inside the image.

    None where a corner has no projection.
    """
    (u0, u1), (v0, v1) = u_range, v_range
    corners = np.array([origin + u0 * x_axis + v0 * y_axis, origin + u1 * x_axis + v0 * y_axis,
                        origin + u1 * x_axis + v1 * y_axis, origin + u0 * x_axis + v1 * y_axis])
    uv = project(corners)
    if not np.isfinite(uv).all():
        return None
    box = _polygon_mask(uv, valid.shape)
    if box is None:
        rr = cc = np.zeros(0, np.int64)
        n_in = 0
    else:
        # the valid ones of the polygon's pixels, by masking the box before np.nonzero
        mask, x0, y0 = box
        h, w = mask.shape
        n_in = int(np.count_nonzero(mask))
        rr, cc = np.nonzero(mask.view(np.bool_) & valid[y0:y0 + h, x0:x0 + w])
        rr, cc = rr + y0, cc + x0
    return rr, cc, min(n_in / max(polygon_area(uv), 1.0), 1.0)


def polygon_area(uv: np.ndarray) -> float:
    """Area of a simple polygon (k, 2), in its units squared (shoelace formula)."""
    du, dv = uv[:, 0], uv[:, 1]
    # np.roll(x, -1), without its generality's cost (thousands of calls a scan)
    return 0.5 * abs(float(du @ np.concatenate((dv[1:], dv[:1]))
                           - dv @ np.concatenate((du[1:], du[:1]))))


__all__ = ["fill_polygon", "polygon_area", "rectangle_pixels"]

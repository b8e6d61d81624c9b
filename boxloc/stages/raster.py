"""Rasterization of a projected polygon (the paper's ref [10]; here ``cv2.fillPoly``)."""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from boxloc.kernels import kernel

#: Sub-pixel precision of the polygon's vertices for fillPoly, bits.
SHIFT = 4


def _polygon_mask(uv: np.ndarray, shape: tuple[int, int]
                  ) -> tuple[np.ndarray, int, int] | None:
    """The polygon's pixels as a uint8 mask over its bounding box clipped to the image,
    and the box's first column and row; None when the box misses the image."""
    H, W = shape
    x0, y0, x1, y1, pts = _box(np.ascontiguousarray(uv, np.float64), H, W)
    if x1 < x0 or y1 < y0:
        return None
    mask = np.zeros((y1 - y0 + 1, x1 - x0 + 1), np.uint8)
    cv2.fillPoly(mask, [pts], 1, lineType=cv2.LINE_8, shift=SHIFT)
    return mask, int(x0), int(y0)


@kernel
def _box(uv: np.ndarray, H: int, W: int) -> tuple[int, int, int, int, np.ndarray]:
    """The polygon's bounding box (x0, y0, x1, y1) clipped to the image, and its vertices
    in fillPoly's fixed point relative to (x0, y0) (int32, (k, 2)): the NumPy expressions
    they replace, value for value (clip, floor, ceil, round half to even), in one call."""
    # keep cv2's fixed-point coordinates in range for vertices far outside the image
    lim = 4.0 * max(H, W)
    k = uv.shape[0]
    c = np.empty((k, 2))
    for i in range(k):
        for a in range(2):
            c[i, a] = min(max(uv[i, a], -lim), lim)
    lo0, lo1 = c[0, 0], c[0, 1]
    hi0, hi1 = c[0, 0], c[0, 1]
    for i in range(1, k):
        lo0, lo1 = min(lo0, c[i, 0]), min(lo1, c[i, 1])
        hi0, hi1 = max(hi0, c[i, 0]), max(hi1, c[i, 1])
    bx0, by0 = int(np.floor(lo0)), int(np.floor(lo1))
    x0, y0 = max(bx0, 0), max(by0, 0)
    x1, y1 = min(int(np.ceil(hi0)), W - 1), min(int(np.ceil(hi1)), H - 1)
    pts = np.empty((k, 2), np.int32)
    for i in range(k):
        pts[i, 0] = np.int32(np.rint((c[i, 0] - x0) * (1 << SHIFT)))
        pts[i, 1] = np.int32(np.rint((c[i, 1] - y0) * (1 << SHIFT)))
    return x0, y0, x1, y1, pts


@kernel
def _valid_in(mask: np.ndarray, valid: np.ndarray, x0: int, y0: int
              ) -> tuple[np.ndarray, np.ndarray, int]:
    """The valid pixels (rows, cols; row by row, as np.nonzero) of a polygon's mask over its
    box at (x0, y0), and the number of the mask's pixels."""
    h, w = mask.shape
    n_in = 0
    k = 0
    for i in range(h):
        for j in range(w):
            if mask[i, j]:
                n_in += 1
                if valid[y0 + i, x0 + j]:
                    k += 1
    rr = np.empty(k, np.int64)
    cc = np.empty(k, np.int64)
    q = 0
    for i in range(h):
        for j in range(w):
            if mask[i, j] and valid[y0 + i, x0 + j]:
                rr[q] = y0 + i
                cc[q] = x0 + j
                q += 1
    return rr, cc, n_in


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
        # the valid ones of the polygon's pixels (a kernel: one pass over the box)
        mask, x0, y0 = box
        rr, cc, n_in = _valid_in(mask, valid, x0, y0)
    return rr, cc, min(n_in / max(polygon_area(uv), 1.0), 1.0)


def polygon_area(uv: np.ndarray) -> float:
    """Area of a simple polygon (k, 2), in its units squared (shoelace formula)."""
    du, dv = uv[:, 0], uv[:, 1]
    # np.roll(x, -1), without its generality's cost (thousands of calls a scan)
    return 0.5 * abs(float(du @ np.concatenate((dv[1:], dv[:1]))
                           - dv @ np.concatenate((du[1:], du[:1]))))


__all__ = ["fill_polygon", "polygon_area", "rectangle_pixels"]

"""The pallet, and box footprints on the base plane: corners, separation, stacking.

A box is a row ``(cx, cy, cz, sx, sy, sz, yaw)`` in the base frame (metres, radians; z up,
the floor at z = 0). Its footprint is the rotated rectangle it covers in the xy plane.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["PALLET_SIZE"]

#: The pallet slab (x, y, z extent), metres; centred on the base origin, standing on z = 0.
PALLET_SIZE = (1.2, 0.8, 0.144)
_PALLET_TOP = PALLET_SIZE[2]
#: Box footprints that overlap by more than this (every axis) are "resting on" each other.
_REST_OVERLAP = 0.001


def _footprint_sep(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Separating-axis distance of box footprints (rotated rectangles), metres.

    Parameters
    ----------
    a : (N, 7), b : (M, 7) float64
        Boxes (cx, cy, cz, sx, sy, sz, yaw).

    Returns
    -------
    (N, M) float64
        Positive: the footprints are disjoint, at least this far apart along some axis.
        Negative: they overlap, by at least ``-sep`` along every axis.
    """
    d = b[None, :, :2] - a[:, None, :2]
    ca, sa = np.cos(a[:, 6])[:, None], np.sin(a[:, 6])[:, None]
    cb, sb = np.cos(b[:, 6])[None, :], np.sin(b[:, 6])[None, :]
    hxa, hya = a[:, 3, None] / 2, a[:, 4, None] / 2
    hxb, hyb = b[None, :, 3] / 2, b[None, :, 4] / 2
    sep = np.full(d.shape[:2], -np.inf)
    for ax, ay in ((ca, sa), (-sa, ca), (cb, sb), (-sb, cb)):
        ra = hxa * np.abs(ca * ax + sa * ay) + hya * np.abs(-sa * ax + ca * ay)
        rb = hxb * np.abs(cb * ax + sb * ay) + hyb * np.abs(-sb * ax + cb * ay)
        gap = np.abs(d[..., 0] * ax + d[..., 1] * ay) - ra - rb
        sep = np.maximum(sep, gap)
    return sep


def _footprint_corners(box: np.ndarray) -> np.ndarray:
    """(4, 2) corners of a box's footprint in the base xy plane."""
    c, s = math.cos(box[6]), math.sin(box[6])
    hx, hy = box[3] / 2, box[4] / 2
    local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    return box[:2] + local @ np.array([[c, s], [-s, c]])


def _collides(box: np.ndarray, placed: list[np.ndarray], clearance: float) -> bool:
    """Whether ``box`` comes closer than ``clearance`` to a placed box at overlapping heights."""
    if not placed:
        return False
    P = np.asarray(placed)
    lo, hi = box[2] - box[5] / 2, box[2] + box[5] / 2
    z_overlap = (np.minimum(hi, P[:, 2] + P[:, 5] / 2)
                 - np.maximum(lo, P[:, 2] - P[:, 5] / 2)) > 1e-9
    sep = _footprint_sep(box[None], P)[0]
    return bool((z_overlap & (sep < clearance - 1e-12)).any())


def _rests_on(boxes: np.ndarray) -> np.ndarray:
    """``covered[i]``: some box rests on box i's top, shape (B,), bool."""
    B = len(boxes)
    if B == 0:
        return np.zeros(0, bool)
    top = boxes[:, 2] + boxes[:, 5] / 2
    bottom = boxes[:, 2] - boxes[:, 5] / 2
    touching = np.abs(bottom[None, :] - top[:, None]) < 1e-6  # [i, j]: j's bottom on i's top
    overlap = _footprint_sep(boxes, boxes) < -_REST_OVERLAP
    on = touching & overlap
    np.fill_diagonal(on, False)
    return np.asarray(on.any(1), dtype=bool)


def _rot_z(yaw: float) -> np.ndarray:
    """(2, 2) rotation of the base xy plane by ``yaw`` radians."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s], [s, c]])

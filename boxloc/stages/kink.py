"""Kinks: where two bulged lids meet, the face's slope jumps.

Touching cartons of equal height whose lids bulge (the cardboard sags up toward the middle
of each top) meet in a shallow V. Its depth is the bulge, millimetres, spread over the
cartons' half-widths, so the groove statistic of :mod:`boxloc.stages.seams`, which compares
a narrow window with flanks a few point spacings away, sees a fraction of a millimetre of
it. What the V does show, over the whole face, is a jump of the slope across the seam: a
lid bulged ``b`` over a carton of width ``w`` meets its neighbour at a slope of ``4 b / w``
each side (0.27 rad between them for 8.8 mm over 0.26 m), where one carton's lid is smooth.

:func:`kink_z` fits the face's residuals (off its plane) with a smooth surface, a quadratic
in both in-plane coordinates with the product term a bulged lid has, plus a hinge
``|x - x0|`` at each line tested, and tests the hinges' sum against zero, one-sided: a V
opens toward the sensor (the residuals rise away from the line). A ridge (tape along a
lid's middle) is the other sign and no seam. The variance of the fitted hinge is the
jackknife's over square blocks of the face (the fit again without each block, CR3), so
that spatially correlated and heteroscedastic noise, and whatever of the lid's shape the
quadratic misses, widen it as they widen the hinge's true scatter; the critical value is
Student's t with the blocks less one as degrees of freedom (few blocks: a wide null).

On one bulged lid under noise smoothed over 2.5 spacings, normal or Student's t with 3
dof, the test at its middle fired on 0.7-1.8 % of 600 draws at alpha = 1 % (the plain
cluster-robust sum over blocks of 16 spacings: 3.8 %; its z's scatter was 1.38).
"""

from __future__ import annotations

import math

import numpy as np

from boxloc.distributions import t_isf

#: Side of the blocks the jackknife leaves out in turn, in point spacings: past the
#: correlation lengths measured on real stereo depth (0.17-0.24 left at 8 px).
KINK_BLOCK_SPACINGS = 24.0
#: Fewest blocks for a kink test; with fewer the hinge's variance is not estimated.
KINK_MIN_BLOCKS = 8
#: The points read lie this many point spacings inside the face's sides: a rectangle's
#: sides may lie a centimetre off its top's, and the bevel and mixed pixels there bend
#: the fit (on 12 draws of one flat 0.30 x 0.45 m top at 1.5 m, 11 of 298 rows fired at
#: 3 spacings, none of 254 at 6).
KINK_INSET_SPACINGS = 6.0
#: Length of the blocks along a side for :func:`side_kink_z`, in point spacings (the band
#: across the side is narrower than a face's blocks).
KINK_SIDE_BLOCK_SPACINGS = 12.0
#: A side's kink is tested only where the face's points beyond it number at least this
#: share of those within the same reach inside it (a neighbour's lid, not a wall's foot).
KINK_BEYOND_SHARE = 0.5


def kink_z(u: np.ndarray, v: np.ndarray, w: np.ndarray, axis: int, lines: list[float],
           width: float, length: float, spacing: float) -> tuple[float, int]:
    """Test for a slope jump (a V opening toward the sensor) along lines across a face.

    Parameters
    ----------
    u, v : (n,) float64
        The points' coordinates in the face, metres (0..width, 0..length inside it).
    w : (n,) float64
        Their residuals off the face's plane, toward the sensor positive (any unit).
    axis : int
        0: the lines are u = const; 1: v = const.
    lines : list of float
        The lines' positions along ``axis``, metres.
    width, length : float
        The face's extent, metres.
    spacing : float
        Point spacing on the face, metres.

    Returns
    -------
    z : float
        The hinges' summed coefficient over its cluster-robust standard error (NaN where
        the face has too few blocks or points, or the fit is singular).
    dof : int
        Blocks less one: the degrees of freedom of ``z``'s t null (0 with ``z`` NaN).
    """
    m = KINK_INSET_SPACINGS * spacing
    inside = (u >= m) & (u <= width - m) & (v >= m) & (v <= length - m)
    if inside.sum() < 50:
        return math.nan, 0
    uu, vv, ww = u[inside], v[inside], w[inside]
    x, y = (uu, vv) if axis == 0 else (vv, uu)
    sx, sy = (width, length) if axis == 0 else (length, width)
    # centred and scaled to about -1..1: a well-conditioned design
    xs = (x - 0.5 * sx) / (0.5 * sx)
    ys = (y - 0.5 * sy) / (0.5 * sy)
    y2 = ys * ys
    hinges = [np.abs(xs - (p - 0.5 * sx) / (0.5 * sx)) for p in lines]
    smooth = [np.ones_like(xs), xs, xs * xs, ys, y2, xs * ys, xs * xs * y2]
    # each hinge's strength follows the lids' bulge across the line (largest at their middle)
    smooth += [h * y2 for h in hinges]
    b = KINK_BLOCK_SPACINGS * spacing
    block = np.floor(uu / b).astype(np.int64) * 1_000_003 + np.floor(vv / b).astype(np.int64)
    return _hinge_z(np.column_stack(smooth + hinges), len(hinges), ww, block)


def side_kink_z(u: np.ndarray, v: np.ndarray, w: np.ndarray, axis: int, at: float,
                inward: float, start: float, end: float, reach: float, spacing: float
                ) -> tuple[float, int]:
    """Test for a slope jump along one side of a face (the line ``at`` along ``axis``, from
    ``start`` to ``end`` along it; the face on the side of it ``inward``, +1 or -1, points
    to), from the points within ``reach`` of it on both sides: where a bulged lid meets
    its neighbour's, its side is the V's bottom.

    As :func:`kink_z`, with a hinge at the line in a fit that is linear across it and
    quadratic along it (near the seam each lid's profile is its slope), and the blocks
    ``KINK_SIDE_BLOCK_SPACINGS`` long along the side, the band's full width across.
    """
    x, y = (u, v) if axis == 0 else (v, u)
    m = KINK_INSET_SPACINGS * spacing
    near = (np.abs(x - at) <= reach) & (y >= start + m) & (y <= end - m)
    if near.sum() < 50 or end - start <= 2 * m:
        return math.nan, 0
    # a lid on both sides: the face's points run on beyond the side as far as before it.
    # Where a wall rises from the side (a taller neighbour, the pallet's rim) only its
    # foot is near the plane, and its slope is no seam's
    n_in = int((near & ((x - at) * inward > 0)).sum())
    n_out = int((near & ((x - at) * inward < 0)).sum())
    if n_out < KINK_BEYOND_SHARE * n_in:
        return math.nan, 0
    xs = (x[near] - at) / reach
    yc = y[near]
    ys = (yc - 0.5 * (start + end)) / (0.5 * (end - start))
    y2 = ys * ys
    h = np.abs(xs)
    X = np.column_stack([np.ones_like(xs), xs, ys, y2, xs * ys, xs * y2, h * y2, h])
    block = np.floor((yc - start) / (KINK_SIDE_BLOCK_SPACINGS * spacing)).astype(np.int64)
    return _hinge_z(X, 1, w[near], block)


def _hinge_z(X: np.ndarray, k: int, w: np.ndarray, block: np.ndarray) -> tuple[float, int]:
    """The sum of the last ``k`` coefficients of the least-squares fit of ``w`` by the
    columns of ``X`` (n, p), over its jackknife standard error over the blocks; and the
    blocks less one. NaN, 0 where there are too few blocks or the fit is singular."""
    ids, inv = np.unique(block, return_inverse=True)
    G = len(ids)
    if G < KINK_MIN_BLOCKS:
        return math.nan, 0
    XtX = X.T @ X
    try:
        A = np.linalg.inv(XtX)
    except np.linalg.LinAlgError:
        return math.nan, 0
    if not np.all(np.isfinite(A)):
        return math.nan, 0
    beta = A @ (X.T @ w)
    e = w - X @ beta
    # the jackknife over blocks (CR3): the fit without each block in turn. The plain
    # cluster sum (CR1) read the hinge's scatter 1.4 times too small on a bulged face
    # whose noise was correlated over a few spacings: the hinge leans on few blocks
    p = X.shape[1]
    S = np.zeros((G, p))
    np.add.at(S, inv, X * e[:, None])
    M = np.zeros((G, p, p))
    np.add.at(M, inv, X[:, :, None] * X[:, None, :])
    try:
        D = np.linalg.solve(XtX[None, :, :] - M, S[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:
        return math.nan, 0
    V = D.T @ D * ((G - 1.0) / G)
    c = np.zeros(p)
    c[-k:] = 1.0
    var = float(c @ V @ c)
    if not (var > 0.0 and math.isfinite(var)):
        return math.nan, 0
    return float(c @ beta) / math.sqrt(var), G - 1


def kink_critical(alpha: float, dof: int) -> float:
    """One-sided critical value of :func:`kink_z` at ``alpha``: Student's t, ``dof``."""
    return float(t_isf(alpha, dof)) if dof > 0 else math.inf

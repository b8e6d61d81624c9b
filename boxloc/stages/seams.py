"""Seams: straight lines of range points lying behind a face's plane.

Two boxes of equal height that touch leave a seam between their tops: their bevelled or
rounded edges and the gap form a groove a few millimetres deep and wide. Seen from 2-3 m
that groove is shallower than the noise of one sample, so the edge stage, which tests each
scan line on its own, finds it only in part. Along a *known* direction the evidence adds
up: the points of a whole side, binned by their distance across it, give a profile whose
groove bin is significantly behind its flanks. This module supplies that profile test to

* :func:`boxloc.stages.hypotheses.dimensions_from_edges` — seams inside the region a vertex's
  edge accumulators span are extra dimension candidates (the paper's 1-D accumulators,
  with range points as voters where edge points are missing);
* :func:`boxloc.stages.verify.verify` — a side with no line of boundary edges is still a boundary
  if it is a seam, and a rectangle with a seam inside is two faces, not one.

The statistic compares the mean residual of the points within ``SEAM_INNER`` spacings of a
position with the mean of the two flanks ``SEAM_FLANK`` spacings away (their average, so a
tilt of the reference plane cancels): z = (flanks - groove) / sd, positive when the groove
lies behind. The groove must also lie behind each flank on its own, by at least half its
depth (the flanks differ by less than the groove is deep): a ridge beside the window, tape
or a label on a lid, lifts one flank by its height and makes the flat lid beside it look a
groove half as deep, level with the other flank. (That condition does see a tilt: the
residuals are to the face's own refitted plane.) Every search and test takes the larger
statistic of two groove widths (:data:`SEAM_SCALES`: the windows scaled by 1 and by 2),
Bonferroni over both: the valley between two bulged lids is wider than a bevel's groove.

The variance comes from the points' own scatter (a robust scale of their residuals, at
least the noise model's), so a sensor noisier than its model does not make seams out of
noise; where the noise is correlated (structured-light depth), the statistic's own spread
over the positions is divided out as well. A sensor whose rows share part of their noise
(``NoiseModel.row_corr``; the Kinect: about a quarter of the variance) puts a whole row a
little behind or in front of the plane: along a row that is one groove window's worth of
evidence, not hundreds of independent points. With the points' image rows given, the
statistic's variance counts each row's shared offset once (and across the rows, where the
offsets cancel between the groove and its flanks, only the rest).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy import special

from boxloc.distributions import norm_isf
from boxloc.kernels import kernel
from boxloc.stages.raster import rectangle_pixels

#: Half-width of the groove window, in point spacings (the groove plus the uncertainty of
#: where a side is).
SEAM_INNER = 1.0
#: Inner and outer distance of each flank window from the groove, in point spacings
#: (beyond the bevels of both boxes).
SEAM_FLANK = (2.5, 5.0)
#: The groove windows tried, in multiples of the point spacing (the windows above scaled):
#: the groove of a bevel or a gap, a spacing or two wide, and the valley between two bulged
#: lids, which falls over the lids' shoulders, several spacings wide. A narrow window sees
#: only the valley's bottom: on a development scene of bulged lids (1.2 cm, 2 m, laser) the
#: true seams gave z 1-4 at 1 spacing and 5-9 at 2. Tested together, Bonferroni over both.
SEAM_SCALES = (1.0, 2.0)
#: Level of the flanks' balance (two-sided; the default alpha): a difference of the flanks'
#: counts beyond its z and one spacing's column is a band of no return beside the window,
#: not a seam (see :func:`_seam_stats`).
FLANK_BALANCE_ALPHA = 0.01
FLANK_BALANCE_Z = float(norm_isf(FLANK_BALANCE_ALPHA / 2.0))


@dataclass(frozen=True)
class FacePoints:
    """Range points of one face's region, in the face's frame.

    Attributes
    ----------
    u, v : (n,) float64
        Coordinates along the rectangle's x and y axes, metres.
    w : (n,) float64
        Signed distance to the plane refitted to the region's points (positive toward
        the sensor), metres.
    scale : float
        Standard deviation of one residual: the robust scatter of ``w`` (1.4826 MAD), at
        least the noise model's median sigma there, metres.
    spacing : float
        Point spacing at the region's centre, metres.
    row : (n,) int64
        Image row of each point (for ``row_corr``).
    row_corr : float
        Correlation of two points' noise in the same image row
        (:attr:`boxloc.scan.NoiseModel.row_corr`).
    spread : (tuple of float, tuple of float)
        :func:`seam_spread` of the statistic along u and along v, at each of
        :data:`SEAM_SCALES`, which a seam at a side (tested at too few positions to measure
        it) is divided by; all 1 until the face's interior has measured it
        (:func:`boxloc.stages.verify.verify`).
    """

    u: np.ndarray
    v: np.ndarray
    w: np.ndarray
    scale: float
    spacing: float
    row: np.ndarray
    row_corr: float = 0.0
    spread: tuple[tuple[float, ...], tuple[float, ...]] = ((1.0,) * len(SEAM_SCALES),
                                                           (1.0,) * len(SEAM_SCALES))

    def __len__(self) -> int:
        return int(self.u.shape[0])


def face_points(
    points: np.ndarray,
    valid: np.ndarray,
    sigma: np.ndarray,
    project: Callable[[np.ndarray], np.ndarray],
    origin: np.ndarray,
    x_axis: np.ndarray,
    y_axis: np.ndarray,
    normal: np.ndarray,
    u_range: tuple[float, float],
    v_range: tuple[float, float],
    spacing: float,
    alpha: float,
    row_corr: float = 0.0,
    gain: np.ndarray | None = None,
) -> FacePoints:
    """The range points of a rectangular region of a face's plane, with their residuals.

    Parameters
    ----------
    points : (H, W, 3) float64
        Organized cloud, metres.
    valid : (H, W) bool
    sigma : (H, W) float64
        Per-point noise along the ray, metres (the first inlier test's scale).
    project : callable
        The sensor's projection, (n, 3) -> (n, 2) pixels.
    origin, x_axis, y_axis, normal : (3,) float64
        The face's frame.
    u_range, v_range : (float, float)
        The region, metres along x_axis and y_axis (clipped to the image).
    spacing : float
        Point spacing there, metres.
    alpha : float
        Significance level; a point is on the face if its distance to the plane passes a
        z test Bonferroni-corrected over the region's points (a groove a few sigma deep
        stays in, another surface does not).
    row_corr : float
        :attr:`FacePoints.row_corr`.
    gain : (H, W) float64 >= 1, optional
        How much louder than the scan's typical level the noise is around each pixel
        (:func:`boxloc.stages.edges.local_scale`). Real depth noise is heavy-tailed the way
        a scale mixture is: its amplitude wanders over a face (a stereo matcher's quality
        with the texture), and one scale for the whole face makes a seam of every window
        in a louder patch (a patch three times louder on a tilted plane: false seams in at
        least 10 of 20 draws, ``tests/test_seams.py``). Each residual is divided by its
        pixel's gain (the points' noise then has one scale), and a point's on-plane test
        allows for it. It does not mend the active-stereo field's own tail: true tops
        still cross a seam at 1 % on about 3 % of their axes (docs/method.md).

    Returns
    -------
    FacePoints
    """
    empty = FacePoints(np.zeros(0), np.zeros(0), np.zeros(0), np.nan, spacing,
                       np.zeros(0, np.int64), row_corr)
    pix = rectangle_pixels(project, valid, origin, x_axis, y_axis, u_range, v_range)
    if pix is None:
        return empty
    rr, cc, _ = pix
    flat = rr * valid.shape[1] + cc
    if len(flat) < 3:
        return empty
    # the element-wise work, gathers and medians in kernels; the products stay NumPy's
    # (BLAS: their rounding is theirs)
    P, s, D = _gather(np.ascontiguousarray(points, np.float64).reshape(-1, 3),
                      np.ascontiguousarray(sigma, np.float64).reshape(-1), flat,
                      np.asarray(origin, np.float64))
    g = None
    if gain is not None:
        g = np.ascontiguousarray(gain, np.float64).reshape(-1)[flat]
        if (g == 1.0).all():
            g = None  # the scan's typical level everywhere: the residuals as they are
    s_model = s
    if g is not None:
        s = s * g
    w = D @ normal
    zc = float(norm_isf(alpha / (2.0 * len(flat))))
    # the face's own points first (relative to the given plane, tilt allowed for by the
    # median), then the plane refitted to them
    on, n_on = _near_plane(w, s, zc)
    if n_on < 3:
        return empty
    c, X1, X2 = _centred(P, on)
    _, V = np.linalg.eigh(X1.T @ X2)
    nf = V[:, 0] if V[:, 0] @ normal > 0 else -V[:, 0]
    wf = (P - c) @ nf
    wf_all = wf
    n_on, wf, mad, s_med, Don, r_on = _kept(wf, s, zc, D, rr)
    if n_on < 3:
        return empty
    if g is not None:  # the residuals in units of the scan's typical level (kernels' median)
        on_f = np.abs(wf_all) <= zc * s  # _kept's points
        wf = wf / g[on_f]
        mad = _median(np.abs(wf - _median(wf)))
        s_med = _median(s_model[on_f])
    # the points' own scatter, but never below the noise model (a noise-free or quantized
    # surface would otherwise make seams of rounding)
    scale = max(float(1.4826 * mad), float(s_med), 1e-9)
    # each point's place on the face from its pixel's ray, not from the noisy point: range
    # noise moves a point along its ray, which on a tilted face moves its orthogonal
    # projection across the face too, in step with its residual, and a window then takes
    # in the boundary's points by the sign of their noise
    Don = _on_plane_along_rays(Don, np.asarray(origin, np.float64), c, nf)
    return FacePoints(Don @ x_axis, Don @ y_axis, wf, scale, spacing, r_on, row_corr)


#: Sine of the angle below which a ray is too close to a face's plane to be moved onto it.
_MIN_RAY_COS = math.sin(math.radians(1.0))


def _on_plane_along_rays(D: np.ndarray, origin: np.ndarray, c: np.ndarray, nf: np.ndarray
                         ) -> np.ndarray:
    """Points ``origin + D`` (n, 3) moved along their rays from the sensor onto the plane
    through ``c`` with unit normal ``nf``, as offsets from ``origin`` again. A ray within
    a degree of the plane keeps its point (the intersection is ill-conditioned there)."""
    P = D + origin
    # the products NumPy's (BLAS, einsum: their rounding is theirs), the rest in a kernel
    return _along_rays(P, np.sqrt(np.einsum("ij,ij->i", P, P)), P @ nf, float(c @ nf),
                       origin)


@kernel
def _along_rays(P: np.ndarray, r: np.ndarray, pn: np.ndarray, cn: float, origin: np.ndarray
                ) -> np.ndarray:
    """:func:`_on_plane_along_rays`' element-wise part, bit for bit: P (n, 3), r its rows'
    norms, pn = P @ nf, cn = c @ nf; P * scale - origin, scale = t / r (1 where r is not
    above 0), t = cn / cos where |cos| = |pn / r| > ``_MIN_RAY_COS``, else r."""
    n = P.shape[0]
    out = np.empty((n, 3))
    for i in range(n):
        ri = r[i]
        scale = 1.0
        if ri > 0.0:
            cos = pn[i] / ri
            t = cn / cos if abs(cos) > _MIN_RAY_COS else ri
            scale = t / ri
        for a in range(3):
            out[i, a] = P[i, a] * scale - origin[a]
    return out


# --- face_points' kernels: each NumPy expression it replaces, bit for bit --------------------


#: Buckets of :func:`_middle`'s histogram: the middle one holds about n / 1024 values.
_MEDIAN_BUCKETS = 1024


@kernel
def _middle(x: np.ndarray) -> tuple[float, float]:
    """The order statistics x_(m - 1) and x_(m), m = n // 2, of finite x (n >= 2).

    A histogram of the values (buckets of equal width: a value's bucket is a monotonic
    function of it) finds the bucket holding rank m; only that bucket's values are
    partitioned. O(n) in three passes; values bunched in one bucket cost a partition of
    them, as np.median's own.
    """
    n = x.shape[0]
    m = n // 2
    lo = hi = x[0]
    for i in range(1, n):
        lo = min(lo, x[i])
        hi = max(hi, x[i])
    if not hi > lo:
        return lo, lo
    nb = _MEDIAN_BUCKETS
    scale = nb / (hi - lo)
    if not math.isfinite(scale):
        scale = 0.0
    count = np.zeros(nb, np.int64)
    for i in range(n):
        count[min(int((x[i] - lo) * scale), nb - 1)] += 1
    below = 0  # values in the buckets before the one holding rank m
    bm = 0
    while below + count[bm] <= m:
        below += count[bm]
        bm += 1
    y = np.empty(count[bm])
    k = 0
    for i in range(n):
        if min(int((x[i] - lo) * scale), nb - 1) == bm:
            y[k] = x[i]
            k += 1
    y = np.partition(y, m - below)
    xm = y[m - below]
    if m - below == 0:  # rank m - 1: the largest value of the earlier buckets
        prev = -math.inf
        for i in range(n):
            if min(int((x[i] - lo) * scale), nb - 1) < bm:
                prev = max(prev, x[i])
        return prev, xm
    xm1 = y[0]  # rank m - 1: the largest value below rank m in the bucket
    for i in range(1, m - below):
        xm1 = max(xm1, y[i])
    return xm1, xm


@kernel
def _median(x: np.ndarray) -> float:
    """``np.median(x)`` bit for bit: NaN if any is NaN (or x is empty); else the middle
    order statistic, or the two, through np.mean's sum and count: (0.0 + a) / 1 or
    ((0.0 + a) + b) / 2 (the 0.0 turns a -0.0 into +0.0, as NumPy's sum does)."""
    n = x.shape[0]
    if n == 0:
        return math.nan
    for i in range(n):
        if math.isnan(x[i]):
            return math.nan
    if n == 1:
        return (0.0 + x[0]) / 1.0
    a, b = _middle(x)
    if n % 2:
        return (0.0 + b) / 1.0
    return ((0.0 + a) + b) / 2.0


@kernel
def _gather(points: np.ndarray, sigma: np.ndarray, flat: np.ndarray, origin: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``P = points[flat]``, ``s = sigma[flat]`` and ``D = P - origin`` in one pass;
    points (N, 3), sigma (N,), flat (n,) int64; P, D (n, 3), s (n,)."""
    n = flat.shape[0]
    P = np.empty((n, 3))
    D = np.empty((n, 3))
    s = np.empty(n)
    for q in range(n):
        i = flat[q]
        s[q] = sigma[i]
        for a in range(3):
            P[q, a] = points[i, a]
            D[q, a] = points[i, a] - origin[a]
    return P, s, D


@kernel
def _near_plane(w: np.ndarray, s: np.ndarray, zc: float) -> tuple[np.ndarray, int]:
    """The points near the given plane, ``|w - median(w)| <= zc s + 3 x 1.4826 x
    median(|w - median(w)|)`` (bool (n,)), and their number."""
    dw = np.abs(w - _median(w))
    t = 3.0 * 1.4826 * _median(dw)
    on = np.empty(w.shape[0], np.bool_)
    k = 0
    for i in range(w.shape[0]):
        on[i] = dw[i] <= zc * s[i] + t
        k += on[i]
    return on, k


@kernel
def _centred(P: np.ndarray, on: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``Q = P[on]``, its mean c (np.mean's column sums: sequential, from 0.0) and ``Q - c``
    twice: the scatter matrix's two operands as before (one array for both would make
    NumPy's matmul take another BLAS routine, syrk)."""
    k = 0
    c = np.zeros(3)
    for i in range(P.shape[0]):
        if on[i]:
            for a in range(3):
                c[a] += P[i, a]
            k += 1
    for a in range(3):
        c[a] = c[a] / k
    X1 = np.empty((k, 3))
    X2 = np.empty((k, 3))
    q = 0
    for i in range(P.shape[0]):
        if on[i]:
            for a in range(3):
                X1[q, a] = X2[q, a] = P[i, a] - c[a]
            q += 1
    return c, X1, X2


@kernel
def _kept(wf: np.ndarray, s: np.ndarray, zc: float, D: np.ndarray, rr: np.ndarray
          ) -> tuple[int, np.ndarray, float, float, np.ndarray, np.ndarray]:
    """The points on the refitted plane, ``|wf| <= zc s``: their number, residuals, the
    median absolute deviation of those, the median of their ``s``, their D and rows."""
    on = np.abs(wf) <= zc * s
    w_on = wf[on]
    mad = _median(np.abs(w_on - _median(w_on)))
    return w_on.shape[0], w_on, mad, _median(s[on]), D[on], rr[on]


def _window_offsets(h: float) -> tuple[tuple[float, float], ...]:
    """The groove window and the two flanks, as (from, to) offsets from a centre, metres."""
    a, b = SEAM_FLANK[0] * h, SEAM_FLANK[1] * h
    return (-SEAM_INNER * h, SEAM_INNER * h), (-b, -a), (a, b)


#: Twice a flank's width, in spacings: (nl + nr) / this is one spacing's column of points,
#: by which the two flanks' counts may differ on the sampling grid alone (:func:`_seam_stats`).
_FLANK_COLUMNS = 2.0 * (SEAM_FLANK[1] - SEAM_FLANK[0])


def _reach(centres: np.ndarray, h: float) -> tuple[float, float]:
    """The strip [lo, hi] the windows around ``centres`` (not empty) reach at window scale
    ``h``: the flanks reach farthest."""
    r = SEAM_FLANK[1] * h
    return float(centres.min() - r), float(centres.max() + r)


def _strip(scaled: Iterable[tuple[float, np.ndarray]]) -> tuple[float, float]:
    """The strip that the windows of several scales reach: (window scale, centres) pairs
    (each scale's :func:`_reach`, together)."""
    ends = [_reach(c, hs) for hs, c in scaled]
    return min(lo for lo, _ in ends), max(hi for _, hi in ends)


def _in_reach(coord: np.ndarray, centres: np.ndarray, h: float) -> np.ndarray:
    """Which points some window around the centres reaches: a search near one side of a
    face then sorts and sums a strip, not the whole face."""
    if len(centres) == 0:
        return np.zeros(len(coord), bool)
    lo, hi = _reach(centres, h)
    return (coord >= lo) & (coord <= hi)


def _windows(coord: np.ndarray, w: np.ndarray, centres: np.ndarray, h: float
             ) -> tuple[np.ndarray, ...]:
    """Count and sum of w in the groove window and in each flank, per centre."""
    order = np.argsort(coord)
    cs = coord[order]
    cum = np.r_[0.0, np.cumsum(w[order])]
    out: list[np.ndarray] = []
    for lo, hi in _window_offsets(h):
        i0 = np.searchsorted(cs, centres + lo, "left")
        i1 = np.searchsorted(cs, centres + hi, "right")
        out += [(i1 - i0).astype(np.float64), cum[i1] - cum[i0]]
    return tuple(out)


#: Largest bucket :func:`_near_sorted` sorts by insertion; a bigger one (points bunched in
#: one bucket) is sorted by mergesort.
_BUCKET_INSERTION = 32


@kernel
def _strip_sorted(coord: np.ndarray, w: np.ndarray, row: np.ndarray, lo: float, hi: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """The points with ``lo <= coord <= hi``, sorted by ``coord``, with their ``w`` and
    ``row``; and whether their coordinates are all distinct.

    A bucket sort (buckets of equal width over the points' span; a point's bucket is a
    monotonic function of its coordinate), then insertion sort within each bucket: O(n)
    for points spread over a face. Distinct coordinates have one sorted order, np.argsort's
    too; where two tie, np.argsort's order among them decides the rounding of the window
    sums, and the caller sorts with it instead.
    """
    n = coord.shape[0]
    idx = np.empty(n, np.int64)
    k = 0
    for i in range(n):
        if coord[i] >= lo and coord[i] <= hi:
            idx[k] = i
            k += 1
    cs = np.empty(k)
    ws = np.empty(k)
    rs = np.empty(k, row.dtype)
    if k == 0:
        return cs, ws, rs, True
    cmin = cmax = coord[idx[0]]
    for q in range(1, k):
        c = coord[idx[q]]
        cmin = min(cmin, c)
        cmax = max(cmax, c)
    scale = k / (cmax - cmin) if cmax > cmin else 0.0
    if not math.isfinite(scale):  # a span below ~1e-308: everything in one bucket
        scale = 0.0
    # counting sort into the buckets (stable), then each bucket sorted in place
    bucket = np.empty(k, np.int64)
    start = np.zeros(k + 1, np.int64)
    for q in range(k):
        b = min(int((coord[idx[q]] - cmin) * scale), k - 1)
        bucket[q] = b
        start[b + 1] += 1
    for b in range(k):
        start[b + 1] += start[b]
    fill = start[:k].copy()
    srt = np.empty(k, np.int64)
    for q in range(k):
        srt[fill[bucket[q]]] = idx[q]
        fill[bucket[q]] += 1
    for b in range(k):
        a, e = start[b], start[b + 1]
        if e - a > _BUCKET_INSERTION:
            keys = np.empty(e - a)
            for q in range(a, e):
                keys[q - a] = coord[srt[q]]
            o = np.argsort(keys, kind="mergesort")
            part = srt[a:e].copy()
            for q in range(e - a):
                srt[a + q] = part[o[q]]
            continue
        for q in range(a + 1, e):
            v = srt[q]
            c = coord[v]
            p = q - 1
            while p >= a and coord[srt[p]] > c:
                srt[p + 1] = srt[p]
                p -= 1
            srt[p + 1] = v
    distinct = True
    for q in range(k):
        cs[q] = coord[srt[q]]
        ws[q] = w[srt[q]]
        rs[q] = row[srt[q]]
        if q and cs[q] == cs[q - 1]:
            distinct = False
    return cs, ws, rs, distinct


def _near_sorted(coord: np.ndarray, w: np.ndarray, row: np.ndarray, centres: np.ndarray,
                 h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points some window around the centres reaches (:func:`_in_reach`), in the order
    ``np.argsort`` of their coordinates puts them: coord, w and row, each (k,).

    ``coord`` and ``w`` are float64 and ``centres`` is not empty.
    """
    lo, hi = _reach(centres, h)
    cs, ws, rs, distinct = _strip_sorted(coord, w, row, lo, hi)
    if not distinct:  # ties: np.argsort's order among them, as _windows sorts
        near = (coord >= lo) & (coord <= hi)
        order = np.argsort(coord[near])
        cs, ws, rs = coord[near][order], w[near][order], row[near][order]
    return cs, ws, rs


@kernel
def _sorted_window_sums(cs: np.ndarray, ws: np.ndarray, centres: np.ndarray, los: np.ndarray,
                        his: np.ndarray) -> np.ndarray:
    """:func:`_windows` of points already sorted by their coordinate ``cs``, bit for bit.

    Returns
    -------
    (2 K, m) float64
        Per window k (``los[k]``, ``his[k]`` from a centre): the count and the sum of ``ws``,
        the sum as a difference of np.cumsum's running sums (sequential, the first term
        itself) at np.searchsorted's "left" and "right" indices.
    """
    n = cs.shape[0]
    cum = np.zeros(n + 1)
    if n:
        cum[1] = ws[0]
        for i in range(1, n):
            cum[i + 1] = cum[i] + ws[i]
    m = centres.shape[0]
    out = np.empty((2 * los.shape[0], m))
    for k in range(los.shape[0]):
        for j in range(m):
            q = centres[j] + los[k]  # first point >= q
            a, b = 0, n
            while a < b:
                mid = (a + b) >> 1
                if cs[mid] < q:
                    a = mid + 1
                else:
                    b = mid
            i0 = a
            q = centres[j] + his[k]  # first point > q
            a, b = 0, n
            while a < b:
                mid = (a + b) >> 1
                if cs[mid] <= q:
                    a = mid + 1
                else:
                    b = mid
            out[2 * k, j] = float(a - i0)
            out[2 * k + 1, j] = cum[a] - cum[i0]
    return out


@kernel
def _sorted_row_sums(cs: np.ndarray, r: np.ndarray, centres: np.ndarray, los: np.ndarray,
                     his: np.ndarray, coefs: np.ndarray, R: int) -> np.ndarray:
    """Per (centre, row) sums of the statistic's weights, (m * R,) float64, of points
    sorted by their coordinate ``cs``.

    For each window k, point i and centre j whose window k holds the point (j from the
    first centre >= cs[i] - his[k] to the last <= cs[i] - los[k]), coefs[k, j] is added to
    S[j * R + r[i]]. Bit for bit the expansion of every (point, centre) pair summed by
    np.bincount: within one window every term added to S[j * R + row] is the same
    coefs[k, j], so the order of the points does not change the sums, only that of the
    windows. Along sorted points the centres' range only moves forward (no searches).
    """
    m = centres.shape[0]
    S = np.zeros(m * R)
    for k in range(los.shape[0]):
        j0 = 0
        j1 = 0
        for i in range(cs.shape[0]):
            a = cs[i] - his[k]
            b = cs[i] - los[k]
            while j0 < m and centres[j0] < a:  # first centre >= a
                j0 += 1
            while j1 < m and centres[j1] <= b:  # first centre > b
                j1 += 1
            ri = r[i]
            for j in range(j0, j1):
                S[j * R + ri] += coefs[k, j]
    return S


@kernel
def _pairwise_sum(a: np.ndarray, lo: int, n: int) -> float:
    """``a[lo:lo + n].sum()`` bit for bit: NumPy's pairwise summation of float64 (eight
    accumulators over blocks of at most 128, halves split at a multiple of 8 above)."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[lo + i]
        return res
    if n <= 128:
        r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
        r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
        i = 8
        while i < n - (n % 8):
            r0 += a[lo + i]
            r1 += a[lo + i + 1]
            r2 += a[lo + i + 2]
            r3 += a[lo + i + 3]
            r4 += a[lo + i + 4]
            r5 += a[lo + i + 5]
            r6 += a[lo + i + 6]
            r7 += a[lo + i + 7]
            i += 8
        res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        while i < n:
            res += a[lo + i]
            i += 1
        return res
    n2 = n // 2
    n2 -= n2 % 8
    return _pairwise_sum(a, lo, n2) + _pairwise_sum(a, lo + n2, n - n2)


@kernel(error_model="numpy")
def _row_term_kernel(cs: np.ndarray, row: np.ndarray, centres: np.ndarray, los: np.ndarray,
                     his: np.ndarray, ni: np.ndarray, nl: np.ndarray, nr: np.ndarray
                     ) -> np.ndarray:
    """:func:`_row_term` in one kernel, bit for bit: the weights (-1 / ni, 0.5 / nl,
    0.5 / nr), :func:`_sorted_row_sums` over the rows counted from the first, and per
    centre the sum of the squares over the rows as NumPy sums a row of a C array
    (:func:`_pairwise_sum`)."""
    n = cs.shape[0]
    rmin = row[0]
    rmax = row[0]
    for i in range(1, n):
        rmin = min(rmin, row[i])
        rmax = max(rmax, row[i])
    R = rmax - rmin + 1
    m = centres.shape[0]
    coefs = np.empty((3, m))
    for j in range(m):
        coefs[0, j] = -1.0 / ni[j]
        coefs[1, j] = 0.5 / nl[j]
        coefs[2, j] = 0.5 / nr[j]
    r = np.empty(n, np.int64)
    for i in range(n):
        r[i] = row[i] - rmin
    S = _sorted_row_sums(cs, r, centres, los, his, coefs, R)
    for q in range(S.shape[0]):
        S[q] = S[q] * S[q]
    out = np.empty(m)
    for j in range(m):
        out[j] = _pairwise_sum(S, j * R, R)
    return out


@kernel(error_model="numpy")
def _seam_tail(ni: np.ndarray, si: np.ndarray, nl: np.ndarray, sl: np.ndarray,
               nr: np.ndarray, sr: np.ndarray, rt: np.ndarray, row_corr: float,
               use_rows: bool, scale: float, flank_z: float, flank_cols: float
               ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_seam_stats`' statistic and sign conditions from the window sums, element by
    element in its NumPy expressions' order (``rt``: the row term, where ``use_rows``)."""
    m = ni.shape[0]
    z = np.empty(m)
    both = np.empty(m, np.bool_)
    for j in range(m):
        ok = ni[j] > 0 and nl[j] > 0 and nr[j] > 0
        mi = si[j] / ni[j]
        ml = sl[j] / nl[j]
        mr = sr[j] / nr[j]
        d = 0.5 * (ml + mr) - mi
        var = 1.0 / ni[j] + 0.25 / nl[j] + 0.25 / nr[j]
        if use_rows:
            var = (1.0 - row_corr) * var + row_corr * rt[j]
        sd = scale * np.sqrt(var)
        b = ok and (ml > mi) and (mr > mi)
        b = b and (abs(nl[j] - nr[j]) <= (flank_z * np.sqrt(nl[j] + nr[j])
                                          + (nl[j] + nr[j]) / flank_cols))
        both[j] = b and (abs(ml - mr) <= d)
        z[j] = d / sd if ok else np.nan
    return z, both


def _row_term(coord: np.ndarray, row: np.ndarray, centres: np.ndarray, h: float,
              ni: np.ndarray, nl: np.ndarray, nr: np.ndarray) -> np.ndarray:
    """sum over image rows of (the statistic's weights of that row's points)^2, per centre.

    The statistic is sum_i c_i w_i with c = -1/ni in the groove window and 1/(2 nl), 1/(2 nr)
    in the flanks; a noise offset shared by one row's points adds row_corr * scale^2 *
    (sum of that row's c_i)^2 to its variance. Each point lies in the windows of a few
    centres only: the sums run over those (point, centre) pairs (a numba kernel: O(n + m
    + pairs), no expanded pair arrays). ``coord`` and ``centres`` ascend.
    """
    r = (row - row.min()).astype(np.int64)  # image rows: small integers, no need to sort
    R = int(r.max()) + 1
    with np.errstate(divide="ignore"):
        coefs = np.stack((-1.0 / ni, 0.5 / nl, 0.5 / nr)).astype(np.float64)
    # x lies in the window [c + lo, c + hi] of the centres c in [x - hi, x - lo]
    offs = np.array(_window_offsets(h), np.float64)
    S = _sorted_row_sums(np.ascontiguousarray(coord, np.float64), r,
                         np.ascontiguousarray(centres, np.float64), offs[:, 0].copy(),
                         offs[:, 1].copy(), coefs, R)
    return (S * S).reshape(len(centres), R).sum(1)


#: Points sorted by their coordinate, with their residuals and rows, all coordinates
#: distinct (:func:`_presorted`).
_Sorted = tuple[np.ndarray, np.ndarray, np.ndarray]


def _presorted(coord: np.ndarray, w: np.ndarray, row: np.ndarray | None, lo: float,
               hi: float) -> _Sorted | None:
    """The points with ``lo <= coord <= hi`` sorted once for several :func:`_seam_stats`
    calls whose strips lie inside it (the scales of one search): each takes its strip as a
    slice. Only where the coordinates are distinct (then a slice is the subset's one
    sorted order); None otherwise, or where the kernels do not apply."""
    if coord.dtype != np.float64 or w.dtype != np.float64 or not len(coord):
        return None
    rows = np.zeros(len(coord), np.int64) if row is None else np.asarray(row, np.int64)
    cs, ws, rs, distinct = _strip_sorted(coord, w, rows, float(lo), float(hi))
    return (cs, ws, rs) if distinct else None


def _seam_stats(coord: np.ndarray, w: np.ndarray, scale: float, centres: np.ndarray,
                h: float, row: np.ndarray | None = None, row_corr: float = 0.0,
                pre: _Sorted | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Flanks minus groove over its standard deviation (NaN where a window is empty), and
    whether the groove lies behind each flank on its own, by at least half its depth.
    ``pre``: :func:`_presorted` of the same points over a strip holding this one's."""
    if len(centres) and coord.dtype == np.float64 and w.dtype == np.float64:
        # the points in reach, sorted once for the windows and the row term (kernels)
        if pre is not None:
            lo, hi = _reach(centres, h)
            cs = pre[0]
            a = int(np.searchsorted(cs, lo, "left"))
            b = int(np.searchsorted(cs, hi, "right"))
            coord, w, rows = cs[a:b], pre[1][a:b], pre[2][a:b]
        else:
            rows = np.zeros(len(coord), np.int64) if row is None else np.asarray(row, np.int64)
            coord, w, rows = _near_sorted(coord, w, rows, centres, h)
        row = None if row is None else rows
        offs = np.array(_window_offsets(h), np.float64)
        los, his = offs[:, 0].copy(), offs[:, 1].copy()
        centres = np.ascontiguousarray(centres, np.float64)
        ni, si, nl, sl, nr, sr = _sorted_window_sums(coord, w, centres, los, his)
        # the row term and the statistic in kernels (the per-call cost of some twenty
        # small NumPy expressions, thousands of calls a scan)
        use_rows = row_corr > 0 and row is not None and len(coord) > 0
        rt = (_row_term_kernel(np.ascontiguousarray(coord), np.ascontiguousarray(rows),
                               centres, los, his, ni, nl, nr) if use_rows else ni)
        return _seam_tail(ni, si, nl, sl, nr, sr, rt, float(row_corr), use_rows,
                          float(scale), FLANK_BALANCE_Z, _FLANK_COLUMNS)
    else:
        near = _in_reach(coord, centres, h)
        coord, w = coord[near], w[near]
        ni, si, nl, sl, nr, sr = _windows(coord, w, centres, h)
        if row is not None:  # the row term takes the points sorted
            order = np.argsort(coord, kind="stable")
            coord, row = coord[order], row[near][order]
    ok = (ni > 0) & (nl > 0) & (nr > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mi = si / ni
        d = 0.5 * (sl / nl + sr / nr) - mi
        var = 1.0 / ni + 0.25 / nl + 0.25 / nr
        if row_corr > 0 and row is not None and len(coord):
            # a groove along an image row averages one row's shared offset, not noise
            var = (1.0 - row_corr) * var + row_corr * _row_term(coord, row, centres, h,
                                                                 ni, nl, nr)
        sd = scale * np.sqrt(var)
        both = ok & (sl / nl > mi) & (sr / nr > mi)
        # both flanks hold their share of the points: a groove beside a band of no return
        # (shiny tape, a dark label) is the sensor's edge of a hole, not a seam. The counts
        # may differ by chance and by one spacing's column of points (a flank 2.5 spacings
        # wide holds 2 or 3 columns of the sampling grid)
        both &= np.abs(nl - nr) <= (FLANK_BALANCE_Z * np.sqrt(nl + nr)
                                    + (nl + nr) / _FLANK_COLUMNS)
        # the flanks differ by less than the groove is deep (the groove lies behind its
        # lower flank by at least half its depth): a ridge (tape or a label on a lid) lifts
        # one flank by its height h, and a window on the flat lid beside it lies h / 2
        # behind the flanks' mean, but level with the other flank
        both &= np.abs(sl / nl - sr / nr) <= d
        z = np.where(ok, d / sd, np.nan)
    return z, both


def seam_z(coord: np.ndarray, w: np.ndarray, scale: float, centres: np.ndarray, h: float,
           row: np.ndarray | None = None, row_corr: float = 0.0,
           pre: _Sorted | None = None) -> np.ndarray:
    """Seam statistic at each centre: flanks minus groove over its standard deviation.

    Parameters
    ----------
    coord : (n,) float64
        The points' coordinate across the candidate seam, metres.
    w : (n,) float64
        Their residuals to the face's plane, metres (positive toward the sensor).
    scale : float
        Standard deviation of one residual, metres.
    centres : (m,) float64
        Candidate seam positions, metres.
    h : float
        Point spacing, metres.
    pre : optional
        :func:`_presorted` of the same points over a strip holding this one's.

    Returns
    -------
    z : (m,) float64
        Standard normal under "no seam" where the groove window lies behind both flanks;
        -inf where it does not, or a window is empty (a ridge or a step beside the window
        lifts only one flank).
    """
    z, both = _seam_stats(coord, w, scale, centres, h, row, row_corr, pre)
    return np.where(both, z, -np.inf)


#: Positions the statistic's spread is measured over at least (fewer: taken as 1).
MIN_SPREAD_POSITIONS = 8


def seam_spread(z: np.ndarray) -> float:
    """How far the noise spreads the seam statistic beyond N(0, 1) along one face.

    Correlated noise (structured-light and active-stereo depth) moves whole bands of a
    face a few millimetres: a window's mean then varies far more than its points'
    scatter over their number says. Measured over the statistic's values at a face's
    positions, robustly (seams are few): 1.4826 MAD, at least 1; 1 with fewer than
    :data:`MIN_SPREAD_POSITIONS` finite values.

    Parameters
    ----------
    z : (m,) float64
        :func:`seam_z`'s statistic before its sign conditions (NaN where undefined).
    """
    fin = z[np.isfinite(z)]
    if len(fin) < MIN_SPREAD_POSITIONS:
        return 1.0
    if fin.dtype == np.float64:  # np.median's value, in a kernel (thousands of calls a scan)
        return max(1.0, float(1.4826 * _median(np.abs(fin - _median(fin)))))
    return max(1.0, float(1.4826 * np.median(np.abs(fin - np.median(fin)))))


def face_spread(coord: np.ndarray, w: np.ndarray, scale: float, extent: float, h: float,
                row: np.ndarray | None = None, row_corr: float = 0.0) -> tuple[float, ...]:
    """:func:`seam_spread` at each of :data:`SEAM_SCALES` over every position of a face
    whose windows lie on it (``SEAM_FLANK[1]`` spacings times the scale inside each end,
    where the outer flank reaches the end). In correlated depth noise it stands in for the
    spread of a face whose interior, ``BOUNDARY_BAND`` min_edge inside its sides, is too
    narrow to measure it (a narrow face must not test its sides' seams as if the noise were
    white), and it is the ``floor_spread`` of a wider interior's search
    (:func:`boxloc.stages.verify._test_seam_interior`).

    Parameters
    ----------
    coord : (n,) float64
        The face's points' coordinate across the seams, metres, 0 to ``extent``.
    w : (n,) float64
        Their residuals to the face's plane, metres.
    scale, h, row, row_corr
        As for :func:`seam_z`.

    Returns
    -------
    tuple of float
        The spread at each scale (1 where fewer than :data:`MIN_SPREAD_POSITIONS` positions
        are defined).
    """
    out = []
    grid = []
    for s in SEAM_SCALES:
        reach = SEAM_FLANK[1] * s * h
        grid.append(np.arange(reach, extent - reach + 0.25 * h, 0.5 * h))
    # one sort for every scale, over the strip all of them reach (as _seam_stats does)
    used = [(s, c) for s, c in zip(SEAM_SCALES, grid) if len(c) >= MIN_SPREAD_POSITIONS]
    pre = (_presorted(coord, w, row, *_strip((s * h, c) for s, c in used))
           if used and len(coord) else None)
    for s, centres in zip(SEAM_SCALES, grid):
        if len(centres) < MIN_SPREAD_POSITIONS or len(coord) == 0:
            out.append(1.0)
            continue
        zr, _ = _seam_stats(coord, w, scale, centres, s * h, row, row_corr, pre)
        out.append(seam_spread(zr))
    return tuple(out)


def _spread_beside(z: np.ndarray, both: np.ndarray, centres: np.ndarray, reach: float,
                   crit: float, sp: float) -> float:
    """:func:`seam_spread` of the statistic ``z`` at ``centres`` without the positions whose
    windows (``reach`` either side) hold its strongest groove, where that passes the
    critical value before any spread is divided out; else ``sp``, the spread over all."""
    cand = np.where(both & np.isfinite(z), z, -np.inf)
    k = int(np.argmax(cand))
    if not cand[k] > crit:
        return sp
    away = np.abs(centres - centres[k]) > reach
    return seam_spread(z[away]) if np.isfinite(z[away]).sum() >= MIN_SPREAD_POSITIONS else sp


class Seams(NamedTuple):
    """Result of :func:`find_seams`."""

    #: (k,) float64, metres along the binned coordinate.
    positions: np.ndarray
    #: (k,) float64, their statistics.
    z: np.ndarray
    #: Bonferroni-corrected critical value.
    critical: float
    #: The largest statistic over all positions, significant or not (-inf if none was
    #: computable): what a post-mortem reads when no seam was found.
    z_max: float
    #: :func:`seam_spread` over the positions at each of :data:`SEAM_SCALES`, which that
    #: scale's statistics are divided by (by ``floor_spread`` of :func:`find_seams` where
    #: that is larger).
    spread: tuple[float, ...] = (1.0,) * len(SEAM_SCALES)


def find_seams(coord: np.ndarray, w: np.ndarray, scale: float, lo: float, hi: float,
               h: float, alpha: float, row: np.ndarray | None = None,
               row_corr: float = 0.0, mask_strongest: bool = False,
               spread: tuple[float, ...] | None = None,
               level_span: float | None = None,
               floor_spread: tuple[float, ...] | None = None,
               stats: list[tuple[np.ndarray, np.ndarray]] | None = None) -> Seams:
    """Significant seams between ``lo`` and ``hi`` (local maxima of :func:`seam_z`, the
    larger of its values at the groove widths of :data:`SEAM_SCALES`).

    The critical value is Bonferroni-corrected over the independent positions (one per
    groove window, at each scale) in [lo, hi].

    Parameters
    ----------
    mask_strongest : bool
        Measure the statistic's spread without the positions whose windows hold the
        strongest groove, where that groove passes the critical value before any spread
        is divided out (:func:`_spread_beside`): on a narrow face a seam's own lobes
        inflate the spread that would hide it. Only meaningful where the noise is white:
        with correlated noise the undivided statistic passes the critical value by chance.
    spread : tuple of float, optional
        The statistic's spread at each scale, measured by a search over more of the same
        face (its :attr:`Seams.spread`), instead of over these few positions.
    level_span : float, optional
        Metres of positions the critical value corrects for (default ``hi - lo``): that
        search's, when this one continues it.
    floor_spread : tuple of float, optional
        A second measure of the spread at each scale (:func:`face_spread` over the whole
        face): the statistics are divided by the larger of it and the positions' own, so a
        groove must stand out of both. :attr:`Seams.spread` stays the positions' own.
    stats : list, optional
        The statistic and its sign conditions at each scale: a call given an empty list
        fills it, a call given it filled (the same points, ``lo``, ``hi`` and ``h``) takes
        them instead of computing them again.

    Returns
    -------
    Seams
        positions, z, critical, z_max, spread.
    """
    if hi <= lo or len(coord) == 0:  # no positions: a given spread still stands
        given = (1.0,) * len(SEAM_SCALES) if spread is None else tuple(map(float, spread))
        return Seams(np.zeros(0), np.zeros(0), np.inf, -np.inf, given)
    step = 0.5 * h
    centres = np.arange(lo, hi + 0.5 * step, step)
    span = hi - lo if level_span is None else level_span
    n_indep = sum(max(span / (2.0 * SEAM_INNER * s * h), 1.0) for s in SEAM_SCALES)
    crit = float(norm_isf(alpha / n_indep))
    zs, spreads = [], []
    if not stats:
        # one sort for every scale, over the strip all of them reach
        pre = _presorted(coord, w, row, *_strip((s * h, centres) for s in SEAM_SCALES))
        computed = [_seam_stats(coord, w, scale, centres, s * h, row, row_corr, pre)
                    for s in SEAM_SCALES]
        if stats is not None:
            stats.extend(computed)
    else:
        computed = stats
    for i, s in enumerate(SEAM_SCALES):
        zr, both = computed[i]
        if spread is not None:
            spreads.append(float(spread[i]))
            sp = spreads[-1]
        else:
            # correlated noise (e.g. structured-light depth) spreads the statistic beyond
            # N(0, 1): measure its spread over the positions and divide it out
            spreads.append(seam_spread(zr))
            sp = (_spread_beside(zr, both, centres, SEAM_FLANK[1] * s * h, crit,
                                 spreads[-1]) if mask_strongest else spreads[-1])
        if floor_spread is not None:
            sp = max(sp, float(floor_spread[i]))
        zs.append(np.where(both, zr / sp, -np.inf))
    Z = np.vstack(zs)
    z = Z.max(axis=0)
    width = 2.0 * SEAM_INNER * h * np.asarray(SEAM_SCALES)[Z.argmax(axis=0)]
    left = np.concatenate(([-np.inf], z[:-1]))
    right = np.concatenate((z[1:], [-np.inf]))
    pk = np.flatnonzero((z > crit) & (z >= left) & (z > right))
    # one seam per groove window: the strongest of maxima closer than the wider window
    keep: list[int] = []
    for i in pk[np.argsort(-z[pk], kind="stable")]:
        if all(abs(centres[i] - centres[j]) > max(width[i], width[j]) for j in keep):
            keep.append(int(i))
    pk = np.array(sorted(keep), np.int64)
    fin_z = z[np.isfinite(z)]
    return Seams(centres[pk], z[pk], crit, float(fin_z.max()) if len(fin_z) else -np.inf,
                 tuple(spreads))


def gap_z(coord: np.ndarray, centres: np.ndarray, h: float) -> np.ndarray:
    """Gap statistic at each centre: too few face points in the groove window.

    Boxes that stand a few millimetres apart leave a gap, not a groove: its samples fall
    far behind the plane (or return nothing), so the face's points thin out there while
    both flanks keep theirs. The window's count is tested against the flanks' density
    (Poisson, lower tail) and returned as a standard normal z, comparable to
    :func:`seam_z`.

    Returns
    -------
    z : (m,) float64
        -inf where a flank is empty (the face does not continue on both sides).
    """
    coord = coord[_in_reach(coord, centres, h)]
    ni, _, nl, _, nr, _ = _windows(coord, np.zeros_like(coord), centres, h)
    lam = (nl + nr) * SEAM_INNER / (SEAM_FLANK[1] - SEAM_FLANK[0])
    # scipy.stats.poisson.cdf(ni, lam) is pdtr(floor(ni), lam) for ni >= 0 (counts)
    p = special.pdtr(np.floor(ni), np.maximum(lam, 1e-12))
    return np.where((nl > 0) & (nr > 0), norm_isf(p), -np.inf)


def _seam_at_grid(position: float, h: float, reach: float | None
                  ) -> tuple[list[tuple[float, float, np.ndarray]], float, float]:
    """:func:`seam_at`'s positions at each scale (window g, reach r, centres) and the strip
    [lo, hi] their windows reach."""
    grid = []
    for s in SEAM_SCALES:
        g = SEAM_INNER * s * h
        r = g if reach is None else max(float(reach), g)
        grid.append((g, r, position + np.arange(-r, r + 0.25 * g, g)))
    lo, hi = _strip((s * h, c) for s, (_, _, c) in zip(SEAM_SCALES, grid))
    return grid, lo, hi


def seam_at(coord: np.ndarray, w: np.ndarray, scale: float, position: float, h: float,
            alpha: float, reach: float | None = None, gaps: bool = False,
            row: np.ndarray | None = None, row_corr: float = 0.0,
            spread: float | tuple[float, ...] = 1.0,
            pre: _Sorted | None = None) -> tuple[float, float]:
    """The strongest seam (or gap) statistic near ``position``, over the groove widths of
    :data:`SEAM_SCALES`.

    Parameters
    ----------
    reach : float, optional
        Search from ``position - reach`` to ``position + reach`` (metres) in groove-window
        steps; default one groove window (``SEAM_INNER * h`` at each scale).
    gaps : bool
        Count a gap (:func:`gap_z`, at the narrowest window) as a seam. Only where the face
        is known to continue beyond ``position``: elsewhere a shadow or a dropout also thins
        the points out.
    spread : float or tuple of float
        :func:`seam_spread` of the statistic along the face at each scale
        (:attr:`Seams.spread` of its interior; one float: the same at every scale): a few
        positions near one side cannot measure it. Divides the groove's statistic, not the
        gap's (a count, which correlated depth noise does not spread).
    pre : optional
        The points sorted over the strip the searches reach (:func:`_presorted`, over
        :func:`_seam_at_grid`'s strip), where a caller has them.

    Returns
    -------
    z : float
        The largest :func:`seam_z` (or :func:`gap_z`) over the positions and scales tried;
        -inf where the windows hold no points.
    critical : float
        Bonferroni-corrected over the positions tried (independent ones: one per groove
        window, at least three per scale).
    """
    spreads = np.broadcast_to(np.asarray(spread, np.float64), (len(SEAM_SCALES),))
    z_best, n_indep = -np.inf, 0.0
    grid, lo, hi = _seam_at_grid(position, h, reach)
    if pre is None:  # one sort for every scale, over the strip all of them reach
        pre = _presorted(coord, w, row, lo, hi)
    for s, sp, (g, r, centres) in zip(SEAM_SCALES, spreads, grid):
        n_indep += max(3.0, 2.0 * r / g + 1.0)
        z = seam_z(coord, w, scale, centres, s * h, row, row_corr, pre) / sp
        if gaps and s == SEAM_SCALES[0]:
            z = np.maximum(z, gap_z(coord, centres, h))
        z_best = max(z_best, float(z.max()))
    return z_best, float(norm_isf(alpha / n_indep))


__all__ = ["FacePoints", "Seams", "face_points", "face_spread", "find_seams", "gap_z",
           "norm_isf", "seam_at", "seam_spread", "seam_z", "MIN_SPREAD_POSITIONS", "SEAM_FLANK",
           "SEAM_INNER", "SEAM_SCALES"]

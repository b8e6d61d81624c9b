"""Stage 6: verification of a rectangle hypothesis by the range points inside it (paper §2.2).

The rectangle, shrunk by the border margin, is projected into the range image and
rasterized (the paper's ref [10]; here ``cv2.fillPoly``). Its points are tested against the
rectangle's plane with their propagated uncertainty (point-on-plane, chi2(1) at alpha):

* ``VERIFY_TILT`` — the face's normal is within ``max_tilt`` of up (a prior: graspable
  faces are tops);
* ``VERIFY_INTERIOR`` — no edge crosses the interior: the interior's edge points (beyond
  the band where the sides' own edges lie) make no significant straight line parallel to a
  side, against the same number of points scattered uniformly over the interior (Poisson,
  maximum over the positions, at alpha). How many there are is not itself tested: a sensor
  that sees a face at grazing incidence scatters noise edges over it, and their number
  grows with the face's area and the noise, not with the presence of an edge;
* ``VERIFY_BOUNDARY`` — each of the four sides is a real boundary of a top face: edge
  points where the face drops away (jump, convex crease) or meets an equal neighbour
  (groove) form a significant line along it (Poisson against the interior's scattered
  edges, at alpha), and all four together cover the fraction p of the perimeter. The
  points lie on the face's plane, or, for a jump, behind it but nearer to it than to the
  jump's far side (a mixed pixel: a footprint wider than a pixel straddles the end). This
  extends the paper's |P_f| > p from the two far sides to all four, and rejects a
  sub-rectangle of a larger face, and the floor or pallet between boxes (bounded by
  concave creases where the boxes rise: a side needs more convex than concave edge
  points). A side with no such line is still a boundary if
  it is a seam (``VERIFY_SEAM_SIDE``: the range points along it, binned across it, show a
  groove behind the plane; :mod:`boxloc.stages.seams`), which is how two touching boxes of equal
  height part where the edge stage saw their seam only in part;
* ``VERIFY_SEAM_INTERIOR`` — no seam crosses the interior, at alpha Bonferroni-corrected
  over the positions (a rectangle over two touching boxes is two faces);
* ``VERIFY_SEAM_MIDLINE`` — nor its middle, where each half could be a box: two equal
  boxes side by side, the commonest pair in a layer, part there, and one position needs a
  far lower critical value than the interior's search over them all;
* ``VERIFY_CONTINUATION`` — the face ends at each side: fewer than
  ``min_inlier_fraction`` of the pixels in a strip just beyond the side lie on the face's
  refitted plane (:func:`continuation`), or the side is a seam or a gap between equal
  neighbours (``VERIFY_SEAM_SIDE``, searched across the band where the side's edges are
  counted). Edge evidence alone does not make a side where the plane runs on: sensor
  artefacts (structured-light depth) put short lines of jump edges inside faces, and a
  rectangle cut short there would be accepted first and hide the whole face;
* ``VERIFY_RAISED_BEYOND`` — nor does it run on under something thin: a side (no seam)
  beyond which most of that strip lies in front of the plane, no higher than the flatness
  prior, is the edge of tape or a label on the lid, not the face's end;
* ``VERIFY_EXPOSED`` — points significantly *in front* of the face's refitted plane
  (something resting on it or hanging over it), counted in the core beyond twice the
  border margin, are not more frequent than points significantly behind it (noise is symmetric,
  occluders are not: a sign test at alpha, which does not depend on the noise model being
  exact; row 0), and not more frequent than the noise model puts there (alpha/2 of the
  points) over the core (row 1) or in its busiest cell (row 2, Bonferroni over the cells).
  The face is covered if row 0 rejects and row 1 or row 2 does;
* ``VERIFY_INLIERS`` — at least ``min_inlier_fraction`` of the returns inside are on the
  plane (the rest are noise, bulge and mixed pixels; holes count ``hole_weight``, by
  default nothing; row 0), and at least ``min_return_fraction`` of the pixels inside
  returned (a rectangle mostly unseen is not verified by its points; row 1);
* ``VERIFY_MEAN`` — the inliers' mean signed distance is zero within the propagated
  uncertainty of the plane and of the mean (chi2(1)).

Each test has its function (``_test_tilt`` ... ``_test_mean``), in this order, the README's.
:func:`verify` runs them cheapest first, and the continuation last: it needs the plane
refitted to the points inside.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import special

from boxloc.config import Config
from boxloc.distributions import binom_isf, binom_sf
from boxloc.kernels import kernel
from boxloc.products import EdgeKind, EdgeMap, VerifyReason
from boxloc.scan import NoiseModel, Scan
from boxloc.stages.design_effect import exceedance_design_effects, patch_factor
from boxloc.stages.edges import noise_gain
from boxloc.stages.lines import MIN_LINE_POINTS
from boxloc.stages.raster import fill_polygon, polygon_area, rectangle_pixels
from boxloc.stages.seams import (
    MIN_SPREAD_POSITIONS,
    SEAM_FLANK,
    SEAM_SCALES,
    FacePoints,
    _centred,
    _median,
    _presorted,
    _seam_at_grid,
    face_points,
    face_spread,
    find_seams,
    seam_at,
)
from boxloc.stages.sizes import match_size
from boxloc.stats import TestKind, TestTable, chi2_critical

#: A run of this many pixels without a point on a face's plane ends the face (a sensor's
#: dropouts inside a face are shorter; the gap beyond a box's side is longer).
EXTENT_GAP_PX = 4

#: Edges within this fraction of the shortest box edge from a side belong to that side: a
#: seam that splits a rectangle into two boxes lies at least min_edge from a side, while
#: the side's own second edges (bevel, rounded cardboard) and the error of the estimated
#: dimensions put boundary edges up to a centimetre or two inside.
BOUNDARY_BAND = 0.5
#: A side without a line of edges still shows the face's end where at most this fraction
#: of the valid pixels just beyond it lie on the face's refitted plane (a continuing face
#: would have 1 - alpha of them on it), and at most as many in front of it: the plane
#: folds or steps away there, a crease or a jump the scan lines did not resolve
#: (``VERIFY_PLANE_END``).
PLANE_END_FRACTION = 0.2
#: Share of the strip beyond a side in front of the face's plane, no higher than the
#: flatness prior, from which the face runs on under it (``VERIFY_RAISED_BEYOND``): tape
#: or a label lying over the side. Half: the strip then lies mostly on the raised thing.
RAISED_FRACTION = 0.5


@dataclass
class VerifyContext:
    """Per-scan arrays the verification of every hypothesis reads (built once)."""

    points: np.ndarray  # (H, W, 3) float64
    sigma: np.ndarray  # (H, W) float64: range sigma, NaN where no return
    lateral2: np.ndarray  # (H, W) float64: lateral variance
    valid: np.ndarray  # (H, W) bool
    edge_points: np.ndarray  # (N, 3)
    edge_kinds: np.ndarray  # (N,) EdgeKind
    pixel_angle: float  # radians per pixel: the edge-point spacing is range * pixel_angle
    up: np.ndarray  # (3,) the up direction of the tilt prior
    project: Callable[[np.ndarray], np.ndarray]  # the sensor's projection to pixels
    #: level of a seam as a face's boundary (SEAM_PEAK, VERIFY_SEAM_SIDE): alpha over the
    #: scan's seam searches (:func:`seam_alpha`)
    seam_alpha: float
    #: (N,) jump height or fold angle of each edge point (``EdgeMap.strength``); None: not
    #: known (every jump counts as a boundary)
    edge_strength: np.ndarray | None = None
    #: (H, W) >= 1: the noise's local loudness (:func:`boxloc.stages.edges.noise_gain`, as
    #: the edge stage measures it), which the seam tests divide the residuals by; None: 1
    gain: np.ndarray | None = None
    #: :meth:`_per_pixel`'s arrays, built at its first call
    _flat: tuple[np.ndarray, ...] | None = field(default=None, init=False, repr=False,
                                                 compare=False)

    @classmethod
    def build(cls, scan: Scan, edges: EdgeMap, config: Config, up: np.ndarray,
              n_vertices: int = 1, gain: np.ndarray | None = None) -> VerifyContext:
        """The context of one scan; ``gain``: :func:`boxloc.stages.edges.noise_gain` of the
        scan and config if already computed (the pipeline's), else computed here."""
        P = scan.points.astype(np.float64)
        r = scan.range.astype(np.float64)
        sr = config.noise.sigma_range(r)
        sl = config.noise.sigma_lateral(r, scan.sensor.pixel_angle)
        valid = np.isfinite(r)
        if gain is None:
            gain = noise_gain(scan, config)
        return cls(P, sr, sl**2, valid, edges.points, edges.kinds,
                   scan.sensor.pixel_angle, np.asarray(up, dtype=np.float64),
                   scan.sensor.project, seam_alpha(config.alpha, n_vertices), edges.strength,
                   gain)

    def spacing_at(self, point: np.ndarray) -> float:
        """Expected spacing of edge points along an edge at ``point``, metres."""
        return float(np.linalg.norm(point)) * self.pixel_angle

    def _per_pixel(self) -> tuple[np.ndarray, ...]:
        """The points (H W, 3), their squared norms, ``sigma ** 2`` and ``lateral2``, each
        (H W,), flat: :meth:`var_along` gathers from them by flat index, once per scan
        instead of squaring and summing per call (the same element-wise values: einsum's
        sum of one row does not depend on the other rows)."""
        if self._flat is None:
            P = np.ascontiguousarray(self.points, np.float64).reshape(-1, 3)
            self._flat = (P, np.einsum("ij,ij->i", P, P),
                          np.ascontiguousarray(self.sigma).reshape(-1) ** 2,
                          np.ascontiguousarray(self.lateral2).reshape(-1))
        return self._flat

    def gather(self, rr: np.ndarray, cc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The points at pixels (rr, cc), (n, 3) (``points[rr, cc]``), and the pixels' flat
        indices (for :meth:`var_along`)."""
        flat = rr * self.valid.shape[1] + cc
        return _take_rows(self._per_pixel()[0], flat), flat

    def var_along(self, rr: np.ndarray, cc: np.ndarray, direction: np.ndarray,
                  P: np.ndarray | None = None, flat: np.ndarray | None = None) -> np.ndarray:
        """Variance of the points at pixels (rr, cc) along a unit direction, m^2: range
        noise along the ray, lateral noise across it. ``P`` and ``flat``, where given, are
        :meth:`gather`'s of the same pixels."""
        pts, norm2, sigma2, lateral2 = self._per_pixel()
        if flat is None:
            flat = rr * self.valid.shape[1] + cc
        if P is None:
            P = _take_rows(pts, flat)
        # the product stays NumPy's (BLAS: its rounding is its own); the rest in a kernel
        return _mix_var(P @ direction, np.asarray(flat, np.int64), norm2, sigma2, lateral2)

    def pixels_in(self, origin: np.ndarray, x_axis: np.ndarray, y_axis: np.ndarray,
                  u_range: tuple[float, float], v_range: tuple[float, float]) -> float:
        """Pixels a rectangle in 3D covers in the image, at most the image's: the work of
        reading its range points (a unit of the hypothesis stage's work budget).

        The projected quadrilateral's area; a corner without a projection (a ray table
        has no ray there) counts the rectangle's area over the pixel footprint at its
        centre instead.
        """
        (u0, u1), (v0, v1) = u_range, v_range
        c = np.array([origin + u * x_axis + v * y_axis
                      for u, v in ((u0, v0), (u1, v0), (u1, v1), (u0, v1))])
        uv = self.project(c)
        if np.isfinite(uv).all():
            area = polygon_area(uv)
        else:
            area = abs((u1 - u0) * (v1 - v0)) / self.spacing_at(c.mean(0)) ** 2
        return min(area, float(self.valid.size))

    def samples_along(self, a: np.ndarray, b: np.ndarray) -> float:
        """Edge points expected along the 3D segment a-b: its length in the image, pixels.

        A side seen at grazing incidence is foreshortened in the image and gets fewer edge
        points than its length over :meth:`spacing_at` (one per pixel it crosses).
        """
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        q = self.project(np.stack([a, b]))
        return self._samples_between(a, b, q[0], q[1])

    def samples_along_sides(self, corners: np.ndarray) -> list[float]:
        """:meth:`samples_along` of each side 0-3 of a rectangle (``SIDE_CORNERS``), its
        corners (4, 3) projected at once (a projection maps each point on its own)."""
        c = np.asarray(corners, np.float64)
        q = self.project(c)
        return [self._samples_between(c[i], c[j], q[i], q[j]) for i, j in SIDE_CORNERS]

    def _samples_between(self, a: np.ndarray, b: np.ndarray, qa: np.ndarray, qb: np.ndarray
                         ) -> float:
        n = float(np.hypot(*(qb - qa)))
        # off the image (a ray table has no ray there): its length over the spacing
        return n if np.isfinite(n) else float(np.linalg.norm(b - a)) / self.spacing_at(
            0.5 * (a + b))


@dataclass
class VerifyOutcome:
    """Everything :func:`verify` found about one rectangle (one row of Verification)."""

    n_inside: int
    n_valid: int
    n_inliers: int
    n_front: int
    n_behind: int
    inlier_fraction: float
    mean_distance: float
    sigma_mean: float
    n_interior_edges: int
    plane_center: np.ndarray
    plane_normal: np.ndarray
    plane_cov: np.ndarray
    rms: float
    error: float  # sum of squared normalized residuals of the inliers (MDL xi)
    accepted: bool
    reason: VerifyReason
    inlier_pixels: np.ndarray
    tests: TestTable


def _poisson_sf(k: float, lam: float) -> float:
    """``scipy.stats.poisson.sf(k, lam)`` for one count, bit for bit, without the
    distribution's argument handling (a quarter of a millisecond a call, thousands a scan):
    P(X > k) for X ~ Poisson(lam), 1 below 0."""
    k = math.floor(k)
    if k < 0:
        return 1.0
    return float(special.pdtrc(k, lam))


def _interior_line(
    u: np.ndarray, v: np.ndarray, width: float, length: float, spacing: float,
    margin: float = 0.0,
) -> tuple[float, float]:
    """Most significant straight edge inside a rectangle, parallel to a side, and its p-value.

    Interior edge points, those at least ``margin`` from every side, vote into 1-D
    accumulators along x and along y (bins of three point spacings over the interior,
    ``margin`` to ``width - margin``); the highest bin is tested against the points
    scattered uniformly over the interior (Poisson, maximum over the bins). A seam the
    edge stage saw only in part still makes a significant peak, scattered noise does not.
    The uniform level is that of the interior the points can lie in: spread over the whole
    extent, it would make the scatter on a narrow face look like a line.

    Parameters
    ----------
    u, v : ndarray (n,)
        The points' coordinates along x and y, metres, each in [margin, extent - margin].
    width, length : float
        The rectangle's extent along x and y, metres.
    spacing : float
        Point spacing on the face, metres.
    margin : float
        Width of the band along the sides that is not interior, metres.

    Returns
    -------
    count : float
        Points in the highest bin of the accumulator with the smaller p-value (the two
        have different numbers of bins, so their counts do not compare).
    p_value : float
        Probability of so high a bin by uniform scatter (1 if no points).
    """
    count, p, _ = _interior_line_span(u, v, width, length, spacing, margin)
    return count, p


def _interior_line_span(
    u: np.ndarray, v: np.ndarray, width: float, length: float, spacing: float,
    margin: float = 0.0,
) -> tuple[float, float, float]:
    """:func:`_interior_line`, and how far the points of its highest bin spread along it
    (metres): a line across a face spans it, a clump of artefact edges does not."""
    n = len(u)
    if n == 0:
        return 0.0, 1.0, 0.0
    h = 3.0 * spacing
    best, best_p, best_span = 0.0, 1.0, 0.0
    for coord, other, extent in ((u, v, width), (v, u, length)):
        nb = max(int(np.ceil((extent - 2.0 * margin) / h)), 1)
        idx = np.clip(((coord - margin) / h).astype(np.int64), 0, nb - 1)
        acc = np.bincount(idx, minlength=nb)
        top = int(np.argmax(acc))
        k = float(acc[top])
        lam = n / nb
        p = float(min(1.0, nb * _poisson_sf(k - 1, lam)))
        if p < best_p or (p == best_p and k > best):
            along = other[idx == top]
            best, best_p = k, p
            best_span = float(along.max() - along.min()) if len(along) else 0.0
    return best, best_p, best_span


@kernel
def _n_distinct(x: np.ndarray) -> int:
    """``len(np.unique(x))`` of int64 values."""
    if x.shape[0] == 0:
        return 0
    s = np.sort(x)
    k = 1
    for i in range(1, s.shape[0]):
        k += s[i] != s[i - 1]
    return k


def _side_seam(fp: FacePoints, side: int, width: float, length: float, spacing: float,
               alpha: float, reach: float | None = None, gaps: bool = False
               ) -> tuple[float, float]:
    """Seam statistic along one side of a rectangle, and its critical value.

    ``side`` is 0-3: v=0, v=length, u=0, u=width; ``reach`` and ``gaps`` as in
    :func:`boxloc.stages.seams.seam_at`; the statistic is divided by its spread along the
    face (``fp.spread``, from :func:`_test_seam_interior`). A seam
    runs the whole side: both halves must show a groove or gap (a local dent does not), so
    the weaker half caps the statistic.
    """
    if side < 2:
        return seam_line(fp, 1, (0.0, length)[side], width, spacing, alpha, reach, gaps)
    return seam_line(fp, 0, (0.0, width)[side - 2], length, spacing, alpha, reach, gaps)


def seam_line(fp: FacePoints, axis: int, at: float, L: float, spacing: float, alpha: float,
              reach: float | None = None, gaps: bool = False,
              spread: tuple[float, ...] | None = None, start: float = 0.0,
              halves: bool = False) -> tuple[float, float]:
    """Seam statistic along the line ``coord = at`` of a face (coord = u for ``axis`` 0, v
    for 1), over its points from ``start`` to ``L`` along the line, and its critical value.

    As :func:`boxloc.stages.seams.seam_at` at ``at`` with ``reach`` and ``gaps``; the
    statistic is divided by ``spread`` (default ``fp.spread`` along the axis). A seam runs
    the whole line: both halves must show a groove or gap (a local dent does not), so a
    half that shows none (z <= 0) caps the statistic. With ``halves``, each half must
    show its share of the seam: the statistic is capped at sqrt(2) times the weaker
    half's (a groove along the whole line gives each half about 1/sqrt(2) of the whole
    line's z; one along half of it gives the other half nothing, and the whole line
    still about 1/sqrt(2) of that half's z, which a deep groove lifts past the critical
    value: a cut laid across a turned carton's middle and on along a true seam).
    """
    if axis == 1:
        sel = (fp.u >= start) & (fp.u <= L)
        coord, along = fp.v, fp.u
    else:
        sel = (fp.v >= start) & (fp.v <= L)
        coord, along = fp.u, fp.v
    sp = fp.spread[axis] if spread is None else spread
    # only the points in the strip seam_at's windows reach: the three searches take them,
    # not the whole face's (the same strips, in the same order)
    _, lo, hi = _seam_at_grid(at, spacing, reach)
    idx = np.flatnonzero(sel & (coord >= lo) & (coord <= hi))
    coord, along, w, row = coord[idx], along[idx], fp.w[idx], fp.row[idx]
    # the side's strip sorted once: each half's is its part, in the same order (distinct
    # coordinates; with ties each search sorts its own)
    whole = _presorted(coord, w, np.arange(len(coord)), lo, hi)
    pre = None if whole is None else (whole[0], whole[1], row[whole[2]])
    zs, zc = seam_at(coord, w, fp.scale, at, spacing, alpha, reach, gaps, row, fp.row_corr, sp,
                     pre)
    mid = 0.5 * (start + L)  # 0.5 * L exactly from 0
    for half in (along < mid, along >= mid):
        pre_h = None
        if whole is not None and half.any():
            part = half[whole[2]]
            pre_h = (whole[0][part], whole[1][part], row[whole[2][part]])
        zh, _ = seam_at(coord[half], w[half], fp.scale, at, spacing, alpha, reach,
                        gaps, row[half], fp.row_corr, sp, pre_h)
        if zh <= 0:
            zs = min(zs, zh)
        elif halves:
            zs = min(zs, math.sqrt(2.0) * zh)
    return zs, zc


def continuation(
    ctx: VerifyContext,
    origin: np.ndarray,
    x_axis: np.ndarray,
    y_axis: np.ndarray,
    width: float,
    length: float,
    plane_point: np.ndarray,
    plane_normal: np.ndarray,
    margin: float,
    depth: float,
    k: float,
    memo: dict[Any, Any] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How far a face's plane continues beyond each side of a rectangle.

    For each side, the pixels of a strip outside it (from ``margin`` to ``margin + depth``
    beyond the side, the corners' margins left out) are tested against the plane with
    their own noise (point-on-plane, z at ``k``; no flatness prior: the strip is a few
    spacings from the face's own edge, so a bulge has not yet departed from it). Beyond a
    true side lie another surface, the face's own side wall or nothing; beyond a side cut
    through a face, the same plane.

    Parameters
    ----------
    origin, x_axis, y_axis : (3,) float64
        The rectangle's frame.
    width, length : float
        Metres.
    plane_point, plane_normal : (3,) float64
        The face's refitted plane.
    margin, depth : float
        Metres.
    k : float
        Critical |z| of one point.
    memo : dict, optional
        Shared by the calls for one rectangle (:func:`_beyond_sides`).

    Returns
    -------
    fraction : (4,) float64
        Fraction of the strip's valid pixels on the plane, sides 0-3 (v=0, v=length, u=0,
        u=width); NaN where the strip has fewer than ``MIN_LINE_POINTS`` valid pixels or
        leaves the image.
    n_valid : (4,) int64
    in_image : (4,) bool
        At least half of the strip's area lies inside the image: only then can it show
        that the face ends (a face that runs out of the image may continue beyond it).
    """
    frac, _, n_valid, in_image, _ = _beyond_sides(ctx, origin, x_axis, y_axis, width, length,
                                               plane_point, plane_normal, margin, depth, k,
                                               memo)
    return frac, n_valid, in_image


def _beyond_sides(
    ctx: VerifyContext, origin: np.ndarray, x_axis: np.ndarray, y_axis: np.ndarray,
    width: float, length: float, plane_point: np.ndarray, plane_normal: np.ndarray,
    margin: float, depth: float, k: float, memo: dict[Any, Any] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`continuation`'s strips: per side 0-3 the fraction of their valid pixels on
    the plane and the fraction in front of it (toward the sensor, beyond ``k``), both NaN
    where too few; the valid pixels; whether the strip is mostly in the image; the median
    height of its points above the plane (metres, toward the sensor; NaN where too few).

    ``memo``: a dict kept over the calls for one rectangle (one frame, width and length):
    each strip is rasterized and gathered once, and a call with the same plane, margin,
    depth and k as an earlier one returns copies of its arrays."""
    key = ("result", plane_point.tobytes(), plane_normal.tobytes(), margin, depth, k)
    if memo is not None and key in memo:
        return tuple(a.copy() for a in memo[key])
    m, d = margin, depth
    strips = (((m, width - m), (-m - d, -m)), ((m, width - m), (length + m, length + m + d)),
              ((-m - d, -m), (m, length - m)), ((width + m, width + m + d), (m, length - m)))
    frac = np.full(4, np.nan)
    front = np.full(4, np.nan)
    height = np.full(4, np.nan)
    n_valid = np.zeros(4, np.int64)
    in_image = np.zeros(4, bool)
    for si, (u_range, v_range) in enumerate(strips):
        pkey = ("strip", si, margin, depth)
        if memo is not None and pkey in memo:
            pix, gathered = memo[pkey]
        else:
            pix = rectangle_pixels(ctx.project, ctx.valid, origin, x_axis, y_axis, u_range,
                                   v_range)
            gathered = (ctx.gather(pix[0], pix[1]) if pix is not None
                        and len(pix[0]) >= MIN_LINE_POINTS else None)
            if memo is not None:
                memo[pkey] = pix, gathered
        if pix is None:
            continue
        rr, cc, inside = pix
        # most of the strip must be in the image to show anything of the side
        in_image[si] = inside >= 0.5
        n_valid[si] = len(rr)
        if gathered is None:
            continue
        P, flat = gathered
        var = ctx.var_along(rr, cc, plane_normal, P, flat)
        h = (P - plane_point) @ plane_normal
        z = h / np.sqrt(var)
        frac[si] = float((np.abs(z) <= k).mean())
        front[si] = float((z > k).mean())
        height[si] = float(np.median(h))
    if memo is not None:
        memo[key] = (frac.copy(), front.copy(), n_valid.copy(), in_image.copy(), height.copy())
    return frac, front, n_valid, in_image, height


def face_sigma(config: Config, point: np.ndarray) -> float:
    """Standard deviation of a face's points off its plane at ``point``, metres: the
    range noise there and the flatness prior (bulge)."""
    return math.hypot(config.noise.sigma_range(float(np.linalg.norm(point))), config.flatness)


def plane_var(plane_cov: np.ndarray, normal: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Variance of the distance to a plane, from the plane's own uncertainty, of points at
    offsets D (n, 3) from the plane's point, m^2 (n,): the point's error along the normal
    plus the normal's error times the offset.

    Parameters
    ----------
    plane_cov : (6, 6) float64
        Covariance of the plane's (point, normal).
    normal : (3,) float64
    D : (n, 3) float64
    """
    So, Sn = plane_cov[:3, :3], plane_cov[3:, 3:]
    # einsum sums one row in another order (and a strided Sn in yet another): the kernel
    # only where it matches it, C-contiguous rows, two or more
    if (D.dtype == np.float64 and D.ndim == 2 and D.shape[0] > 1 and D.shape[1] == 3
            and D.flags.c_contiguous and Sn.dtype == np.float64):
        return normal @ So @ normal + _quad_rows(D, np.ascontiguousarray(Sn))
    return normal @ So @ normal + np.einsum("ni,ij,nj->n", D, Sn, D)


@kernel
def _take_rows(P: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """``P[flat]`` of a (N, 3) array."""
    out = np.empty((flat.shape[0], 3))
    for q in range(flat.shape[0]):
        i = flat[q]
        out[q, 0] = P[i, 0]
        out[q, 1] = P[i, 1]
        out[q, 2] = P[i, 2]
    return out


@kernel
def _mix_var(pd: np.ndarray, flat: np.ndarray, norm2: np.ndarray, sigma2: np.ndarray,
             lateral2: np.ndarray) -> np.ndarray:
    """:meth:`VerifyContext.var_along` from the points' products with the direction, element
    by element as its NumPy expression: cn2 = pd ** 2 / norm2, sigma2 cn2 + lateral2 (1 -
    cn2)."""
    out = np.empty(pd.shape[0])
    for q in range(pd.shape[0]):
        i = flat[q]
        cn2 = pd[q] * pd[q] / norm2[i]
        out[q] = sigma2[i] * cn2 + lateral2[i] * (1 - cn2)
    return out


@kernel
def _quad_rows(D: np.ndarray, S: np.ndarray) -> np.ndarray:
    """``np.einsum("ni,ij,nj->n", D, S, D)`` bit for bit, without its iterator's per-call
    cost: per row, the terms (D_i S_ij) D_j summed in (i, j) order from 0.0."""
    out = np.empty(D.shape[0])
    for q in range(D.shape[0]):
        acc = 0.0
        for i in range(3):
            for j in range(3):
                acc += D[q, i] * S[i, j] * D[q, j]
        out[q] = acc
    return out


def face_extent(
    ctx: VerifyContext, origin: np.ndarray, along: np.ndarray, across: np.ndarray,
    normal: np.ndarray, plane_cov: np.ndarray, strip: tuple[float, float], reach: float,
    k: float, flatness: float,
) -> tuple[float, float]:
    """How far a face's plane runs from ``origin`` along ``along``, in a strip beside it.

    The valid pixels of the strip (``strip`` metres across, out to ``reach`` along and a
    gap beyond) are tested against the plane (point-on-plane at ``k``, with the points'
    noise, the flatness prior and the plane's own uncertainty); the face ends where the
    points on it first leave a gap of ``EXTENT_GAP_PX`` pixels (dropouts are shorter). The
    end is placed half a pixel beyond its last point, where the edge stage puts a jump.
    A face whose points run on past ``reach`` has no end in sight: its extent is not the
    reach (a rectangle cut there has a side where nothing ends) but infinite.

    Parameters
    ----------
    origin, along, across, normal : (3,) float64
        The face's vertex, the axis to measure along, the axis across the strip, and the
        plane's normal.
    plane_cov : (6, 6) float64
        Covariance of (origin, normal).
    strip : (float, float)
        The strip's extent across, metres from the arm (inside the face).
    reach : float
        How far to look along the axis, metres.
    k : float
        Critical |z| of one point.
    flatness : float
        The flatness prior, metres.

    Returns
    -------
    extent : float
        Metres along the axis, at most ``reach`` (NaN: fewer than two points on the plane,
        or the strip leaves the image; inf: the plane runs on past ``reach``).
    gap : float
        The gap that ends the face there, metres.
    """
    # metres per pixel along the axis near the vertex, foreshortening included
    near = strip[1]
    step = near / max(ctx.samples_along(origin, origin + near * along), 1.0)
    gap = EXTENT_GAP_PX * step
    # a gap beyond the reach: a face that ends just inside it shows its end
    pix = rectangle_pixels(ctx.project, ctx.valid, origin, along, across,
                           (0.0, reach + gap), strip)
    if pix is None:
        return np.nan, gap
    rr, cc, _ = pix
    P, flat = ctx.gather(rr, cc)
    D = P - origin
    var = ctx.var_along(rr, cc, normal, P, flat) + flatness**2 + plane_var(plane_cov, normal, D)
    on = np.abs(D @ normal) <= k * np.sqrt(var)
    t = np.sort(D[on] @ along)
    t = t[t >= 0.0]
    # the face starts at the vertex, give or take the arm's own edge artefacts (as far
    # out as the strip is from the arm)
    if len(t) < 2 or t[0] > strip[0]:
        return np.nan, gap
    jumps = np.flatnonzero(np.diff(t) > gap)
    last = t[jumps[0]] if len(jumps) else t[-1]
    if last > reach:
        # the points run on past the reach before a gap ends them: no end in sight
        return np.inf, gap
    return float(last + 0.5 * step), gap


#: The two corners (rows of :func:`rectangle_corners`) of each side 0-3 of a rectangle:
#: v=0, v=length, u=0, u=width, the numbering of every per-side test.
SIDE_CORNERS = ((0, 1), (3, 2), (0, 3), (1, 2))


def rectangle_corners(
    origin: np.ndarray, x_axis: np.ndarray, y_axis: np.ndarray, width: float, length: float
) -> np.ndarray:
    """Corners (4, 3): origin, +x, +x+y, +y."""
    return np.array(
        [origin, origin + width * x_axis, origin + width * x_axis + length * y_axis,
         origin + length * y_axis]
    )


def rasterize(scan: Scan, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Pixels (rows, cols) inside the projected polygon, clipped to the image; None if a
    corner has no projection or less than half the polygon lies in the image."""
    uv = scan.sensor.project(corners)
    if not np.isfinite(uv).all():
        return None
    rr, cc = fill_polygon(uv, scan.shape)
    if len(rr) < 0.5 * polygon_area(uv):
        return None
    return rr, cc


@dataclass(frozen=True)
class _Hypothesis:
    """One rectangle to verify, in its own frame, with the scales its tests derive from it."""

    origin: np.ndarray  # (3,) the generating vertex, metres
    x_axis: np.ndarray  # (3,) unit
    y_axis: np.ndarray  # (3,) unit
    normal: np.ndarray  # (3,) unit, toward the sensor
    width: float  # extent along x_axis, metres
    length: float  # extent along y_axis, metres
    plane_cov: np.ndarray  # (6, 6) covariance of (origin, normal)
    centre: np.ndarray  # (3,) metres
    attempt_id: int  # entity ``a`` of every test
    alpha: float
    seam_alpha: float  # a seam as a boundary (VerifyContext.seam_alpha)
    k: float  # critical |z| of one point: sqrt(chi2(1)) at alpha
    spacing: float  # edge-point spacing at the centre, metres
    margin: float  # the border margin: the bevel and mixed pixels of the edge itself, metres
    interior_margin: float  # edges beyond it from every side are interior, metres
    band: float  # a side's edges lie within it of the side, metres
    #: level of the searches for an edge line or a seam inside (VERIFY_INTERIOR,
    #: VERIFY_SEAM_INTERIOR): alpha, over the parts of a split tested together
    interior_alpha: float = 0.0

    def __post_init__(self) -> None:
        if not self.interior_alpha:
            object.__setattr__(self, "interior_alpha", self.alpha)

    @property
    def flank(self) -> float:
        """How far beyond the rectangle the seam tests read range points, metres."""
        return (SEAM_FLANK[1] * max(SEAM_SCALES) + 1.0) * self.spacing


def seam_alpha(alpha: float, n_vertices: int) -> float:
    """The level at which a seam counts as a face's boundary: alpha over the scan's seam
    searches, two per vertex (one per axis).

    A seam side is the weakest evidence a face ends (no edge line, the same plane beyond):
    tested at alpha per search, a bare pallet top of a few vertices showed a false seam,
    and so two false faces, in 3 of 100 scans. Over the scan's searches the scan errs at
    most at alpha. A seam *inside* a rectangle keeps alpha (it rejects, erring toward no
    face).
    """
    return alpha / max(1, 2 * int(n_vertices))


def _hypothesis(ctx: VerifyContext, origin: np.ndarray, x_axis: np.ndarray, y_axis: np.ndarray,
                normal: np.ndarray, width: float, length: float, plane_cov: np.ndarray,
                config: Config, attempt_id: int) -> _Hypothesis:
    centre = origin + 0.5 * width * x_axis + 0.5 * length * y_axis
    spacing = ctx.spacing_at(centre)
    m = 2.0 * spacing
    # the interior lies beyond the band where the boundary's own edges lie (rounded or
    # bevelled cardboard gives a second, parallel edge a few mm inside)
    return _Hypothesis(
        origin=origin, x_axis=x_axis, y_axis=y_axis, normal=normal, width=width, length=length,
        plane_cov=plane_cov, centre=centre, attempt_id=attempt_id, alpha=config.alpha,
        seam_alpha=ctx.seam_alpha,
        k=float(np.sqrt(chi2_critical(1.0, config.alpha))), spacing=spacing, margin=m,
        interior_margin=max(m, BOUNDARY_BAND * config.min_edge), band=1.5 * m,
    )


@dataclass(frozen=True)
class _FaceEdges:
    """The edge points the tests of one rectangle read: those within a side's band of it."""

    u: np.ndarray  # (n,) along x_axis from the origin, metres
    v: np.ndarray  # (n,) along y_axis from the origin, metres
    kinds: np.ndarray  # (n,) EdgeKind
    near_plane: np.ndarray  # (n,) bool: on the rectangle's plane
    interior: np.ndarray  # (n,) bool: on the plane and beyond the interior margin
    #: (n,) bool: a jump point behind the plane, nearer to it than to the jump's far side
    #: (a mixed pixel: the sensor's footprint straddles the face's end; at 1280x960 a
    #: laser's is 4-5 pixels, and its jump points lay 26-52 mm behind a top 35 cm above
    #: the floor). It shows where the face ends, as a jump point on the plane does.
    blend: np.ndarray
    #: (n,) bool: a jump no higher than the flatness prior allows within one face (tape, a
    #: label, a bulge's fold), or None where the strengths are unknown
    minor: np.ndarray | None = None


def _face_edges(ctx: VerifyContext, hyp: _Hypothesis, config: Config) -> _FaceEdges:
    E = ctx.edge_points - hyp.origin
    eu, ev = E @ hyp.x_axis, E @ hyp.y_axis
    # every edge test looks at most a side's band beyond the rectangle: the rest of the
    # scan's edge points need no plane test
    band, width, length = hyp.band, hyp.width, hyp.length
    reach = (eu >= -band) & (eu <= width + band) & (ev >= -band) & (ev <= length + band)
    E, eu, ev = E[reach], eu[reach], ev[reach]
    ew = E @ hyp.normal
    sig_e = face_sigma(config, hyp.centre)
    # a face's boundary, seam and crossing edges lie on its plane (a jump point is placed
    # half a sample beyond the face's last point, hence the spacing)
    # ... and the rectangle's own plane is uncertain: a small error of its normal moves
    # the far sides' edges off it by the error times their distance from the vertex
    near_plane = (np.abs(ew) <= hyp.k * np.sqrt(sig_e**2 + plane_var(hyp.plane_cov, hyp.normal, E))
                  + hyp.spacing)
    mi = hyp.interior_margin
    interior = near_plane & (eu > mi) & (eu < width - mi) & (ev > mi) & (ev < length - mi)
    kinds = ctx.edge_kinds[reach]
    minor = None
    blend = np.zeros(len(E), bool)
    if ctx.edge_strength is not None and len(ctx.edge_strength) == len(ctx.edge_points):
        strength = ctx.edge_strength[reach]
        minor = (kinds == EdgeKind.JUMP) & (strength <= hyp.k * config.flatness)
        blend = (kinds == EdgeKind.JUMP) & ~near_plane & (ew < 0) & (-ew <= 0.5 * strength)
    return _FaceEdges(eu, ev, kinds, near_plane, interior, blend, minor)


@dataclass
class _Sides:
    """What the boundary tests found of each side 0-3 (v=0, v=length, u=0, u=width)."""

    covered: list[int]  # distinct positions along the side with boundary edges
    ok: list[bool]  # the side is a boundary
    expected: list[float]  # edge points expected along the side (its length in the image)
    seams: set[int] = field(default_factory=set)  # sides shown to be seams (or gaps)

    def fraction(self) -> float:
        """The fraction of the perimeter covered."""
        return float(sum(self.covered) / sum(self.expected))

    def bound(self, support_fraction: float) -> bool:
        """Every side a boundary, together covering ``support_fraction`` of the perimeter."""
        return all(self.ok) and self.fraction() >= support_fraction

    def copy(self) -> _Sides:
        """A copy whose lists and set can change without changing these."""
        return _Sides(list(self.covered), list(self.ok), list(self.expected), set(self.seams))


@dataclass(frozen=True)
class _FaceFit:
    """The valid pixels inside the rectangle (shrunk by the border margin), fitted by a plane."""

    rows: np.ndarray  # (n,) pixel rows
    cols: np.ndarray  # (n,) pixel columns
    points: np.ndarray  # (n, 3) metres
    offset: np.ndarray  # (n,) signed distance to the rectangle's plane, metres
    var: np.ndarray  # (n,) each point's variance along the normal, flatness included, m^2
    centre: np.ndarray  # (3,) the refitted plane's point, metres
    normal: np.ndarray  # (3,) the refitted plane's normal, toward the sensor
    cov: np.ndarray  # (6, 6) of (centre, normal)
    z: np.ndarray  # (n,) normalized distance to the refitted plane
    inliers: np.ndarray  # (n,) bool: |z| <= k
    core: np.ndarray  # (n,) bool: beyond twice the border margin from every side
    front: np.ndarray  # (n,) bool: in the core, significantly in front of the plane
    behind: np.ndarray  # (n,) bool: in the core, significantly behind it
    du: np.ndarray  # (n,) along x_axis from the origin, metres
    dv: np.ndarray  # (n,) along y_axis from the origin, metres
    rms: float  # of the inliers' distances to the refitted plane, metres (NaN: none)
    error: float  # sum of the inliers' squared z (the MDL xi)


# --- the tests, in the order of the README's table ------------------------------------------


def tilt_from_up(normal: np.ndarray, up: np.ndarray) -> float:
    """The angle between a face's unit normal (3,) and up (3,), radians."""
    return float(np.arccos(np.clip(normal @ up, -1, 1)))


def _test_tilt(hyp: _Hypothesis, up: np.ndarray, max_tilt: float) -> tuple[bool, TestTable]:
    """VERIFY_TILT: the face's normal within ``max_tilt`` of up. Returns (tilted, row)."""
    tilt = tilt_from_up(hyp.normal, up)
    return tilt > max_tilt, TestTable.decision(
        TestKind.VERIFY_TILT, hyp.attempt_id, -1, tilt, max_tilt, tilt <= max_tilt, hyp.alpha)


def _test_interior(edges: _FaceEdges, hyp: _Hypothesis, min_span: float = 0.0,
                   minor_too: bool = True) -> tuple[bool, TestTable]:
    """VERIFY_INTERIOR: no straight line of edge points crosses the interior (one whose
    points spread at least ``min_span`` along it, metres; of jumps no higher than the
    flatness prior allows, only if ``minor_too``)."""
    inside = edges.interior
    if not minor_too and edges.minor is not None:
        inside = inside & ~edges.minor
    line_count, line_p, span = _interior_line_span(edges.u[inside], edges.v[inside],
                                                   hyp.width, hyp.length, hyp.spacing,
                                                   hyp.interior_margin)
    min_line = float(MIN_LINE_POINTS)
    line_ok = not (line_count >= min_line and line_p < hyp.interior_alpha
                   and span >= min_span)
    return line_ok, TestTable.decision(TestKind.VERIFY_INTERIOR, hyp.attempt_id, -1, line_count,
                                       min_line, line_ok, hyp.alpha, p_value=line_p)


def _test_boundary(edges: _FaceEdges, hyp: _Hypothesis, ctx: VerifyContext,
                   support_fraction: float) -> tuple[_Sides, TestTable]:
    """VERIFY_BOUNDARY: each side a significant line of convex edges (jump, convex crease,
    groove), outnumbering the concave creases along it; all four covering the fraction p
    of the perimeter (the paper's |P_f| > p, over all four sides)."""
    u, v, band = edges.u, edges.v, hyp.band
    width, length, spacing, mi = hyp.width, hyp.length, hyp.spacing, hyp.interior_margin
    convex = (edges.near_plane | edges.blend) & np.isin(
        edges.kinds, (EdgeKind.JUMP, EdgeKind.CREASE_CONVEX, EdgeKind.GROOVE))
    sides = (
        (np.abs(v) <= band, u, width),
        (np.abs(v - length) <= band, u, width),
        (np.abs(u) <= band, v, length),
        (np.abs(u - width) <= band, v, length),
    )
    # background: convex edge points scattered over the interior, per unit area
    area_in = max((width - 2 * mi) * (length - 2 * mi), spacing * spacing)
    density = float((convex & edges.interior).sum()) / area_in

    def side_lines(kind_mask: np.ndarray) -> tuple[list[int], list[float]]:
        counts, p_values = [], []
        for near, along, L in sides:
            sel = kind_mask & near & (along >= 0) & (along <= L)
            # distinct positions along the side (one per spacing): coverage, not density
            k_s = _n_distinct(np.floor(along[sel] / spacing).astype(np.int64))
            counts.append(k_s)
            p_values.append(_poisson_sf(k_s - 1, density * L * 2 * band))
        return counts, p_values

    covered, side_p = side_lines(convex)
    # concave creases along a side: the face meets a wall rising from it (the pallet or a
    # lower box beside a taller one), which a top face's side never does
    concave, _ = side_lines(edges.near_plane & (edges.kinds == EdgeKind.CREASE_CONCAVE))
    side_min = [max(MIN_LINE_POINTS, kc) for kc in concave]
    corners = rectangle_corners(hyp.origin, hyp.x_axis, hyp.y_axis, width, length)
    expected = ctx.samples_along_sides(corners)
    ok = [(k >= kmin and pv < hyp.alpha) for k, kmin, pv in zip(covered, side_min, side_p)]
    result = _Sides(covered, ok, expected)
    frac = result.fraction()
    return result, TestTable.decision(
        TestKind.VERIFY_BOUNDARY, hyp.attempt_id, -1, np.r_[covered, frac],
        np.r_[side_min, support_fraction], np.r_[ok, frac >= support_fraction], hyp.alpha,
        p_value=np.r_[side_p, np.nan])


def _test_seam_sides(fp: FacePoints, hyp: _Hypothesis, sides: _Sides,
                     support_fraction: float) -> list[TestTable]:
    """VERIFY_SEAM_SIDE: a side without its line of edges, or whose line covers too little,
    is a boundary if it is a seam between touching faces along its whole length.

    Completes ``sides`` (``ok``, ``covered``, ``seams``) with the seams found.
    """
    tests: list[TestTable] = []

    def seams_along(tried: list[int]) -> None:
        zz = np.array([_side_seam(fp, si, hyp.width, hyp.length, hyp.spacing,
                                  hyp.seam_alpha) for si in tried])
        for si, (zs, zc) in zip(tried, zz):
            if zs > zc:
                sides.seams.add(si)
                sides.ok[si] = True
                sides.covered[si] = int(sides.expected[si])
        tests.append(TestTable.decision(TestKind.VERIFY_SEAM_SIDE, hyp.attempt_id, tried,
                                        zz[:, 0], zz[:, 1], zz[:, 0] > zz[:, 1], hyp.alpha))

    if not all(sides.ok) and len(fp):
        seams_along([si for si in range(4) if not sides.ok[si]])
    if (all(sides.ok) and len(fp)
            and sum(sides.covered) < support_fraction * sum(sides.expected)):
        # every side has its line, but together they cover too little of the perimeter:
        # a side whose line is a few points of a seam between equal neighbours is covered
        # by the seam along its whole length
        seams_along([si for si in range(4) if si not in sides.seams])
    return tests


def _test_size_sides(fp: FacePoints, hyp: _Hypothesis, sides: _Sides,
                     size_sides: frozenset[int]) -> TestTable:
    """SKU_SPLIT_SEAM: the sides a listed size implies are boundaries on the size's
    evidence; the groove along each, however weak, is recorded (b = side, statistic z,
    critical the seam level's z, accepted where the seam is seen).

    Completes ``sides`` (``ok``, ``covered``, ``seams``) with them.
    """
    tried = sorted(size_sides)
    zz = np.array([_side_seam(fp, si, hyp.width, hyp.length, hyp.spacing, hyp.seam_alpha)
                   if len(fp) else (np.nan, np.nan) for si in tried])
    for si in tried:
        sides.ok[si] = True
        sides.covered[si] = int(sides.expected[si])
        sides.seams.add(si)
    return TestTable.decision(TestKind.SKU_SPLIT_SEAM, hyp.attempt_id, tried, zz[:, 0],
                              zz[:, 1], zz[:, 0] > zz[:, 1], hyp.alpha)


def whole_face_spread(fp: FacePoints, axis: int, size: float, ext: float, spacing: float
                      ) -> tuple[float, ...]:
    """:func:`face_spread` along u (``axis`` 0) or v (1), 0 to ``size``, over the face's
    points whose other coordinate lies within 0 to ``ext``."""
    coord, other = (fp.u, fp.v) if axis == 0 else (fp.v, fp.u)
    on = (other >= 0) & (other <= ext) & (coord >= 0) & (coord <= size)
    return face_spread(coord[on], fp.w[on], fp.scale, size, spacing, fp.row[on],
                       fp.row_corr)


#: Each half of a face must be at least this share of ``min_edge`` long for
#: ``VERIFY_SEAM_MIDLINE`` to test its middle (measured dimensions fall a little short of
#: two boxes' extent, as ``dimensions_from_extent`` allows for one box's).
MIDLINE_HALF = 0.9
#: The most equal parts in a row :func:`_test_seam_midline` looks for the seams of (a
#: layer's row of one SKU; more parts are left to the interior's search over every
#: position): bounded work, n - 1 lines per n and axis.
MAX_TILING_PARTS = 4


def _test_seam_midline(fp: FacePoints, hyp: _Hypothesis, min_edge: float,
                       sizes: tuple[tuple[float, float, float], ...] = (),
                       tolerance: float = 0.0) -> tuple[bool, list[TestTable]]:
    """VERIFY_SEAM_MIDLINE: no seams where a face that could be n equal boxes in a row
    would have them (n = 2 .. :data:`MAX_TILING_PARTS`).

    Two equal boxes side by side are one flat rectangle where their seam is faint: zero
    gap, sharp or slightly bevelled edges. Its seam then lies at the middle, and only
    there: a groove statistic at one position, over the few the dimensions' error allows
    (:func:`seam_line`: the whole line, both its halves showing it), has a critical value
    far below that of :func:`_test_seam_interior`'s search over every position, which
    also keeps clear of the sides by half ``min_edge`` and so reads a narrow face's seam
    over a short strip. On the development matrix draw (seed 1) the middles of 4 of 22
    false surfaces, two boxes each, showed a seam, and of 194 true tops 3 (1.5 %, about
    the level over their axes); run in the pipeline, where a rejected rectangle leaves the
    search to the next candidates, 5 false surfaces went and no true top. Three or four
    equal cartons in a row (a layer of one SKU) put their seams at the thirds or quarters,
    none at the middle: their n - 1 lines are tested together, the sum of their groove
    z over sqrt(n - 1) (N(0, 1) where the face is one box; each line's z alone is about
    1/sqrt(n - 1) of it where all n - 1 seams are there), against the one line's critical
    value. On a development packed layer of 0.15 m cartons (structured light at 1 m, 320
    px; seed 1, scene 74) three rectangles spanned three cartons each: their interiors'
    searches read the seams at z 3.2-3.3 against 3.57.

    Tested along each axis for each n whose parts are at least ``MIDLINE_HALF``
    ``min_edge`` long and, with a carton list, match a listed size (``SKU_SIZE``'s test).
    Grooves only, no gaps: a line of holes at the middle of an active-stereo or
    structured-light lid is as often tape or a label (the same draw: with gaps, 9 true tops
    lost for 9 false surfaces). b = axis + 2 (n - 2): 0 for the line u = width / 2, 1 for
    v = length / 2, 2 and 3 for the thirds along u and v, ...; statistic the groove z (the
    lines' sum over sqrt(n - 1); NaN: no points), critical at alpha. Returns (split, rows).
    """
    if not len(fp):
        return False, []
    bs, zs, crits = [], [], []
    for axis, size, other in ((0, hyp.width, hyp.length), (1, hyp.length, hyp.width)):
        for n in range(2, MAX_TILING_PARTS + 1):
            part = size / n
            if part < MIDLINE_HALF * min_edge:
                break
            if sizes and not match_size(min(part, other), max(part, other), sizes, tolerance,
                                        hyp.alpha)[3]:
                continue
            lines = [seam_line(fp, axis, k * size / n, other, hyp.spacing, hyp.alpha)
                     for k in range(1, n)]
            z = sum(zk for zk, _ in lines) / math.sqrt(n - 1)
            bs.append(axis + 2 * (n - 2))
            zs.append(z if np.isfinite(z) else np.nan)
            crits.append(lines[0][1])
    if not bs:
        return False, []
    split = [bool(z > c) for z, c in zip(zs, crits)]
    return any(split), [TestTable.decision(TestKind.VERIFY_SEAM_MIDLINE, hyp.attempt_id, bs,
                                           zs, crits, [not x for x in split], hyp.alpha)]


def _test_seam_interior(fp: FacePoints, hyp: _Hypothesis, correlated: bool = False
                        ) -> tuple[bool, list[TestTable],
                                   tuple[tuple[float, ...], tuple[float, ...]]]:
    """VERIFY_SEAM_INTERIOR: no seam crosses the face (the points of the interior, binned
    along x and along y). Returns (crossed, its row, if any points, and the statistic's
    spread over the interior's positions along x and along y, which the side seams'
    statistics are divided by too, scale by scale: correlated noise spreads them alike).

    Where the model is ``correlated`` the spread is measured over the whole face too
    (:func:`face_spread`). An axis's interior too narrow to measure it in takes the whole
    face's, for its own search as for the sides'. A wider one whose search crosses a seam
    divides it again by the larger of the two (elsewhere the larger could only lower the
    statistic, and the row holds the interior's own): the interior's positions are few
    independent samples of a field whose amplitude wanders (a stereo matcher's quality
    with the texture), and on the development packed active-stereo layers the tops' own
    interiors crossed a seam on 7.4 % of their axes at a level of 1 % (0.4-1.1 % for the
    laser, none for structured light); divided by the larger spread, 2.8 %."""
    if not len(fp):
        return False, [], fp.spread
    mi, width, length = hyp.interior_margin, hyp.width, hyp.length
    int_z, int_crit, spread = [], [], []  # spread: per axis, per scale
    for axis, coord, other, size, ext in ((0, fp.u, fp.v, width, length),
                                          (1, fp.v, fp.u, length, width)):
        lo_hi = (mi, size - mi)
        sel = (other >= mi) & (other <= ext - mi)
        narrow = (size - 2 * mi) / (0.5 * hyp.spacing) + 1 < MIN_SPREAD_POSITIONS or not sel.any()
        # the whole face's spread only where the model is correlated: where it is white,
        # what spreads a face is its own shape (a bulged lid's curve across a narrow top),
        # which its sides' seams are not
        c_in, w_in, r_in = coord[sel], fp.w[sel], fp.row[sel]
        stats: list[tuple[np.ndarray, np.ndarray]] = []  # the second search reuses them
        found = find_seams(c_in, w_in, fp.scale, lo_hi[0], lo_hi[1],
                           hyp.spacing, hyp.interior_alpha, r_in, fp.row_corr,
                           spread=(whole_face_spread(fp, axis, size, ext, hyp.spacing)
                                   if correlated and narrow else None), stats=stats)
        if correlated and not narrow and found.z_max > found.critical:
            # measured only where the interior's own spread lets a seam cross: elsewhere the
            # larger spread could only lower the statistic (the row then holds the own's)
            found = find_seams(c_in, w_in, fp.scale, lo_hi[0], lo_hi[1],
                               hyp.spacing, hyp.interior_alpha, r_in, fp.row_corr,
                               floor_spread=whole_face_spread(fp, axis, size, ext,
                                                              hyp.spacing), stats=stats)
        # the strongest groove anywhere inside, significant or not (NaN: none measurable)
        int_z.append(found.z_max if np.isfinite(found.z_max) else np.nan)
        int_crit.append(found.critical)
        spread.append(found.spread)  # the sides' (the whole face's where it stood in)
    row = TestTable.decision(TestKind.VERIFY_SEAM_INTERIOR, hyp.attempt_id, [0, 1], int_z,
                             int_crit, [not z > c for z, c in zip(int_z, int_crit)], hyp.alpha)
    return any(z > c for z, c in zip(int_z, int_crit)), [row], (spread[0], spread[1])


def _test_plane_ends(ctx: VerifyContext, hyp: _Hypothesis, fit: _FaceFit | None,
                     sides: _Sides, support_fraction: float,
                     memo: dict[Any, Any] | None = None) -> list[TestTable]:
    """VERIFY_PLANE_END: a side that is no boundary by its edges (nor a seam) is one where
    the face's refitted plane ends just beyond it, dropping away: at most
    ``PLANE_END_FRACTION`` of the valid pixels of the strip beyond the side (as
    :func:`continuation` reads it, at least ``MIN_LINE_POINTS`` of them, most of the strip
    in the image) lie on the plane, and at most as many in front of it. Such a
    side counts as covered by the share of the strip off the plane. Returns its row (b =
    side, statistic = the fraction on the plane, critical = ``PLANE_END_FRACTION``), if any
    side was tried. Without ``fit`` the rectangle's own plane (origin, normal) stands in.

    Where the sides together cover less than ``support_fraction`` of the perimeter, the
    sides that are boundaries by their edges are tried too, and covered the same way: a
    sensor that smears its depth edges finds a jump at only a quarter of the positions
    along a side (active stereo), while the range points beyond show the drop all along
    it, as :func:`_test_seam_sides` covers a side by its seam. :func:`verify` asks this of
    flat regions only (``support_fraction`` 0 otherwise): a region is never a surface, and
    on a box's rectangle it made false surfaces on bare active-stereo pallets."""
    short = sides.fraction() < support_fraction
    todo = [si for si in range(4) if not sides.ok[si] or (short and si not in sides.seams)]
    if not todo:
        return []
    m = hyp.margin
    centre, normal = (hyp.origin, hyp.normal) if fit is None else (fit.centre, fit.normal)
    frac, front, _, in_image, _ = _beyond_sides(ctx, hyp.origin, hyp.x_axis, hyp.y_axis,
                                             hyp.width, hyp.length, centre, normal, m,
                                             hyp.flank - m, hyp.k, memo)
    # a top's side drops away (behind the plane); a wall rising in front of it is a lower
    # face's side, which a top's never is (the concave creases of VERIFY_BOUNDARY)
    ends = [bool(in_image[si] and np.isfinite(frac[si]) and frac[si] <= PLANE_END_FRACTION
                 and front[si] <= PLANE_END_FRACTION) for si in todo]
    for si, e in zip(todo, ends):
        if e:
            sides.ok[si] = True
            sides.covered[si] = max(sides.covered[si],
                                    int(round((1.0 - frac[si]) * sides.expected[si])))
    return [TestTable.decision(TestKind.VERIFY_PLANE_END, hyp.attempt_id, todo, frac[todo],
                               PLANE_END_FRACTION, ends, hyp.alpha)]


def _test_continuation(ctx: VerifyContext, fp: FacePoints, hyp: _Hypothesis, fit: _FaceFit,
                       sides: _Sides, min_inlier_fraction: float, flatness: float,
                       memo: dict[Any, Any] | None = None
                       ) -> tuple[np.ndarray, np.ndarray, list[TestTable]]:
    """VERIFY_CONTINUATION: the face ends at each side, its plane does not run on beyond,
    unless the side is a seam or a gap between equal neighbours (a rectangle cut short
    inside a face is not a face).

    VERIFY_RAISED_BEYOND: nor does it run on under something thin. Where at least
    ``RAISED_FRACTION`` of the strip beyond a side (no seam) lies in front of the plane,
    no higher than the flatness prior allows (its median height at most k ``flatness``),
    the side is the edge of tape or a label lying on the lid, whose step up reads as a
    line of jump edges on the plane: the face runs on under it. (A top's side has a lower
    surface beyond it, or nothing, or a taller box; one a few millimetres taller cannot
    be told from tape, and does not count either.) On a development basket-weave layer
    (packed seed 3, scene 43) a rectangle took a tape edge 0.1 m inside a carton's lid as
    its side: 263 jump points along it, and the strip beyond 89 % in front of the plane.

    Returns
    -------
    ends : (4,) bool
        The face ends at the side.
    cut : (4,) bool
        The side's strip leaves the image with too few points to test, and the side is no
        seam: the face may run on out of sight.
    rows : list of TestTable
        VERIFY_SEAM_SIDE for the sides whose plane runs on, if any, then
        VERIFY_CONTINUATION, VERIFY_RAISED_BEYOND and VERIFY_RAISED_HEIGHT.
    """
    m = hyp.margin
    cont, front, _, in_image, height = _beyond_sides(ctx, hyp.origin, hyp.x_axis, hyp.y_axis,
                                                     hyp.width, hyp.length, fit.centre,
                                                     fit.normal, m, hyp.flank - m, hyp.k, memo)
    continues = cont >= min_inlier_fraction
    ends = ~continues
    extra_seam: list[tuple[int, float, float]] = []
    for si in np.flatnonzero(continues):
        if si in sides.seams:
            ends[si] = True
            continue
        # anywhere in the band where the side's boundary edges are counted
        zs, zc = (_side_seam(fp, int(si), hyp.width, hyp.length, hyp.spacing,
                             hyp.seam_alpha, hyp.band, True) if len(fp) else (-np.inf, np.inf))
        extra_seam.append((int(si), zs, zc))
        ends[si] = zs > zc
        if ends[si]:
            sides.seams.add(int(si))
    rows = []
    if extra_seam:
        es = np.array(extra_seam)
        rows.append(TestTable.decision(TestKind.VERIFY_SEAM_SIDE, hyp.attempt_id,
                                       es[:, 0].astype(int), es[:, 1], es[:, 2],
                                       es[:, 1] > es[:, 2], hyp.alpha))
    # a side whose strip leaves the image cannot show that the face ends there, unless
    # the strip's part in the image has points enough to test or the side is a seam: the
    # face may run on out of sight
    cut = np.array([not in_image[si] and not np.isfinite(cont[si]) and si not in sides.seams
                    for si in range(4)])
    ends &= ~cut
    rows.append(TestTable.decision(TestKind.VERIFY_CONTINUATION, hyp.attempt_id, [0, 1, 2, 3],
                                   cont, min_inlier_fraction, ends, hyp.alpha))
    # no higher than the flatness prior (NaN: no strip, not thin); its row records it, so
    # a post-mortem sees how high the strip stood
    thin = height <= hyp.k * flatness
    seam = np.isin(np.arange(4), list(sides.seams))
    raised = ~seam & (front >= RAISED_FRACTION) & thin  # NaN front: False
    ends &= ~raised
    rows.append(TestTable.decision(TestKind.VERIFY_RAISED_BEYOND, hyp.attempt_id, [0, 1, 2, 3],
                                   front, RAISED_FRACTION, ~raised, hyp.alpha))
    rows.append(TestTable.decision(TestKind.VERIFY_RAISED_HEIGHT, hyp.attempt_id,
                                   [0, 1, 2, 3], height, hyp.k * flatness, thin, hyp.alpha))
    return ends, cut, rows


def _cells(iu: np.ndarray, iv: np.ndarray) -> tuple[np.ndarray, int]:
    """Each point's cell among the cells that hold points, numbered in the order of (iu,
    iv), and their number: ``np.unique(iu * 1e6 + iv, return_inverse=True)``'s inverse and
    length for whole iu, iv (float64, |iv| < 1e6), from a count per cell of their box."""
    if not iu.size:
        return np.zeros(0, np.int64), 0
    a = (iu - iu.min()).astype(np.int64)
    b = (iv - iv.min()).astype(np.int64)
    key = a * (int(b.max()) + 1) + b
    present = np.bincount(key) > 0
    rank = np.cumsum(present) - 1
    return rank[key], int(present.sum())


def _test_exposed(fit: _FaceFit, hyp: _Hypothesis, noise: NoiseModel
                  ) -> tuple[bool, TestTable]:
    """VERIFY_EXPOSED: nothing rests on the face. Covered only if the points in front of
    its plane outnumber those behind (sign test) and are more frequent than the noise
    puts there, over the core or in its busiest cell.

    Where the noise model has a correlation (a row offset, correlation lengths), the points
    beyond k come in runs and every count varies more than a binomial one: a count x of n
    is taken as x / D of n / D independent points, D its design effect under the model
    (:mod:`boxloc.stages.design_effect`), or the patchiness the scan's own flat tiles show
    (``noise.exceed_dispersion``) where that is larger; the core's count of front points
    that times its tiles' :func:`~boxloc.stages.design_effect.patch_factor` (the patches
    reach beyond a tile; a cell, a few tiles at most, keeps the tile's, and the sign test
    too, since within a patch the points fall on either side alike). How often the noise
    puts a point in front is the scan's own rate too (``noise.exceed_rate``; alpha / 2 for
    normal noise): active-stereo depth has heavy tails in patches, and on bulged lids,
    whose middles stand in front of their plane, a model's normal rate called most layers
    covered. The rows record the effective counts (the raw ones for white noise, D = 1)."""
    alpha = hyp.alpha
    core = fit.core
    rows = fit.rows[core]
    # cells of four border margins: the corner of a box above is a few square centimetres
    cell = 4.0 * hyp.margin
    inv, n_ids = _cells(np.floor(fit.du[core] / cell), np.floor(fit.dv[core] / cell))
    D_f, D_s = exceedance_design_effects(rows, np.zeros(len(rows), np.int64), 1, hyp.k, noise)
    D_cell = exceedance_design_effects(rows, inv, n_ids, hyp.k, noise)[0]
    patchy = float(noise.exceed_dispersion)
    # the scan measured the patchiness tile by tile; the core's count of front points
    # spans many tiles, and a patch of large noise raises it over all of them. Not the
    # sign test's: within a patch the points fall on either side alike
    D_f = np.maximum(D_f, patchy * patch_factor(rows, fit.cols[core], noise))
    D_s, D_cell = np.maximum(D_s, patchy), np.maximum(D_cell, patchy)
    rate = max(alpha / 2, float(noise.exceed_rate))  # of a point in front, under the noise

    def eff(x: Any, D: Any) -> np.ndarray:
        return np.rint(np.asarray(x, np.float64) / D).astype(np.int64)

    n_front, n_behind = int(fit.front.sum()), int(fit.behind.sum())
    m_out = int(eff(n_front + n_behind, D_s[0]))
    f_sign = int(eff(n_front, D_s[0]))
    p_front = float(binom_sf(f_sign - 1, m_out, 0.5)) if f_sign else 1.0
    # ... and more frequent than the noise puts in front (z > k: alpha / 2 of the points
    # for normal noise), so that a handful of stray points, with none behind, is no occluder
    n_core = int(eff(int(core.sum()), D_f[0]))
    f_rate = int(eff(n_front, D_f[0]))
    p_rate = float(binom_sf(f_rate - 1, n_core, rate)) if f_rate else 1.0
    # ... or, in one place (the corner of a box above), more frequent than that: the
    # busiest cell of the core, Bonferroni over the cells
    n_cell = eff(np.bincount(inv, minlength=n_ids), D_cell)
    f_cell = eff(np.bincount(inv, weights=fit.front[core].astype(np.float64),
                             minlength=n_ids), D_cell)
    n_cells = max(n_ids, 1)
    if f_cell.any():
        p_cells = binom_sf(f_cell - 1, n_cell, rate)
        c_best = int(np.argmin(np.where(f_cell > 0, p_cells, np.inf)))
        p_local = float(min(p_cells[c_best] * n_cells, 1.0))
        f_local, n_local = int(f_cell[c_best]), int(n_cell[c_best])
    else:
        p_local, f_local, n_local = 1.0, 0, int(n_cell.max()) if len(n_cell) else 0
    exposed = p_front >= alpha or (p_rate >= alpha and p_local >= alpha)
    return exposed, TestTable.decision(
        TestKind.VERIFY_EXPOSED, hyp.attempt_id, [m_out, n_core, n_local],
        [f_sign, f_rate, f_local],
        [binom_isf(alpha, m_out, 0.5) if m_out else 0.0,
         binom_isf(alpha, n_core, rate),
         binom_isf(alpha / n_cells, n_local, rate)],
        [p_front >= alpha, p_rate >= alpha, p_local >= alpha], alpha,
        p_value=[p_front, p_rate, p_local])


def _test_inliers(fit: _FaceFit, n_inside: int, n_valid: int, hyp: _Hypothesis,
                  min_inlier_fraction: float, min_return_fraction: float, hole_weight: float
                  ) -> tuple[float, bool, TestTable]:
    """VERIFY_INLIERS: the fraction of the points inside on the plane (row 0; entity b the
    points counted: the returns plus ``hole_weight`` of the holes), and, where
    ``min_return_fraction`` is above 0, the fraction of the pixels inside that returned
    (row 1; b the pixels).

    A hole is no evidence against a face (``hole_weight`` 0): active-stereo and
    time-of-flight sensors return nothing from dark labels and tape, and on the development
    scenes a third to two fifths of a found box's pixels were holes, with 98-99 % of the
    returns on its plane. A rectangle mostly unseen is no face either, hence row 1.
    Returns (the fraction of row 0, whether the rows accept, the rows)."""
    n_in = int(fit.inliers.sum())
    counted = n_valid + hole_weight * (n_inside - n_valid)
    frac = n_in / max(counted, 1)
    b, stat, crit = [round(counted)], [frac], [min_inlier_fraction]
    if min_return_fraction > 0:
        b.append(n_inside)
        stat.append(n_valid / max(n_inside, 1))
        crit.append(min_return_fraction)
    ok = np.asarray(stat) >= np.asarray(crit)
    return frac, bool(ok.all()), TestTable.decision(
        TestKind.VERIFY_INLIERS, hyp.attempt_id, b, stat, crit, ok, hyp.alpha)


def _test_mean(fit: _FaceFit, hyp: _Hypothesis, flatness: float
               ) -> tuple[float, float, TestTable]:
    """VERIFY_MEAN: the inliers' mean distance to the rectangle's plane is zero within the
    propagated uncertainty. Returns (the mean, its variance, m^2, row)."""
    inl = fit.inliers
    n_in = int(inl.sum())
    if n_in >= 3:
        mean = float(fit.offset[inl].mean())
        dc = fit.points[inl].mean(0) - hyp.origin
        # the face may depart from R's plane by the flatness prior as a whole (bulge)
        s2_mean = float(fit.var[inl].mean() / n_in
                        + plane_var(hyp.plane_cov, hyp.normal, dc[None])[0] + flatness**2)
        T_mean = mean**2 / s2_mean
    else:
        mean, s2_mean, T_mean = np.nan, np.nan, np.inf
    return mean, s2_mean, TestTable.chi2(TestKind.VERIFY_MEAN, hyp.attempt_id, n_in, T_mean,
                                         1.0, hyp.alpha)


# --- the face's points ---------------------------------------------------------------------


def _fit_face(ctx: VerifyContext, hyp: _Hypothesis, rows: np.ndarray, cols: np.ndarray,
              flatness: float) -> _FaceFit | None:
    """The points at valid pixels (rows, cols) inside the rectangle, against its plane and
    against the plane refitted to them; None if fewer than 3 lie on the rectangle's."""
    k, m, normal = hyp.k, hyp.margin, hyp.normal
    P, flat = ctx.gather(rows, cols)
    D = P - hyp.origin
    w0 = D @ normal
    # each point's noise along the normal; the flatness prior covers cardboard bulge
    var_pt = ctx.var_along(rows, cols, normal, P, flat) + flatness**2
    # 1) points on the plane of R, with R's own uncertainty
    var_pl = plane_var(hyp.plane_cov, normal, D)
    on0 = np.abs(w0) <= k * np.sqrt(var_pt + var_pl)
    if on0.sum() < 3:
        return None
    # 2) the face's plane refitted to them, with covariance
    # Q = P[on0], its mean c and (Q - c) twice, in a kernel (as face_points)
    c, X1, X2 = _centred(P, on0)
    lam, V = np.linalg.eigh(X1.T @ X2)
    nf = V[:, 0] if V[:, 0] @ normal > 0 else -V[:, 0]
    # 3) inliers, front and behind against the refitted plane (point noise only)
    z = ((P - c) @ nf) / np.sqrt(var_pt)
    inl = np.abs(z) <= k
    # front and behind count in the core only, beyond twice the border margin: next to
    # a jump edge structured-light sensors pull the points toward the sensor by up to a
    # centimetre, a few pixels further in than the margin; an occluder resting on the
    # face reaches into the core (a strip of a face hidden by a taller neighbour is
    # wider than those pixels)
    du, dv = D @ hyp.x_axis, D @ hyp.y_axis
    mc = 2.0 * m
    core = (du > mc) & (du < hyp.width - mc) & (dv > mc) & (dv < hyp.length - mc)
    if not core.any():
        core[:] = True
    n_in = int(inl.sum())
    s2 = float(max(lam[0] / max(int(on0.sum()) - 3, 1), _median(var_pt[on0])))
    cov = np.zeros((6, 6))
    cov[:3, :3] = s2 / max(n_in, 1) * np.eye(3)
    cov[3:, 3:] = s2 * (np.outer(V[:, 1], V[:, 1]) / max(lam[1], 1e-12)
                        + np.outer(V[:, 2], V[:, 2]) / max(lam[2], 1e-12))
    rms = float(np.sqrt(np.mean(((P[inl] - c) @ nf) ** 2))) if n_in else np.nan
    return _FaceFit(rows=rows, cols=cols, points=P, offset=w0, var=var_pt, centre=c, normal=nf,
                    cov=cov, z=z, inliers=inl, core=core, front=(z > k) & core,
                    behind=(z < -k) & core, du=du, dv=dv, rms=rms,
                    error=float((z[inl] ** 2).sum()))


def _failed(reason: VerifyReason, tests: list[TestTable], alpha: float, *, n_inside: int = 0,
            n_valid: int = 0, n_interior_edges: int = 0) -> VerifyOutcome:
    """The outcome of a rectangle rejected before its plane was refitted."""
    return VerifyOutcome(
        n_inside=n_inside, n_valid=n_valid, n_inliers=0, n_front=0, n_behind=0,
        inlier_fraction=0.0, mean_distance=np.nan, sigma_mean=np.nan,
        n_interior_edges=n_interior_edges, plane_center=np.full(3, np.nan),
        plane_normal=np.full(3, np.nan), plane_cov=np.full((6, 6), np.nan), rms=np.nan,
        error=np.nan, accepted=False, reason=reason, inlier_pixels=np.zeros(0, np.int32),
        tests=TestTable.concat(tests, alpha),
    )


def verify(
    scan: Scan,
    ctx: VerifyContext,
    origin: np.ndarray,
    x_axis: np.ndarray,
    y_axis: np.ndarray,
    normal: np.ndarray,
    width: float,
    length: float,
    plane_cov: np.ndarray,
    config: Config,
    attempt_id: int,
    size_sides: frozenset[int] = frozenset(),
    family: int = 1,
    region: bool = False,
    region_sides: frozenset[int] = frozenset(),
) -> VerifyOutcome:
    """Verify one rectangle hypothesis by the range points inside it.

    The tests run cheapest first, each stopping the verification when it fails: the tilt;
    on the edge points, the interior and the boundary (completed by seams); on the range
    points around the rectangle, the seams inside; then, on the points inside (the plane
    refitted to them), a side still without evidence of its end gets it where the plane
    drops away just beyond it (``VERIFY_PLANE_END``: a fold or step the scan lines missed),
    and the boundary is decided; then exposure, inliers, their mean, and whether the
    face's plane runs on beyond its sides. Every test made is recorded.

    Parameters
    ----------
    origin, x_axis, y_axis, normal : ndarray (3,)
        The rectangle's frame (generating vertex; unit axes; normal toward the sensor).
    width, length : float
        Extent along x_axis and y_axis, metres.
    plane_cov : ndarray (6, 6)
        Covariance of (origin, normal) of the rectangle's plane.
    attempt_id : int
        Recorded as entity ``a`` of every test.
    size_sides : frozenset of int
        Sides (0-3) that a listed carton size puts inside a larger flat region (a part of
        a split, :mod:`boxloc.stages.sizes`): the size is their evidence of the box's end,
        so they count as boundaries and as ends (a seam) whatever the edges say; the
        groove there, however weak, is recorded (SKU_SPLIT_SEAM).
    family : int
        The rectangle is one of ``family`` parts of a split, verified together: the
        searches for a line or seam inside each run at alpha / ``family`` (Bonferroni), so
        that the split as a whole errs at alpha. 1 for a hypothesis of its own.
    region : bool
        The rectangle is a whole flat region larger than a box
        (:func:`boxloc.stages.hypotheses.dimensions_from_region`), verified by its
        outline, exposure and plane: the searches for a line or a seam inside are recorded
        but reject nothing (a region is several boxes; a seam at an implied cut, or tape
        and labels on the lids, lie inside it), and an edge line counts only if its points
        spread along it as far as the supported part of the shortest box edge
        (``support_fraction`` ``min_edge``): a sensor's artefact edges clump.
    region_sides : frozenset of int
        Sides (0-3) of a part of a split region that lie on the region's outline, whose
        verification showed the face ends there: a side whose own stretch of edges is too
        short to show it (VERIFY_BOUNDARY rejects) is a boundary on the region's evidence.

    Returns
    -------
    VerifyOutcome
    """
    hyp = _hypothesis(ctx, origin, x_axis, y_axis, normal, width, length, plane_cov, config,
                      attempt_id)
    if family > 1:
        hyp = dataclasses.replace(hyp, interior_alpha=hyp.alpha / family)
    alpha, m = hyp.alpha, hyp.margin
    tests: list[TestTable] = []

    tilted, row = _test_tilt(hyp, ctx.up, config.max_tilt)
    tests.append(row)
    if tilted:
        return _failed(VerifyReason.TILTED, tests, alpha)
    if width <= 2 * m or length <= 2 * m:
        return _failed(VerifyReason.TOO_FEW_POINTS, tests, alpha)
    # cheap tests first, on the edge points (no rasterization)
    edges = _face_edges(ctx, hyp, config)
    n_int = int(edges.interior.sum())
    # in a flat region and its parts, a jump no higher than the flatness prior lies within
    # one face (tape, a label): the region is flat there, so it parts no two boxes
    line_ok, row = _test_interior(
        edges, hyp, config.support_fraction * config.min_edge if region else 0.0,
        minor_too=not (region or family > 1))
    tests.append(row)
    sides, row = _test_boundary(edges, hyp, ctx, config.support_fraction)
    tests.append(row)
    # a whole flat region is verified by its outline: what lies inside (a seam the sizes
    # imply, a decoration's edges) decides only how it splits, and is recorded
    # a part of a split region is one by the listed size; inside it, the range points'
    # seam test decides (tape and labels put lines of edges on the lids)
    if not line_ok and not region and family == 1:
        return _failed(VerifyReason.INTERIOR_EDGES, tests, alpha, n_interior_edges=n_int)

    # seams, from the range points of the rectangle and a margin around it (the flanks)
    B = hyp.flank
    fp = face_points(ctx.points, ctx.valid, ctx.sigma, ctx.project, origin, x_axis, y_axis,
                     normal, (-B, width + B), (-B, length + B), hyp.spacing, alpha,
                     config.noise.row_corr, ctx.gain)
    # the interior's seam statistics first: their spread along the face scales the sides',
    # where the scan's noise is correlated (its model's correlation lengths). With white
    # noise a side's windows share nothing with the interior's, and what spreads the
    # interior's statistic is the face's own shape (tape, labels, a dent), not noise
    crossed, interior_rows, spread = _test_seam_interior(fp, hyp, config.noise.correlated)
    if config.noise.correlated:
        fp = dataclasses.replace(fp, spread=spread)
    else:
        # ... and at the wider groove widths always: a window of several spacings averages
        # the face's low-frequency shape and any correlation the model has not measured
        fp = dataclasses.replace(fp, spread=((1.0,) + spread[0][1:], (1.0,) + spread[1][1:]))
    if size_sides:
        tests.append(_test_size_sides(fp, hyp, sides, size_sides))
    for si in sorted(region_sides):
        if not sides.ok[si]:  # on the region's evidence
            sides.ok[si] = True
            sides.covered[si] = int(sides.expected[si])
            sides.seams.add(si)
    tests += _test_seam_sides(fp, hyp, sides, config.support_fraction)
    tests += interior_rows
    if crossed and not region:
        return _failed(VerifyReason.INTERIOR_SEAM, tests, alpha, n_interior_edges=n_int)
    if not region and family == 1:  # a region's or a part's seams are the sizes' business
        split, rows = _test_seam_midline(fp, hyp, config.min_edge, config.box_sizes,
                                         config.size_tolerance)
        tests += rows
        if split:
            return _failed(VerifyReason.INTERIOR_SEAM, tests, alpha, n_interior_edges=n_int)
    bound = sides.bound(config.support_fraction)
    # the strips beyond the sides, rasterized once for the plane-end and continuation tests
    strips: dict[Any, Any] = {}
    # a region's sides short of p together may be covered by the plane's end; a box's not
    # (on bare active-stereo pallets that made false surfaces): 0 asks for no coverage
    end_fraction = config.support_fraction if region else 0.0
    # until the plane is refitted, a rectangle whose boundary rests on its plane's end
    # fails as BOUNDARY, with the rows that showed that end
    unbound: list[TestTable] = []
    if not bound:
        # sides without their line of edges may still end where the face's plane drops
        # away just beyond them: first against the rectangle's own plane (cheap: the strips
        # only); only where that shows an end is the plane refitted to decide (below)
        unbound = _test_plane_ends(ctx, hyp, None, sides.copy(), end_fraction, strips)
        if not unbound or not unbound[0].accepted.any():
            return _failed(VerifyReason.BOUNDARY, tests + unbound, alpha,
                           n_interior_edges=n_int)

    # the points inside the rectangle shrunk by the border margin
    ras = rasterize(scan, rectangle_corners(origin + m * x_axis + m * y_axis, x_axis, y_axis,
                                            width - 2 * m, length - 2 * m))
    def before_fit(reason: VerifyReason, **counts: int) -> VerifyOutcome:
        # a rectangle whose boundary rested on its plane's end fails as BOUNDARY
        return _failed(VerifyReason.BOUNDARY if unbound else reason, tests + unbound, alpha,
                       n_interior_edges=n_int, **counts)

    if ras is None:
        return before_fit(VerifyReason.OUTSIDE_IMAGE)
    n_inside = len(ras[0])
    valid = ctx.valid[ras]
    rv, cv = ras[0][valid], ras[1][valid]
    n_valid = len(rv)
    if n_valid < 3:
        return before_fit(VerifyReason.TOO_FEW_POINTS, n_inside=n_inside, n_valid=n_valid)
    fit = _fit_face(ctx, hyp, rv, cv, config.flatness)
    if fit is None:
        return before_fit(VerifyReason.INLIERS, n_inside=n_inside, n_valid=n_valid)
    if not bound:
        # sides without their line of edges: the face's plane may still end just beyond
        tests += _test_plane_ends(ctx, hyp, fit, sides, end_fraction, strips)
        if not sides.bound(config.support_fraction):
            return _failed(VerifyReason.BOUNDARY, tests, alpha, n_inside=n_inside,
                           n_valid=n_valid, n_interior_edges=n_int)

    exposed, row = _test_exposed(fit, hyp, config.noise)
    tests.append(row)
    frac, enough, row = _test_inliers(fit, n_inside, n_valid, hyp, config.min_inlier_fraction,
                                      config.min_return_fraction, config.hole_weight)
    tests.append(row)
    mean, s2_mean, mean_t = _test_mean(fit, hyp, config.flatness)
    tests.append(mean_t)
    ends, cut, rows = _test_continuation(ctx, fp, hyp, fit, sides, config.min_inlier_fraction,
                                         config.flatness, strips)
    tests += rows

    reason = (VerifyReason.NOT_EXPOSED if not exposed
              else VerifyReason.INLIERS if not enough
              else VerifyReason.MEAN_OFFSET if not bool(mean_t.accepted[0])
              else VerifyReason.CONTINUES if not (ends | cut).all()
              else VerifyReason.OUTSIDE_IMAGE if cut.any()
              else VerifyReason.ACCEPTED)  # the first test failed, in that order
    inl = fit.inliers
    W = scan.shape[1]
    return VerifyOutcome(
        n_inside=n_inside, n_valid=n_valid, n_inliers=int(inl.sum()),
        n_front=int(fit.front.sum()), n_behind=int(fit.behind.sum()), inlier_fraction=frac,
        mean_distance=mean, sigma_mean=float(np.sqrt(s2_mean)) if np.isfinite(s2_mean) else np.nan,
        n_interior_edges=n_int, plane_center=fit.centre, plane_normal=fit.normal,
        plane_cov=fit.cov, rms=fit.rms, error=fit.error, accepted=reason == VerifyReason.ACCEPTED,
        reason=reason, inlier_pixels=(rv[inl] * W + cv[inl]).astype(np.int32),
        tests=TestTable.concat(tests, alpha),
    )

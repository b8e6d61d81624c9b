"""Stage 6: verification of a rectangle hypothesis by the range points inside it (paper §2.2).

The rectangle, shrunk by the border margin, is projected into the range image and
rasterized (the paper's ref [10]; here ``cv2.fillPoly``). Its points are tested against the
rectangle's plane with their propagated uncertainty (point-on-plane, chi2(1) at alpha):

* ``VERIFY_TILT`` — the face's normal is within ``max_tilt`` of up (a prior: graspable
  faces are tops);
* ``VERIFY_EXPOSED`` — points significantly *in front* of the face's refitted plane
  (something resting on it or hanging over it), counted in the core beyond twice the
  border margin, are not more frequent than points significantly behind it (noise is symmetric,
  occluders are not: a sign test at alpha, which does not depend on the noise model being
  exact; row 0), and not more frequent than the noise model puts there (alpha/2 of the
  points) over the core (row 1) or in its busiest cell (row 2, Bonferroni over the cells).
  The face is covered if row 0 rejects and row 1 or row 2 does;
* ``VERIFY_INLIERS`` — at least ``min_inlier_fraction`` of the pixels inside are on the
  plane (the rest are dropouts and noise);
* ``VERIFY_MEAN`` — the inliers' mean signed distance is zero within the propagated
  uncertainty of the plane and of the mean (chi2(1));
* ``VERIFY_INTERIOR`` — no edge crosses the interior: the interior's edge points (beyond
  the band where the sides' own edges lie) make no significant straight line parallel to a
  side, against the same number of points scattered uniformly over the interior (Poisson,
  maximum over the positions, at alpha). How many there are is not itself tested: a sensor
  that sees a face at grazing incidence scatters noise edges over it, and their number
  grows with the face's area and the noise, not with the presence of an edge;
* ``VERIFY_BOUNDARY`` — each of the four sides is a real boundary of a top face: edge
  points where the face drops away (jump, convex crease) or meets an equal neighbour
  (groove) form a significant line along it (Poisson against the interior's scattered
  edges, at alpha), and all four together cover the fraction p of the perimeter. This
  extends the paper's |P_f| > p from the two far sides to all four, and rejects a
  sub-rectangle of a larger face, and the floor or pallet between boxes (bounded by
  concave creases where the boxes rise: a side needs more convex than concave edge
  points). A side with no such line is still a boundary if
  it is a seam (``VERIFY_SEAM_SIDE``: the range points along it, binned across it, show a
  groove behind the plane; :mod:`boxloc.seams`), which is how two touching boxes of equal
  height part where the edge stage saw their seam only in part;
* ``VERIFY_SEAM_INTERIOR`` — no seam crosses the interior, at alpha Bonferroni-corrected
  over the positions (a rectangle over two touching boxes is two faces);
* ``VERIFY_CONTINUATION`` — the face ends at each side: fewer than
  ``min_inlier_fraction`` of the pixels in a strip just beyond the side lie on the face's
  refitted plane (:func:`continuation`), or the side is a seam or a gap between equal
  neighbours (``VERIFY_SEAM_SIDE``, searched across the band where the side's edges are
  counted). Edge evidence alone does not make a side where the plane runs on: sensor
  artefacts (structured-light depth) put short lines of jump edges inside faces, and a
  rectangle cut short there would be accepted first and hide the whole face.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import stats as st

from boxloc.config import Config
from boxloc.lines import MIN_LINE_POINTS
from boxloc.products import EdgeKind, EdgeMap, VerifyReason
from boxloc.raster import fill_polygon, polygon_area, rectangle_pixels
from boxloc.scan import Scan
from boxloc.seams import SEAM_FLANK, FacePoints, face_points, find_seams, seam_at
from boxloc.stats import TestKind, TestTable, chi2_critical

#: A run of this many pixels without a point on a face's plane ends the face (a sensor's
#: dropouts inside a face are shorter; the gap beyond a box's side is longer).
EXTENT_GAP_PX = 4

#: Edges within this fraction of the shortest box edge from a side belong to that side: a
#: seam that splits a rectangle into two boxes lies at least min_edge from a side, while
#: the side's own second edges (bevel, rounded cardboard) and the error of the estimated
#: dimensions put boundary edges up to a centimetre or two inside.
BOUNDARY_BAND = 0.5


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

    @classmethod
    def build(cls, scan: Scan, edges: EdgeMap, config: Config, up: np.ndarray) -> VerifyContext:
        P = scan.points.astype(np.float64)
        r = scan.range.astype(np.float64)
        sr = config.noise.sigma_range(r)
        sl = config.noise.sigma_lateral(r, scan.sensor.pixel_angle)
        valid = np.isfinite(r)
        return cls(P, sr, sl**2, valid, edges.points, edges.kinds,
                   scan.sensor.pixel_angle, np.asarray(up, dtype=np.float64),
                   scan.sensor.project)

    def spacing_at(self, point: np.ndarray) -> float:
        """Expected spacing of edge points along an edge at ``point``, metres."""
        return float(np.linalg.norm(point)) * self.pixel_angle

    def var_along(self, rr: np.ndarray, cc: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Variance of the points at pixels (rr, cc) along a unit direction, m^2: range
        noise along the ray, lateral noise across it."""
        P = self.points[rr, cc]
        cn2 = (P @ direction) ** 2 / np.einsum("ij,ij->i", P, P)
        return self.sigma[rr, cc] ** 2 * cn2 + self.lateral2[rr, cc] * (1 - cn2)

    def samples_along(self, a: np.ndarray, b: np.ndarray) -> float:
        """Edge points expected along the 3D segment a-b: its length in the image, pixels.

        A side seen at grazing incidence is foreshortened in the image and gets fewer edge
        points than its length over :meth:`spacing_at` (one per pixel it crosses).
        """
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        q = self.project(np.stack([a, b]))
        n = float(np.hypot(*(q[1] - q[0])))
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
    n = len(u)
    if n == 0:
        return 0.0, 1.0
    h = 3.0 * spacing
    best, best_p = 0.0, 1.0
    for coord, extent in ((u, width), (v, length)):
        nb = max(int(np.ceil((extent - 2.0 * margin) / h)), 1)
        acc = np.bincount(np.clip(((coord - margin) / h).astype(np.int64), 0, nb - 1),
                          minlength=nb)
        k = float(acc.max())
        lam = n / nb
        p = float(min(1.0, nb * st.poisson.sf(k - 1, lam)))
        if p < best_p or (p == best_p and k > best):
            best, best_p = k, p
    return best, best_p


def _side_seam(fp: FacePoints, side: int, width: float, length: float, spacing: float,
               alpha: float, reach: float | None = None, gaps: bool = False
               ) -> tuple[float, float]:
    """Seam statistic along one side of a rectangle, and its critical value.

    ``side`` is 0-3: v=0, v=length, u=0, u=width; ``reach`` and ``gaps`` as in
    :func:`boxloc.seams.seam_at`. A seam
    runs the whole side: both halves must show a groove or gap (a local dent does not), so
    the weaker half caps the statistic.
    """
    if side < 2:
        sel = (fp.u >= 0) & (fp.u <= width)
        coord, along, at, L = fp.v, fp.u, (0.0, length)[side], width
    else:
        sel = (fp.v >= 0) & (fp.v <= length)
        coord, along, at, L = fp.u, fp.v, (0.0, width)[side - 2], length
    zs, zc = seam_at(coord[sel], fp.w[sel], fp.scale, at, spacing, alpha, reach,
                     gaps, fp.row[sel], fp.row_corr)
    for half in (sel & (along < 0.5 * L), sel & (along >= 0.5 * L)):
        zh, _ = seam_at(coord[half], fp.w[half], fp.scale, at, spacing, alpha, reach,
                        gaps, fp.row[half], fp.row_corr)
        if zh <= 0:
            zs = min(zs, zh)
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
    m, d = margin, depth
    strips = (((m, width - m), (-m - d, -m)), ((m, width - m), (length + m, length + m + d)),
              ((-m - d, -m), (m, length - m)), ((width + m, width + m + d), (m, length - m)))
    frac = np.full(4, np.nan)
    n_valid = np.zeros(4, np.int64)
    in_image = np.zeros(4, bool)
    for si, (u_range, v_range) in enumerate(strips):
        pix = rectangle_pixels(ctx.project, ctx.valid, origin, x_axis, y_axis, u_range,
                               v_range)
        if pix is None:
            continue
        rr, cc, inside = pix
        # most of the strip must be in the image to show anything of the side
        in_image[si] = inside >= 0.5
        n_valid[si] = len(rr)
        if len(rr) < MIN_LINE_POINTS:
            continue
        P = ctx.points[rr, cc]
        var = ctx.var_along(rr, cc, plane_normal)
        z = ((P - plane_point) @ plane_normal) / np.sqrt(var)
        frac[si] = float((np.abs(z) <= k).mean())
    return frac, n_valid, in_image


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
    return normal @ So @ normal + np.einsum("ni,ij,nj->n", D, Sn, D)


def face_extent(
    ctx: VerifyContext, origin: np.ndarray, along: np.ndarray, across: np.ndarray,
    normal: np.ndarray, plane_cov: np.ndarray, strip: tuple[float, float], reach: float,
    k: float, flatness: float,
) -> tuple[float, float]:
    """How far a face's plane runs from ``origin`` along ``along``, in a strip beside it.

    The valid pixels of the strip (``strip`` metres across, out to ``reach`` along) are
    tested against the plane (point-on-plane at ``k``, with the points' noise, the
    flatness prior and the plane's own uncertainty); the face ends where the points on it
    first leave a gap of ``EXTENT_GAP_PX`` pixels (dropouts are shorter). The end is
    placed half a pixel beyond its last point, where the edge stage puts a jump.

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
        Metres along the axis (NaN: fewer than two points on the plane, or the strip
        leaves the image).
    gap : float
        The gap that ends the face there, metres.
    """
    pix = rectangle_pixels(ctx.project, ctx.valid, origin, along, across, (0.0, reach), strip)
    # metres per pixel along the axis near the vertex, foreshortening included
    near = strip[1]
    step = near / max(ctx.samples_along(origin, origin + near * along), 1.0)
    gap = EXTENT_GAP_PX * step
    if pix is None:
        return np.nan, gap
    rr, cc, _ = pix
    P = ctx.points[rr, cc]
    D = P - origin
    var = ctx.var_along(rr, cc, normal) + flatness**2 + plane_var(plane_cov, normal, D)
    on = np.abs(D @ normal) <= k * np.sqrt(var)
    t = np.sort(D[on] @ along)
    t = t[t >= 0.0]
    # the face starts at the vertex, give or take the arm's own edge artefacts (as far
    # out as the strip is from the arm)
    if len(t) < 2 or t[0] > strip[0]:
        return np.nan, gap
    jumps = np.flatnonzero(np.diff(t) > gap)
    last = t[jumps[0]] if len(jumps) else t[-1]
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
) -> VerifyOutcome:
    """Verify one rectangle hypothesis by the range points inside it.

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

    Returns
    -------
    VerifyOutcome
    """
    alpha = config.alpha
    chi1 = chi2_critical(1.0, alpha)
    k = float(np.sqrt(chi1))
    centre = origin + 0.5 * width * x_axis + 0.5 * length * y_axis
    spacing = ctx.spacing_at(centre)
    m = 2.0 * spacing  # border margin: the bevel and mixed pixels of the edge itself
    tests: list[TestTable] = []

    def fail(reason: VerifyReason, **kw: object) -> VerifyOutcome:
        base = dict(
            n_inside=0, n_valid=0, n_inliers=0, n_front=0, n_behind=0, inlier_fraction=0.0,
            mean_distance=np.nan, sigma_mean=np.nan, n_interior_edges=0,
            plane_center=np.full(3, np.nan), plane_normal=np.full(3, np.nan),
            plane_cov=np.full((6, 6), np.nan), rms=np.nan, error=np.nan, accepted=False,
            reason=reason, inlier_pixels=np.zeros(0, np.int32),
            tests=TestTable.concat(tests, alpha),
        )
        base.update(kw)
        return VerifyOutcome(**base)  # type: ignore[arg-type]

    tilt = float(np.arccos(np.clip(normal @ ctx.up, -1, 1)))
    tests.append(TestTable.decision(TestKind.VERIFY_TILT, attempt_id, -1, tilt, config.max_tilt,
                                    tilt <= config.max_tilt, alpha))
    if tilt > config.max_tilt:
        return fail(VerifyReason.TILTED)
    if width <= 2 * m or length <= 2 * m:
        return fail(VerifyReason.TOO_FEW_POINTS)
    # cheap tests first, on the edge points (no rasterization): interior and boundary
    # edge points near the face's plane, in the rectangle's frame
    E = ctx.edge_points - origin
    eu, ev = E @ x_axis, E @ y_axis
    # every edge test below looks at most a side's band beyond the rectangle: the rest of
    # the scan's edge points need no plane test
    band = 1.5 * m
    reach = (eu >= -band) & (eu <= width + band) & (ev >= -band) & (ev <= length + band)
    E, eu, ev = E[reach], eu[reach], ev[reach]
    edge_kinds = ctx.edge_kinds[reach]
    ew = E @ normal
    sig_e = face_sigma(config, centre)
    # a face's boundary, seam and crossing edges lie on its plane (a jump point is placed
    # half a sample beyond the face's last point, hence the spacing)
    # ... and the rectangle's own plane is uncertain: a small error of its normal moves
    # the far sides' edges off it by the error times their distance from the vertex
    near_plane = np.abs(ew) <= k * np.sqrt(sig_e**2 + plane_var(plane_cov, normal, E)) + spacing
    # interior edges: strictly inside, beyond the band where the boundary's own edges lie
    # (rounded or bevelled cardboard gives a second, parallel edge a few mm inside)
    mi = max(m, BOUNDARY_BAND * config.min_edge)
    inside_e = near_plane & (eu > mi) & (eu < width - mi) & (ev > mi) & (ev < length - mi)
    n_int = int(inside_e.sum())
    line_count, line_p = _interior_line(eu[inside_e], ev[inside_e], width, length, spacing,
                                        mi)
    min_line = float(MIN_LINE_POINTS)
    line_ok = not (line_count >= min_line and line_p < alpha)
    tests.append(TestTable.decision(TestKind.VERIFY_INTERIOR, attempt_id, -1, line_count,
                                    min_line, line_ok, alpha, p_value=line_p))
    # boundary: every side covered by convex edge evidence (jump, convex crease, groove)
    convex = near_plane & np.isin(edge_kinds, (EdgeKind.JUMP, EdgeKind.CREASE_CONVEX,
                                               EdgeKind.GROOVE))
    sides = (
        (np.abs(ev) <= band, eu, width),
        (np.abs(ev - length) <= band, eu, width),
        (np.abs(eu) <= band, ev, length),
        (np.abs(eu - width) <= band, ev, length),
    )
    # background: convex edge points scattered over the interior, per unit area
    area_in = max((width - 2 * mi) * (length - 2 * mi), spacing * spacing)
    density = float((convex & inside_e).sum()) / area_in

    def side_lines(kind_mask: np.ndarray, dens: float) -> tuple[list[int], list[float]]:
        cov_, p_ = [], []
        for near, along, L in sides:
            sel = kind_mask & near & (along >= 0) & (along <= L)
            # distinct positions along the side (one per spacing): coverage, not density
            k_s = len(np.unique(np.floor(along[sel] / spacing).astype(np.int64)))
            cov_.append(k_s)
            p_.append(float(st.poisson.sf(k_s - 1, dens * L * 2 * band)) if k_s else 1.0)
        return cov_, p_

    covered, side_p = side_lines(convex, density)
    # concave creases along a side: the face meets a wall rising from it (the pallet or a
    # lower box beside a taller one), which a top face's side never does
    concave, _ = side_lines(near_plane & (edge_kinds == EdgeKind.CREASE_CONCAVE), density)
    side_min = [max(MIN_LINE_POINTS, kc) for kc in concave]
    corners = rectangle_corners(origin, x_axis, y_axis, width, length)
    side_n = [ctx.samples_along(corners[a], corners[b]) for a, b in SIDE_CORNERS]
    # each side a significant line of boundary edges, outnumbering any concave ones; all
    # sides together covering the fraction p of the perimeter (the paper's |P_f| > p, over
    # all four sides)
    side_ok = [(k >= kmin and pv < alpha) for k, kmin, pv in zip(covered, side_min, side_p)]
    frac = float(sum(covered) / sum(side_n))
    bound_ok = all(side_ok) and frac >= config.support_fraction
    tests.append(TestTable.decision(TestKind.VERIFY_BOUNDARY, attempt_id, -1,
                                    np.r_[covered, frac], np.r_[side_min,
                                                                config.support_fraction],
                                    np.r_[side_ok, frac >= config.support_fraction], alpha,
                                    p_value=np.r_[side_p, np.nan]))

    if not line_ok:
        return fail(VerifyReason.INTERIOR_EDGES, n_interior_edges=n_int)

    # seams, from the range points of the rectangle and a margin around it (the flanks)
    B = (SEAM_FLANK[1] + 1.0) * spacing
    fp = face_points(ctx.points, ctx.valid, ctx.sigma, ctx.project, origin, x_axis, y_axis,
                     normal, (-B, width + B), (-B, length + B), spacing, alpha,
                     config.noise.row_corr)
    seam_sides: set[int] = set()  # sides shown to be seams (or gaps), here or below

    def seams_along(tried: list[int]) -> None:
        """Test the tried sides for a seam; a seam is a boundary along the whole side."""
        zz = np.array([_side_seam(fp, si, width, length, spacing, alpha) for si in tried])
        for si, (zs, zc) in zip(tried, zz):
            if zs > zc:
                seam_sides.add(si)
                side_ok[si] = True
                covered[si] = int(side_n[si])
        tests.append(TestTable.decision(TestKind.VERIFY_SEAM_SIDE, attempt_id, tried,
                                        zz[:, 0], zz[:, 1], zz[:, 0] > zz[:, 1], alpha))

    if not all(side_ok) and len(fp):
        seams_along([si for si in range(4) if not side_ok[si]])
    if all(side_ok) and len(fp) and sum(covered) < config.support_fraction * sum(side_n):
        # every side has its line, but together they cover too little of the perimeter:
        # a side whose line is a few points of a seam between equal neighbours is covered
        # by the seam along its whole length
        seams_along([si for si in range(4) if si not in seam_sides])
    frac = float(sum(covered) / sum(side_n))
    bound_ok = all(side_ok) and frac >= config.support_fraction
    # no seam inside: the points of the interior, binned along x and along y
    int_z, int_crit = [], []
    if len(fp):
        for coord, other, lo_hi, ext in ((fp.u, fp.v, (mi, width - mi), length),
                                         (fp.v, fp.u, (mi, length - mi), width)):
            sel = (other >= mi) & (other <= ext - mi)
            found = find_seams(coord[sel], fp.w[sel], fp.scale, lo_hi[0], lo_hi[1],
                               spacing, alpha, fp.row[sel], fp.row_corr)
            # the strongest groove anywhere inside, significant or not (NaN: none measurable)
            int_z.append(found.z_max if np.isfinite(found.z_max) else np.nan)
            int_crit.append(found.critical)
        tests.append(TestTable.decision(TestKind.VERIFY_SEAM_INTERIOR, attempt_id, [0, 1],
                                        int_z, int_crit,
                                        [not z > c for z, c in zip(int_z, int_crit)], alpha))
    if any(z > c for z, c in zip(int_z, int_crit)):
        return fail(VerifyReason.INTERIOR_SEAM, n_interior_edges=n_int)
    if not bound_ok:
        return fail(VerifyReason.BOUNDARY, n_interior_edges=n_int)

    inner = rectangle_corners(origin + m * x_axis + m * y_axis, x_axis, y_axis,
                              width - 2 * m, length - 2 * m)
    ras = rasterize(scan, inner)
    if ras is None:
        return fail(VerifyReason.OUTSIDE_IMAGE)
    rr, cc = ras
    n_inside = len(rr)
    valid = ctx.valid[rr, cc]
    rv, cv = rr[valid], cc[valid]
    n_valid = len(rv)
    if n_valid < 3:
        return fail(VerifyReason.TOO_FEW_POINTS, n_inside=n_inside, n_valid=n_valid)
    P = ctx.points[rv, cv]
    D = P - origin
    w0 = D @ normal
    # each point's noise along the normal; the flatness prior covers cardboard bulge
    var_pt = ctx.var_along(rv, cv, normal) + config.flatness**2
    # 1) points on the plane of R, with R's own uncertainty
    var_pl = plane_var(plane_cov, normal, D)
    on0 = np.abs(w0) <= k * np.sqrt(var_pt + var_pl)
    if on0.sum() < 3:
        return fail(VerifyReason.INLIERS, n_inside=n_inside, n_valid=n_valid)
    # 2) the face's plane refitted to them, with covariance
    Q = P[on0]
    c = Q.mean(0)
    lam, V = np.linalg.eigh((Q - c).T @ (Q - c))
    nf = V[:, 0] if V[:, 0] @ normal > 0 else -V[:, 0]
    # 3) inliers, front and behind against the refitted plane (point noise only)
    z = ((P - c) @ nf) / np.sqrt(var_pt)
    inl = np.abs(z) <= k
    # front and behind count in the core only, beyond twice the border margin: next to
    # a jump edge structured-light sensors pull the points toward the sensor by up to a
    # centimetre, a few pixels further in than the margin; an occluder resting on the
    # face reaches into the core (a strip of a face hidden by a taller neighbour is
    # wider than those pixels)
    du, dv = D @ x_axis, D @ y_axis
    mc = 2.0 * m
    core = (du > mc) & (du < width - mc) & (dv > mc) & (dv < length - mc)
    if not core.any():
        core[:] = True
    front = (z > k) & core
    behind = (z < -k) & core
    n_in, n_front, n_behind = int(inl.sum()), int(front.sum()), int(behind.sum())
    s2 = float(max(lam[0] / max(int(on0.sum()) - 3, 1), np.median(var_pt[on0])))
    cov = np.zeros((6, 6))
    cov[:3, :3] = s2 / max(n_in, 1) * np.eye(3)
    cov[3:, 3:] = s2 * (np.outer(V[:, 1], V[:, 1]) / max(lam[1], 1e-12)
                        + np.outer(V[:, 2], V[:, 2]) / max(lam[2], 1e-12))
    rms = float(np.sqrt(np.mean(((P[inl] - c) @ nf) ** 2))) if n_in else np.nan
    err = float((z[inl] ** 2).sum())

    # exposed: a sign test, front vs behind outliers
    m_out = n_front + n_behind
    p_front = float(st.binom.sf(n_front - 1, m_out, 0.5)) if n_front else 1.0
    # ... and more frequent than the noise model puts in front (alpha/2 of the points:
    # z > k), so that a handful of stray points, with none behind, is no occluder
    n_core = int(core.sum())
    p_rate = float(st.binom.sf(n_front - 1, n_core, alpha / 2)) if n_front else 1.0
    # ... or, in one place (the corner of a box above, a few square centimetres), more
    # frequent than that: the busiest cell of the core (cells of four border margins),
    # Bonferroni over the cells
    cell = 4.0 * m
    cid = (np.floor(du[core] / cell) * 1e6 + np.floor(dv[core] / cell)).astype(np.int64)
    ids, inv = np.unique(cid, return_inverse=True)
    n_cell = np.bincount(inv, minlength=len(ids))
    f_cell = np.bincount(inv, weights=front[core].astype(np.float64), minlength=len(ids))
    n_cells = max(len(ids), 1)
    if n_front:
        p_cells = np.asarray(st.binom.sf(f_cell - 1, n_cell, alpha / 2))
        c_best = int(np.argmin(np.where(f_cell > 0, p_cells, np.inf)))
        p_local = float(min(p_cells[c_best] * n_cells, 1.0))
        f_local, n_local = int(f_cell[c_best]), int(n_cell[c_best])
    else:
        p_local, f_local, n_local = 1.0, 0, int(n_cell.max()) if len(n_cell) else 0
    exposed = p_front >= alpha or (p_rate >= alpha and p_local >= alpha)
    tests.append(TestTable.decision(
        TestKind.VERIFY_EXPOSED, attempt_id, [m_out, n_core, n_local],
        [n_front, n_front, f_local],
        [float(st.binom.isf(alpha, m_out, 0.5)) if m_out else 0.0,
         float(st.binom.isf(alpha, n_core, alpha / 2)),
         float(st.binom.isf(alpha / n_cells, n_local, alpha / 2))],
        [p_front >= alpha, p_rate >= alpha, p_local >= alpha], alpha,
        p_value=[p_front, p_rate, p_local]))
    frac = n_in / max(n_inside, 1)
    tests.append(TestTable.decision(TestKind.VERIFY_INLIERS, attempt_id, n_inside, frac,
                                    config.min_inlier_fraction,
                                    frac >= config.min_inlier_fraction, alpha))
    # mean distance of the inliers to R's plane: zero within the propagated uncertainty
    if n_in >= 3:
        wi = w0[inl]
        mean = float(wi.mean())
        dc = P[inl].mean(0) - origin
        # the face may depart from R's plane by the flatness prior as a whole (bulge)
        s2_mean = float(var_pt[inl].mean() / n_in + plane_var(plane_cov, normal, dc[None])[0]
                        + config.flatness**2)
        T_mean = mean**2 / s2_mean
    else:
        mean, s2_mean, T_mean = np.nan, np.nan, np.inf
    mean_t = TestTable.chi2(TestKind.VERIFY_MEAN, attempt_id, n_in, T_mean, 1.0, alpha)
    tests.append(mean_t)
    # the face ends at each side: its plane does not continue beyond, unless the side is a
    # seam with an equal neighbour (a rectangle cut short inside a face is not a face)
    cont, _, in_image = continuation(ctx, origin, x_axis, y_axis, width, length, c, nf, m,
                                     B - m, k)
    continues = cont >= config.min_inlier_fraction
    ends = ~continues
    extra_seam: list[tuple[int, float, float]] = []
    for si in np.flatnonzero(continues):
        if si in seam_sides:
            ends[si] = True
            continue
        # anywhere in the band where the side's boundary edges are counted
        zs, zc = (_side_seam(fp, int(si), width, length, spacing, alpha, band, True) if len(fp)
                  else (-np.inf, np.inf))
        extra_seam.append((int(si), zs, zc))
        ends[si] = zs > zc
        if ends[si]:
            seam_sides.add(int(si))
    if extra_seam:
        es = np.array(extra_seam)
        tests.append(TestTable.decision(TestKind.VERIFY_SEAM_SIDE, attempt_id,
                                        es[:, 0].astype(int), es[:, 1], es[:, 2],
                                        es[:, 1] > es[:, 2], alpha))
    # a side whose strip leaves the image cannot show that the face ends there, unless
    # the strip's part in the image has points enough to test or the side is a seam: the
    # face may run on out of sight
    cut = np.array([not in_image[si] and not np.isfinite(cont[si]) and si not in seam_sides
                    for si in range(4)])
    ends &= ~cut
    tests.append(TestTable.decision(TestKind.VERIFY_CONTINUATION, attempt_id, [0, 1, 2, 3],
                                    cont, config.min_inlier_fraction, ends, alpha))

    if not exposed:
        reason = VerifyReason.NOT_EXPOSED
    elif frac < config.min_inlier_fraction:
        reason = VerifyReason.INLIERS
    elif not bool(mean_t.accepted[0]):
        reason = VerifyReason.MEAN_OFFSET
    elif not (ends | cut).all():
        reason = VerifyReason.CONTINUES
    elif cut.any():
        reason = VerifyReason.OUTSIDE_IMAGE
    else:
        reason = VerifyReason.ACCEPTED
    H, W = scan.shape
    return VerifyOutcome(
        n_inside=n_inside, n_valid=n_valid, n_inliers=n_in, n_front=n_front,
        n_behind=n_behind, inlier_fraction=frac, mean_distance=mean,
        sigma_mean=float(np.sqrt(s2_mean)) if np.isfinite(s2_mean) else np.nan,
        n_interior_edges=n_int, plane_center=c, plane_normal=nf, plane_cov=cov, rms=rms,
        error=err, accepted=reason == VerifyReason.ACCEPTED, reason=reason,
        inlier_pixels=(rv[inl] * W + cv[inl]).astype(np.int32),
        tests=TestTable.concat(tests, alpha),
    )

"""A box's height, from its visible side faces or from the step down beyond its top's sides
(issue #21, point 3; the paper leaves it open).

Two measurements, per side of the top's rectangle (0-3: v=0, v=length, u=0, u=width):

* **side** (:func:`side_height`) — a side face that faces the sensor is seen below the
  top's edge. Its points lie on the vertical plane through the edge (point on plane, z
  at alpha, with each point's noise across that plane and the flatness prior), and run
  down from the edge without a gap of ``EXTENT_GAP_PX`` samples to where the face meets
  what the box stands on (a concave crease: beyond it the points leave the plane). The
  height is how far down the run reaches, half a sample beyond its last point, as the
  face's extent is measured along an arm (:func:`boxloc.stages.verify.face_extent`). A
  run whose end shows no foot, where the rays just beyond it meet something in front of
  the face and higher up (a neighbour across a narrow gap hides the rest), is no height.
* **step** (:func:`step_height`) — the points in a strip beyond the side, on the plane
  parallel to the top (a neighbour's top, the layer below, the pallet, the floor): the
  median of their depth below the top's plane. Only a strip whose points mostly (the
  ``min_inlier_fraction`` prior) lie on one such surface, significantly below the top,
  counts: a wall or a taller neighbour beyond a side is no step.

No carton is taller than the longest edge of any (``max_edge``, the site's largest box), so
a measurement significantly deeper than that (z at alpha of its sigma) is no box's height:
a side face running on down a flush stack, or the step down to the floor beyond the pallet.
It is not used, and a HEIGHT_WITHIN_BOX row records it (only those rows: the others are the
BOX_HEIGHT row's). A flush stack shorter than that still reads as one tall carton.

A side face seen gives the height directly. Without one, the step down: the smallest
step of the four sides, since the nearest surface below is the most likely to be what the
box stands on (a box on the floor at the pallet's edge sees the floor through its outer
side, the pallet top through the inner ones). Where the matched carton size lists a
height, a measurement that differs from it (chi2, 1 dof, with the size tolerance) is not
this carton's: the side of a stack of them, flush, or the step down to the floor beyond
the pallet; the listed height is reported instead (``HeightSource.SKU``), as it is where
nothing is measured. A measurement that agrees with it is combined with it, each weighed by
its variance (the size tolerance the listed height's sigma), and keeps its source: a side
face seen noisily, centimetres off, then moves toward the listed height by its weight.
Without a list, such a measurement is reported as it is: from the top alone, a flush stack
of sharp-edged cartons cannot be told from one tall carton.

The reported tops of one flush layer (:func:`flush_layers`: touching, coplanar) stand on
one support, so their boxes are equally tall. A side face seen runs from the top's edge down
to the box's foot or, flush with the layer below, on down the stack: at least the box's
height. So the layer's smallest side measurement is its height (:func:`pool_layers`): a top
whose own measurement is significantly deeper (the stack's side, the floor beyond the
layer), or missing, takes it, and a LAYER_HEIGHT row says so. A step is not pooled: beyond
a side it may find a shorter neighbour standing on the same support, less than the height.
Where no top of a layer shows its foot (flush all round), the layer still measures the
stack.

The standard deviations propagate the noise model: for the side, the sample spacing down
the face (the run ends within one sample) and the top plane's offset; for the step, the
two surfaces' offsets (each a mean over its points, with their robust spread) and the
flatness prior (a bulged lid, a sagging lower top). A BOX_HEIGHT row records each estimate
(statistic the height, critical its sigma; accepted where the height is above z at alpha
sigmas).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from scipy.sparse.csgraph import connected_components

from boxloc.config import Config
from boxloc.distributions import norm_isf
from boxloc.products import HeightSource, SurfaceSet
from boxloc.scan import Scan
from boxloc.stages.lines import MIN_LINE_POINTS
from boxloc.stages.raster import fill_polygon, rectangle_pixels
from boxloc.stages.verify import EXTENT_GAP_PX, SIDE_CORNERS, VerifyContext
from boxloc.stats import TestKind, TestTable, chi2_critical

#: Two reported tops touch (one flush layer, :func:`flush_layers`) within this many point
#: spacings of each other.
LAYER_GAP_SPACINGS = 4.0
#: How far down a side face is searched, as a multiple of ``Config.max_edge``: far enough to
#: see a face run on past any carton's height (down a flush stack: HEIGHT_WITHIN_BOX).
SIDE_REACH = 1.5


def side_height(ctx: VerifyContext, a: np.ndarray, b: np.ndarray, out: np.ndarray,
                down: np.ndarray, reach: float, k: float, flatness: float
                ) -> tuple[float, float, int]:
    """How far the side face below the top's edge a-b runs down.

    Parameters
    ----------
    ctx : VerifyContext
        The scan's points and noise.
    a, b : (3,) float64
        The ends of the top's edge, metres, sensor frame.
    out : (3,) float64
        Unit vector in the top's plane, perpendicular to the edge, pointing away from the
        top: the side face's normal.
    down : (3,) float64
        Unit vector down the side face (minus the top's normal).
    reach : float
        How far down to look, metres.
    k : float
        Critical |z| of one point.
    flatness : float
        The flatness prior, metres.

    Returns
    -------
    height : float
        Metres down the face to its end; NaN where the face is not seen (it faces away
        from the sensor, or fewer than ``MIN_LINE_POINTS`` points lie on it near the edge)
        or hidden below its run by something in front of it.
    sigma : float
        Its standard deviation, metres: one sample down the face.
    n : int
        Points on the face.
    """
    mid = 0.5 * (a + b)
    if out @ mid >= 0:  # the face looks away from the sensor: not seen
        return np.nan, np.nan, 0
    edge = b - a
    L = float(np.linalg.norm(edge))
    if L <= 0:
        return np.nan, np.nan, 0
    along = edge / L
    # the face's pixels: its quadrilateral down to the reach, projected
    quad = np.array([a, b, b + reach * down, a + reach * down])
    uv = ctx.project(quad)
    if not np.isfinite(uv).all():
        return np.nan, np.nan, 0
    H, W = ctx.valid.shape
    rr, cc = fill_polygon(uv, (H, W))
    keep = ctx.valid[rr, cc]
    rr, cc = rr[keep], cc[keep]
    if len(rr) < MIN_LINE_POINTS:
        return np.nan, np.nan, 0
    P, flat = ctx.gather(rr, cc)
    D = P - a
    # the edge's own mixed pixels and bevel stay out: a sample in from the ends
    spacing = ctx.spacing_at(mid)
    s = D @ along
    t = D @ down
    var = ctx.var_along(rr, cc, out, P, flat) + flatness**2
    on = ((np.abs(D @ out) <= k * np.sqrt(var)) & (s > 2 * spacing) & (s < L - 2 * spacing)
          & (t > -spacing))
    if on.sum() < MIN_LINE_POINTS:
        return np.nan, np.nan, 0
    ts = np.sort(t[on])
    # the sample spacing down the face: the points of one image column, foreshortened
    n_rows = max(ctx.samples_along(a, a + reach * down), 1.0)
    step = reach / n_rows
    if ts[0] > max(EXTENT_GAP_PX * step, 2 * spacing):
        return np.nan, np.nan, 0  # the face does not start at the edge: something else
    gaps = np.flatnonzero(np.diff(ts) > EXTENT_GAP_PX * step)
    last = ts[gaps[0]] if len(gaps) else ts[-1]
    n = int(np.searchsorted(ts, last, side="right"))
    if n < MIN_LINE_POINTS:
        return np.nan, np.nan, 0
    # where the face meets what the box stands on: that surface's points just in front of
    # the foot (beyond the face's plane, in its lower half) give the depth robustly; the
    # run's last point alone is the most extreme of many (mixed and noisy pixels at the
    # crease)
    dist = D @ out
    foot = ((dist > k * np.sqrt(var)) & (dist < 4.0 * EXTENT_GAP_PX * step)
            & (s > 2 * spacing) & (s < L - 2 * spacing) & (t > 0.5 * last)
            & (t < last + EXTENT_GAP_PX * step))
    if foot.sum() >= MIN_LINE_POINTS:
        tf = t[foot]
        med = float(np.median(tf))
        mad = 1.4826 * float(np.median(np.abs(tf - med)))
        if mad <= k * float(np.sqrt(np.median(var[foot]))):  # a surface parallel to the top
            s2 = (math.pi / 2) * mad**2 / int(foot.sum()) + flatness**2
            return med, float(math.sqrt(s2)), n
    # no foot seen. Where the rays just past the run's end meet something nearer than the
    # face, and higher up than the run reached (a neighbour in front of the face across a
    # gap hides the rest of it), the face runs on unseen: its run is no height
    ray = P / np.linalg.norm(P, axis=1)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        X = (float(a @ out) / (ray @ out))[:, None] * ray - a  # each ray on the face's plane
    sp, tp = X @ along, X @ down
    past = ((tp > last) & (tp <= last + EXTENT_GAP_PX * step) & (sp > 2 * spacing)
            & (sp < L - 2 * spacing) & (dist > 0))
    if past.sum() >= MIN_LINE_POINTS:
        hidden = (t[past] < 0.5 * last) & (tp[past] - t[past] > k * np.sqrt(var[past]))
        if hidden.mean() > 0.5:
            return np.nan, np.nan, 0
    # the run's end, within a sample
    return float(last), float(math.hypot(step / math.sqrt(3.0), flatness)), n


def step_height(ctx: VerifyContext, corners: np.ndarray, side: int, centre: np.ndarray,
                normal: np.ndarray, x_axis: np.ndarray, y_axis: np.ndarray, width: float,
                length: float, depth: float, k: float, flatness: float,
                min_fraction: float) -> tuple[float, float, int]:
    """The step down beyond one side of a top: the depth of the surface there below the
    top's plane.

    The strip beyond side ``side`` (from two samples out to ``depth`` beyond it, clear of
    the corners) is read; its points significantly below the top's plane (z at ``k``)
    must be at least ``min_fraction`` of the strip's points and lie on one surface parallel
    to the top (their depths within ``k`` of their robust spread of the median, the spread
    itself no more than the points' noise and the flatness prior at ``k``).

    Returns
    -------
    height, sigma : float
        Metres; NaN where the strip shows no step.
    n : int
        Points on the lower surface.
    """
    spacing = ctx.spacing_at(centre)
    m = 2.0 * spacing
    strips = (((m, width - m), (-m - depth, -m)),
              ((m, width - m), (length + m, length + m + depth)),
              ((-m - depth, -m), (m, length - m)),
              ((width + m, width + m + depth), (m, length - m)))
    u_range, v_range = strips[side]
    origin = corners[0]
    # the strip's rays, where they cross the top's plane
    pix = rectangle_pixels(ctx.project, ctx.valid, origin, x_axis, y_axis, u_range, v_range)
    if pix is None:
        return np.nan, np.nan, 0
    rr, cc, _ = pix
    if len(rr) < MIN_LINE_POINTS:
        return np.nan, np.nan, 0
    P, flat = ctx.gather(rr, cc)
    d = (centre - P) @ normal  # depth below the top's plane
    sig = np.sqrt(ctx.var_along(rr, cc, normal, P, flat) + flatness**2)
    below = d > k * sig
    if below.mean() < min_fraction or below.sum() < MIN_LINE_POINTS:
        return np.nan, np.nan, 0
    db = d[below]
    med = float(np.median(db))
    mad = 1.4826 * float(np.median(np.abs(db - med)))
    s_pt = float(np.median(sig[below]))
    # one surface parallel to the top: its depths spread no more than its points' noise
    if mad > k * s_pt:
        return np.nan, np.nan, 0
    on = np.abs(db - med) <= k * max(mad, 1e-9) + 1e-12
    if on.sum() < min_fraction * len(db):
        return np.nan, np.nan, 0
    n = int(on.sum())
    h = float(np.median(db[on]))
    # the lower surface's offset (its points' spread over their number, the median's
    # efficiency pi/2) and both surfaces' flatness
    s2 = (math.pi / 2) * mad**2 / n + 2.0 * flatness**2
    return h, float(math.sqrt(s2)), n


def height_context(scan: Scan, config: Config, up: np.ndarray) -> VerifyContext:
    """The scan's points and noise as the height measurements read them (no edges)."""
    P = scan.points.astype(np.float64)
    r = scan.range.astype(np.float64)
    return VerifyContext(P, config.noise.sigma_range(r),
                         config.noise.sigma_lateral(r, scan.sensor.pixel_angle) ** 2,
                         np.isfinite(r), np.zeros((0, 3)), np.zeros(0, np.uint8),
                         scan.sensor.pixel_angle, np.asarray(up, np.float64),
                         scan.sensor.project, config.alpha)


def box_heights(scan_ctx: VerifyContext, surfaces: SurfaceSet, config: Config,
                sku_height: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, TestTable]:
    """The height of every surface's box.

    Parameters
    ----------
    scan_ctx : VerifyContext
        The scan's points and noise (:meth:`VerifyContext.build`).
    surfaces : SurfaceSet
        Their corners, centres, normals, axes and dimensions (metres, sensor frame).
    config : Config
        ``alpha``, ``flatness``, ``min_inlier_fraction``, ``max_edge``, ``min_edge``.
    sku_height : (s,) float64, optional
        The listed height of each surface's matched carton size (NaN: none).

    Returns
    -------
    height, sigma : (s,) float64
        Metres, NaN where none.
    source : (s,) int8
        :class:`HeightSource`.
    tests : TestTable
        HEIGHT_WITHIN_BOX per measurement deeper than any carton is tall (rejected; a =
        attempt, b = the side, 4 + the side for a step), then LAYER_HEIGHT per top of a
        flush layer but the one whose side measurement is the layer's
        (:func:`pool_layers`), then HEIGHT_SKU_AGREEMENT per measured top with a listed
        height (accepted: combined with it; rejected: the listed height replaces it), then
        BOX_HEIGHT per height (a = attempt, b = source).
    """
    n = len(surfaces)
    height = np.full(n, np.nan)
    sigma = np.full(n, np.nan)
    source = np.full(n, HeightSource.NONE, np.int8)
    k = math.sqrt(chi2_critical(1.0, config.alpha))
    z_a = float(norm_isf(config.alpha))
    rows: list[tuple[int, int, float, float, bool]] = []
    too_tall: list[tuple[int, int, float, float, bool]] = []
    for i in range(n):
        height[i], sigma[i], source[i], tall_i = _measure(scan_ctx, surfaces, i, config, k,
                                                          z_a)
        too_tall += tall_i
    layer_rows = pool_layers(height, sigma, source, flush_layers(scan_ctx, surfaces, config),
                             surfaces.attempt, z_a, config.alpha)
    agree: list[tuple[int, int, float]] = []  # HEIGHT_SKU_AGREEMENT: a, b, chi2
    for i in range(n):
        h_sku = sku_height[i] if sku_height is not None else np.nan
        if np.isfinite(h_sku):
            chi2 = (math.inf if source[i] == HeightSource.NONE else
                    (height[i] - h_sku) ** 2 / (sigma[i] ** 2 + config.size_tolerance**2))
            if source[i] != HeightSource.NONE:
                agree.append((int(surfaces.attempt[i]), int(source[i]), float(chi2)))
            if chi2 <= chi2_critical(1.0, config.alpha):
                # this carton's height measured: the measurement and the listed height,
                # each weighed by its variance (the tolerance the listed one's sigma)
                w_m, w_s = 1.0 / sigma[i] ** 2, 1.0 / config.size_tolerance**2
                height[i] = (w_m * height[i] + w_s * float(h_sku)) / (w_m + w_s)
                sigma[i] = math.sqrt(1.0 / (w_m + w_s))
            else:
                # nothing measured, or what was is not this carton's height: the side of a
                # stack of them, or the step down to the floor beyond the pallet
                height[i], source[i] = float(h_sku), HeightSource.SKU
                sigma[i] = config.size_tolerance
        if source[i] != HeightSource.NONE:
            rows.append((int(surfaces.attempt[i]), int(source[i]), float(height[i]),
                         float(sigma[i]), bool(height[i] > z_a * sigma[i])))
    a, b, chi2s = (list(col) for col in zip(*agree)) if agree else ([], [], [])
    return height, sigma, source, TestTable.concat(
        [_decisions(TestKind.HEIGHT_WITHIN_BOX, too_tall, config.alpha), layer_rows,
         TestTable.chi2(TestKind.HEIGHT_SKU_AGREEMENT, a, b, np.asarray(chi2s, np.float64),
                        1.0, config.alpha),
         _decisions(TestKind.BOX_HEIGHT, rows, config.alpha)], config.alpha)


def _decisions(kind: TestKind, rows: list[tuple[int, int, float, float, bool]],
               alpha: float) -> TestTable:
    """Rows (a, b, statistic, critical, accepted) of one kind as a table; empty without."""
    if not rows:
        return TestTable.empty(alpha)
    r = list(zip(*rows))
    return TestTable.decision(kind, r[0], r[1], r[2], r[3], r[4], alpha)


def _measure(ctx: VerifyContext, surfaces: SurfaceSet, i: int, config: Config, k: float,
             z_a: float) -> tuple[float, float, int, list[tuple[int, int, float, float, bool]]]:
    """Surface i's own height measurement: (height, sigma, :class:`HeightSource`), NaN and
    NONE where none is significant and within one carton's height, and a HEIGHT_WITHIN_BOX
    row (a, b, statistic, critical, accepted) for each measurement deeper than that."""
    a = int(surfaces.attempt[i])
    too_tall: list[tuple[int, int, float, float, bool]] = []

    def one_box(h: float, s: float, b: int) -> bool:
        crit = config.max_edge + z_a * s
        if h <= crit:
            return True
        too_tall.append((a, b, h, crit, False))
        return False

    C = surfaces.corners[i]
    c, nrm = surfaces.centers[i], surfaces.normals[i]
    x, y = surfaces.x_axis[i], surfaces.y_axis[i]
    w, ln = float(surfaces.width[i]), float(surfaces.length[i])
    outs = (-y, y, -x, x)
    sides = []
    for si, (ia, ib) in enumerate(SIDE_CORNERS):
        h, s, m = side_height(ctx, C[ia], C[ib], outs[si], -nrm,
                              SIDE_REACH * config.max_edge, k, config.flatness)
        if np.isfinite(h) and h > z_a * s and one_box(h, s, si):
            sides.append((m, h, s))
    if sides:
        # the side seen best (most points) gives the height
        _, h, s = max(sides)
        return h, s, int(HeightSource.SIDE), too_tall
    steps = []
    for si in range(4):
        h, s, m = step_height(ctx, C, si, c, nrm, x, y, w, ln, 0.5 * config.min_edge, k,
                              config.flatness, config.min_inlier_fraction)
        if np.isfinite(h) and h > z_a * s and one_box(h, s, 4 + si):
            steps.append((h, s))
    if steps:
        h, s = min(steps)
        return h, s, int(HeightSource.STEP), too_tall
    return np.nan, np.nan, int(HeightSource.NONE), too_tall


def _rect_gap(a: np.ndarray, b: np.ndarray) -> float:
    """Distance between two convex quadrilaterals (4, 2), metres; 0 where a corner of one
    lies in the other (OpenCV's signed distance of each corner to the other's outline)."""
    d = max(cv2.pointPolygonTest(q.astype(np.float32).reshape(-1, 1, 2),
                                 (float(x), float(y)), True)
            for p, q in ((a, b), (b, a)) for x, y in p)
    return max(0.0, -float(d))


def flush_layers(ctx: VerifyContext, surfaces: SurfaceSet, config: Config) -> np.ndarray:
    """Which reported tops form one flush layer: (s,) int labels, the connected components
    of the pairs that touch and are coplanar.

    Two tops touch where their rectangles, in the first one's plane, lie within
    :data:`LAYER_GAP_SPACINGS` point spacings of each other (a carton's side is located
    within a spacing or two, and cartons in a layer stand a few millimetres apart at
    most), and are coplanar where each one's centre lies on the other's plane (z at alpha
    of both centres' uncertainty along the normal and the flatness prior, twice).
    """
    n = len(surfaces)
    k = math.sqrt(chi2_critical(1.0, config.alpha))
    N, C = surfaces.normals, surfaces.centers
    # each centre's variance along its normal
    v = np.einsum("si,sij,sj->s", N, np.asarray(surfaces.covariances, np.float64)[:, :3, :3], N)
    joined = np.zeros((n, n), bool)
    for i in range(n):
        ci, xi, yi = C[i], surfaces.x_axis[i], surfaces.y_axis[i]
        qi = np.stack([(surfaces.corners[i] - ci) @ xi, (surfaces.corners[i] - ci) @ yi], 1)
        for j in range(i + 1, n):
            tol = k * math.sqrt(v[i] + v[j] + 2.0 * config.flatness**2)
            # written so that an unknown (NaN) uncertainty joins nothing
            if not (abs(float((C[j] - ci) @ N[i])) <= tol
                    and abs(float((ci - C[j]) @ N[j])) <= tol):
                continue
            qj = np.stack([(surfaces.corners[j] - ci) @ xi, (surfaces.corners[j] - ci) @ yi], 1)
            gap = LAYER_GAP_SPACINGS * ctx.spacing_at(0.5 * (ci + C[j]))
            joined[i, j] = _rect_gap(qi, qj) <= gap
    return np.asarray(connected_components(joined, directed=False)[1], np.int64)


def pool_layers(height: np.ndarray, sigma: np.ndarray, source: np.ndarray, layer: np.ndarray,
                attempt: np.ndarray, z_a: float, alpha: float) -> TestTable:
    """Give the tops of one flush layer the layer's smallest side-face height, in place,
    where their own measurement reaches significantly deeper or is missing.

    The tops of a flush layer stand on one support (equal top heights, touching), so its
    boxes are equally tall, and a side face of one runs down to the box's foot or, flush
    with the layer below, on down the stack: at least that height. The smallest side
    measurement is the layer's height; a top whose own measurement (side or step) exceeds it
    significantly (z at alpha of the difference's sigma), or that has none, takes it. Steps
    give no layer height: beyond a side a step may find a shorter neighbour on the same
    support, less than the height.

    Returns
    -------
    TestTable
        LAYER_HEIGHT per top of a layer with a side measurement, but the one that gave
        it (a = its attempt, b = the attempt whose side measurement is the layer's).
    """
    rows: list[tuple[int, int, float, float, bool]] = []
    measured = np.isfinite(height) & (source != HeightSource.NONE)
    for lab in np.unique(layer):
        members = np.flatnonzero(layer == lab)
        have = members[measured[members] & (source[members] == HeightSource.SIDE)]
        if len(members) < 2 or len(have) == 0:
            continue
        g = int(have[np.argmin(height[have])])
        hg, sg, src = float(height[g]), float(sigma[g]), int(source[g])
        for i in members:
            if i == g:
                continue
            z = ((float(height[i]) - hg) / math.hypot(float(sigma[i]), sg) if measured[i]
                 else math.inf)
            take = z > z_a
            rows.append((int(attempt[i]), int(attempt[g]), z, z_a, take))
            if take:
                height[i], sigma[i], source[i] = hg, sg, src
    return _decisions(TestKind.LAYER_HEIGHT, rows, alpha)

"""The result: graspable surfaces with pose, size, grasp point, covariance and pick order.

Each surface comes from one hypothesis chosen by MDL. Its rectangle (from the generating
vertex and the verified dimensions) is moved onto the plane refitted to the range points
inside it; width <= length; the normal points toward the sensor; the grasp point is the
centre (the paper grasps "from the center of gravity of the fully exposed surfaces"). The
pick order takes the top-most surface first (height along ``scan.up``), so the pile is
unloaded from the top.

A part of a flat region split by a carton list (``DimensionSource.SKU_SPLIT``) takes the
region's refitted plane instead of its own: the split says its parts are tops of one layer
in that plane, which the region's points fix from many more rows. A part's own plane can
be tilted by 10-20 degrees where correlated noise dominates a small top (structured light
at 2.8 m, 0.17 x 0.21 m cartons: 3-21 degrees from the truth over one layer's 21 parts,
against 0.25 for the region's).

A cardboard lid bulges: its rim rests on the walls and its middle rises, so the plane
fitted to its points lies above the box's top by a part of the bulge (4/9 of it for the
shape below). :func:`fit_bulge` fits the inliers with a rim-supported bulge term, and
``SURFACE_BULGE`` tests that term against zero; when it is significant the centre is put
on the rim's plane (the box's top), and ``SurfaceSet.bulge`` says how far the lid's middle
stands above it. A deviation from the paper, whose surfaces are planes.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from boxloc.config import Config
from boxloc.products import (
    SPLIT_SOURCES,
    DimensionSource,
    HypothesisSet,
    Selection,
    SurfaceSet,
    Verification,
    VertexSet,
)
from boxloc.scan import Scan
from boxloc.stages.ambiguous import end_evidence
from boxloc.stages.height import box_heights, height_context
from boxloc.stages.sizes import match_size
from boxloc.stages.vertices import _skew
from boxloc.stats import TestKind, TestTable

#: the fewest inliers :func:`fit_bulge` fits (four parameters, and a few to spare)
MIN_BULGE_POINTS = 16


def _plane_attempt(hypotheses: HypothesisSet, j: int) -> int:
    """The attempt whose refitted plane surface attempt ``j`` lies in: for a part of a
    split region (SKU_SPLIT or SEEN_SPLIT, whose ``att_support`` is the region's hypothesis), the
    region's REGION (or ROW) attempt that was split (``att_support`` > 0); else ``j``."""
    H = hypotheses
    if H.att_source[j] not in SPLIT_SOURCES:
        return j
    r = np.flatnonzero((H.att_hypothesis == int(H.att_support[j]))
                       & np.isin(H.att_source, (DimensionSource.REGION, DimensionSource.ROW))
                       & (H.att_support > 0))
    return int(r[0]) if len(r) else j


def fit_bulge(
    points: np.ndarray, center: np.ndarray, x_axis: np.ndarray, y_axis: np.ndarray,
    normal: np.ndarray, width: float, length: float, sigma: np.ndarray,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Fit a face's points with a plane and a rim-supported bulge.

    The height of a point over the plane through ``center`` is modelled as
    ``h = a + b u + c v + k (1 - u^2) (1 - v^2)``, with ``u``, ``v`` its coordinates
    along the axes scaled to [-1, 1] over the rectangle: ``a + b u + c v`` is the rim's
    plane (the bulge term vanishes on the rectangle's sides) and ``k`` the bulge at the
    centre. Weighted least squares.

    Parameters
    ----------
    points : (n, 3) float64
        The face's inlier points, metres.
    center, x_axis, y_axis, normal : (3,) float64
        The rectangle's centre and unit axes (x along ``width``); normal toward the sensor.
    width, length : float
        Metres.
    sigma : (n,) float64
        Standard deviation of each point along the normal, metres.

    Returns
    -------
    coef : (4,) float64
        ``a, b, c, k``, metres.
    cov : (4, 4) float64
        Their covariance, m^2.

    None where the points cannot determine the four (all on one line, say).
    """
    D = np.asarray(points, np.float64) - center
    u = D @ x_axis / (0.5 * width)
    v = D @ y_axis / (0.5 * length)
    A = np.stack([np.ones_like(u), u, v, (1.0 - u * u) * (1.0 - v * v)], axis=1)
    w = 1.0 / np.asarray(sigma, np.float64)
    if np.linalg.matrix_rank(A * w[:, None]) < 4:
        return None
    cov = np.linalg.inv((A * (w * w)[:, None]).T @ A)
    coef = cov @ (A.T @ ((D @ normal) * w * w))
    return coef, cov


def make_surfaces(
    scan: Scan,
    vertices: VertexSet,
    hypotheses: HypothesisSet,
    verification: Verification,
    selection: Selection,
    config: Config,
) -> SurfaceSet:
    """Turn the selected hypotheses into graspable surfaces, ordered by pick order.

    Returns
    -------
    SurfaceSet
        ``covariances`` are of (centre, rotation vector), (s, 6, 6), metres and radians.
    """
    flat = scan.points.reshape(-1, 3)
    rows = []
    tests = []
    for k in np.flatnonzero(selection.chosen):
        j = int(selection.candidates[k])
        h = int(verification.hypothesis[j])
        w = float(hypotheses.att_width[j])
        ln = float(hypotheses.att_length[j])
        o, x, y = hypotheses.origins[h], hypotheses.x_axis[h], hypotheses.y_axis[h]
        jp = _plane_attempt(hypotheses, j)
        nf = verification.plane_normals[jp]
        pc = verification.plane_centers[jp]
        c = o + 0.5 * w * x + 0.5 * ln * y
        c = c - ((c - pc) @ nf) * nf
        # in-plane axes re-orthogonalized to the refitted normal
        x = x - (x @ nf) * nf
        x /= np.linalg.norm(x)
        y = np.cross(nf, x)
        if w > ln:
            w, ln = ln, w
            x, y = y, -x  # keeps x cross y = normal
        pts = flat[verification.inliers_of(j)].astype(np.float64)
        bulge = 0.0
        fit = None
        if len(pts) >= MIN_BULGE_POINTS:
            sig = config.noise.sigma_range(np.linalg.norm(pts, axis=1))
            fit = fit_bulge(pts, c, x, y, nf, w, ln, sig)
        if fit is not None:  # else untestable: the centre stays on the points' plane
            coef, C = fit
            t = TestTable.chi2(TestKind.SURFACE_BULGE, j, 0, coef[3] ** 2 / C[3, 3], 1,
                               config.alpha)
            tests.append(t)
            bulge = float(coef[3])
            if not t.accepted[0]:
                c = c + coef[0] * nf
        corners = np.array([c - 0.5 * w * x - 0.5 * ln * y, c + 0.5 * w * x - 0.5 * ln * y,
                            c + 0.5 * w * x + 0.5 * ln * y, c - 0.5 * w * x + 0.5 * ln * y])
        Vc = vertices.covariances[h]
        Sd1, Sd2 = Vc[3:6, 3:6], Vc[6:, 6:]
        cov = np.zeros((6, 6))
        cov[:3, :3] = Vc[:3, :3] + 0.25 * (w * w * Sd1 + ln * ln * Sd2)
        # rotation: tilt of the normal (plane refit) and turn about it (the vertex lines)
        Sn = verification.plane_covariances[jp][3:, 3:]
        K = _skew(nf)
        cov[3:, 3:] = K.T @ Sn @ K + float(y @ Sd1 @ y + x @ Sd2 @ x) * np.outer(nf, nf)
        # what shows each side is the box's end
        tests.append(end_evidence(verification.tests.select(verification.tests.a == j), j,
                                  hypotheses.att_source[j] in SPLIT_SOURCES))
        q = selection.Q[k, k]
        score = float(q / max(config.mdl_k1 * selection.n_points[k], 1e-12))
        rows.append((h, j, c, nf, x, y, w, ln, corners, score, cov, bulge))
    up = hypotheses.up
    heights = np.array([r[2] @ up for r in rows])
    order = np.lexsort((np.array([r[0] for r in rows]), -heights)) if rows else np.zeros(0, int)
    rows = [rows[i] for i in order]
    s = len(rows)

    def col(i: int, shape: tuple[int, ...], dtype: type = np.float64) -> np.ndarray:
        return np.array([r[i] for r in rows], dtype).reshape((s, *shape))

    surf = SurfaceSet(
        hypothesis=col(0, (), np.int32),
        attempt=col(1, (), np.int32),
        centers=col(2, (3,)),
        normals=col(3, (3,)),
        x_axis=col(4, (3,)),
        y_axis=col(5, (3,)),
        width=col(6, ()),
        length=col(7, ()),
        corners=col(8, (4, 3)),
        grasp_points=col(2, (3,)),
        scores=col(9, ()),
        covariances=col(10, (6, 6)),
        pick_order=np.arange(s, dtype=np.int32),
        bulge=col(11, ()),
        tests=TestTable.concat(tests, config.alpha),
    )
    return with_sizes_and_heights(scan, surf, config, up)


def with_sizes_and_heights(scan: Scan, surf: SurfaceSet, config: Config,
                           up: np.ndarray) -> SurfaceSet:
    """``surf`` with each box's matched carton size (SKU_SIZE against ``config.box_sizes``;
    flagged where sizes are listed and none matches) and its height
    (:func:`boxloc.stages.height.box_heights`; the matched size's listed height where
    nothing is measured)."""
    n = len(surf)
    sku = np.full(n, -1, np.int32)
    flagged = np.zeros(n, bool)
    sku_h = np.full(n, np.nan)
    rows = []
    if config.box_sizes:
        for i in range(n):
            j, T, crit, ok = match_size(float(surf.width[i]), float(surf.length[i]),
                                        config.box_sizes, config.size_tolerance, config.alpha)
            rows.append(TestTable.chi2(TestKind.SKU_SIZE, int(surf.attempt[i]), j, T, 2.0,
                                       config.alpha))
            if ok:
                sku[i], sku_h[i] = j, config.box_sizes[j][2]
            flagged[i] = not ok
    height, sigma, source, h_rows = box_heights(height_context(scan, config, up), surf, config,
                                                sku_h)
    return dataclasses.replace(
        surf, tests=TestTable.concat([surf.tests, *rows, h_rows], config.alpha),
        height=height, height_sigma=sigma, height_source=source, sku=sku, sku_flagged=flagged)

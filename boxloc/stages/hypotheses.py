"""Stage 5: one rectangle hypothesis per vertex, with its dimensions (the paper's Fig. 2).

``generate_hypotheses`` is lines 2-8 of the paper's ``findgraspablesurfaces``: for every
vertex V_i a rectangle R is aligned with it (origin at the vertex, x along d1, y along d2);
its dimensions come first from a diagonal vertex (``dimensions_from_vertices``, lines
11-17), else from the edge points (``dimensions_from_edges``, lines 18-30). Each candidate
pair of dimensions is an *attempt*, verified by :func:`boxloc.stages.verify.verify`; the
hypothesis keeps the first verified attempt. Attempts are tried smallest area first, the
tightest rectangle the evidence supports, so a row of touching boxes is not merged.

The paper returns after verifying the first candidate; here a candidate that fails
verification is followed by the next one (at most ``MAX_ATTEMPTS``), and every attempt is
recorded, so a post-mortem sees what else was tried.

Where the edge stage saw the seam between two touching boxes of equal height only in part,
the edge accumulators have no peak there; seams found in the range points of the region
(:mod:`boxloc.stages.seams`) are added as far-side candidates (``DimensionSource.SEAMS``), and
verification tests the seam itself instead of counting edge points along it.

A far side with too few edge points for a peak (a sensor that rounds the corners of a
face, or a side seen at grazing incidence) leaves the accumulators without the right
candidate; the face's extent along each arm, how far its plane runs in a strip beside the
arm (:func:`boxloc.stages.verify.face_extent`), gives one (``DimensionSource.EXTENT``). These
candidates are tried after those from the edges, with a budget of their own
(``MAX_EXTENT_ATTEMPTS``), so the paper's candidates always come first. Last come seams in
the last short box edge before ``max_edge`` (:func:`dimensions_near_max_edge`), which the
seam search of the edges' candidates cannot see.

A vertex whose plane (the normal of its two lines) is tilted beyond ``max_tilt`` from up
gets no search: every rectangle of it shares that normal and would fail the tilt prior
first (``HYPOTHESIS_TILT`` records it). Such vertices are the corners of side faces, which
a tall stack seen at an angle shows in numbers.

Per-vertex work is independent (the paper's parallel implementation); with
``config.workers > 1`` it runs in processes and the result is identical to serial.
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter, deque
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import special
from scipy.spatial import cKDTree

from boxloc.config import Config
from boxloc.distributions import poisson_isf
from boxloc.products import (
    SPLIT_SOURCES,
    AmbiguityReason,
    DimensionSource,
    EdgeMap,
    HeightSource,
    HypothesisSet,
    Verification,
    VerifyReason,
    VertexSet,
)
from boxloc.scan import Scan
from boxloc.stages.height import step_height
from boxloc.stages.seams import (
    SEAM_FLANK,
    SEAM_SCALES,
    face_points,
    find_seams,
    norm_isf,
)
from boxloc.stages.sizes import (
    Split,
    distinct,
    match_size,
    other_tiling,
    region_splits,
    row_cartons,
    seen_tilings,
)
from boxloc.stages.verify import (
    BOUNDARY_BAND,
    SIDE_CORNERS,
    VerifyContext,
    VerifyOutcome,
    face_extent,
    face_sigma,
    plane_var,
    rectangle_corners,
    seam_line,
    tilt_from_up,
    verify,
    whole_face_spread,
)
from boxloc.stages.vertices import _skew, append_vertices, normal_covariance
from boxloc.stats import (
    BUDGET_HYPOTHESES,
    BUDGET_HYPOTHESIS_WORK,
    TestKind,
    TestTable,
    chi2_critical,
)

#: Most dimension candidates verified per vertex (bounds the work on cluttered scenes).
MAX_ATTEMPTS = 6
#: Most candidates from the face's extent verified per vertex, after the others; as many
#: again from seams near ``max_edge`` (:func:`dimensions_near_max_edge`), after those.
MAX_EXTENT_ATTEMPTS = 3
#: Most rounds of neighbours' corners (a row of touching boxes grows by one box a round).
MAX_NEIGHBOUR_ROUNDS = 8
#: A verified face's plane runs on beyond a seam side, to an equal neighbour, where at
#: least this share of the strip beyond lies on it (VERIFY_CONTINUATION's statistic):
#: half. A lower or taller neighbour leaves almost none on it; an equal one with a bulged
#: lid holds only part (its rim by the seam, not its rising middle: 0.64-0.69 beside
#: 1.2 cm lids), short of ``min_inlier_fraction``, which decides whether the face itself
#: runs on.
NEIGHBOUR_RUNS_ON = 0.5
#: How far a flat region is followed along an arm, as a multiple of ``max_edge``: a pallet
#: layer (1.2 m) of the longest cartons is twice the longest edge; a few in a row on a
#: wider pallet or a conveyor, four.
REGION_REACH = 4.0
#: ``VertexSet.parent_side`` of a part's corner in a flat region split at the seams a
#: listed carton size implies (0-3 are a neighbour's seam sides, 4 a box corner's
#: third edge).
SIZE_PART = 5
#: Height of a pallet (EUR / ISO 6780: 144 mm), metres: a layer of cartons listed without a
#: height must stand more than this above what lies beyond it to be split into them, so
#: that a bare pallet on the floor, itself a flat region, is not.
PALLET_HEIGHT = 0.144


@dataclass
class Rectangle:
    """A rectangle aligned with its generating vertex (the paper's R)."""

    vertex: int
    origin: np.ndarray
    x_axis: np.ndarray
    y_axis: np.ndarray
    normal: np.ndarray
    plane_cov: np.ndarray  # (6, 6): origin, normal
    width: float = np.nan
    length: float = np.nan


@dataclass
class _Attempt:
    source: DimensionSource
    diagonal: int
    width: float
    length: float
    support: float
    threshold: float
    outcome: VerifyOutcome | None = None
    #: sides (0-3) a listed carton's size puts inside the flat region: a ROW's far side
    inner: frozenset[int] = frozenset()
    #: a ROW's carton at the vertex: its extent along x and along y, metres
    carton: tuple[float, float] = (np.nan, np.nan)


@dataclass
class _VertexWork:
    """Everything found for one vertex."""

    vertex: int
    attempts: list[_Attempt] = field(default_factory=list)
    tests: list[TestTable] = field(default_factory=list)
    acc_bin: float = np.nan
    acc_x: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    acc_y: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    peaks_x: np.ndarray = field(default_factory=lambda: np.zeros(0))
    peaks_y: np.ndarray = field(default_factory=lambda: np.zeros(0))
    n_candidates: int = 0
    #: the seams :func:`_seam_peaks` found, that search's noise scale and, per axis, its
    #: statistic's spread (Seams.spread; empty: no seam search ran)
    seams_x: np.ndarray = field(default_factory=lambda: np.zeros(0))
    seams_y: np.ndarray = field(default_factory=lambda: np.zeros(0))
    seam_scale: float = np.nan
    seam_spread: tuple[tuple[float, ...], ...] = ()
    #: how far the plane runs along each arm (:func:`dimensions_from_extent`; NaN: unknown)
    extent: tuple[float, float] = (np.nan, np.nan)
    #: pixels its rectangle searches read (:meth:`VerifyContext.pixels_in`): its share of
    #: ``Config.max_hypothesis_work``
    pixels: float = 0.0


@dataclass
class _Context:
    scan: Scan
    config: Config
    vertices: VertexSet
    normal_cov: np.ndarray
    edge_points: np.ndarray
    edge_cov: np.ndarray
    edge_tree: cKDTree | None
    verify_ctx: VerifyContext
    #: ``config.box_sizes`` is the scan's own carton list (:func:`_seen_cartons`), not the
    #: user's: a split's parts are SEEN_SPLIT
    seen_sizes: bool = False

    @classmethod
    def build(cls, scan: Scan, edges: EdgeMap, vertices: VertexSet, config: Config,
              up: np.ndarray, gain: np.ndarray | None = None) -> _Context:
        return cls(
            scan=scan, config=config, vertices=vertices,
            normal_cov=normal_covariance(vertices) if len(vertices) else np.zeros((0, 3, 3)),
            edge_points=edges.points, edge_cov=edges.covariances,
            edge_tree=cKDTree(edges.points) if len(edges) else None,
            verify_ctx=VerifyContext.build(scan, edges, config, up, len(vertices), gain),
        )


def align(vertices: VertexSet, i: int, normal_cov: np.ndarray) -> Rectangle:
    """Rectangle R aligned with vertex i (paper Fig. 2, line 3)."""
    cov = np.zeros((6, 6))
    cov[:3, :3] = vertices.covariances[i][:3, :3]
    cov[3:, 3:] = normal_cov[i]
    return Rectangle(i, vertices.points[i], vertices.d1[i], vertices.d2[i],
                     vertices.normals[i], cov)


def dimensions_from_vertices(R: Rectangle, ctx: _Context, work: _VertexWork) -> list[_Attempt]:
    """Candidate dimensions from diagonal vertices (paper Fig. 2, lines 11-15).

    A vertex V_j is diagonal to R if it is coplanar with R (its point on R's plane and
    its normal parallel to R's: chi2(3)), its directions are parallel to R's (chi2(2)),
    it lies in R's first quadrant (one-sided z tests on both coordinates) and its arms
    point back toward R's origin.
    """
    V = ctx.vertices
    cfg = ctx.config
    alpha = cfg.alpha
    others = np.array([j for j in range(len(V)) if j != R.vertex], np.int64)
    if len(others) == 0:
        return []
    D = V.points[others] - R.origin
    u, v = D @ R.x_axis, D @ R.y_axis
    near = (np.abs(u) <= cfg.max_edge * 1.05) & (np.abs(v) <= cfg.max_edge * 1.05)
    # arms pointing back: d1_j, d2_j == -x, -y in either order
    a1x, a1y = V.d1[others] @ R.x_axis, V.d1[others] @ R.y_axis
    a2x, a2y = V.d2[others] @ R.x_axis, V.d2[others] @ R.y_axis
    straight = (a1x < -0.5) & (a2y < -0.5)
    swapped = (a1y < -0.5) & (a2x < -0.5)
    cand = near & (straight | swapped) & (u > 0) & (v > 0)
    idx = others[cand]
    if len(idx) == 0:
        return []
    Dc = D[cand]
    n = R.normal
    Sx, Sn = R.plane_cov[:3, :3], R.plane_cov[3:, 3:]
    # coplanar: point on plane (1) + normals parallel (2) = chi2(3)
    w = Dc @ n
    Sj = V.covariances[idx][:, :3, :3]
    var_w = (plane_var(R.plane_cov, n, Dc) + np.einsum("i,nij,j->n", n, Sj, n)
             + 2 * cfg.flatness**2)
    nj = V.normals[idx]
    e = np.cross(n, nj)
    Snj = ctx.normal_cov[idx]
    Kn = _skew(n)
    Knj = _skew(nj)
    Sn_t = Sn + cfg.angle_tolerance**2 * (np.eye(3) - np.outer(n, n))
    See = Kn @ Snj @ Kn.T + np.einsum("nij,jk,nlk->nil", Knj, Sn_t, Knj)
    T_par_n = np.array([_pinv_quad(e[k], See[k], 2) for k in range(len(idx))])
    T_cop = w**2 / np.maximum(var_w, 1e-30) + T_par_n
    cop = TestTable.chi2(TestKind.COPLANAR, R.vertex, idx, T_cop, 3.0, alpha)
    # parallel: R's x axis against the matching direction of V_j, chi2(2)
    sw = swapped[cand]
    dj = np.where(sw[:, None], V.d2[idx], V.d1[idx])
    Sdj = np.where(sw[:, None, None], V.covariances[idx][:, 6:, 6:],
                   V.covariances[idx][:, 3:6, 3:6])
    Sdx = V.covariances[R.vertex][3:6, 3:6] + cfg.angle_tolerance**2 * (
        np.eye(3) - np.outer(R.x_axis, R.x_axis))
    e2 = np.cross(R.x_axis, dj)
    Kx = _skew(R.x_axis)
    Kd = _skew(dj)
    See2 = Kx @ Sdj @ Kx.T + np.einsum("nij,jk,nlk->nil", Kd, Sdx, Kd)
    T_par = np.array([_pinv_quad(e2[k], See2[k], 2) for k in range(len(idx))])
    par = TestTable.chi2(TestKind.PARALLEL, R.vertex, idx, T_par, 2.0, alpha)
    # first quadrant: u and v significantly positive (one-sided z at alpha each)
    uc, vc = u[cand], v[cand]
    var_u = np.einsum("i,nij,j->n", R.x_axis, Sj, R.x_axis) + R.x_axis @ Sx @ R.x_axis
    var_v = np.einsum("i,nij,j->n", R.y_axis, Sj, R.y_axis) + R.y_axis @ Sx @ R.y_axis
    zq = np.minimum(uc / np.sqrt(var_u), vc / np.sqrt(var_v))
    zc = float(_norm_isf(alpha))
    quad = TestTable.decision(TestKind.FIRST_QUADRANT, R.vertex, idx, zq, zc, zq > zc, alpha)
    work.tests += [cop, par, quad]
    ok = cop.accepted & par.accepted & quad.accepted
    ok &= (uc >= cfg.min_edge * 0.9) & (vc >= cfg.min_edge * 0.9)
    ok &= (uc <= cfg.max_edge) & (vc <= cfg.max_edge)
    out = [
        _Attempt(DimensionSource.VERTICES, int(idx[k]), float(uc[k]), float(vc[k]),
                 float(T_cop[k] + T_par[k]), float(cop.critical[0] + par.critical[0]))
        for k in np.flatnonzero(ok)
    ]
    out.sort(key=lambda a: (a.width * a.length, a.diagonal))
    return out


def dimensions_from_edges(R: Rectangle, ctx: _Context, work: _VertexWork) -> list[_Attempt]:
    """Candidate dimensions from edge points and two 1-D accumulators (Fig. 2, lines 18-28).

    ``preprocess`` keeps the edge points on R's plane (point-on-plane, chi2(1)) in its
    first quadrant (P_c); their coordinates along x and y vote into A_x and A_y, each vote
    spread over the bins by the point's own localization error (a sensor that blurs its
    edges, ``noise.edge_px``, gives wide votes). For each pair of peaks (M_x, M_y), P_f are
    the points of both peaks inside the rectangle (on a peak: within the bin window or the
    point's own error at alpha); the pair is supported if |P_f| > p, with p =
    support_fraction of the far sides' expected edge points, one per pixel each side
    covers in the image (a side seen at grazing incidence is foreshortened).
    """
    cfg = ctx.config
    alpha = cfg.alpha
    if ctx.edge_tree is None:
        return []
    nb = np.asarray(ctx.edge_tree.query_ball_point(R.origin, cfg.max_edge * math.sqrt(2)),
                    np.int64)
    if len(nb) == 0:
        return []
    D = ctx.edge_points[nb] - R.origin
    u, v, w = D @ R.x_axis, D @ R.y_axis, D @ R.normal
    Ce = ctx.edge_cov[nb]
    var_w = (np.einsum("i,nij,j->n", R.normal, Ce, R.normal)
             + plane_var(R.plane_cov, R.normal, D))
    T = w**2 / np.maximum(var_w, 1e-30)
    crit = chi2_critical(1.0, alpha)
    on_plane = T <= crit
    su = np.sqrt(np.einsum("i,nij,j->n", R.x_axis, Ce, R.x_axis))
    sv = np.sqrt(np.einsum("i,nij,j->n", R.y_axis, Ce, R.y_axis))
    kq = math.sqrt(crit)
    quad = (u > -kq * su) & (v > -kq * sv) & (u <= cfg.max_edge) & (v <= cfg.max_edge)
    Pc = on_plane & quad
    work.tests.append(TestTable.decision(
        TestKind.POINT_ON_PLANE, R.vertex, int(quad.sum()), int((Pc).sum()), crit, True, alpha,
        dof=1.0,
    ))
    work.n_candidates = int(Pc.sum())
    if Pc.sum() == 0:
        return []
    u, v, su, sv = u[Pc], v[Pc], su[Pc], sv[Pc]
    spacing = ctx.verify_ctx.spacing_at(R.origin)
    h = max(spacing, 2.0 * float(np.median(np.concatenate([su, sv]))))
    nbins = int(math.ceil(cfg.max_edge / h)) + 2
    # the generating vertex's own sides (v ~ 0 for A_x, u ~ 0 for A_y) say nothing of the
    # far sides and would spread votes evenly over the accumulator: leave them out
    band = BOUNDARY_BAND * cfg.min_edge
    ax = _soft_votes(u[v > band], su[v > band], h, nbins)
    ay = _soft_votes(v[u > band], sv[u > band], h, nbins)
    work.acc_bin, work.acc_x, work.acc_y = h, ax.astype(np.float32), ay.astype(np.float32)
    min_peak = cfg.support_fraction * cfg.min_edge / spacing
    px = _peaks(ax, h, cfg.min_edge * 0.9, min_peak, alpha)
    py = _peaks(ay, h, cfg.min_edge * 0.9, min_peak, alpha)
    work.peaks_x, work.peaks_y = px, py
    sx, sy = _seam_peaks(R, ctx, work, px, py, spacing, band)
    out: list[_Attempt] = []
    sup_tests: list[tuple[float, float, bool]] = []
    # a seam for a far side: no edge support to count, verification tests the seam
    seam_pairs = [(a, b) for a in sx for b in np.r_[py, sy]] + [(a, b) for a in px for b in sy]
    out += [_Attempt(DimensionSource.SEAMS, -1, float(a), float(b), np.nan, np.nan)
            for a, b in seam_pairs]
    for Mx in px:
        for My in py:
            # on a side: within the bin window, or the point's own localization at alpha
            on_x = np.abs(u - Mx) <= np.maximum(1.5 * h, kq * su)
            on_y = np.abs(v - My) <= np.maximum(1.5 * h, kq * sv)
            Pi = on_x | on_y
            Pf = Pi & (u <= Mx + 1.5 * h) & (v <= My + 1.5 * h)
            _, c1, c2, c3 = rectangle_corners(R.origin, R.x_axis, R.y_axis, Mx, My)
            p = cfg.support_fraction * (ctx.verify_ctx.samples_along(c1, c2)
                                        + ctx.verify_ctx.samples_along(c3, c2))
            n_f = int(Pf.sum())
            sup_tests.append((n_f, p, n_f > p))
            if n_f > p:
                out.append(_Attempt(DimensionSource.EDGES, -1, float(Mx), float(My),
                                    float(n_f), float(p)))
    if sup_tests:
        s = np.array(sup_tests)
        work.tests.append(TestTable.decision(TestKind.EDGE_SUPPORT, R.vertex, -1, s[:, 0],
                                             s[:, 1], s[:, 2].astype(bool), alpha))
    out.sort(key=lambda a: a.width * a.length)
    return out


def dimensions_from_extent(R: Rectangle, ctx: _Context, work: _VertexWork) -> list[_Attempt]:
    """Candidate dimensions from how far R's plane runs along each arm.

    The extent along x is measured in a strip beside the x arm, from ``BOUNDARY_BAND``
    to 0.9 ``min_edge`` across it (inside any box the vertex can belong to, clear of the
    arm's own edge), and likewise along y. The two extents together are the first
    candidate; then each with the other axis's accumulator peaks, smallest area first.
    """
    cfg = ctx.config
    k = math.sqrt(chi2_critical(1.0, cfg.alpha))
    lo = 0.9 * cfg.min_edge
    strip = (BOUNDARY_BAND * cfg.min_edge, lo)
    ext, gaps = [], []
    for along, across in ((R.x_axis, R.y_axis), (R.y_axis, R.x_axis)):
        work.pixels += ctx.verify_ctx.pixels_in(R.origin, along, across, (0.0, cfg.max_edge),
                                                strip)
        e, g = face_extent(ctx.verify_ctx, R.origin, along, across, R.normal, R.plane_cov,
                           strip, cfg.max_edge, k, cfg.flatness)
        ext.append(e)
        gaps.append(g)
    ext_a = np.array(ext)
    work.extent = (float(ext_a[0]), float(ext_a[1]))
    usable = np.isfinite(ext_a) & (ext_a >= lo) & (ext_a <= cfg.max_edge)
    work.tests.append(TestTable.decision(TestKind.FACE_EXTENT, R.vertex, [0, 1], ext_a,
                                         np.array(gaps), usable, cfg.alpha))
    ex = ext_a[:1][usable[:1]]
    ey = ext_a[1:][usable[1:]]
    both = [(float(a), float(b)) for a in ex for b in ey]
    pairs = {(float(a), float(b)) for a in ex for b in work.peaks_y}
    pairs |= {(float(a), float(b)) for a in work.peaks_x for b in ey}
    pairs -= set(both)
    # the extent on both arms first; then one arm's extent with the other's peaks
    out = [_Attempt(DimensionSource.EXTENT, -1, a, b, np.nan, np.nan)
           for a, b in both + sorted(pairs, key=lambda ab: (ab[0] * ab[1], ab[0]))]
    return out


def dimensions_from_region(R: Rectangle, ctx: _Context, work: _VertexWork) -> list[_Attempt]:
    """The whole flat region at R's vertex, when it is larger than any box.

    Where touching boxes of equal height show no seam (sharp edges, no gap: a tightly
    packed layer), their tops are one flat region, and no candidate up to ``max_edge``
    verifies (each is cut short inside it). R's plane is followed along each arm as in
    :func:`dimensions_from_extent`, out to ``REGION_REACH`` ``max_edge``. If both extents
    end within the reach, are box edges long (0.9 ``min_edge``) and one is longer than
    ``max_edge``, the region is a candidate (``DimensionSource.REGION``), verified like a
    box's top: that its every side ends with evidence (jump, crease, groove, seam) and no
    seam or edge line crosses it. A region that verifies is never a surface: it is
    ambiguous, or split at the seams a listed carton size implies (:func:`_split_regions`).
    FACE_EXTENT rows with b = 2 (x), 3 (y) record the extents where one is longer than
    ``max_edge``.

    With a carton list, ROW candidates follow (:func:`dimensions_from_rows`), tried only
    where the whole region does not verify.
    """
    cfg = ctx.config
    k = math.sqrt(chi2_critical(1.0, cfg.alpha))
    lo = 0.9 * cfg.min_edge
    strip = (BOUNDARY_BAND * cfg.min_edge, lo)
    reach = REGION_REACH * cfg.max_edge
    ext, gaps = [], []
    for along, across in ((R.x_axis, R.y_axis), (R.y_axis, R.x_axis)):
        work.pixels += ctx.verify_ctx.pixels_in(R.origin, along, across, (0.0, reach), strip)
        e, g = face_extent(ctx.verify_ctx, R.origin, along, across, R.normal, R.plane_cov,
                           strip, reach, k, cfg.flatness)
        ext.append(e)
        gaps.append(g)
    ext_a, gap_a = np.array(ext), np.array(gaps)
    if not (np.isfinite(ext_a) & (ext_a > cfg.max_edge)).any():
        return []
    # the region's end must be seen on both arms, and each must be a box edge long
    ends = np.isfinite(ext_a) & (ext_a >= lo) & (ext_a < reach - gap_a)
    work.tests.append(TestTable.decision(TestKind.FACE_EXTENT, R.vertex, [2, 3], ext_a, gap_a,
                                         ends, cfg.alpha))
    region = ([_Attempt(DimensionSource.REGION, -1, float(ext_a[0]), float(ext_a[1]), 0.0,
                        np.nan)] if ends.all() else [])
    return region + dimensions_from_rows(R, ctx, work, ext_a, ends)


def dimensions_from_rows(R: Rectangle, ctx: _Context, work: _VertexWork, ext: np.ndarray,
                         ends: np.ndarray) -> list[_Attempt]:
    """With a carton list, the row of listed cartons along each arm of R whose flat region
    ends along it (``ends``, :func:`dimensions_from_region`'s extents ``ext``), where the
    list says what lines that side (:func:`boxloc.stages.sizes.row_cartons`).

    A layer cut off by the image's border, or one whose far sides the sensor smears, does
    not verify whole; but a side seen from R's corner to the layer's end is lined by
    cartons whose edges add up to it, and where only n of one listed edge do, those
    cartons reach the listed depth into the layer: a rectangle of the side's length by
    that depth (``DimensionSource.ROW``), with its far side (``inner``) on the size's
    evidence. Its other three sides need the scan's: the row's end at the side's far
    corner most of all, which a side cut short by the border does not have. Each arm's
    decision is an SKU_ROW row. The region must reach the depth along the other arm (or
    not end along it within reach).
    """
    cfg = ctx.config
    if not cfg.box_sizes:
        return []
    out = []
    z = math.sqrt(chi2_critical(1.0, cfg.alpha)) * cfg.size_tolerance
    for arm in (0, 1):
        if not ends[arm]:
            continue
        row = row_cartons(float(ext[arm]), cfg.box_sizes, cfg.size_tolerance, cfg.alpha)
        stat = np.nan if row.exhausted else float(min(row.ways, 2))
        work.tests.append(TestTable.decision(TestKind.SKU_ROW, R.vertex, arm, stat, 1.0,
                                             row.unique, cfg.alpha))
        other = ext[1 - arm]
        if not row.unique or (ends[1 - arm] and not other >= row.depth - z):
            continue
        L = float(ext[arm])
        end = _row_end(R, ctx, arm, L, row.n)
        work.tests.append(end)
        if not end.accepted[0]:
            continue
        w, ln, inner = (L, row.depth, 1) if arm == 0 else (row.depth, L, 3)
        if not _in_image(ctx.scan, rectangle_corners(R.origin, R.x_axis, R.y_axis, w, ln)):
            continue
        carton = (row.along, row.depth) if arm == 0 else (row.depth, row.along)
        out.append(_Attempt(DimensionSource.ROW, -1, w, ln, 0.0, np.nan,
                            inner=frozenset({inner}), carton=carton))
    return out


def _seam_peaks(R: Rectangle, ctx: _Context, work: _VertexWork, px: np.ndarray,
                py: np.ndarray, spacing: float, band: float) -> tuple[np.ndarray, np.ndarray]:
    """Seams inside the region the edge peaks span: extra candidates for the far sides.

    Where the edge stage saw a seam between touching boxes only in part, its accumulator
    has no peak there; the range points of the region, binned across each axis, still show
    the groove (:func:`boxloc.stages.seams.find_seams`, at the scan's seam level over the
    positions, :func:`boxloc.stages.verify.seam_alpha`). The region
    runs to the farthest edge peak on each axis (``max_edge`` where there is none), and a
    seam must leave a short box edge (0.9 ``min_edge``) of it beyond
    (:func:`dimensions_near_max_edge` looks past that, last).
    """
    cfg = ctx.config
    U, V = _seam_reach(px, cfg), _seam_reach(py, cfg)
    vc = ctx.verify_ctx
    work.pixels += vc.pixels_in(R.origin, R.x_axis, R.y_axis, (0.0, U), (0.0, V))
    fp = face_points(vc.points, vc.valid, vc.sigma, vc.project, R.origin, R.x_axis, R.y_axis,
                     R.normal, (0.0, U), (0.0, V), spacing, cfg.alpha, cfg.noise.row_corr,
                     vc.gain)
    lo = 0.9 * cfg.min_edge
    found: list[np.ndarray] = []
    spreads: list[tuple[float, ...]] = []
    for b, (coord, other, ext) in enumerate(((fp.u, fp.v, U), (fp.v, fp.u, V))):
        sel = other > band
        # where the noise is white, a seam's own lobes must not hide it (find_seams)
        seams = find_seams(coord[sel], fp.w[sel], fp.scale, lo, ext - lo, spacing,
                           vc.seam_alpha, fp.row[sel], fp.row_corr,
                           mask_strongest=not cfg.noise.correlated)
        pos, z, crit = seams[:3]
        found.append(pos)
        spreads.append(seams.spread)
        if len(pos):
            work.tests.append(TestTable.decision(TestKind.SEAM_PEAK, R.vertex, b, z, crit,
                                                 True, cfg.alpha))
    work.seams_x, work.seams_y = found[0], found[1]
    work.seam_scale, work.seam_spread = fp.scale, tuple(spreads)
    return found[0], found[1]


def _seam_reach(peaks: np.ndarray, cfg: Config) -> float:
    """How far :func:`_seam_peaks`' region runs along an axis: its farthest edge peak,
    ``max_edge`` where there is none."""
    return float(peaks.max()) if len(peaks) else cfg.max_edge


def dimensions_near_max_edge(R: Rectangle, ctx: _Context,
                             work: _VertexWork) -> list[_Attempt]:
    """Far sides from seams between ``max_edge`` less a short box edge (0.9 ``min_edge``)
    and ``max_edge``: the last candidates of a vertex, once no other verified.

    :func:`_seam_peaks` leaves a short box edge of its region beyond any seam it finds, so
    on an axis without an edge peak it never looks past ``max_edge`` less ``min_edge``.
    The far side of a box of a tightly packed layer nearly ``max_edge`` long lies there,
    with no edge (its neighbour is flush) and no extent (the plane runs on): the layer
    would be one flat region. On each axis with neither an edge peak nor a seam, where
    the plane runs on into that last short box edge (:func:`dimensions_from_extent`'s
    extent; unknown counts), :func:`_seams_near_max` looks there; each seam it finds
    pairs with the other axis's edge peaks and seams, near ``max_edge`` or not
    (``DimensionSource.SEAMS``), smallest area first.
    """
    if not work.seam_spread:  # no seam search ran: no region to extend
        return []
    cfg = ctx.config
    U, V = _seam_reach(work.peaks_x, cfg), _seam_reach(work.peaks_y, cfg)
    spacing = ctx.verify_ctx.spacing_at(R.origin)
    band = BOUNDARY_BAND * cfg.min_edge
    near = [np.zeros(0), np.zeros(0)]
    reach = cfg.max_edge - 0.9 * cfg.min_edge
    for b, (peaks, seams, across) in enumerate(((work.peaks_x, work.seams_x, V),
                                                (work.peaks_y, work.seams_y, U))):
        # NaN extent (not measured, or the strip left the image): the plane may run on
        if not len(peaks) and not len(seams) and not work.extent[b] <= reach:
            near[b] = _seams_near_max(R, ctx, work, b, across, spacing, band)
    nx, ny = near
    xs = np.r_[work.peaks_x, work.seams_x]
    ys = np.r_[work.peaks_y, work.seams_y]
    pairs = [(a, b) for a in nx for b in np.r_[ys, ny]] + [(a, b) for a in xs for b in ny]
    pairs.sort(key=lambda ab: (ab[0] * ab[1], ab[0]))
    return [_Attempt(DimensionSource.SEAMS, -1, float(a), float(b), np.nan, np.nan)
            for a, b in pairs]


def _seams_near_max(R: Rectangle, ctx: _Context, work: _VertexWork, b: int, across: float,
                    spacing: float, band: float) -> np.ndarray:
    """Seams along axis b (0: x, 1: y) between ``max_edge`` less a short box edge (0.9
    ``min_edge``) and ``max_edge``, where :func:`_seam_peaks`' search cannot show one.

    That search goes on here, as one: the strip read reaches the groove windows' flanks
    either side of the positions (across the arm from ``band`` to ``across``), and the
    statistic keeps that search's noise scale (or the strip's, if larger), its spread and
    a critical value corrected over the whole axis (0.9 ``min_edge`` to ``max_edge``), so a
    short strip neither sees seams the face's own scatter would hide nor tests at a
    laxer level. SEAM_PEAK rows with b = 2 (x), 3 (y).
    """
    cfg = ctx.config
    lo = 0.9 * cfg.min_edge
    flank = (SEAM_FLANK[1] * max(SEAM_SCALES) + 1.0) * spacing
    start = max(cfg.max_edge - lo + 0.5 * spacing, lo)
    a0, a1 = max(start - flank, 0.0), cfg.max_edge + flank
    ur, vr = ((a0, a1), (band, across)) if b == 0 else ((band, across), (a0, a1))
    vc = ctx.verify_ctx
    work.pixels += vc.pixels_in(R.origin, R.x_axis, R.y_axis, ur, vr)
    fp = face_points(vc.points, vc.valid, vc.sigma, vc.project, R.origin, R.x_axis, R.y_axis,
                     R.normal, ur, vr, spacing, cfg.alpha, cfg.noise.row_corr, vc.gain)
    if not len(fp):
        return np.zeros(0)
    coord = fp.u if b == 0 else fp.v
    pos, z, crit = find_seams(coord, fp.w, max(fp.scale, work.seam_scale), start,
                              cfg.max_edge, spacing, vc.seam_alpha, fp.row, fp.row_corr,
                              spread=work.seam_spread[b], level_span=cfg.max_edge - lo)[:3]
    if len(pos):
        work.tests.append(TestTable.decision(TestKind.SEAM_PEAK, R.vertex, 2 + b, z, crit,
                                             True, cfg.alpha))
    return pos


def _soft_votes(x: np.ndarray, sx: np.ndarray, h: float, nbins: int) -> np.ndarray:
    """1-D accumulator of bin width h: each point's vote spread over the bins by its own
    localization error (a normal of std ``sx`` at ``x``), so a blurred edge votes where it
    may lie; a point much sharper than a bin votes into its bin alone (a histogram)."""
    if len(x) == 0:
        return np.zeros(nbins)
    x = np.clip(x, 0.0, nbins * h - 1e-9)
    s = np.maximum(sx, 1e-3 * h)
    # only the bins within 6 sigma of a point get a share (beyond: < 1e-9 of a vote)
    lo = np.clip(np.floor((x - 6.0 * s) / h), 0, nbins - 1).astype(np.int64)
    hi = np.clip(np.floor((x + 6.0 * s) / h), 0, nbins - 1).astype(np.int64)
    # one column more: a bin's upper edge is the next one's lower edge, the same argument
    # to ndtr ((j + 1) h - x), so its values are computed once
    J = lo[:, None] + np.arange(int((hi - lo).max()) + 2)[None, :]
    T = special.ndtr((J * h - x[:, None]) / s[:, None])
    j = J[:, :-1]
    below, above = T[:, :-1].copy(), T[:, 1:].copy()
    # mass beyond the ends stays in the end bins (as the clipped histogram did)
    below[j == 0] = 0.0
    above[j == nbins - 1] = 1.0
    mass = np.where(j <= hi[:, None], above - below, 0.0)
    return np.bincount(np.minimum(j, nbins - 1).ravel(), weights=mass.ravel(), minlength=nbins)


def _peaks(acc: np.ndarray, h: float, lo: float, min_height: float, alpha: float) -> np.ndarray:
    """Positions (metres) of the significant peaks of a 1-D accumulator.

    A peak is a local maximum of the 3-bin window sum that is at least ``min_height`` (the
    support of the shortest side) and significantly above the accumulator's uniform vote
    level (Poisson, maximum over the windows, at level alpha). Its position is the
    centroid of the three bins.
    """
    if acc.size < 3:
        return np.zeros(0)
    s3 = np.convolve(acc, [1, 1, 1], mode="same").astype(np.float64)
    lam = 3.0 * float(acc.sum()) / acc.size
    # the smallest window sum that uniform votes exceed with probability alpha over all bins
    k_sig = poisson_isf(alpha / acc.size, lam) + 1.0 if lam > 0 else 1.0
    left = np.r_[-1, s3[:-1]]
    right = np.r_[s3[1:], -1]
    pk = np.flatnonzero((s3 >= left) & (s3 > right) & (s3 >= max(min_height, k_sig)))
    out = []
    for i in pk:
        a, b = max(int(i) - 1, 0), min(int(i) + 2, acc.size)
        wts = acc[a:b].astype(np.float64)
        pos = (np.arange(a, b) + 0.5) * h
        x = float((wts * pos).sum() / max(wts.sum(), 1e-12))
        if x >= lo:
            out.append(x)
    return np.array(out)


def _norm_isf(alpha: float) -> float:
    return float(norm_isf(alpha))


def _pinv_quad(e: np.ndarray, S: np.ndarray, rank: int) -> float:
    """e^T S^+ e with S's pseudo-inverse of the given rank."""
    w, V = np.linalg.eigh(S)
    w, V = w[-rank:], V[:, -rank:]
    y = V.T @ e
    return float((y**2 / np.maximum(w, 1e-30)).sum())


#: What one piece of the stage's work returns: the vertex's work (or, for its region, what
#: to add to it), its rectangle, and whether a box top was verified.
_Piece = tuple[_VertexWork, Rectangle, bool]


def _work_on_vertex(i: int, ctx: _Context) -> _VertexWork:
    """Lines 3-8 of findgraspablesurfaces for one vertex."""
    work, R, ok = _search_vertex(i, ctx)
    if not ok:
        _add_region(work, _search_region((i, R), ctx)[0])
    return work


def _too_tilted(R: Rectangle, ctx: _Context) -> float | None:
    """R's tilt from up (radians) where it exceeds ``max_tilt``, else None. Every rectangle
    of the vertex shares R's normal, so each would fail VERIFY_TILT first."""
    t = tilt_from_up(R.normal, ctx.verify_ctx.up)
    return t if t > ctx.config.max_tilt else None


def _search_vertex(i: int, ctx: _Context) -> _Piece:
    """The search for a box top at vertex i: dimensions from the diagonal vertices, the
    edges and seams, then the face's extent, until one verifies. A vertex whose plane is
    tilted beyond ``max_tilt`` gets only its HYPOTHESIS_TILT row: no top of it could
    verify."""
    work = _VertexWork(vertex=i)
    R = align(ctx.vertices, i, ctx.normal_cov)
    t = _too_tilted(R, ctx)
    if t is not None:
        work.tests.append(TestTable.decision(TestKind.HYPOTHESIS_TILT, i, -1, t,
                                             ctx.config.max_tilt, False, ctx.config.alpha))
        return work, R, False
    ok, tried = _try_in_turn(R, ctx, work, dimensions_from_vertices(R, ctx, work), MAX_ATTEMPTS)
    if not ok:
        ok, _ = _try_in_turn(R, ctx, work, dimensions_from_edges(R, ctx, work),
                             MAX_ATTEMPTS - tried)
    if not ok:
        # the same rectangle again (within a bin) is no new evidence
        tol = work.acc_bin if np.isfinite(work.acc_bin) else 0.0
        ok, _ = _try_in_turn(R, ctx, work, dimensions_from_extent(R, ctx, work),
                             MAX_EXTENT_ATTEMPTS, tol)
    if not ok:
        ok, _ = _try_in_turn(R, ctx, work, dimensions_near_max_edge(R, ctx, work),
                             MAX_EXTENT_ATTEMPTS, tol)
    return work, R, ok


def _search_region(item: tuple[int, Rectangle], ctx: _Context) -> _Piece:
    """The flat region at a vertex where no box top verified (what the vertex's work gains:
    :func:`_add_region`). It is never a surface, so no neighbour's corner comes from it,
    and it can wait until every vertex has been searched for a box top."""
    i, R = item
    work = _VertexWork(vertex=i)
    if _too_tilted(R, ctx) is not None:  # recorded by the vertex's own search
        return work, R, False
    whole = False
    for att in dimensions_from_region(R, ctx, work):
        if att.source == DimensionSource.ROW and whole:
            break  # rows stand in for a region that does not verify whole
        _verify(R, att, ctx, att.inner)
        work.pixels += _verified_pixels(R, att, ctx)
        out = att.outcome
        assert out is not None
        if out.accepted:  # a verified region larger than a box is never a surface
            whole = att.source == DimensionSource.REGION
            att.outcome = dataclasses.replace(out, accepted=False,
                                              reason=VerifyReason.AMBIGUOUS)
            att.threshold = float(AmbiguityReason.LARGER_THAN_MAX_BOX if whole
                                  else np.nan)
        work.attempts.append(att)
    rows = [a for a in work.attempts if a.source == DimensionSource.ROW
            and a.outcome is not None and a.outcome.reason == VerifyReason.AMBIGUOUS]
    if len(rows) == 2 and not _same_corner_carton(rows[0], rows[1],
                                                  ctx.config.size_tolerance):
        for a in rows:  # the two rows lay the corner's carton differently: neither holds
            a.support, a.threshold = -1.0, float(AmbiguityReason.SEVERAL_TILINGS)
    return work, R, False


def _row_end(R: Rectangle, ctx: _Context, arm: int, L: float, n: int) -> TestTable:
    """The ROW_END row of R's side along ``arm`` (0: x, 1: y), ``L`` metres and ``n``
    cartons long: whether a vertex stands at its far end, a corner of the region that was
    seen (its arms back along the side and on along R's other arm, within 60 degrees as
    for a diagonal vertex), by the chi-square of its position in R's plane."""
    V, cfg = ctx.vertices, ctx.config
    along, other = (R.x_axis, R.y_axis) if arm == 0 else (R.y_axis, R.x_axis)
    idx = np.array([j for j in range(len(V)) if j != R.vertex], np.int64)
    if len(idx):
        back = ((V.d1[idx] @ along < -0.5) & (V.d2[idx] @ other > 0.5)) | (
            (V.d2[idx] @ along < -0.5) & (V.d1[idx] @ other > 0.5))
        idx = idx[back]
    if not len(idx):
        return TestTable.chi2(TestKind.ROW_END, R.vertex, -1, np.inf, 2.0, cfg.alpha)
    D = V.points[idx] - (R.origin + L * along)
    S = V.covariances[idx][:, :3, :3] + V.covariances[R.vertex][:3, :3]
    var_a = np.einsum("i,nij,j->n", along, S, along) + n * cfg.size_tolerance**2
    var_o = np.einsum("i,nij,j->n", other, S, other)
    T = (D @ along) ** 2 / var_a + (D @ other) ** 2 / np.maximum(var_o, 1e-30)
    k = int(np.argmin(T))
    return TestTable.chi2(TestKind.ROW_END, R.vertex, int(idx[k]), float(T[k]), 2.0,
                          cfg.alpha)


#: Pixels inside the image's border every corner of a ROW must project: a side that runs
#: to the border ends there in the scan, not necessarily on the pallet, and the cartons at
#: its end may run on out of sight.
ROW_BORDER_PX = 3.0


def _in_image(scan: Scan, corners: np.ndarray) -> bool:
    """Whether every corner (k, 3) projects ``ROW_BORDER_PX`` or more inside the image."""
    uv = scan.sensor.project(corners)
    H, W = scan.shape[:2]
    m = ROW_BORDER_PX
    return bool(np.isfinite(uv).all() and (uv[:, 0] >= m).all() and (uv[:, 0] <= W - 1 - m).all()
                and (uv[:, 1] >= m).all() and (uv[:, 1] <= H - 1 - m).all())


def _same_corner_carton(a: _Attempt, b: _Attempt, tol: float) -> bool:
    """Whether two rows from one vertex put the same carton at its corner (their
    ``carton`` extents along x and y within ``3 tol``)."""
    return bool(np.all(np.abs(np.subtract(a.carton, b.carton)) <= 3.0 * tol))


def _add_region(work: _VertexWork, region: _VertexWork) -> None:
    """The region's tests and attempts after the vertex's own (where a search without a
    budget puts them)."""
    work.tests += region.tests
    work.attempts += region.attempts
    work.pixels += region.pixels


def _try_in_turn(R: Rectangle, ctx: _Context, work: _VertexWork, cands: list[_Attempt],
                 budget: int, same: float = -1.0) -> tuple[bool, int]:
    """Verify candidates in order until one is accepted or ``budget`` were verified; a
    candidate within ``same`` metres of one already tried in both dimensions is skipped.
    Returns whether one was accepted, and how many were verified.

    A candidate rejected for a seam at its middle (:func:`_midline_half`) is followed by
    its half at the vertex, before the rest."""
    tried = 0
    queue = deque(cands)
    while queue:
        att = queue.popleft()
        if tried >= budget:
            break
        if any(abs(att.width - a.width) <= same and abs(att.length - a.length) <= same
               for a in work.attempts):
            continue
        tried += 1
        _verify(R, att, ctx)
        work.pixels += _verified_pixels(R, att, ctx)
        work.attempts.append(att)
        if att.outcome is not None and att.outcome.accepted:
            return True, tried
        half = _midline_half(att)
        if half is not None:
            queue.appendleft(half)
    return False, tried


def _midline_half(att: _Attempt) -> _Attempt | None:
    """The part at the vertex of a candidate whose verification found the seams of n equal
    boxes in a row (VERIFY_SEAM_MIDLINE rejected along x, y or both: two boxes, or four,
    side by side; or three in a row): the nearest seam is the box's far side, as
    significant as the test that rejected the whole. Its own verification tests it as a
    side. Along each axis the fewest parts whose seams showed: the quarters' lines include
    the middle, whose seam alone can lift their sum, and four boxes are halved twice.
    None where no midline row rejected."""
    out = att.outcome
    if out is None or out.reason != VerifyReason.INTERIOR_SEAM:
        return None
    rows = out.tests.of_kind(TestKind.VERIFY_SEAM_MIDLINE)
    split = rows.b[~rows.accepted]
    if not len(split):
        return None
    parts = [min((int(b) // 2 + 2 for b in split if b % 2 == axis), default=1)
             for axis in (0, 1)]
    w, ln = att.width / parts[0], att.length / parts[1]
    # the attempt's support: the strongest of the rows that chose its parts
    used = ~rows.accepted & (rows.b // 2 + 2 == np.take(parts, rows.b % 2))
    k = int(np.argmax(np.where(used, rows.statistic - rows.critical, -np.inf)))
    return _Attempt(DimensionSource.MIDLINE, -1, w, ln, float(rows.statistic[k]),
                    float(rows.critical[k]))


def _verify(R: Rectangle, att: _Attempt, ctx: _Context,
            size_sides: frozenset[int] = frozenset(), family: int = 1) -> None:
    # a part's sides that are not cuts lie on its region's verified outline
    outline = (frozenset(range(4)) - size_sides if att.source in SPLIT_SOURCES
               else frozenset())
    att.outcome = verify(ctx.scan, ctx.verify_ctx, R.origin, R.x_axis, R.y_axis, R.normal,
                         att.width, att.length, R.plane_cov, ctx.config, attempt_id=-1,
                         size_sides=size_sides, family=family,
                         region=att.source in (DimensionSource.REGION, DimensionSource.ROW),
                         region_sides=outline)


def _verified_pixels(R: Rectangle, att: _Attempt, ctx: _Context) -> float:
    """Pixels the verification of ``att`` read: its rectangle's, unless it stopped before
    reading any range point (tilted, or an edge line inside)."""
    out = att.outcome
    if out is None or out.reason in (VerifyReason.TILTED, VerifyReason.INTERIOR_EDGES):
        return 0.0
    return ctx.verify_ctx.pixels_in(R.origin, R.x_axis, R.y_axis, (0.0, att.width),
                                    (0.0, att.length))


_WORKER_CTX: list[_Context] = []
#: the end of the items of :meth:`_PixelBudget._run`
_END = object()


def _init_worker(ctx: _Context) -> None:
    _WORKER_CTX[:] = [ctx]


def _work_chunk(ids: list[int]) -> list[_VertexWork]:
    ctx = _WORKER_CTX[0]
    return [_work_on_vertex(i, ctx) for i in ids]


def _in_worker(fn: Callable[[Any, _Context], _Piece], item: Any) -> _Piece:
    return fn(item, _WORKER_CTX[0])


def generate_hypotheses(
    scan: Scan, edges: EdgeMap, vertices: VertexSet, *, config: Config,
    up: np.ndarray | None = None, gain: np.ndarray | None = None,
) -> tuple[VertexSet, HypothesisSet, Verification]:
    """One hypothesis per vertex with its dimensions, and the verification of every attempt.

    The vertices of two lines come first. Then, round by round, the corners of each
    verified rectangle's seam sides become vertices of the touching neighbour beyond
    (:func:`neighbour_vertices`), and get hypotheses of their own, until a round adds
    none or ``MAX_NEIGHBOUR_ROUNDS`` have run.

    Parameters
    ----------
    scan : Scan
    edges : EdgeMap
    vertices : VertexSet
        From the vertex stage.
    config : Config
    up : ndarray (3,), optional
        Up in the sensor frame (default ``scan.up``), for the tilt prior.
    gain : (H, W) float64, optional
        :func:`boxloc.stages.edges.noise_gain` of the scan and config, if already computed
        (the pipeline's: the edge stage used the same).

    Returns
    -------
    VertexSet
        ``vertices`` and the neighbours' corners after them (``parent`` >= 0); hypothesis
        i belongs to vertex i.
    HypothesisSet, Verification
    """
    up = scan.up if up is None else np.asarray(up, dtype=np.float64)
    ctx = _Context.build(scan, edges, vertices, config, up, gain)
    budget = _VertexBudget(config.max_vertices)
    pixels = _PixelBudget(config.max_hypothesis_work)
    ids = range(len(vertices))
    works = _work_on(ids, pixels.order(budget.take(ids, ctx.vertices, up), ctx.vertices, up),
                     ctx, pixels)
    new_from = 0
    for _ in range(MAX_NEIGHBOUR_ROUNDS):
        V = neighbour_vertices(ctx.vertices, works, new_from, config)
        new_from = len(ctx.vertices)
        if len(V) == len(ctx.vertices):
            ctx = dataclasses.replace(ctx, vertices=V)
            break
        ctx = dataclasses.replace(ctx, vertices=V, normal_cov=normal_covariance(V))
        ids = range(new_from, len(V))
        works += _work_on(ids, pixels.order(budget.take(ids, V, up), V, up), ctx, pixels)
    pixels.regions(works, ctx)
    ctx, works = _split_regions(ctx, works)
    _seams_in_line(ctx, works)
    repeated = _multiples_of_neighbours(ctx, works)
    sizes, seen_rows = _seen_cartons(ctx, works, repeated)
    if sizes:
        # the flat regions split by the scan's own cartons, as by a carton list
        listed = dataclasses.replace(ctx, config=dataclasses.replace(config, box_sizes=sizes),
                                     seen_sizes=True)
        ctx, works = _split_regions(listed, works, convert=False)
        ctx = dataclasses.replace(ctx, config=config, seen_sizes=False)
    hyps, ver = _assemble(works, ctx.vertices, config, up)
    rows = [TestTable.budget(BUDGET_HYPOTHESES, budget.needed, budget.budget, budget.exhausted,
                             config.alpha),
            TestTable.budget(BUDGET_HYPOTHESIS_WORK, pixels.spent, pixels.budget,
                             pixels.exhausted, config.alpha)]
    hyps = dataclasses.replace(hyps, tests=TestTable.concat([hyps.tests, seen_rows, *rows],
                                                            config.alpha))
    return ctx.vertices, hyps, ver


@dataclass
class _VertexBudget:
    """``Config.max_vertices``: how many vertices get their rectangles searched (0: all)."""

    budget: int
    done: int = 0
    needed: int = 0
    exhausted: bool = False

    def take(self, ids: range, vertices: VertexSet, up: np.ndarray) -> list[int]:
        """The ``ids`` to work on, in order: over the budget, the highest vertices (along
        ``up``), as graspable tops are on top of the pile."""
        ids_l = list(ids)
        self.needed += len(ids_l)
        room = len(ids_l) if not self.budget else max(0, self.budget - self.done)
        if room >= len(ids_l):
            self.done += len(ids_l)
            return ids_l
        self.exhausted = True
        height = vertices.points[ids_l] @ up
        self.done += room
        return sorted(ids_l[j] for j in np.argsort(-height, kind="stable")[:room])


@dataclass
class _PixelBudget:
    """``Config.max_hypothesis_work``: pixels the rectangle searches of all vertices may read
    (0: no budget).

    Under a budget the work is done in order of value, each piece whole, while the pixels
    read so far are below the budget: in each round the search of every vertex for a box
    top, the highest first (:meth:`order`); after the last round the flat regions of the
    vertices where none verified (never surfaces). What is left gets no work. Each
    vertex's work does not depend on the others', so a scan under the budget has the
    products of a run without it.
    """

    budget: int
    spent: int = 0
    exhausted: bool = False
    #: the vertices (and rectangles) whose flat region waits for :meth:`regions`
    pending: list[tuple[int, Rectangle]] = field(default_factory=list)

    def order(self, todo: list[int], vertices: VertexSet, up: np.ndarray) -> list[int]:
        """``todo`` in the order to work on them: under a budget the highest (along ``up``)
        first, as graspable tops are on top of the pile (ties by id)."""
        if not self.budget or len(todo) < 2:
            return todo
        height = vertices.points[todo] @ up
        return [todo[j] for j in np.argsort(-height, kind="stable")]

    def search(self, ids: list[int], ctx: _Context) -> list[_VertexWork]:
        """The work on ``ids`` (in working order) within the budget."""
        if not self.budget:
            return _work_on_ids(ids, ctx)
        pieces = self._run(_search_vertex, ids, ctx)
        self.pending += [(w.vertex, R) for w, R, ok in pieces if not ok]
        return [w for w, _, _ in pieces]

    def regions(self, works: list[_VertexWork], ctx: _Context) -> None:
        """The pending flat regions, added to their vertices' work, within the budget."""
        by_vertex = {w.vertex: w for w in works}
        for region, _, _ in self._run(_search_region, self.pending, ctx):
            _add_region(by_vertex[region.vertex], region)
        self.pending = []

    def _run(self, fn: Callable[[Any, _Context], _Piece], items: list[Any], ctx: _Context
             ) -> list[_Piece]:
        """``fn`` on each item in order while there is room. With ``workers`` processes a
        window of two items per worker runs ahead, and the pieces are taken in order as a
        serial run would (one started after the budget ran out is dropped)."""
        out: list[_Piece] = []
        nw = ctx.config.workers
        if nw > 1 and len(items) > 1:
            with ProcessPoolExecutor(nw, initializer=_init_worker, initargs=(ctx,)) as ex:
                ahead: deque[Future[_Piece]] = deque()
                todo = iter(items)
                while True:
                    while self._room and len(ahead) < 2 * nw:
                        item = next(todo, _END)
                        if item is _END:
                            break
                        ahead.append(ex.submit(_in_worker, fn, item))
                    if not ahead or not self._room:
                        break
                    out += self._admit(ahead.popleft().result())
                for f in ahead:
                    f.cancel()
        else:
            for item in items:
                if not self._room:
                    break
                out += self._admit(fn(item, ctx))
        if len(out) < len(items):
            self.exhausted = True
        return out

    @property
    def _room(self) -> bool:
        return self.spent < self.budget

    def _admit(self, piece: _Piece) -> list[_Piece]:
        """``[piece]``, its pixels spent, if it started while there was room; else ``[]``."""
        if not self._room:
            return []
        self.spent += int(round(piece[0].pixels))
        return [piece]


def _work_on(ids: range, todo: list[int], ctx: _Context, pixels: _PixelBudget
             ) -> list[_VertexWork]:
    """The work on each vertex of ``ids``, in order; those not in ``todo`` (over the vertex
    budget) or not reached within the pixel budget get none."""
    done = {w.vertex: w for w in pixels.search(todo, ctx)}
    return [done.get(i) or _VertexWork(vertex=i) for i in ids]


def _work_on_ids(ids: list[int], ctx: _Context) -> list[_VertexWork]:
    config = ctx.config
    if config.workers > 1 and len(ids) > 1:
        chunks = [ids[k :: config.workers] for k in range(config.workers)]
        with ProcessPoolExecutor(config.workers, initializer=_init_worker, initargs=(ctx,)) as ex:
            parts = list(ex.map(_work_chunk, chunks))
        by_id = {w.vertex: w for part in parts for w in part}
        return [by_id[i] for i in ids]
    return [_work_on_vertex(i, ctx) for i in ids]


def _accepted(w: _VertexWork) -> _Attempt | None:
    return next((a for a in w.attempts if a.outcome is not None and a.outcome.accepted), None)


def _corner(C: np.ndarray, u: float, v: float, tol: float) -> np.ndarray:
    """Position covariance (3, 3) of the corner u d1 + v d2 of a verified rectangle whose
    vertex has joint covariance C (9, 9): the vertex's point, and the arms' direction
    error, which verification bounded to the angle tolerance, times the lengths."""
    return C[:3, :3] + (u * u + v * v) * tol * tol * np.eye(3)


def neighbour_vertices(vertices: VertexSet, works: list[_VertexWork], new_from: int,
                       config: Config) -> VertexSet:
    """``vertices`` and, after them, the corners of touching neighbours across seams.

    A side of a verified rectangle that is a seam (``VERIFY_SEAM_SIDE``) as strong as the
    search for one inside the rectangle had to find, beyond which the face's plane runs on
    (``VERIFY_CONTINUATION`` at least ``NEIGHBOUR_RUNS_ON``: a neighbour of equal
    height), is a side of that neighbour too, and its two ends are two of the neighbour's
    corners: one vertex each, with its arms across the seam and along it. Those are the
    corners the line stage misses when both sides are seams (an interior box of a neat
    layer).

    A corner is not added where the neighbour has been found already (a verified
    rectangle, that no strong seam crosses, covers its quadrant just beyond it) or has a
    vertex already (one of the same quadrant coincides with it: chi2 of the positions,
    3 dof, at alpha). Every corner offered is a ``NEIGHBOUR_CORNER`` test row.

    Parameters
    ----------
    vertices : VertexSet
        All vertices so far; ``works[i]`` is vertex i's.
    works : list
        The work of every vertex so far.
    new_from : int
        Corners are offered from ``works[new_from:]`` (the last round's).
    config : Config

    Notes
    -----
    The new vertex's position covariance is the parent's point's, and the angle tolerance
    times the distance along the arms (:func:`_corner`); its directions keep the parent's
    covariances.
    """
    alpha = config.alpha
    crit = chi2_critical(3.0, alpha)
    k = math.sqrt(chi2_critical(1.0, alpha))
    tol = config.angle_tolerance
    pts, D1, D2, N, COV = (list(vertices.points), list(vertices.d1), list(vertices.d2),
                           list(vertices.normals), list(vertices.covariances))
    parent: list[int] = []  # of each new corner, and its seam side
    side_of: list[int] = []
    # the verified rectangles that no strong seam crosses (one that is crossed will be
    # rejected, and must not hide its neighbours)
    acc = [(w.vertex, a) for w in works if (a := _accepted(w)) is not None]
    cross = _crossings([(vertices.points[i], vertices.d1[i], vertices.d2[i], a)
                        for i, a in acc], config)
    found = [(i, a) for (i, a), (_, _, crosses) in zip(acc, cross) if not crosses]
    mi, probe = BOUNDARY_BAND * config.min_edge, 0.75 * config.min_edge
    fi = np.array([i for i, _ in found], np.int64)
    f_wl = np.array([(a.width, a.length) for _, a in found], np.float64).reshape(-1, 2)
    f_c = np.array([a.outcome.plane_center for _, a in found]).reshape(-1, 3)  # type: ignore
    f_n = np.array([a.outcome.plane_normal for _, a in found]).reshape(-1, 3)  # type: ignore
    f_sig = np.array([face_sigma(config, c) for c in f_c])

    def covered(p: np.ndarray, d1: np.ndarray, d2: np.ndarray) -> int:
        """The vertex whose verified rectangle covers the quadrant at p, or -1."""
        if not len(fi):
            return -1
        q = p + probe * (d1 + d2)  # inside any box there, beyond the band of its sides
        dq = q - vertices.points[fi]
        u = np.einsum("ij,ij->i", dq, vertices.d1[fi])
        v = np.einsum("ij,ij->i", dq, vertices.d2[fi])
        on = np.abs(np.einsum("ij,ij->i", q - f_c, f_n)) <= k * f_sig
        hit = np.flatnonzero((u > mi) & (u < f_wl[:, 0] - mi) & (v > mi)
                             & (v < f_wl[:, 1] - mi) & on)
        return int(fi[hit[0]]) if len(hit) else -1

    n0 = len(pts)
    base = (np.asarray(pts).reshape(-1, 3), np.asarray(D1).reshape(-1, 3),
            np.asarray(D2).reshape(-1, 3), np.asarray(COV).reshape(-1, 9, 9)[:, :3, :3])

    def nearest(p: np.ndarray, d1: np.ndarray, d2: np.ndarray, S: np.ndarray
                ) -> tuple[float, int]:
        """chi2 (3 dof) and id of the nearest vertex of the same quadrant, else (inf, -1)."""
        P, A1, A2, C3 = base
        if len(pts) > n0:  # the corners added in this call
            P, A1, A2 = (np.r_[P, pts[n0:]], np.r_[A1, D1[n0:]], np.r_[A2, D2[n0:]])
            C3 = np.r_[C3, np.asarray(COV[n0:])[:, :3, :3]]
        same = np.flatnonzero((A1 @ d1 >= 0.5) & (A2 @ d2 >= 0.5))
        if not len(same):
            return np.inf, -1
        dp = p - P[same]
        # a micrometre of slack keeps a degenerate covariance solvable
        x = np.linalg.solve(C3[same] + S + 1e-12 * np.eye(3), dp[..., None])[..., 0]
        c2 = np.einsum("ij,ij->i", dp, x)
        b = int(np.argmin(c2))
        return float(c2[b]), int(same[b])

    rows: list[tuple[int, int, float]] = []
    for w in works[new_from:]:
        att = _accepted(w)
        if att is None:
            continue
        i = w.vertex
        t = att.outcome.tests  # type: ignore[union-attr]
        seam = t.of_kind(TestKind.VERIFY_SEAM_SIDE)
        crit_in = t.of_kind(TestKind.VERIFY_SEAM_INTERIOR).critical
        strong = seam.accepted & (seam.statistic >= (crit_in.max() if len(crit_in) else np.inf))
        cont = t.of_kind(TestKind.VERIFY_CONTINUATION)
        runs_on = {int(b) for b, f in zip(cont.b, cont.statistic) if f >= NEIGHBOUR_RUNS_ON}
        o, x, y, n = vertices.points[i], vertices.d1[i], vertices.d2[i], vertices.normals[i]
        C = vertices.covariances[i]
        W, L = att.width, att.length
        uv = ((0.0, 0.0), (W, 0.0), (W, L), (0.0, L))  # the corners in the rectangle's frame
        for si in sorted({int(b) for b in seam.b[strong]} & runs_on):
            ends = tuple(uv[k] for k in SIDE_CORNERS[si])
            out, along_x = (-y, y, -x, x)[si], si < 2
            for e, (u, v) in enumerate(ends):
                p = o + u * x + v * y
                u2, v2 = ends[1 - e]
                d2 = (u2 - u) * x + (v2 - v) * y
                d2 = d2 / np.linalg.norm(d2)
                d1 = out.copy()
                # the outward arm is +-y (side along x) or +-x, the other along the side
                s_out, s_along = ((C[6:, 6:], C[3:6, 3:6]) if along_x
                                  else (C[3:6, 3:6], C[6:, 6:]))
                if np.cross(d1, d2) @ n < 0:  # keep the normal toward the sensor
                    d1, d2, s_out, s_along = d2, d1, s_along, s_out
                cov = np.zeros((9, 9))
                cov[:3, :3] = _corner(C, u, v, tol)
                cov[3:6, 3:6], cov[6:, 6:] = s_out, s_along
                best_j = covered(p, d1, d2)
                if best_j >= 0:  # the neighbour is found already
                    best = 0.0
                else:
                    best, best_j = nearest(p, d1, d2, cov[:3, :3])
                rows.append((i, best_j, best))
                if best <= crit:
                    continue
                pts.append(p)
                D1.append(d1)
                D2.append(d2)
                N.append(n)
                COV.append(cov)
                parent.append(i)
                side_of.append(si)
    n_new = len(pts) - len(vertices)
    tests = vertices.tests
    if rows:
        r = np.array(rows)
        tests = TestTable.concat([tests, TestTable.chi2(
            TestKind.NEIGHBOUR_CORNER, r[:, 0].astype(np.int32), r[:, 1].astype(np.int32),
            r[:, 2], 3.0, alpha)], alpha)
    new = list(zip(pts[n0:], D1[n0:], D2[n0:], N[n0:], COV[n0:]))
    return append_vertices(vertices, new, [-1] * n_new, [-1] * n_new, parent, side_of,
                           tests)


def _multiples_as_regions(works: list[_VertexWork], config: Config) -> set[int]:
    """With a carton list, a verified rectangle that is a multiple of a listed size
    (:func:`boxloc.stages.sizes.region_splits`) is a flat region, not a box: it becomes a
    REGION attempt (``VerifyReason.AMBIGUOUS``), to be split or left ambiguous. Among
    them, the ids of those whose size is itself listed (SKU_SIZE accepts): one box is
    one way to cut them.

    A rectangle of two touching cartons that show no seam, no longer than ``max_edge``,
    verifies like one box; only the list tells it is two.
    """
    single: set[int] = set()
    if not config.box_sizes:
        return single
    for w in works:
        a = _accepted(w)
        if a is None or a.source == DimensionSource.REGION:
            continue
        if not region_splits(a.width, a.length, config.box_sizes, config.size_tolerance,
                             config.alpha):
            continue
        if match_size(a.width, a.length, config.box_sizes, config.size_tolerance,
                      config.alpha)[3]:
            single.add(id(a))
        assert a.outcome is not None
        a.outcome = dataclasses.replace(a.outcome, accepted=False,
                                        reason=VerifyReason.AMBIGUOUS)
        a.source, a.support, a.threshold = DimensionSource.REGION, 0.0, np.nan
    return single


def _attempt_ids(works: list[_VertexWork]) -> dict[int, int]:
    """Each attempt's id (by ``id`` of the object) as :func:`_assemble` numbers them."""
    return {id(t): k for k, t in enumerate(t for w in works for t in w.attempts)}


def _verified_boxes(works: list[_VertexWork]) -> list[tuple[int, _Attempt]]:
    """(vertex, attempt) of each vertex's accepted rectangle that is not a region or row."""
    return [(w.vertex, a) for w in works if (a := _accepted(w)) is not None
            and a.source not in (DimensionSource.REGION, DimensionSource.ROW)]


def _centre(vertices: VertexSet, i: int, a: _Attempt) -> np.ndarray:
    """The centre of attempt a's rectangle at vertex i, (3,) metres."""
    return rectangle_corners(vertices.points[i], vertices.d1[i], vertices.d2[i],
                             a.width, a.length).mean(0)


def _in_core(vertices: VertexSet, c: np.ndarray, i: int, a: _Attempt, margin: float) -> bool:
    """Whether point c lies inside attempt a's rectangle at vertex i, ``margin`` metres
    clear of its sides."""
    d = c - vertices.points[i]
    u, v = d @ vertices.d1[i], d @ vertices.d2[i]
    return bool(margin < u < a.width - margin and margin < v < a.length - margin)


def _distinct_regions(works: list[_VertexWork], vertices: VertexSet,
                      min_edge: float) -> list[list[tuple[int, _Attempt]]]:
    """The verified flat regions (``VerifyReason.AMBIGUOUS`` REGION attempts), grouped by
    region: the first found, then the same region found again from its other corners
    (each centre inside the other, beyond ``BOUNDARY_BAND`` ``min_edge`` of its sides),
    which are marked duplicates (``support`` -1). Each is a (vertex, attempt) pair."""
    groups: list[list[tuple[int, _Attempt, np.ndarray]]] = []
    mi = BOUNDARY_BAND * min_edge
    for w in works:
        for a in w.attempts:
            if (a.source not in (DimensionSource.REGION, DimensionSource.ROW)
                    or a.outcome is None or a.outcome.reason != VerifyReason.AMBIGUOUS
                    or a.support < 0):  # two rows at one corner that disagree
                continue
            i = w.vertex
            c = _centre(vertices, i, a)
            g = next((g for g in groups if _in_core(vertices, c, g[0][0], g[0][1], mi)
                      and _in_core(vertices, g[0][2], i, a, mi)), None)
            if g is None:
                groups.append([(i, a, c)])
            else:
                a.support = -1.0
                g.append((i, a, c))
    return [[(i, a) for i, a, _ in g] for g in groups]


_Seam = Callable[..., tuple[float, float]]


def _region_seams(R: Rectangle, att: _Attempt, ctx: _Context) -> _Seam:
    """The groove statistic along a line of a region, however weak: ``seam(axis, at,
    start, end, halves=False)`` is (z, critical) of :func:`boxloc.stages.verify.seam_line`
    at the seam level along ``u = at`` (``axis`` 0) or ``v = at`` (1), over the region's
    points from ``start`` to ``end`` along it (metres in ``R``'s frame); NaN, NaN without
    points.

    As a side's seam is tested: along the whole line (both halves must show it, so a seam
    that crosses it, between two cartons turned across it, is no seam along it), over the
    statistic's robust spread along the whole region (:func:`boxloc.stages.seams.
    face_spread`: correlated depth noise spreads it beyond N(0, 1)). A grid's cut asks
    each half for its share too (``halves``, :func:`_cut_evidence`), so that a deep seam
    along half a cut does not carry the cut across a turned carton's middle (development
    packed seed 1, scene 126: a basket weave split as the grid of its outline, four
    wrong rectangles). A carton's side in a seen tiling does not: the tiling needs every
    one of them, and on a development laser weave with bulged lids (packed ``--n 4
    --interlocked 64`` seed 2, scene 16) two of its true sides, seen at z 4.0-4.1 against
    3.74, fell below with it and the layer went from 4 tops found to none."""
    vc = ctx.verify_ctx
    spacing = vc.spacing_at(R.origin + 0.5 * att.width * R.x_axis + 0.5 * att.length * R.y_axis)
    fp = face_points(vc.points, vc.valid, vc.sigma, vc.project, R.origin, R.x_axis, R.y_axis,
                     R.normal, (0.0, att.width), (0.0, att.length), spacing, ctx.config.alpha,
                     ctx.config.noise.row_corr, vc.gain)
    spreads: dict[int, tuple[float, ...]] = {}
    memo: dict[tuple[int, float, float, float, bool], tuple[float, float]] = {}

    def seam(axis: int, at: float, start: float, end: float, halves: bool = False
             ) -> tuple[float, float]:
        if not len(fp):
            return np.nan, np.nan
        key = (axis, at, start, end, halves)
        if key not in memo:
            if axis not in spreads:
                size, ext = (att.width, att.length) if axis == 0 else (att.length, att.width)
                spreads[axis] = whole_face_spread(fp, axis, size, ext, spacing)
            memo[key] = seam_line(fp, axis, at, end, spacing, vc.seam_alpha,
                                  spread=spreads[axis], start=start, halves=halves)
        return memo[key]

    return seam


def _cut_evidence(seam: _Seam, att: _Attempt, cuts_x: list[float], cuts_y: list[float]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(z, critical) of ``seam`` (:func:`_region_seams`) along each whole cut of a grid,
    the cuts along x then y, each half showing its share (``halves``)."""
    zz = [seam(0, c, 0.0, att.length, halves=True) for c in cuts_x] + \
        [seam(1, c, 0.0, att.width, halves=True) for c in cuts_y]
    return (np.array([p[0] for p in zz], np.float64),
            np.array([p[1] for p in zz], np.float64))


def _too_low(R: Rectangle, att: _Attempt, ctx: _Context, listed: float,
             skip: frozenset[int] = frozenset()) -> TestTable | None:
    """Whether a region stands at least a listed carton's height above what lies beyond
    its sides, as a layer of those cartons must (a bare pallet, 0.144 m above the floor,
    is a flat region of about a multiple of many sizes).

    The smallest step down beyond its four sides (:func:`boxloc.stages.height.
    step_height`) against the listed height: a BOX_HEIGHT row (b = ``HeightSource.STEP``,
    statistic the step, critical the listed height less z at alpha of both
    uncertainties; for a carton listed without a height, a pallet's height,
    ``PALLET_HEIGHT``, plus them: its layer stands on a pallet, higher above the floor
    than the pallet alone), rejected if the region is too low, so a bare pallet is not
    split into cartons. None where no step is seen (a wall or a taller neighbour beyond
    every side, or the pallet on a stand). Sides in ``skip`` (a row's far side, inside
    the layer) are not looked beyond.
    """
    cfg = ctx.config
    out = att.outcome
    assert out is not None
    k = math.sqrt(chi2_critical(1.0, cfg.alpha))
    C = rectangle_corners(R.origin, R.x_axis, R.y_axis, att.width, att.length)
    steps = [step_height(ctx.verify_ctx, C, si, out.plane_center, out.plane_normal, R.x_axis,
                         R.y_axis, att.width, att.length, 0.5 * cfg.min_edge, k,
                         cfg.flatness, cfg.min_inlier_fraction)[:2]
             for si in range(4) if si not in skip]
    seen = [(h, s) for h, s in steps if np.isfinite(h)]
    if not seen:
        return None
    h, s = min(seen)
    z = _norm_isf(cfg.alpha) * math.hypot(s, cfg.size_tolerance)
    # at least the listed height; without one, significantly more than a pallet's
    crit = listed - z if np.isfinite(listed) else PALLET_HEIGHT + z
    return TestTable.decision(TestKind.BOX_HEIGHT, -1, int(HeightSource.STEP), h, crit,
                              h >= crit, cfg.alpha)


#: Corners of one flat region its split is tried from: a rectangle has four.
MAX_REGION_CORNERS = 4

_Part = tuple[tuple[np.ndarray, ...], int, _Attempt, frozenset[int]]  # vertex, parent, plan, cut


def _plan_split(ctx: _Context, h: int, att: _Attempt, single: set[int]) -> list[_Part]:
    """The parts of one flat region (REGION attempt ``att`` at vertex ``h``) by the carton
    list, measured from that vertex's corner; [] where it is not split (``att.threshold``
    then says why). See :func:`_split_regions`."""
    cfg = ctx.config
    vertices = ctx.vertices
    out = att.outcome
    assert out is not None
    R = align(vertices, h, ctx.normal_cov)
    # a row of one carton is one (its depth is the list's): a split of 1 x 1
    splits = distinct(region_splits(att.width, att.length, cfg.box_sizes,
                                    cfg.size_tolerance, cfg.alpha,
                                    multiples_only=att.source != DimensionSource.ROW))
    if not splits:
        att.threshold = float(AmbiguityReason.NOT_A_MULTIPLE_OF_A_SIZE)
        return []
    evidence = []
    seam = _region_seams(R, att, ctx)
    for sp in splits:
        ax, bx = att.width / sp.nx, att.length / sp.ny  # the measured part
        z, zc = _cut_evidence(seam, att, [ax * i for i in range(1, sp.nx)],
                              [bx * j for j in range(1, sp.ny)])
        evidence.append((z, zc, bool(len(z)) and bool(np.all(z > zc))))
    seen = [i for i, e in enumerate(evidence) if e[2]]
    tiling = None
    if len(seen) == 1:
        pick = seen[0]  # every cut's seam seen: each cell is one carton, the grid
    elif len(splits) == 1 and id(att) not in single:
        pick = 0
    else:  # several ways to cut it (one box of a listed size among them), no seam shown
        att.threshold = float(AmbiguityReason.SEVERAL_SPLITS)
        return []
    sp, (z, zc, _) = splits[pick], evidence[pick]
    if not seen:
        # not every seam shown: the grid only if no other tiling fits its outline and the
        # seams that are
        ok = z > zc
        seams = ([i * sp.a for i in range(1, sp.nx) if ok[i - 1]],
                 [j * sp.b for j in range(1, sp.ny) if ok[sp.nx - 2 + j]])
        tiling = other_tiling(sp, cfg.box_sizes, cfg.size_tolerance, seams=seams)
    rows = [TestTable.chi2(TestKind.SKU_SIZE, -1, sp.sku, sp.statistic, 2.0, cfg.alpha),
            TestTable.decision(TestKind.SKU_SPLIT_SEAM, -1, np.arange(len(z)), z, zc,
                               z > zc, cfg.alpha)]
    cells: list[tuple[float, float, float, float, frozenset[int]]] | None = None
    if tiling is not None:
        rows.append(TestTable.decision(
            TestKind.SKU_TILING, -1, sp.sku,
            np.nan if tiling.exhausted else float(tiling.turned), 0.0, tiling.unique,
            cfg.alpha))
        if not tiling.unique:
            # another tiling fits the outline: the layer is the one its seams show, if one
            cells, seen_rows = _seen_tiling(sp, att, seam, cfg, len(z))
            rows += seen_rows
            if cells is None:
                att.outcome = dataclasses.replace(
                    out, tests=TestTable.concat([out.tests, *rows], cfg.alpha))
                att.threshold = float(AmbiguityReason.SEVERAL_TILINGS)
                return []
    low = _too_low(R, att, ctx, cfg.box_sizes[sp.sku][2], skip=att.inner)
    if low is not None:
        rows.append(low)
    att.outcome = dataclasses.replace(out, tests=TestTable.concat([out.tests, *rows],
                                                                  cfg.alpha))
    if low is not None and not low.accepted[0]:
        att.threshold = float(AmbiguityReason.TOO_LOW_FOR_THE_SIZE)
        return []
    att.threshold = np.nan
    if cells is None:  # the grid: its parts measured as the region's extent over the count
        pw, pl = att.width / sp.nx, att.length / sp.ny
        cells = [(i * pw, j * pl, pw, pl, frozenset(si for si, ok in enumerate(
            (j > 0, j < sp.ny - 1, i > 0, i < sp.nx - 1)) if ok))
            for j in range(sp.ny) for i in range(sp.nx)]
    if att.inner:  # a row's far side is each of its cartons' far side: the list's cut
        cells = [(*c[:4], c[4] | att.inner) for c in cells]
    C = vertices.covariances[h]
    origin, x_axis, y_axis, normal = _in_plane(R, out)
    parts: list[_Part] = []
    for u, v, pw, pl, inner in cells:
        cov = np.zeros((9, 9))
        cov[:3, :3] = _corner(C, u, v, cfg.angle_tolerance)
        cov[3:, 3:] = C[3:, 3:]
        parts.append(((origin + u * x_axis + v * y_axis, x_axis, y_axis, normal, cov), h,
                      _Attempt(DimensionSource.SEEN_SPLIT if ctx.seen_sizes
                               else DimensionSource.SKU_SPLIT, -1, pw, pl, float(h), np.nan),
                      inner))
    return parts


def _seen_tiling(sp: Split, att: _Attempt, seam: _Seam, cfg: Config, n_cuts: int
                 ) -> tuple[list[tuple[float, float, float, float, frozenset[int]]] | None,
                            list[TestTable]]:
    """The cartons of a region whose grid ``sp`` is not the only tiling of its outline, as
    its seams show them (:func:`boxloc.stages.sizes.seen_tilings`): the one tiling whose
    every carton side inside the region shows a seam (``seam``, :func:`_region_seams`, at
    the seam level), in the region's measured frame (the grid's nominal frame stretched to
    the region's extent). None where no such tiling or several exist.

    Rows: SKU_SEEN_TILING (b = the cartons laid otherwise than the grid in the tiling
    found, -1 if none; statistic = the tilings found, 2 for two or more, NaN where the
    search stopped at its budget; critical 1; accepted for exactly one), and for the one
    found, SKU_SPLIT_SEAM of each carton side inside it (b from ``n_cuts`` on, the grid's
    cuts before them; in the order the cartons were laid, each carton's sides in side
    order, y = its start, its end, then x = its start, its end, each once).
    """
    sx, sy = att.width / (sp.nx * sp.a), att.length / (sp.ny * sp.b)

    def measured(axis: int, at: float, start: float, end: float) -> tuple[float, float]:
        """``seam`` along a line given in the grid's nominal frame."""
        k, ks = (sx, sy) if axis == 0 else (sy, sx)
        return seam(axis, at * k, start * ks, end * ks)

    def seen(axis: int, at: float, start: float, end: float) -> bool:
        z, zc = measured(axis, at, start, end)
        return bool(z > zc)

    found = seen_tilings(sp, cfg.box_sizes, cfg.size_tolerance, seen)
    U, V, tol = sp.nx * sp.a, sp.ny * sp.b, cfg.size_tolerance
    turned = -1
    if found.tilings:
        turned = sum(1 for _, _, fx, fy in found.tilings[0]
                     if abs(fx - sp.a) > tol or abs(fy - sp.b) > tol)
    stat = np.nan if found.exhausted else float(min(len(found.tilings), 2))
    rows = [TestTable.decision(TestKind.SKU_SEEN_TILING, -1, turned, stat, 1.0, found.unique,
                               cfg.alpha)]
    if not found.unique:
        return None, rows
    cells = []
    sides: list[tuple[int, float, float, float]] = []
    for x0, y0, fx, fy in found.tilings[0]:
        x1, y1 = x0 + fx, y0 + fy
        inner = []
        for si, ok, side in ((0, y0 > tol, (1, y0, x0, x1)), (1, y1 < V - tol, (1, y1, x0, x1)),
                             (2, x0 > tol, (0, x0, y0, y1)), (3, x1 < U - tol, (0, x1, y0, y1))):
            if ok:
                inner.append(si)
                if side not in sides:
                    sides.append(side)
        cells.append((x0 * sx, y0 * sy, fx * sx, fy * sy, frozenset(inner)))
    zz = [measured(*side) for side in sides]
    z = np.array([p[0] for p in zz], np.float64)
    zc = np.array([p[1] for p in zz], np.float64)
    rows.append(TestTable.decision(TestKind.SKU_SPLIT_SEAM, -1, n_cuts + np.arange(len(z)),
                                   z, zc, z > zc, cfg.alpha))
    return cells, rows


def _in_plane(R: Rectangle, out: VerifyOutcome
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The region's corner and axes moved into the plane its verification refitted to its
    points (origin, x, y, normal toward the sensor): a split's grid is laid in it.

    The corner's own plane comes from its two lines, whose directions a smeared depth edge
    tilts by degrees; the region's points fix the layer's plane to a fraction of that. A
    grid laid in the corner's plane drifts off the layer by the tilt times the distance:
    on a development active-stereo layer of 28 cartons (packed seed 2, scene 23) the
    parts' planes lay 0-120 mm off their points, and the parts farther out failed as
    off their own planes (``INLIERS``) or off in the mean (``MEAN_OFFSET``). The corner is
    projected onto the refitted plane along its normal; the x axis too, and y is turned
    to lie in the plane on x's side it was. Unchanged where no plane was refitted.
    """
    n = np.asarray(out.plane_normal, np.float64)
    c = np.asarray(out.plane_center, np.float64)
    if not (np.all(np.isfinite(n)) and np.all(np.isfinite(c))):
        return R.origin, R.x_axis, R.y_axis, R.normal
    n = n / np.linalg.norm(n)
    origin = R.origin - float((R.origin - c) @ n) * n
    x = R.x_axis - float(R.x_axis @ n) * n
    x = x / np.linalg.norm(x)
    y = np.cross(n, x)
    if float(y @ R.y_axis) < 0:
        y = -y
    return origin, x, y, n


def _same_rectangle(vertices: VertexSet, a: tuple[int, _Attempt], b: tuple[int, _Attempt],
                    tol: float) -> bool:
    """Whether two REGION attempts outline the same rectangle (every corner of one within
    ``tol`` of a corner of the other): the same split, not worth trying twice."""
    ca, cb = (rectangle_corners(vertices.points[i], vertices.d1[i], vertices.d2[i], t.width,
                                t.length) for i, t in (a, b))
    d = np.linalg.norm(ca[:, None, :] - cb[None, :, :], axis=-1)
    return bool((d.min(axis=1) <= tol).all())


def _split_regions(ctx: _Context, works: list[_VertexWork], convert: bool = True
                   ) -> tuple[_Context, list[_VertexWork]]:
    """Split each verified flat region at the seams a listed carton size implies.

    Without ``Config.box_sizes`` every region stays ambiguous (``LARGER_THAN_MAX_BOX``),
    unless the scan shows its cartons (:func:`_seen_cartons`): then this runs again with
    that list (``ctx.seen_sizes``; ``convert`` False: a verified rectangle that is a
    multiple of a seen carton is a region only where it lies beside one,
    :func:`_multiples_of_neighbours`), and the parts are SEEN_SPLIT.
    With them, the region's extent is tested against every listed size's grids (nx x ny,
    either orientation; :func:`boxloc.stages.sizes.region_splits`). No grid fits:
    ``NOT_A_MULTIPLE_OF_A_SIZE``. More than one cuts it differently and the range points
    show the seams of exactly one (every cut's groove significant at the seam level), that
    one; else ``SEVERAL_SPLITS``. One grid whose cuts show no seam is the split only if
    no other tiling by the listed cartons fits its outline (a SKU_TILING row,
    :func:`boxloc.stages.sizes.other_tiling`); else ``SEVERAL_TILINGS``. The split's
    SKU_SIZE row and a SKU_SPLIT_SEAM row per cut (b = the cut, x first; the groove there
    however weak) join the region's tests.

    Each part becomes a vertex (``parent`` the region's, ``parent_side`` ``SIZE_PART``)
    with one attempt of the part's size (``DimensionSource.SKU_SPLIT``), verified with its
    cut sides on the size's evidence (``size_sides``). If any part fails, the split is
    not trusted: every part is set ``AMBIGUOUS``.

    A region is measured, and its grid laid, from the corner it was found at. Found from
    several corners (:func:`_distinct_regions`), a split not trusted from the first is
    tried from the next, up to ``MAX_REGION_CORNERS`` distinct outlines: each corner's
    lines place that corner, while a sensor that smears depth across the far jumps ends
    the plane a few centimetres short of them, so the grids differ by that much at the
    far sides, and one may put a part across a real seam or off the layer where another
    does not. A split is trusted only whole, every part verified, from one corner.

    A REGION attempt's ``support`` is the number of parts (0: not split, the region as
    reported ambiguous; -1: another corner's outline of a region), its ``threshold`` the
    :class:`AmbiguityReason` (NaN: split; a corner tried whose parts failed:
    ``NO_END_EVIDENCE``). Where a later corner splits the region, the first one found
    becomes the duplicate.
    """
    cfg = ctx.config
    single = _multiples_as_regions(works, cfg) if convert else set()
    groups = _distinct_regions(works, ctx.vertices, cfg.min_edge)
    if not groups or not cfg.box_sizes:
        return ctx, works
    tried: list[list[tuple[int, _Attempt]]] = [[] for _ in groups]
    pending = list(range(len(groups)))
    part_works: list[_VertexWork] = []
    while pending:
        plans: list[_Part] = []
        owners: list[int] = []
        for g in pending:
            # the next corner whose outline differs from those tried and that has a split
            for c in groups[g]:
                if len(tried[g]) >= MAX_REGION_CORNERS:
                    break
                if any(c[1] is t[1] or _same_rectangle(ctx.vertices, c, t, cfg.size_tolerance)
                       for t in tried[g]):
                    continue
                tried[g].append(c)
                parts = _plan_split(ctx, c[0], c[1], single)
                if parts:
                    plans += parts
                    owners += [g] * len(parts)
                    break
        if not plans:
            break
        n0 = len(ctx.vertices)
        V = append_vertices(ctx.vertices, [p[0] for p in plans], [-1] * len(plans),
                            [-1] * len(plans), [p[1] for p in plans],
                            [SIZE_PART] * len(plans), ctx.vertices.tests)
        ctx = dataclasses.replace(ctx, vertices=V, normal_cov=normal_covariance(V))
        n_parts = Counter(owners)  # parts of each group's split, in the order planned
        for k, ((_, _, att, cut), g) in enumerate(zip(plans, owners)):
            w = _VertexWork(vertex=n0 + k)
            # the parts of one split are tested together: their interior searches at alpha
            # over the parts
            _verify(align(V, n0 + k, ctx.normal_cov), att, ctx, cut, n_parts[g])
            w.attempts.append(att)
            part_works.append(w)
        # a split is trusted only whole: a part that fails leaves the region to the next
        # corner, or ambiguous
        done = set()
        for g in n_parts:
            mine = [p[2] for p, o in zip(plans, owners) if o == g]
            region = tried[g][-1][1]
            if all(a.outcome is not None and a.outcome.accepted for a in mine):
                region.support = float(len(mine))
                if region is not groups[g][0][1]:
                    groups[g][0][1].support = -1.0
                done.add(g)
                continue
            for a in mine:
                if a.outcome is not None and a.outcome.accepted:
                    a.outcome = dataclasses.replace(a.outcome, accepted=False,
                                                    reason=VerifyReason.AMBIGUOUS)
            region.threshold = float(AmbiguityReason.NO_END_EVIDENCE)
        pending = [g for g in sorted(set(owners) - done) if len(tried[g]) < MAX_REGION_CORNERS]
    return ctx, works + part_works


_Rect = tuple[np.ndarray, np.ndarray, np.ndarray, _Attempt]  # origin, x, y, attempt


def _crossings(rects: list[_Rect], config: Config) -> list[tuple[float, int, bool]]:
    """For each verified rectangle: the largest fraction of another one's strong seam
    side that lies in its core, that other's index (-1 if none) and whether it crosses.

    A seam side is strong for this if it is as strong as the rectangle's own search for
    a seam anywhere inside had to find, and significant among all the seam sides offered
    (Bonferroni): one weak false seam must not remove a face. It crosses if at least half
    of it lies in the core (beyond ``BOUNDARY_BAND`` ``min_edge`` of the sides) and on
    the rectangle's plane (point on plane, z at alpha).
    """
    own, zs, p0, p1 = [], [], [], []
    for j, (o, x, y, a) in enumerate(rects):
        c = rectangle_corners(o, x, y, a.width, a.length)
        t = a.outcome.tests.of_kind(TestKind.VERIFY_SEAM_SIDE)  # type: ignore[union-attr]
        for si, z in zip(t.b[t.accepted], t.statistic[t.accepted]):
            e0, e1 = SIDE_CORNERS[int(si)]
            own.append(j)
            zs.append(float(z))
            p0.append(c[e0])
            p1.append(c[e1])
    if not own:
        return [(0.0, -1, False)] * len(rects)
    owner, z_seg = np.array(own), np.array(zs)
    A, B = np.array(p0), np.array(p1)
    k = math.sqrt(chi2_critical(1.0, config.alpha))
    crit_all = float(norm_isf(config.alpha / len(owner)))
    mi = BOUNDARY_BAND * config.min_edge
    s = np.linspace(0.0, 1.0, 21)
    P = A[:, None, :] + s[None, :, None] * (B - A)[:, None, :]  # (segments, 21, 3)
    mid, half = 0.5 * (A + B), 0.5 * np.linalg.norm(B - A, axis=1)
    out: list[tuple[float, int, bool]] = []
    for j, (o, x, y, a) in enumerate(rects):
        res = a.outcome
        assert res is not None
        nf, cf = res.plane_normal, res.plane_center
        sig = face_sigma(config, cf)
        crit_in = res.tests.of_kind(TestKind.VERIFY_SEAM_INTERIOR).critical
        crit = max(float(crit_in.max()) if len(crit_in) else np.inf, crit_all)
        # only segments that can reach the rectangle (its circumscribed circle)
        centre = o + 0.5 * a.width * x + 0.5 * a.length * y
        near = np.linalg.norm(mid - centre, axis=1) <= half + 0.5 * math.hypot(a.width,
                                                                                a.length)
        cand = np.flatnonzero((owner != j) & (z_seg >= crit) & near)
        if not len(cand):
            out.append((0.0, -1, False))
            continue
        Q = P[cand]
        u, v = (Q - o) @ x, (Q - o) @ y
        inside = ((u > mi) & (u < a.width - mi) & (v > mi) & (v < a.length - mi)
                  & (np.abs((Q - cf) @ nf) <= k * sig))
        f = inside.mean(1)
        b = int(np.argmax(f))
        worst = float(f[b])
        out.append((worst, int(owner[cand[b]]) if worst > 0 else -1, worst >= 0.5))
    return out


def _side_segments(rects: list[_Rect]) -> tuple[np.ndarray, np.ndarray]:
    """The four sides of each rectangle: (4n, 2, 3) end points, in ``SIDE_CORNERS``
    order, and (4n,) the rectangle each belongs to."""
    segs = [rectangle_corners(o, x, y, a.width, a.length)[list(SIDE_CORNERS)]
            for o, x, y, a in rects]
    return (np.concatenate(segs) if segs else np.zeros((0, 2, 3)),
            np.repeat(np.arange(len(rects)), len(SIDE_CORNERS)))


def _lines_into(j: int, rects: list[_Rect], segs: np.ndarray, owner: np.ndarray,
                config: Config) -> list[tuple[int, float, int]]:
    """The lines across rectangle j along which another verified rectangle's side runs on
    into it: (axis, position, owner) with axis 1 for a line along j's x (at v = position),
    0 along its y (at u); positions within 1 % of ``min_edge`` are one line, with the first
    owner.

    A side counts if it is parallel to one of j's axes (within z at alpha of
    ``angle_tolerance``), on j's plane (point on plane at z at alpha, its ends), at least
    ``BOUNDARY_BAND`` ``min_edge`` inside j's other sides, and beside j: along the line it
    does not reach into j's core and its near end lies within that band of j's outline (a
    touching neighbour in a row, not a box across the pallet).
    """
    o, x, y, a = rects[j]
    out = a.outcome
    assert out is not None
    k = math.sqrt(chi2_critical(1.0, config.alpha))
    mi = BOUNDARY_BAND * config.min_edge
    sin_tol = math.sin(k * config.angle_tolerance)
    nf, cf = out.plane_normal, out.plane_center
    tol_w = k * face_sigma(config, cf) + config.flatness
    mine = owner != j
    A, B = segs[mine, 0], segs[mine, 1]
    own = owner[mine]
    d = B - A
    L = np.linalg.norm(d, axis=1)
    d = d / np.maximum(L, 1e-12)[:, None]
    on = (np.abs((A - cf) @ nf) <= tol_w) & (np.abs((B - cf) @ nf) <= tol_w)
    found: list[tuple[int, float, int]] = []
    for axis, along, across, size, ext in ((1, x, y, a.length, a.width),
                                          (0, y, x, a.width, a.length)):
        # a line along `along`, at `pos` across it
        par = np.abs(d @ across) <= sin_tol
        pos = (0.5 * (A + B) - o) @ across
        t0, t1 = (A - o) @ along, (B - o) @ along
        lo, hi = np.minimum(t0, t1), np.maximum(t0, t1)
        beside = ((hi <= mi) & (hi >= -mi)) | ((lo >= ext - mi) & (lo <= ext + mi))
        ok = np.flatnonzero(on & par & beside & (pos > mi) & (pos < size - mi))
        taken: list[float] = []
        for i in ok[np.argsort(pos[ok], kind="stable")]:
            if all(abs(pos[i] - p) > 0.01 * config.min_edge for p in taken):
                taken.append(float(pos[i]))
                found.append((axis, float(pos[i]), int(own[i])))
    return found


def _seams_in_line(ctx: _Context, works: list[_VertexWork]) -> None:
    """Reject a verified rectangle across which a touching neighbour's side runs on as a
    seam (``VERIFY_SEAM_IN_LINE``, reason ``INTERIOR_SEAM``).

    In a gridded layer the seam between two flush tops runs straight on into the next row.
    A rectangle over two of them passes the interior's search for a seam anywhere inside
    (at alpha over all its positions) where that seam is weak, while its neighbours' sides,
    found from their own edges or seams, show where it must lie. So each line along which a
    verified neighbour's side runs on into the rectangle (:func:`_lines_into`) is tested
    there: the groove along the whole line (:func:`boxloc.stages.verify.seam_line`, both
    halves), over the spread of the statistic along the face (:func:`boxloc.stages.seams.
    face_spread`, robust), at alpha over the lines tested. Every line's row is recorded.
    A part of a split region is not tested (a split is trusted only whole: rejecting one
    part here would leave the others standing), but its sides are lines for others.
    """
    cfg = ctx.config
    V = ctx.vertices
    acc = [(w.vertex, a) for w in works
           if (a := _accepted(w)) is not None and a.source != DimensionSource.REGION]
    if len(acc) < 2:
        return
    rects: list[_Rect] = [(V.points[h], V.d1[h], V.d2[h], a) for h, a in acc]
    S, own = _side_segments(rects)
    att_id = _attempt_ids(works)
    vc = ctx.verify_ctx
    for j, (h, a) in enumerate(acc):
        if a.source in SPLIT_SOURCES:
            continue  # a part stands or falls with its split (its sides are lines, not it)
        lines = _lines_into(j, rects, S, own, cfg)
        if not lines:
            continue
        out = a.outcome
        assert out is not None
        origin, xa, ya, n = _in_plane(align(V, h, ctx.normal_cov), out)
        spacing = vc.spacing_at(origin + 0.5 * a.width * xa + 0.5 * a.length * ya)
        fp = face_points(vc.points, vc.valid, vc.sigma, vc.project, origin, xa, ya, n,
                         (0.0, a.width), (0.0, a.length), spacing, cfg.alpha,
                         cfg.noise.row_corr, vc.gain)
        if not len(fp):
            continue
        alpha = cfg.alpha / len(lines)
        z, zc, b = [], [], []
        for axis, pos, i in lines:
            size, ext = (a.length, a.width) if axis == 1 else (a.width, a.length)
            zi, ci = seam_line(fp, axis, pos, ext, spacing, alpha,
                               spread=whole_face_spread(fp, axis, size, ext, spacing))
            z.append(zi)
            zc.append(ci)
            b.append(att_id[id(acc[i][1])])
        seen = np.array(z) > np.array(zc)
        row = TestTable.decision(TestKind.VERIFY_SEAM_IN_LINE, -1, b, z, zc, ~seen, cfg.alpha)
        a.outcome = dataclasses.replace(
            out, tests=TestTable.concat([out.tests, row], cfg.alpha),
            accepted=False if seen.any() else out.accepted,
            reason=VerifyReason.INTERIOR_SEAM if seen.any() else out.reason)


def _repeats(p: float, q: float, u: float, v: float, tol: float) -> tuple[float, int]:
    """chi2 (2 dof) of a rectangle's sides (p, q) against (u, n v), n = round(q / v) >= 2,
    each measured side with standard deviation ``tol``; (inf, 0) where n < 2."""
    n = int(round(q / v)) if v > 0 else 0
    if n < 2:
        return math.inf, 0
    return ((p - u) ** 2 / (2.0 * tol * tol) + (q - n * v) ** 2 / ((1 + n * n) * tol * tol),
            n)


def _beside(a: _Rect, b: _Rect, d: float) -> bool:
    """Whether rectangle b lies beside rectangle a as a neighbour in a layer's grid: it
    touches one of a's sides (within ``d`` metres, overlapping it along that side by more
    than ``d``) and starts or ends level with one of the ends of that side (within ``d``).
    The rectangles are (origin, x, y, attempt), their axes parallel or crossed."""
    o, x, y, att = a
    W, L = att.width, att.length
    c = rectangle_corners(b[0], b[1], b[2], b[3].width, b[3].length) - o
    u, v = c @ x, c @ y
    u0, u1, v0, v1 = u.min(), u.max(), v.min(), v.max()
    along_v = min(v1, L) - max(v0, 0.0) > d and (abs(v0) <= d or abs(v1 - L) <= d)
    along_u = min(u1, W) - max(u0, 0.0) > d and (abs(u0) <= d or abs(u1 - W) <= d)
    return bool(((abs(u0 - W) <= d or abs(u1) <= d) and along_v)
                or ((abs(v0 - L) <= d or abs(v1) <= d) and along_u))


def _multiples_of_neighbours(ctx: _Context, works: list[_VertexWork]) -> list[_Attempt]:
    """Leave ambiguous a verified rectangle that is n >= 2 of another verified rectangle
    in its plane (``REPEATS_NEIGHBOUR``; a REGION attempt, ``MULTIPLE_OF_A_NEIGHBOUR``).

    Cartons of one size lie side by side on a pallet layer. Where the noise hides their
    seams, a rectangle over two or three of them has every side's evidence and an
    interior whose tests cannot tell a seam from none: it verifies like one box. A
    carton of that size found beside it, with its own sides' evidence, is the scan's
    own carton list (:func:`_multiples_as_regions` uses a given one): the rectangle is n
    of those as well as one box, and the robot must not grip it as one. Its sides (p, q)
    are tested against (u, n v) of each such neighbour (either way round; chi2 over the
    ``size_tolerance`` of each measured side, 2 dof, at alpha): the row of the best match
    is recorded (b = that neighbour's attempt) whether or not it matches. Neighbours are
    the accepted rectangles that are not regions, rows or a split's parts, on the
    rectangle's plane (centre and normal, z at alpha, as :func:`_lines_into`), and not
    themselves a multiple: rectangles are taken smallest first. A neighbour must lie
    beside the rectangle as in a grid (:func:`_beside`, within z at alpha of
    ``size_tolerance``): boxes of a mixed pile that happen to stand level and measure
    about half of another are not cartons of one layer (development matrix seed 1: five
    true tops lost so, for four false ones, before this condition).

    Returns the neighbour each multiple repeats (its best match), in order, then each box
    beside a flat region left ambiguous (not a multiple) in its plane, as
    :func:`_beside` finds it: the candidates of :func:`_seen_cartons`.
    """
    cfg = ctx.config
    boxes = sorted(_verified_boxes(works), key=lambda b: b[1].width * b[1].length)
    if len(boxes) < 2:
        return []
    V = ctx.vertices
    rect = {id(a): (V.points[h], V.d1[h], V.d2[h], a) for h, a in boxes}
    att_id = _attempt_ids(works)
    k = math.sqrt(chi2_critical(1.0, cfg.alpha))
    sin_tol = math.sin(k * cfg.angle_tolerance)
    crit = chi2_critical(2.0, cfg.alpha)
    near = k * cfg.size_tolerance

    def neighbours(h: int, a: _Attempt, of: list[_Attempt]) -> list[_Attempt]:
        """The boxes of ``of`` beside attempt a's rectangle at vertex h, in its plane."""
        out = a.outcome
        assert out is not None
        nf, cf = out.plane_normal, out.plane_center
        tol_w = k * face_sigma(cfg, cf) + cfg.flatness
        ra = (V.points[h], V.d1[h], V.d2[h], a)
        return [u for u in of if u.outcome is not None
                and np.linalg.norm(np.cross(u.outcome.plane_normal, nf)) <= sin_tol
                and abs(float((u.outcome.plane_center - cf) @ nf)) <= tol_w
                and _beside(ra, rect[id(u)], near)]

    units: list[_Attempt] = []
    multiples: list[tuple[int, _Attempt]] = []
    repeated: list[_Attempt] = []
    for h, a in boxes:
        best, by, unit_of = math.inf, -1, a
        for u in neighbours(h, a, units):
            for p, q in ((a.width, a.length), (a.length, a.width)):
                for s, t in ((u.width, u.length), (u.length, u.width)):
                    T, _ = _repeats(p, q, s, t, cfg.size_tolerance)
                    if T < best:
                        best, by, unit_of = T, att_id[id(u)], u
        if by < 0:
            units.append(a)
            continue
        out = a.outcome
        assert out is not None
        row = TestTable.chi2(TestKind.REPEATS_NEIGHBOUR, -1, by, best, 2.0, cfg.alpha)
        a.outcome = dataclasses.replace(out, tests=TestTable.concat([out.tests, row],
                                                                    cfg.alpha))
        if best > crit or a.source in SPLIT_SOURCES:
            units.append(a)  # a split's part stands or falls with its split
            continue
        a.outcome = dataclasses.replace(a.outcome, accepted=False,
                                        reason=VerifyReason.AMBIGUOUS)
        a.source, a.support = DimensionSource.REGION, 0.0
        a.threshold = float(AmbiguityReason.MULTIPLE_OF_A_NEIGHBOUR)
        multiples.append((h, a))
        repeated.append(unit_of)
    regions = [(w.vertex, a) for w in works for a in w.attempts
               if a.source == DimensionSource.REGION and a.support == 0
               and a.outcome is not None and a.outcome.reason == VerifyReason.AMBIGUOUS
               and all(a is not m for _, m in multiples)]
    _one_per_region(multiples, regions, V, cfg.min_edge)
    # a flat region left ambiguous beside boxes of its plane may be made of them too
    for h, r in regions:
        repeated += neighbours(h, r, units)
    return repeated


def _seen_cartons(ctx: _Context, works: list[_VertexWork], repeated: list[_Attempt]
                  ) -> tuple[tuple[tuple[float, float, float], ...], TestTable]:
    """The scan's own carton list: the sizes of the boxes that a rectangle beside them
    repeats, or that lie beside a flat region left ambiguous in their plane (``repeated``,
    :func:`_multiples_of_neighbours`), each where at least two verified boxes of it lie
    apart (``SEEN_CARTON``). Empty with a carton list (the user's is the list).

    One box and a rectangle of twice its size beside it leave the two readings open (the
    rectangle is ambiguous); a second box of that size elsewhere makes the size the
    layer's carton. On the development matrix (seeds 1-2) a list from one box each time
    split true tops into halves or slivers where that box was itself a false half of a
    lid or measured 2-3 cm off (14 false surfaces in four scans).

    Returns
    -------
    sizes : tuple of (short, long, NaN)
        Metres, as ``Config.box_sizes`` (no height).
    rows : TestTable
        One SEEN_CARTON row per distinct size (a = its first box's attempt).
    """
    cfg = ctx.config
    if cfg.box_sizes or not repeated:
        return (), TestTable.empty(cfg.alpha)
    V = ctx.vertices
    tol = cfg.size_tolerance
    att_id = _attempt_ids(works)
    boxes = _verified_boxes(works)
    sizes: list[tuple[float, float, float]] = []
    tried: list[tuple[float, float]] = []
    a_, b_, n_ = [], [], []
    for u in repeated:
        s, t = min(u.width, u.length), max(u.width, u.length)
        if any(abs(s - p) <= tol and abs(t - q) <= tol for p, q in tried):
            continue
        tried.append((s, t))
        apart: list[np.ndarray] = []
        for h, a in boxes:
            if (abs(min(a.width, a.length) - s) > tol
                    or abs(max(a.width, a.length) - t) > tol):
                continue
            c = _centre(V, h, a)
            if all(np.linalg.norm(c - o) > 0.5 * s for o in apart):
                apart.append(c)
        a_.append(att_id[id(u)])
        n_.append(float(len(apart)))
        b_.append(len(sizes) if len(apart) >= 2 else -1)
        if len(apart) >= 2:
            sizes.append((s, t, math.nan))
    rows = TestTable.decision(TestKind.SEEN_CARTON, a_, b_, n_, [2.0] * len(n_),
                              [n >= 2 for n in n_], cfg.alpha)
    return tuple(sizes), rows


def _one_per_region(multiples: list[tuple[int, _Attempt]],
                    regions: list[tuple[int, _Attempt]], vertices: VertexSet,
                    min_edge: float) -> None:
    """Mark duplicates (``support`` -1) among the multiples of a neighbour that overlap
    one another or a flat region left ambiguous: all taken largest first, a multiple is
    a duplicate if its centre lies inside one kept or it holds a kept one's centre
    (beyond ``BOUNDARY_BAND`` ``min_edge`` of the sides). Overlapping multiples of one
    carton (two of three in a row, each way) are one region to fall back on."""
    mi = BOUNDARY_BAND * min_edge
    kept: list[tuple[int, _Attempt, np.ndarray]] = []
    mine = {id(a) for _, a in multiples}
    for i, a in sorted(multiples + regions, key=lambda r: -r[1].width * r[1].length):
        c = _centre(vertices, i, a)
        if id(a) in mine and any(_in_core(vertices, c, j, b, mi)
                                 or _in_core(vertices, cb, i, a, mi) for j, b, cb in kept):
            a.support = -1.0
        else:
            kept.append((i, a, c))


def _seams_across(att_rows: list[tuple[int, _Attempt]], vertices: VertexSet,
                  config: Config) -> None:
    """Reject a verified rectangle across whose core runs a seam side of another one
    (``VERIFY_SEAM_CROSSING``, reason ``INTERIOR_SEAM``; see :func:`_crossings`).

    Two touching boxes of equal height seen from afar may show their seam only to the
    test at the side's known position, not to the search for the strongest groove
    anywhere inside; the rectangle over both then verifies too, and would win the
    selection for explaining more points with one model.
    """
    acc = [j for j, (_, a) in enumerate(att_rows) if a.outcome and a.outcome.accepted]
    rects = [(vertices.points[h], vertices.d1[h], vertices.d2[h], a)
             for h, a in (att_rows[j] for j in acc)]
    for j, (frac, by, crosses) in zip(acc, _crossings(rects, config)):
        a = att_rows[j][1]
        out = a.outcome
        assert out is not None
        row = TestTable.decision(TestKind.VERIFY_SEAM_CROSSING, -1, acc[by] if by >= 0 else -1,
                                 frac, 0.5, not crosses, config.alpha)
        a.outcome = dataclasses.replace(
            out, tests=TestTable.concat([out.tests, row], config.alpha),
            accepted=False if crosses else out.accepted,
            reason=VerifyReason.INTERIOR_SEAM if crosses else out.reason)


def _ragged(arrs: list[np.ndarray], dtype: type) -> tuple[np.ndarray, np.ndarray]:
    offs = np.zeros(len(arrs) + 1, np.int64)
    if arrs:
        offs[1:] = np.cumsum([len(a) for a in arrs])
    vals: np.ndarray = (np.concatenate(arrs).astype(dtype) if arrs and offs[-1]
                        else np.zeros(0, dtype))
    return offs, vals


def _assemble(
    works: list[_VertexWork], vertices: VertexSet, config: Config, up: np.ndarray
) -> tuple[HypothesisSet, Verification]:
    alpha = config.alpha
    n = len(works)
    att_rows: list[tuple[int, _Attempt]] = [(hi, a) for hi, w in enumerate(works)
                                            for a in w.attempts]
    _seams_across(att_rows, vertices, config)
    kept = np.full(n, -1, np.int32)
    for j, (hi, a) in enumerate(att_rows):
        if a.outcome is not None and a.outcome.accepted and kept[hi] < 0:
            kept[hi] = j
    source = np.zeros(n, np.uint8)
    diag = np.full(n, -1, np.int32)
    width = np.full(n, np.nan)
    length = np.full(n, np.nan)
    corners = np.full((n, 4, 3), np.nan)
    for hi in range(n):
        if kept[hi] >= 0:
            a = att_rows[kept[hi]][1]
            source[hi], diag[hi] = int(a.source), a.diagonal
            width[hi], length[hi] = a.width, a.length
            corners[hi] = rectangle_corners(vertices.points[hi], vertices.d1[hi],
                                            vertices.d2[hi], a.width, a.length)
    ax_off, ax = _ragged([w.acc_x for w in works], np.float32)
    ay_off, ay = _ragged([w.acc_y for w in works], np.float32)
    px_off, px = _ragged([w.peaks_x for w in works], np.float64)
    py_off, py = _ragged([w.peaks_y for w in works], np.float64)
    tests = []
    for w in works:
        tests += w.tests
    k = len(att_rows)
    hyps = HypothesisSet(
        vertex=np.arange(n, dtype=np.int32),
        source=source,
        attempt=kept,
        origins=vertices.points.copy(),
        x_axis=vertices.d1.copy(),
        y_axis=vertices.d2.copy(),
        normals=vertices.normals.copy(),
        width=width,
        length=length,
        corners=corners,
        acc_bin=np.array([w.acc_bin for w in works], np.float64),
        acc_x_offsets=ax_off, acc_x=ax, acc_y_offsets=ay_off, acc_y=ay,
        peaks_x_offsets=px_off, peaks_x=px, peaks_y_offsets=py_off, peaks_y=py,
        n_candidates=np.array([w.n_candidates for w in works], np.int32),
        att_hypothesis=np.array([h for h, _ in att_rows], np.int32),
        att_source=np.array([int(a.source) for _, a in att_rows], np.uint8),
        att_diagonal=np.array([a.diagonal for _, a in att_rows], np.int32),
        att_width=np.array([a.width for _, a in att_rows], np.float64),
        att_length=np.array([a.length for _, a in att_rows], np.float64),
        att_support=np.array([a.support for _, a in att_rows], np.float64),
        att_threshold=np.array([a.threshold for _, a in att_rows], np.float64),
        att_verified=np.array([bool(a.outcome and a.outcome.accepted) for _, a in att_rows],
                              bool),
        up=np.asarray(up, dtype=np.float64).copy(),
        tests=TestTable.concat(tests, alpha),
    )
    outs = [a.outcome for _, a in att_rows]
    vtests = []
    for j, o in enumerate(outs):
        assert o is not None
        t = o.tests
        vtests.append(TestTable(kind=t.kind, a=np.full(len(t), j, np.int32), b=t.b,
                                statistic=t.statistic, dof=t.dof, critical=t.critical,
                                p_value=t.p_value, accepted=t.accepted, alpha=t.alpha))
    in_off, in_pix = _ragged([o.inlier_pixels for o in outs], np.int32)  # type: ignore[union-attr]

    def col(name: str, dtype: type) -> np.ndarray:
        return np.array([getattr(o, name) for o in outs], dtype).reshape(k, *(
            () if not outs else np.shape(getattr(outs[0], name))))

    ver = Verification(
        attempt=np.arange(k, dtype=np.int32),
        hypothesis=hyps.att_hypothesis.copy(),
        n_inside=col("n_inside", np.int32),
        n_valid=col("n_valid", np.int32),
        n_inliers=col("n_inliers", np.int32),
        n_front=col("n_front", np.int32),
        n_behind=col("n_behind", np.int32),
        inlier_fraction=col("inlier_fraction", np.float64),
        mean_distance=col("mean_distance", np.float64),
        sigma_mean=col("sigma_mean", np.float64),
        n_interior_edges=col("n_interior_edges", np.int32),
        plane_centers=col("plane_center", np.float64).reshape(k, 3),
        plane_normals=col("plane_normal", np.float64).reshape(k, 3),
        plane_covariances=col("plane_cov", np.float64).reshape(k, 6, 6),
        rms=col("rms", np.float64),
        accepted=col("accepted", bool),
        reason=col("reason", np.uint8),
        inlier_offsets=in_off,
        inlier_pixels=in_pix,
        error=col("error", np.float64),
        tests=TestTable.concat(vtests, alpha),
    )
    return hyps, ver

"""Stage 4: vertices, pairs of 3D segments that meet orthogonally (paper §2.1).

Every pair of segments is tested, with the propagated covariances of both lines
(Förstner, Brunn & Heuel 2000):

* **meet** — the signed distance between the two lines is zero: chi2(1);
* **orthogonal** — the cosine of their angle is zero: chi2(1);
* **at segment ends** — the intersection lies on both segments, within their extent plus
  ``end_tolerance`` of the shortest box edge (support thins out near junctions, and
  cardboard corners are rounded and dented), so a corner, a T or a cross; not the far
  extension of a line.

An accepted pair gives one vertex per combination of *arms*: the directions from the
intersection along which each segment extends by at least half the shortest box edge. An
L corner gives one vertex, a T two, a cross four (the inner corners of a neat pallet layer
are crosses of seam lines). Each vertex's normal ``d1 x d2`` points toward the sensor.

**Box corners** (:func:`corner_vertices`, a deviation from the paper). A vertex one of
whose segments is a convex crease is a corner of a box where two of its faces meet: the
crease is their common edge, and the box's third edge there runs along the vertex's
normal, into the box. So the corner is also a vertex of the other face, with arms along
the crease and the third edge. This finds a top whose only straight edge is its crease
with the face below, as when a sensor sees the tops as slivers at grazing incidence and
rounds their short sides (the mOSD Kinect frames). Most creases a sensor looking down sees
join a top to a side face, and at their corners the face across is that side face: a
corner is offered only if its face can be a top, within ``max_tilt`` of up (``BOX_CORNER``,
one-sided z on the face normal's propagated error), which on a 300-box pile leaves out
1512 side faces that verification would reject anyway, after the dimension search.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from boxloc.config import Config
from boxloc.distributions import norm_isf
from boxloc.products import EdgeKind, LineSet, VertexSet
from boxloc.stats import TestKind, TestTable, float32_precision

#: ``VertexSet.parent_side`` of a box corner's vertex (:func:`corner_vertices`); 0-3 are
#: the seam sides of a neighbour's corner
THIRD_EDGE = 4


def _skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices of vectors (..., 3) -> (..., 3, 3)."""
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


def line_point_covariance(lines: LineSet, idx: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Covariance of the point at parameter t (from the centroid) on lines idx, (n, 3, 3)."""
    C = lines.covariances[idx]
    return C[:, :3, :3] + (t**2)[:, None, None] * C[:, 3:, 3:]


def find_vertices(lines: LineSet, *, config: Config, up: np.ndarray | None = None
                  ) -> VertexSet:
    """Vertices: orthogonal pairs of line segments that meet near an end of both, and the
    box corners at convex creases (:func:`corner_vertices`).

    Parameters
    ----------
    lines : LineSet
    config : Config
        Uses ``alpha``, ``min_edge``, ``end_tolerance``, ``angle_tolerance``, ``flatness``
        and ``max_tilt``.
    up : ndarray (3,), optional
        Up in the sensor frame; without it every box corner is offered.

    Returns
    -------
    VertexSet
        Vertices and every test made on every pair of lines.
    """
    alpha = config.alpha
    L = len(lines)
    ia, ib = np.triu_indices(L, 1)
    if len(ia) == 0:
        return _empty(alpha)
    c1, b1 = lines.points[ia], lines.directions[ia]
    c2, b2 = lines.points[ib], lines.directions[ib]
    cr = np.cross(b1, b2)
    sin = np.linalg.norm(cr, axis=1)
    ok = sin > 1e-6
    n = np.where(ok[:, None], cr / np.maximum(sin, 1e-12)[:, None], 0.0)

    # closest points: parameters t1 (on line a) and t2 (on line b) from the centroids
    w = c1 - c2
    a = np.einsum("ij,ij->i", b1, b2)
    d1w = np.einsum("ij,ij->i", b1, w)
    d2w = np.einsum("ij,ij->i", b2, w)
    den = np.maximum(1 - a * a, 1e-12)
    t1 = (a * d2w - d1w) / den
    t2 = (d2w - a * d1w) / den
    X1 = c1 + t1[:, None] * b1
    X2 = c2 + t2[:, None] * b2
    X = 0.5 * (X1 + X2)

    # meet: signed distance along the common normal, chi2(1)
    delta = np.einsum("ij,ij->i", X1 - X2, n)
    S1 = line_point_covariance(lines, ia, t1)
    S2 = line_point_covariance(lines, ib, t2)
    var_d = np.einsum("ni,nij,nj->n", n, S1 + S2, n) + 2 * config.flatness**2
    # Every pair of lines is tested (L (L - 1) / 2 pairs, three tests each: most of a
    # scan's tests). The statistics are kept to float32 precision before the decisions,
    # which are made on the value recorded; a log stores them in less space.
    T_meet = float32_precision(delta**2 / np.maximum(var_d, 1e-30))
    meet = TestTable.chi2(TestKind.LINES_MEET, ia, ib, T_meet, 1.0, alpha)

    # orthogonal: cos = b1.b2, var = b2^T S_b1 b2 + b1^T S_b2 b1, chi2(1)
    Sb1 = lines.covariances[ia][:, 3:, 3:]
    Sb2 = lines.covariances[ib][:, 3:, 3:]
    var_c = (np.einsum("ni,nij,nj->n", b2, Sb1, b2) + np.einsum("ni,nij,nj->n", b1, Sb2, b1)
             + config.angle_tolerance**2)
    T_orth = float32_precision(a**2 / np.maximum(var_c, 1e-30))
    orth = TestTable.chi2(TestKind.LINES_ORTHOGONAL, ia, ib, T_orth, 1.0, alpha)

    # at segment ends: the intersection lies within both segments' extent (+ tolerance)
    s1 = np.einsum("ij,ij->i", lines.starts[ia] - c1, b1)
    e1 = np.einsum("ij,ij->i", lines.ends[ia] - c1, b1)
    s2 = np.einsum("ij,ij->i", lines.starts[ib] - c2, b2)
    e2 = np.einsum("ij,ij->i", lines.ends[ib] - c2, b2)
    lo1, hi1 = np.minimum(s1, e1), np.maximum(s1, e1)
    lo2, hi2 = np.minimum(s2, e2), np.maximum(s2, e2)
    beyond = float32_precision(np.maximum.reduce(
        [lo1 - t1, t1 - hi1, lo2 - t2, t2 - hi2, np.zeros_like(t1)]
    ))
    # a segment may stop short of its corner by a fraction of the shortest edge
    tol = config.end_tolerance * config.min_edge
    ends = TestTable.decision(
        TestKind.AT_SEGMENT_ENDS, ia, ib, beyond, tol, beyond <= tol, alpha
    )

    good = ok & meet.accepted & orth.accepted & ends.accepted
    arm = 0.5 * config.min_edge
    pts, D1, D2, N, COV, la, lb = [], [], [], [], [], [], []
    for k in np.flatnonzero(good):
        arms1 = [s for s, ext in ((1.0, hi1[k] - t1[k]), (-1.0, t1[k] - lo1[k])) if ext >= arm]
        arms2 = [s for s, ext in ((1.0, hi2[k] - t2[k]), (-1.0, t2[k] - lo2[k])) if ext >= arm]
        for g1 in arms1:
            for g2 in arms2:
                da, db = g1 * b1[k], g2 * b2[k]
                la_, lb_ = ia[k], ib[k]
                nrm = np.cross(da, db)
                nrm /= np.linalg.norm(nrm)
                if nrm @ X[k] > 0:  # turn the normal toward the sensor (origin)
                    da, db, la_, lb_ = db, da, lb_, la_
                    nrm = -nrm
                # the directions are orthogonal by test; make them exactly so in the plane
                db = db - (db @ da) * da
                db /= np.linalg.norm(db)
                cov = np.zeros((9, 9))
                cov[:3, :3] = 0.25 * (S1[k] + S2[k])
                cov[3:6, 3:6] = lines.covariances[la_][3:, 3:]
                cov[6:, 6:] = lines.covariances[lb_][3:, 3:]
                pts.append(X[k])
                D1.append(da)
                D2.append(db)
                N.append(nrm)
                COV.append(cov)
                la.append(la_)
                lb.append(lb_)
    tests = TestTable.concat([meet, orth, ends], alpha)
    if not pts:
        e = _empty(alpha)
        return VertexSet(**{**e.__dict__, "tests": tests})
    V = VertexSet(
        points=np.array(pts),
        d1=np.array(D1),
        d2=np.array(D2),
        normals=np.array(N),
        covariances=np.array(COV),
        line_a=np.array(la, np.int32),
        line_b=np.array(lb, np.int32),
        tests=tests,
    )
    return corner_vertices(V, lines, config, up)


def corner_vertices(vertices: VertexSet, lines: LineSet, config: Config,
                    up: np.ndarray | None = None) -> VertexSet:
    """Add, for each vertex with a convex-crease arm, the box corner's vertex of the other
    face at that crease: arms along the crease and along the vertex's inward normal.

    Parameters
    ----------
    vertices : VertexSet
        Vertices of two lines.
    lines : LineSet
    config : Config
        ``alpha`` and ``max_tilt``.
    up : ndarray (3,), optional
        With it, a corner is offered only if its face can be a top (``BOX_CORNER``).

    Returns
    -------
    VertexSet
        ``vertices`` followed by the new ones, each with ``parent`` its vertex and
        ``parent_side`` = :data:`THIRD_EDGE`; the arm along the crease keeps its line id,
        the third edge has -1. Covariance: the vertex's point, the crease's direction and,
        for the third edge, the normal's first-order covariance. ``tests`` gain a
        ``BOX_CORNER`` row per corner considered.
    """
    Sn = normal_covariance(vertices)
    crease = lines.kinds == EdgeKind.CREASE_CONVEX
    k = float(norm_isf(config.alpha))
    cos_max = float(np.cos(config.max_tilt))
    new: list[tuple[np.ndarray, ...]] = []
    la, lb, par, seen = [], [], [], set()
    rows: list[tuple[int, int, float]] = []
    for v in range(len(vertices)):
        C = vertices.covariances[v]
        for arm, line, Sd in ((vertices.d1[v], vertices.line_a[v], C[3:6, 3:6]),
                              (vertices.d2[v], vertices.line_b[v], C[6:, 6:])):
            if line < 0 or not crease[line]:
                continue
            # the crease's own direction (a vertex's second arm is squared to its first),
            # so the corners of a T along the crease give the same vertex, bit for bit
            d = lines.directions[line]
            d = d if arm @ d > 0 else -d
            da, db, Sa, Sb, ia, ib = d, -vertices.normals[v], Sd, Sn[v], int(line), -1
            nrm = np.cross(da, db)
            if nrm @ vertices.points[v] > 0:  # the normal toward the sensor
                da, db, Sa, Sb, ia, ib, nrm = db, da, Sb, Sa, ib, ia, -nrm
            key = (vertices.points[v].tobytes(), da.tobytes(), db.tobytes())
            if key in seen:  # the two corners of a T along the crease give the same one
                continue
            seen.add(key)
            if up is not None:
                # n = da x db: its component along up and that component's variance
                ca, cb = np.cross(db, up), np.cross(up, da)
                var = float(ca @ Sa @ ca + cb @ Sb @ cb)
                z = (cos_max - float(nrm @ up)) / max(np.sqrt(var), 1e-12)
                rows.append((v, int(line), z))
                if z > k:
                    continue
            cov = np.zeros((9, 9))
            cov[:3, :3], cov[3:6, 3:6], cov[6:, 6:] = C[:3, :3], Sa, Sb
            new.append((vertices.points[v], da, db, nrm, cov))
            la.append(ia)
            lb.append(ib)
            par.append(v)
    tests = vertices.tests
    if rows:
        a, b, z = (np.array(c) for c in zip(*rows))
        tests = TestTable.concat([tests, TestTable.decision(
            TestKind.BOX_CORNER, a, b, z, k, z <= k, config.alpha)], config.alpha)
    return append_vertices(vertices, new, la, lb, par, [THIRD_EDGE] * len(par), tests)


def append_vertices(vertices: VertexSet, new: Sequence[tuple[np.ndarray, ...]],
                    line_a: list[int], line_b: list[int], parent: list[int],
                    parent_side: list[int], tests: TestTable) -> VertexSet:
    """``vertices`` followed by derived ones, with ``tests`` in place of theirs.

    ``new`` holds one (point, d1, d2, normal, covariance) per derived vertex; the other
    lists give each its lines, its parent vertex and ``parent_side``.
    """
    if not new:
        return dataclasses.replace(vertices, tests=tests)
    P, D1, D2, N, COV = (np.array(a) for a in zip(*new))
    return VertexSet(
        points=np.r_[vertices.points, P], d1=np.r_[vertices.d1, D1],
        d2=np.r_[vertices.d2, D2], normals=np.r_[vertices.normals, N],
        covariances=np.r_[vertices.covariances, COV],
        line_a=np.r_[vertices.line_a, line_a].astype(np.int32),
        line_b=np.r_[vertices.line_b, line_b].astype(np.int32),
        tests=tests,
        parent=np.r_[vertices.parent, parent].astype(np.int32),
        parent_side=np.r_[vertices.parent_side, parent_side].astype(np.int32),
    )


def _empty(alpha: float) -> VertexSet:
    return VertexSet(
        points=np.zeros((0, 3)), d1=np.zeros((0, 3)), d2=np.zeros((0, 3)),
        normals=np.zeros((0, 3)), covariances=np.zeros((0, 9, 9)),
        line_a=np.zeros(0, np.int32), line_b=np.zeros(0, np.int32),
        tests=TestTable.empty(alpha),
    )


def normal_covariance(vertices: VertexSet) -> np.ndarray:
    """Covariance of each vertex normal n = d1 x d2, (V, 3, 3), first order."""
    S1 = vertices.covariances[:, 3:6, 3:6]
    S2 = vertices.covariances[:, 6:, 6:]
    K1 = _skew(vertices.d1)
    K2 = _skew(vertices.d2)
    return K2 @ S1 @ np.swapaxes(K2, 1, 2) + K1 @ S2 @ np.swapaxes(K1, 1, 2)

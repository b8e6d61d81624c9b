"""Stage 3: 3D line segments by a series of constrained Hough transforms.

After Katsoulas (IbPRIA 2003, the paper's ref [6]) and Olson (IJCV 2001, ref [9]): each
trial draws one *distinguished* edge point p0 (k = 1), which leaves a line two free
parameters; they are recovered in two 2-D Hough transforms:

1. **direction** — every other edge point p_i near p0 votes for the direction
   (p_i - p0)/|p_i - p0| on an icosahedral tessellation of the hemisphere (Jeltsch, Dalitz
   & Pohle-Fröhlich 2016), for every cell inside its propagated error region (chi2(2) at
   alpha; bounded-error voting): far points vote sharply, near points broadly, and the
   peak counts the points consistent with one direction;
2. **position** — the points are projected on the plane perpendicular to the found
   direction and vote for the line's offset from p0 in a 2-D accumulator, again spread by
   their propagated error, so p0's own noise does not fix the line.

The inliers (point-on-line test, chi2(2) at alpha) are refitted by total least squares,
with covariance, and split into segments at gaps. Olson's bound gives the number of
trials: t = ceil(ln(1 - P) / ln(1 - eps)), eps = the fraction of edge points on the
smallest line worth finding; it is recomputed as found lines remove their points, and the
search stops after t consecutive trials that find nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numba as nb
import numpy as np
from scipy.spatial import cKDTree

from boxloc.config import Config
from boxloc.products import EdgeMap, LineSet
from boxloc.scan import Scan
from boxloc.stats import BUDGET_LINES, TestKind, TestTable, chi2_critical

#: Largest angular error region a direction vote may spread over; nearer points carry
#: almost no direction information and only slow the accumulator down.
MAX_VOTE_RADIUS = math.radians(8.0)
#: The fewest points that make a line, however near the sensor.
MIN_LINE_POINTS = 6
#: Points voting per trial (a seeded random subset when there are more): the peak's
#: relative height does not depend on it, the cost does.
MAX_VOTERS = 300
#: Direction votes come from points within this many shortest box edges of the
#: distinguished point: far enough for a sharp direction (the error shrinks with distance),
#: near enough that the line's own points are not drowned by the rest of the scene.
VOTE_RADIUS_EDGES = 3.0


@lru_cache(maxsize=8)
def hemisphere_directions(granularity: int) -> np.ndarray:
    """Unit directions of a subdivided icosahedron on the upper hemisphere, (n, 3).

    Granularity 0..6 gives 6, 21, 81, 321, 1281, 5121, 20481 directions (z >= 0, with
    only half of the equator kept), as in Dalitz et al., IPOL 2017.
    """
    t = (1.0 + 5**0.5) / 2.0
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t),
         (0, -1, -t), (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
         (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
         (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    verts = [np.array(p, float) / np.linalg.norm(p) for p in v]
    faces = f
    for _ in range(granularity):
        cache: dict[tuple[int, int], int] = {}

        def mid(a: int, b: int, cache: dict[tuple[int, int], int] = cache) -> int:
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        nf = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            nf += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = nf
    V = np.array(verts)
    eps = 1e-9
    keep = (V[:, 2] > eps) | (
        (np.abs(V[:, 2]) <= eps) & ((V[:, 0] > eps) | ((np.abs(V[:, 0]) <= eps) & (V[:, 1] > 0)))
    )
    return V[keep]


#: Resolution of the lookup table from (polar, azimuth) to the nearest direction cell.
_LUT_POLAR, _LUT_AZIMUTH = 256, 512


@lru_cache(maxsize=8)
def _direction_index(granularity: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lookup structures for voting on the tessellation.

    Returns
    -------
    lut : (P, A) int32
        Nearest hemisphere cell of each (polar, azimuth) bin of the whole sphere.
    nbr : (C, K) int32
        For each cell, the cells within MAX_VOTE_RADIUS plus two cell spacings (-1 pads).
    D : (C, 3) float64
        Cell directions.
    """
    D = hemisphere_directions(granularity)
    both = np.concatenate([D, -D])
    hemi = np.concatenate([np.arange(len(D)), np.arange(len(D))])
    tree = cKDTree(both)
    th = (np.arange(_LUT_POLAR) + 0.5) * math.pi / _LUT_POLAR
    ph = (np.arange(_LUT_AZIMUTH) + 0.5) * 2 * math.pi / _LUT_AZIMUTH
    T, F = np.meshgrid(th, ph, indexing="ij")
    q = np.stack([np.sin(T) * np.cos(F), np.sin(T) * np.sin(F), np.cos(T)], -1).reshape(-1, 3)
    lut = hemi[tree.query(q)[1]].reshape(_LUT_POLAR, _LUT_AZIMUTH).astype(np.int32)
    spacing = math.sqrt(4 * math.pi / len(both))
    reach = 2 * math.sin((MAX_VOTE_RADIUS + 2 * spacing) / 2)
    lists = tree.query_ball_point(D, reach)
    uniq = [np.unique(hemi[np.asarray(li, np.int64)]) for li in lists]
    K = max(len(u) for u in uniq)
    nbr = np.full((len(D), K), -1, np.int32)
    for i, u in enumerate(uniq):
        nbr[i, : len(u)] = u
    return lut, nbr, D


@nb.njit(cache=True)
def _vote_directions(d: np.ndarray, rad: np.ndarray, lut: np.ndarray, nbr: np.ndarray,
                     D: np.ndarray) -> np.ndarray:
    """Each direction d_i votes 1 for every cell within rad_i of +-d_i.

    Bounded-error voting as Olson (2001): a cell's count is the number of points whose
    error region contains it, so every point of a short line counts fully at its
    direction. (Spreading one vote evenly over the region instead lets a few far points
    with sharp regions outvote a short line whose points all lie near p0.)
    """
    nc = D.shape[0]
    acc = np.zeros(nc)
    P, A = lut.shape
    cells = np.empty(nbr.shape[1], np.int64)
    for i in range(d.shape[0]):
        x, y, z = d[i, 0], d[i, 1], d[i, 2]
        th = math.acos(min(1.0, max(-1.0, z)))
        ph = math.atan2(y, x)
        if ph < 0:
            ph += 2 * math.pi
        bi = min(int(th / math.pi * P), P - 1)
        bj = min(int(ph / (2 * math.pi) * A), A - 1)
        c0 = lut[bi, bj]
        cr = math.cos(rad[i])
        n = 0
        for k in range(nbr.shape[1]):
            c = nbr[c0, k]
            if c < 0:
                break
            dot = abs(D[c, 0] * x + D[c, 1] * y + D[c, 2] * z)
            if dot >= cr:
                cells[n] = c
                n += 1
        if n == 0:
            cells[0] = c0
            n = 1
        for k in range(n):
            acc[cells[k]] += 1.0
    return acc


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """u x v of two 3-vectors, with ``np.cross``'s operations (the same bits) but not its
    per-call overhead, which dominated this stage's small-array work."""
    u0, u1, u2 = float(u[0]), float(u[1]), float(u[2])
    v0, v1, v2 = float(v[0]), float(v[1]), float(v[2])
    return np.array([u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0])


def _perp_basis(b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([1.0, 0.0, 0.0]) if abs(b[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = _cross(b, a)
    e1 /= math.sqrt(e1.dot(e1))  # as np.linalg.norm computes it
    e2 = _cross(b, e1)
    return e1, e2


def _tls(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    c = P.mean(0)
    Q = P - c
    w, V = np.linalg.eigh(Q.T @ Q)
    return c, V[:, 2], w


def _point_on_line_stat(
    P: np.ndarray, C: np.ndarray, c: np.ndarray, b: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """chi2(2) statistic of each point's distance to line (c, b); and t along the line."""
    e1, e2 = _perp_basis(b)
    E = np.stack([e1, e2])  # (2, 3)
    D = P - c
    t = D @ b
    r = D @ E.T  # (n, 2)
    S = np.einsum("ij,njk,lk->nil", E, C, E)  # (n, 2, 2)
    det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
    T = (S[:, 1, 1] * r[:, 0] ** 2 - 2 * S[:, 0, 1] * r[:, 0] * r[:, 1]
         + S[:, 0, 0] * r[:, 1] ** 2) / np.maximum(det, 1e-30)
    return T, t


@nb.njit(cache=True)
def _may_lie_on(P: np.ndarray, tr: np.ndarray, idx: np.ndarray, c: np.ndarray, b: np.ndarray,
                crit: float) -> np.ndarray:
    """The points of ``idx`` that can pass the point-on-line test at ``crit`` (a cheap,
    exact pre-filter), in their order.

    The chi2(2) statistic of a point at perpendicular distance r is at least r^2 over the
    largest eigenvalue of its projected covariance, and that is at most the trace ``tr`` of
    its 3-D covariance: a point with r^2 > crit * tr fails the test, whatever its
    covariance's shape (the factor 1 + 1e-9 keeps rounding on the safe side). A point with
    no covariance is kept: the test decides it.
    """
    out = np.empty(idx.shape[0], np.int64)
    m = 0
    b0, b1, b2 = b[0], b[1], b[2]
    for j in range(idx.shape[0]):
        i = idx[j]
        d0 = P[i, 0] - c[0]
        d1 = P[i, 1] - c[1]
        d2 = P[i, 2] - c[2]
        t = d0 * b0 + d1 * b1 + d2 * b2
        r0 = d0 - t * b0
        r1 = d1 - t * b1
        r2 = d2 - t * b2
        if not (r0 * r0 + r1 * r1 + r2 * r2 > crit * tr[i] * (1.0 + 1e-9)) or tr[i] <= 0.0:
            out[m] = i
            m += 1
    return out[:m]


def fit_segment(P: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                       np.ndarray]:
    """Total-least-squares line through points, with the covariance of (centroid, direction).

    Parameters
    ----------
    P : (n, 3) float64, metres
    C : (n, 3, 3) float64
        Point covariances.

    Returns
    -------
    centroid : (3,)
    direction : (3,) unit
    covariance : (6, 6)
        Of (centroid, direction): perpendicular position s2/n, direction s2 / sum t^2 (both
        in the plane perpendicular to the line), with s2 the larger of the residual variance
        and the points' predicted variance; along the line, the centroid's spread / n.
    t : (n,)
        Each point's position along the line from the centroid, metres.
    """
    c, b, w = _tls(P)
    t = (P - c) @ b
    n = len(P)
    res2 = float(w[0] + w[1]) / max(n - 2, 1) / 2.0
    pred = float(np.median(np.einsum("nii->n", C))) / 3.0
    s2 = max(res2, pred)
    cov = np.zeros((6, 6))
    Pp = np.eye(3) - np.outer(b, b)
    cov[:3, :3] = s2 / n * Pp + np.outer(b, b) * (t.var() / n)
    cov[3:, 3:] = s2 / max(float((t**2).sum()), 1e-12) * Pp
    return c, b, cov, t


def _split_at_gaps(t: np.ndarray, gap: float) -> list[np.ndarray]:
    """Index groups of sorted positions t separated by more than gap."""
    order = np.argsort(t, kind="stable")
    ts = t[order]
    cuts = np.flatnonzero(np.diff(ts) > gap) + 1
    return np.split(order, cuts)


def find_lines(scan: Scan, edges: EdgeMap, *, config: Config, rng: np.random.Generator) -> LineSet:
    """3D line segments through the edge points, by constrained Hough transforms.

    Parameters
    ----------
    scan : Scan
        For the sensor's pixel angle (expected edge-point spacing).
    edges : EdgeMap
        Edge points with covariances.
    config : Config
        Uses ``alpha``, ``p_success``, ``min_edge``, ``max_edge``, ``direction_granularity``,
        ``max_line_work``.
    rng : numpy.random.Generator
        Source of the distinguished points (seeded from the scan by the pipeline).

    Returns
    -------
    LineSet

    References
    ----------
    C. F. Olson, "A general method for geometric feature matching and model extraction",
    IJCV 45(1), 2001. D. Katsoulas, "Robust extraction of vertices in range images by
    constraining the Hough transform", IbPRIA 2003.
    """
    rng = np.random.default_rng(rng)
    P = np.asarray(edges.points, dtype=np.float64)
    C = np.asarray(edges.covariances, dtype=np.float64)
    N = P.shape[0]
    alpha = config.alpha
    chi2_2 = chi2_critical(2.0, alpha)
    k2 = math.sqrt(chi2_2)
    pixel_angle = scan.sensor.pixel_angle

    r_med = float(np.median(np.linalg.norm(P, axis=1))) if N else 1.0
    spacing = r_med * pixel_angle  # expected edge-point spacing along an edge, metres
    m_min = max(MIN_LINE_POINTS, int(0.5 * config.min_edge / spacing))
    eps0 = min(1.0, m_min / max(N, 1))

    lut, nbr, dirs = _direction_index(config.direction_granularity)
    fixed = _TrialInputs(
        points=P, covariances=C, cov_trace=np.einsum("nii->n", C), edge_kinds=edges.kinds,
        directions=dirs, lut=lut, neighbours=nbr, k2=k2, chi2_2=chi2_2, spacing=spacing,
        m_min=m_min, min_edge=config.min_edge,
    )
    ptree = cKDTree(P)
    radius = min(config.max_edge, VOTE_RADIUS_EDGES * config.min_edge)

    alive = np.ones(N, bool)
    alive_idx = np.arange(N)  # np.flatnonzero(alive)
    n_alive = N
    segments: list[_Segment] = []
    trial_of: list[int] = []  # the trial that found each segment
    trial = 0
    fails = 0
    work = 0  # neighbour points examined, against config.max_line_work
    budget = config.max_line_work
    exhausted = False

    def needed_trials(n: int) -> int:
        eps = min(1.0, m_min / max(n, 1))
        if eps >= 1.0:
            return 1
        return int(math.ceil(math.log(1.0 - config.p_success) / math.log(1.0 - eps)))

    while n_alive >= m_min and fails < needed_trials(n_alive):
        if budget and work >= budget:
            exhausted = True
            break
        trial += 1
        i0 = int(alive_idx[rng.integers(len(alive_idx))])
        nb = np.asarray(ptree.query_ball_point(P[i0], radius), dtype=np.int64)
        nb = nb[alive[nb] & (nb != i0)]
        work += len(nb)
        found = _trial(fixed, i0, nb, alive_idx, rng) if len(nb) >= m_min else []
        for seg in found:
            alive[seg.support] = False
            segments.append(seg)
            trial_of.append(trial)
        if found:
            alive_idx = np.flatnonzero(alive)  # changes only here
            n_alive = int(alive.sum())
            fails = 0
        else:
            fails += 1

    return _to_lineset(segments, trial_of, trial, eps0, config, config.seed_for(scan.seed),
                       TestTable.budget(BUDGET_LINES, work, budget, exhausted, alpha))


@dataclass(frozen=True)
class _TrialInputs:
    """What every Hough trial of one scan reads: the edge points and the voting tables."""

    points: np.ndarray  # (N, 3) float64, metres
    covariances: np.ndarray  # (N, 3, 3) float64, m^2
    cov_trace: np.ndarray  # (N,) their traces, which bound them (``_may_lie_on``)
    edge_kinds: np.ndarray  # (N,) EdgeKind
    directions: np.ndarray  # (C, 3) the hemisphere's cells (``_direction_index``)
    lut: np.ndarray  # (P, A) int32, the nearest cell of each (polar, azimuth) bin
    neighbours: np.ndarray  # (C, K) int32, the cells a vote can reach from each cell
    k2: float  # sqrt(chi2_2): the error regions' radius in standard deviations
    chi2_2: float  # critical value of the point-on-line test, chi2(2) at alpha
    spacing: float  # expected edge-point spacing along an edge, metres
    m_min: int  # the fewest points that make a line
    min_edge: float  # the shortest box edge, metres


@dataclass(frozen=True)
class _Segment:
    """A line segment one trial found: a row of the ``LineSet``."""

    point: np.ndarray  # (3,) centroid of the support, metres
    direction: np.ndarray  # (3,) unit
    cov: np.ndarray  # (6, 6) of (point, direction)
    start: np.ndarray  # (3,) metres
    end: np.ndarray  # (3,) metres
    support: np.ndarray  # (n,) edge-point indices, ordered along the direction
    stat: np.ndarray  # (n,) their chi2(2) point-on-line statistics, same order
    kind: int  # the EdgeKind most of the support has
    dir_votes: float  # height of the direction accumulator's peak
    pos_votes: float  # height of the position accumulator's peak


def _trial(fixed: _TrialInputs, i0: int, nb: np.ndarray, live: np.ndarray,
           rng: np.random.Generator) -> list[_Segment]:
    """One constrained Hough trial from the distinguished edge point ``i0``.

    Parameters
    ----------
    fixed : _TrialInputs
    i0 : int
        The distinguished point.
    nb : ndarray (n,) int64
        Its live neighbours within the vote radius (``i0`` excluded), the voters.
    live : ndarray (n_alive,) int64
        The points no earlier segment took, ascending; the inliers are sought among them.
    rng : numpy.random.Generator
        Draws the voters when there are more than ``MAX_VOTERS``.

    Returns
    -------
    list of _Segment
        The segments of the line found, in order along it; empty when the trial finds
        none.
    """
    P, C, m_min, k2, chi2_2 = (fixed.points, fixed.covariances, fixed.m_min, fixed.k2,
                               fixed.chi2_2)
    p0 = P[i0]
    V = P[nb] - p0
    ell = np.linalg.norm(V, axis=1)
    ok = ell > 0
    nb, V, ell = nb[ok], V[ok], ell[ok]
    d = V / ell[:, None]
    # propagated angular error: J (S_i + S_0) J^T with J = (I - d d^T) / l; trace/2
    Ssum = C[nb] + C[i0]
    tr = np.einsum("nii->n", Ssum) - np.einsum("ni,nij,nj->n", d, Ssum, d)
    sig_theta = np.sqrt(np.maximum(tr, 0) / 2.0) / ell
    rad = k2 * sig_theta
    use = rad <= MAX_VOTE_RADIUS
    if use.sum() < m_min:
        return []
    vi = np.flatnonzero(use)
    if len(vi) > MAX_VOTERS:
        vi = np.sort(rng.choice(vi, MAX_VOTERS, replace=False))
    # each point votes for every cell of its error region
    acc = _vote_directions(d[vi], rad[vi], fixed.lut, fixed.neighbours, fixed.directions)
    peak = int(np.argmax(acc))
    b = fixed.directions[peak]
    dir_votes = float(acc[peak])
    # points whose error region contains the peak: refine the direction from them
    cosang = np.abs(d @ b)
    agree = np.arccos(np.clip(cosang, -1, 1)) <= np.maximum(rad, 2 * np.arcsin(0.5 * 1e-3))
    agree &= use
    if agree.sum() < m_min - 1:
        return []
    dd = d[agree] * np.sign(d[agree] @ b)[:, None]
    b = dd.mean(0)
    b /= np.linalg.norm(b)

    # HT-2: offset of the line from p0 in the plane perpendicular to b
    e1, e2 = _perp_basis(b)
    E = np.stack([e1, e2])
    sel = np.concatenate([[i0], nb[agree]])
    O = (P[sel] - p0) @ E.T  # (m, 2)
    S2 = np.einsum("ij,njk,lk->nil", E, C[sel], E)
    sig2d = np.sqrt(np.maximum(np.einsum("nii->n", S2) / 2.0, 1e-12))
    cell = float(np.median(sig2d))
    half = int(math.ceil(3 * k2 * sig2d[0] / cell)) + 1
    g = np.arange(-half, half + 1) * cell
    # gaussian-weighted votes truncated at the chi2(2) region, one vote per point; the
    # separable kernel makes the accumulator a product of (points x cells) matrices
    wx = np.exp(-0.5 * ((g[None, :] - O[:, :1]) / sig2d[:, None]) ** 2)
    wy = np.exp(-0.5 * ((g[None, :] - O[:, 1:]) / sig2d[:, None]) ** 2)
    tot = wx.sum(1) * wy.sum(1)
    scale = np.where(tot > 0, 1.0 / np.maximum(tot, 1e-300), 0.0)
    acc2 = (wx * scale[:, None]).T @ wy
    acc2[acc2 < 0] = 0.0
    pk = np.unravel_index(int(np.argmax(acc2)), acc2.shape)
    pos_votes = float(acc2[pk])
    anchor = p0 + g[pk[0]] * e1 + g[pk[1]] * e2

    # inliers among all live points, two rounds of TLS refit
    c, bb = anchor, b
    inl = live[:0]
    for _ in range(2):
        # the full test on the points the trace bound leaves: the same inliers, cheaper
        cand = _may_lie_on(P, fixed.cov_trace, live, c, bb, chi2_2)
        T, _t = _point_on_line_stat(P[cand], C[cand], c, bb)
        inl = cand[T <= chi2_2]
        if len(inl) < m_min:
            return []
        c, bb, _w = _tls(P[inl])
    T, t = _point_on_line_stat(P[inl], C[inl], c, bb)
    keep = T <= chi2_2
    inl, T, t = inl[keep], T[keep], t[keep]
    if len(inl) < m_min:
        return []
    # segments: split at gaps larger than a quarter of the shortest box edge
    gap = max(0.25 * fixed.min_edge, 4.0 * fixed.spacing)
    found: list[_Segment] = []
    for grp in _split_at_gaps(t, gap):
        if len(grp) < m_min:
            continue
        idx = inl[grp]
        extent = float(t[grp].max() - t[grp].min())
        if extent < 0.5 * fixed.min_edge:
            continue
        cs, bs, cov, ts = fit_segment(P[idx], C[idx])
        if bs @ b < 0:
            bs = -bs
            ts = -ts
        Tseg, _ = _point_on_line_stat(P[idx], C[idx], cs, bs)
        kinds = np.bincount(fixed.edge_kinds[idx], minlength=5)
        order = np.argsort(ts)
        found.append(_Segment(
            point=cs, direction=bs, cov=cov, start=cs + ts.min() * bs, end=cs + ts.max() * bs,
            support=idx[order], stat=Tseg[order], kind=int(np.argmax(kinds[1:]) + 1),
            dir_votes=dir_votes, pos_votes=pos_votes,
        ))
    return found


def _to_lineset(
    segments: list[_Segment], trial_of: list[int], n_trials: int, eps0: float, config: Config,
    seed: int, budget_row: TestTable,
) -> LineSet:
    L = len(segments)
    sup = [s.support for s in segments]
    offs = np.zeros(L + 1, np.int64)
    if L:
        offs[1:] = np.cumsum([len(s) for s in sup])

    def stack(rows: list[np.ndarray], shape: tuple[int, ...]) -> np.ndarray:
        return np.array(rows, dtype=np.float64).reshape((L, *shape))

    # one point-on-line test per segment: its worst support point
    tests = [TestTable.chi2(TestKind.POINT_ON_LINE, i, len(s.support), float(s.stat.max()), 2.0,
                            config.alpha) for i, s in enumerate(segments)]
    return LineSet(
        points=stack([s.point for s in segments], (3,)),
        directions=stack([s.direction for s in segments], (3,)),
        covariances=stack([s.cov for s in segments], (6, 6)),
        starts=stack([s.start for s in segments], (3,)),
        ends=stack([s.end for s in segments], (3,)),
        n_support=np.array([len(s) for s in sup], np.int32),
        support_offsets=offs,
        support=(np.concatenate(sup) if L else np.zeros(0)).astype(np.int32),
        support_statistic=(
            np.concatenate([s.stat for s in segments]) if L else np.zeros(0)
        ).astype(np.float32),
        kinds=np.array([s.kind for s in segments], np.uint8),
        trial=np.array(trial_of, np.int32),
        direction_votes=np.array([s.dir_votes for s in segments], np.float64),
        position_votes=np.array([s.pos_votes for s in segments], np.float64),
        n_trials=int(n_trials),
        epsilon=float(eps0),
        p_success=float(config.p_success),
        seed=int(seed),
        tests=TestTable.concat([*tests, budget_row], config.alpha),
    )

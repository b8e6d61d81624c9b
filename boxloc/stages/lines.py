"""Stage 3: 3D line segments by a series of constrained Hough transforms.

After Katsoulas (IbPRIA 2003, the paper's ref [6]) and Olson (IJCV 2001, ref [9]): each
trial draws one *distinguished* edge point p0 (k = 1), which leaves a line two free
parameters; they are recovered in two 2-D Hough transforms:

1. **direction** — every other edge point p_i near p0 votes for the direction
   (p_i - p0)/|p_i - p0| on an icosahedral tessellation of the hemisphere (Jeltsch, Dalitz
   & Pohle-Fröhlich 2016), for every cell inside its propagated error region (the chi2(2)
   ellipse at alpha on the tangent plane, long toward the ray when range noise dominates;
   bounded-error voting): far points vote sharply, near points broadly, and the peak
   counts the points consistent with one direction;
2. **position** — the points are projected on the plane perpendicular to the found
   direction and vote for the line's offset from p0 in a 2-D accumulator, again spread by
   their propagated error, so p0's own noise does not fix the line.

The inliers (point-on-line test, chi2(2) at alpha) are refitted by total least squares,
with covariance, and split into segments at gaps. Olson's bound gives the number of
trials: t = ceil(ln(1 - P) / ln(1 - eps)), eps = the fraction of edge points on the
smallest line worth finding. The search stops after t trials in all (each such line is hit
with probability P), or sooner after t' consecutive trials that find nothing, t' the same
count for the points no line has taken yet.
"""

from __future__ import annotations

import hashlib
import math
import zipfile
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, cast

import numpy as np
from scipy.spatial import cKDTree

from boxloc.config import Config
from boxloc.kernels import kernel
from boxloc.products import EdgeMap, LineSet
from boxloc.scan import Scan
from boxloc.stats import BUDGET_LINES, TestKind, TestTable, chi2_critical

#: Largest angular error region a direction vote may spread over on a low-noise scan;
#: nearer points carry almost no direction information and only slow the accumulator down.
MAX_VOTE_RADIUS = math.radians(8.0)
#: The cap never exceeds this, however noisy the scan: wider regions make every voter
#: vote for a sizeable part of the hemisphere, and the peak is no longer specific.
MAX_VOTE_RADIUS_NOISY = math.radians(16.0)
#: On a noisy scan the cap lets a typical voter this far out (a share of the vote radius)
#: vote: see :func:`vote_radius_cap`.
VOTE_CAP_REACH = 1.0 / 3.0
#: ``MAX_VOTE_RADIUS`` and ``MAX_VOTE_RADIUS_NOISY`` in whole degrees, as the caps are counted
_QUIET_CAP_DEG = round(math.degrees(MAX_VOTE_RADIUS))
_NOISY_CAP_DEG = round(math.degrees(MAX_VOTE_RADIUS_NOISY))
#: The fewest points that make a line, however near the sensor.
MIN_LINE_POINTS = 6
#: Points voting per trial (a seeded random subset when there are more): the peak's
#: relative height does not depend on it, the cost does.
MAX_VOTERS = 300
#: Direction votes come from points within this many shortest box edges of the
#: distinguished point: far enough for a sharp direction (the error shrinks with distance),
#: near enough that the line's own points are not drowned by the rest of the scene.
VOTE_RADIUS_EDGES = 3.0


_T = (1.0 + 5**0.5) / 2.0
#: The icosahedron the direction tessellation subdivides: its 12 vertices (not normalized)
#: and its 20 faces (vertex indices), in the order that numbers the directions.
ICOSAHEDRON_VERTICES = ((-1, _T, 0), (1, _T, 0), (-1, -_T, 0), (1, -_T, 0), (0, -1, _T),
                        (0, 1, _T), (0, -1, -_T), (0, 1, -_T), (_T, 0, -1), (_T, 0, 1),
                        (-_T, 0, -1), (-_T, 0, 1))
ICOSAHEDRON_FACES = ((0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9),
                     (5, 11, 4), (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2),
                     (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10),
                     (8, 6, 7), (9, 8, 1))


def _unit_rows(m: np.ndarray) -> np.ndarray:
    """The rows of (n, 3) ``m`` over their lengths, by element-wise operations only: the same
    bits on every CPU. (``np.linalg.norm`` of one vector is ``sqrt(dot(m, m))``, BLAS's dot,
    whose rounding is its kernel's for the CPU: on an AVX-512 machine it differed from the
    element-wise sum in the last bit for a tenth of random vectors.)"""
    return m / np.sqrt(m[:, 0] * m[:, 0] + m[:, 1] * m[:, 1] + m[:, 2] * m[:, 2])[:, None]


@lru_cache(maxsize=8)
def hemisphere_directions(granularity: int) -> np.ndarray:
    """Unit directions of a subdivided icosahedron on the upper hemisphere, (n, 3).

    Granularity 0..6 gives 6, 21, 81, 321, 1281, 5121, 20481 directions (z >= 0, with
    only half of the equator kept), as in Dalitz et al., IPOL 2017.

    Each level splits every face in four at its edges' normalized midpoints; a midpoint is
    numbered where its edge first occurs (faces in order, edges ab, bc, ca), as a loop over
    the faces would number it (``tests/test_lines.py`` holds that loop: the same bits).
    """
    V = _unit_rows(np.array(ICOSAHEDRON_VERTICES, float))
    F = np.array(ICOSAHEDRON_FACES, np.int64)
    for _ in range(granularity):
        n = len(V)
        E = F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        key = np.minimum(E[:, 0], E[:, 1]) * n + np.maximum(E[:, 0], E[:, 1])
        _, first, inv = np.unique(key, return_index=True, return_inverse=True)
        rank = np.empty(len(first), np.int64)
        rank[np.argsort(first, kind="stable")] = np.arange(len(first))
        m = V[E[first, 0]] + V[E[first, 1]]
        V = np.concatenate([V, np.empty((len(first), 3))])
        V[n + rank] = _unit_rows(m)
        mid = (n + rank[inv]).reshape(-1, 3)  # each face's ab, bc, ca
        a, b, c = F.T
        ab, bc, ca = mid.T
        F = np.stack([a, ab, ca, b, bc, ab, c, ca, bc, ab, bc, ca], 1).reshape(-1, 3)
    eps = 1e-9
    keep = (V[:, 2] > eps) | (
        (np.abs(V[:, 2]) <= eps) & ((V[:, 0] > eps) | ((np.abs(V[:, 0]) <= eps) & (V[:, 1] > 0)))
    )
    return V[keep]


#: Resolution of the lookup table from (polar, azimuth) to the nearest direction cell.
_LUT_POLAR, _LUT_AZIMUTH = 256, 512


@lru_cache(maxsize=8)
def _direction_lut(granularity: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, cKDTree, np.ndarray]:
    """The tessellation's cells, both signs of them with their hemisphere cell and their
    kd-tree, and the lookup table from (polar, azimuth) bins to the nearest cell: what
    :func:`_direction_index` needs whatever the vote cap (built once per granularity; the
    table's 131 072 nearest-cell queries are most of the work)."""
    D = hemisphere_directions(granularity)
    both = np.concatenate([D, -D])
    hemi = np.concatenate([np.arange(len(D)), np.arange(len(D))])
    tree = cKDTree(both)
    th = (np.arange(_LUT_POLAR) + 0.5) * math.pi / _LUT_POLAR
    ph = (np.arange(_LUT_AZIMUTH) + 0.5) * 2 * math.pi / _LUT_AZIMUTH
    # Query the upper half of the bins only (half the time): a lower bin is an upper one's
    # antipode (polar pi - theta, azimuth + pi), whose nearest cell is the antipodal one,
    # the same hemisphere cell. Its coordinates are the antipode's only to rounding, so
    # tests/test_lines.py checks the table against querying every bin, granularities 2-6.
    T, F = np.meshgrid(th[: _LUT_POLAR // 2], ph, indexing="ij")
    q = np.stack([np.sin(T) * np.cos(F), np.sin(T) * np.sin(F), np.cos(T)], -1).reshape(-1, 3)
    upper = hemi[tree.query(q)[1]].reshape(_LUT_POLAR // 2, _LUT_AZIMUTH)
    lut = np.concatenate([upper, np.roll(upper[::-1], _LUT_AZIMUTH // 2, axis=1)])
    return D, both, hemi, tree, lut.astype(np.int32)


@lru_cache(maxsize=64)
def _direction_index(granularity: int, cap_deg: int = _QUIET_CAP_DEG
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lookup structures for voting on the tessellation, for votes of at most ``cap_deg``
    degrees radius: :func:`build_direction_index`'s, read from :data:`DIRECTION_TABLES`
    where set-up saved them for this code (the same arrays, bit for bit), else built."""
    saved = _saved_direction_index(granularity, cap_deg)
    return saved if saved is not None else build_direction_index(granularity, cap_deg)


#: The direction tables a default configuration can use, saved at set-up
#: (:func:`save_direction_tables`, run by ``scripts/warm_up.py``): a process's first scan
#: reads them (about 2 ms) instead of building them (40-100 ms, most of the first scan's
#: extra time in the line stage). Not in git; a missing or stale file is built around.
DIRECTION_TABLES = Path(__file__).resolve().parent.parent / "_direction_tables.npz"


@lru_cache(maxsize=1)
def _tables_stamp() -> str:
    """What the saved tables were computed by: this module's source and NumPy's and SciPy's
    versions (the kd-tree's nearest cells and the subdivision's rounding are theirs). Once
    per process: every vote cap's first use compares it."""
    import scipy

    h = hashlib.sha256(Path(__file__).read_bytes())
    h.update(f"{np.__version__} {scipy.__version__}".encode())
    return h.hexdigest()[:16]


def _saved_direction_index(granularity: int, cap_deg: int
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The tables for (granularity, cap) from :data:`DIRECTION_TABLES`, or None where the
    file is missing, unreadable, stale or without them."""
    key = f"{granularity}_{cap_deg}"
    try:
        with np.load(DIRECTION_TABLES, allow_pickle=False) as z:
            if f"nbr_{key}" not in z.files or str(z["stamp"]) != _tables_stamp():
                return None
            return z[f"lut_{granularity}"], z[f"nbr_{key}"], z[f"dirs_{granularity}"]
    except (OSError, ValueError, KeyError, zipfile.BadZipFile):
        return None


def default_direction_tables() -> list[tuple[int, int]]:
    """The (granularity, cap) pairs the line stage can ask for at the config's default
    granularity: every whole-degree vote cap from the quiet to the noisy one, each at its
    :func:`vote_granularity`."""
    g = Config().direction_granularity
    caps = range(_QUIET_CAP_DEG, _NOISY_CAP_DEG + 1)
    return sorted({(vote_granularity(g, c), c) for c in caps})


def save_direction_tables(path: Path | None = None,
                          pairs: list[tuple[int, int]] | None = None) -> Path:
    """Build the direction tables of ``pairs`` (:func:`default_direction_tables` when None)
    and save them, with their :func:`_tables_stamp`, to ``path`` (:data:`DIRECTION_TABLES`
    when None), written whole to a temporary file and renamed. Returns the path."""
    path = DIRECTION_TABLES if path is None else Path(path)
    arrays: dict[str, np.ndarray] = {"stamp": np.array(_tables_stamp())}
    for g, cap in default_direction_tables() if pairs is None else pairs:
        lut, nbr, D = build_direction_index(g, cap)
        arrays[f"lut_{g}"], arrays[f"dirs_{g}"], arrays[f"nbr_{g}_{cap}"] = lut, D, nbr
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        # uncompressed: read in about a millisecond (NumPy's stubs type a keyword as allow_pickle)
        cast(Any, np.savez)(f, **arrays)
    tmp.replace(path)
    return path


def build_direction_index(granularity: int, cap_deg: int = _QUIET_CAP_DEG
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Build the lookup structures for voting on the tessellation, for votes of at most
    ``cap_deg`` degrees radius.

    Returns
    -------
    lut : (P, A) int32
        Nearest hemisphere cell of each (polar, azimuth) bin of the whole sphere.
    nbr : (C, K) int32
        For each cell, the cells within ``cap_deg`` plus two cell spacings (-1 pads).
    D : (C, 3) float64
        Cell directions.
    """
    D, both, hemi, tree, lut = _direction_lut(granularity)
    spacing = math.sqrt(4 * math.pi / len(both))
    reach = 2 * math.sin((math.radians(cap_deg) + 2 * spacing) / 2)
    lists = tree.query_ball_point(D, reach)
    # each cell's neighbours as hemisphere cells, sorted and unique, in one pass over all
    row = np.repeat(np.arange(len(D)), [len(li) for li in lists])
    cell = hemi[np.concatenate([np.asarray(li, np.int64) for li in lists])]
    order = np.lexsort((cell, row))
    row, cell = row[order], cell[order]
    new = np.ones(len(row), bool)
    new[1:] = (row[1:] != row[:-1]) | (cell[1:] != cell[:-1])
    row, cell = row[new], cell[new]
    counts = np.bincount(row, minlength=len(D))
    col = np.arange(len(row)) - np.repeat(np.cumsum(counts) - counts, counts)
    nbr = np.full((len(D), int(counts.max())), -1, np.int32)
    nbr[row, col] = cell
    return lut, nbr, D


@kernel
def _vote_directions(d: np.ndarray, ainv: np.ndarray, k22: float, cap: float,
                     lut: np.ndarray, nbr: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Each direction d_i votes 1 for every cell of its error ellipse around +-d_i
    (``ainv`` as :func:`_vote_inputs`, at ``k22`` = k2^2) within ``cap`` radians of it.

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
        cr = math.cos(cap)
        e1, e2 = _perp(d[i])
        n = 0
        for k in range(nbr.shape[1]):
            c = nbr[c0, k]
            if c < 0:
                break
            if abs(D[c, 0] * x + D[c, 1] * y + D[c, 2] * z) < cr:
                continue
            # the form is even: -D[c] (the other hemisphere's cell) reads the same
            p1 = D[c, 0] * e1[0] + D[c, 1] * e1[1] + D[c, 2] * e1[2]
            p2 = D[c, 0] * e2[0] + D[c, 1] * e2[1] + D[c, 2] * e2[2]
            if ainv[i, 0] * p1 * p1 + 2.0 * ainv[i, 1] * p1 * p2 + ainv[i, 2] * p2 * p2 <= k22:
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


@kernel
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


@kernel
def _long_groups(t: np.ndarray, gap: float, m_min: int, min_extent: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The runs of positions ``t`` (metres along a line) with no gap larger than ``gap``
    that hold at least ``m_min`` points over at least ``min_extent``.

    Returns
    -------
    order : (n,) int64, the stable sort of ``t``; bounds : (k, 2) int64, each run's
    [start, end) in ``order``, along the line.
    """
    order = np.argsort(t, kind="mergesort")  # stable
    n = t.shape[0]
    bounds = np.empty((n, 2), np.int64)
    k = 0
    lo = 0
    for i in range(1, n + 1):
        if i == n or t[order[i]] - t[order[i - 1]] > gap:
            if i - lo >= m_min and t[order[i - 1]] - t[order[lo]] >= min_extent:
                bounds[k, 0] = lo
                bounds[k, 1] = i
                k += 1
            lo = i
    return order, bounds[:k]


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

    radius = min(config.max_edge, VOTE_RADIUS_EDGES * config.min_edge)
    cov_trace = np.einsum("nii->n", C)
    cap_deg = vote_radius_cap(cov_trace, k2, radius)
    lut, nbr, dirs = _direction_index(vote_granularity(config.direction_granularity, cap_deg),
                                      cap_deg)
    fixed = _TrialInputs(
        points=P, covariances=C, cov_trace=cov_trace, edge_kinds=edges.kinds,
        directions=dirs, lut=lut, neighbours=nbr, k2=k2, chi2_2=chi2_2, spacing=spacing,
        m_min=m_min, min_edge=config.min_edge, max_vote_radius=math.radians(cap_deg),
    )
    ptree = cKDTree(P)
    near: dict[int, np.ndarray] = {}  # each drawn point's neighbours within the radius

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

    needed = needed_trials(n_alive)  # changes only with n_alive
    # Olson's count as a total: in needed(N) trials every line of m_min points is hit with
    # probability p_success (a found line's points leave the draw, which only raises the
    # others' chances). A run of that many failures since the last line found ends the
    # search sooner where the edges are few; the total bounds it on cluttered scans.
    total = needed
    while n_alive >= m_min and fails < needed and trial < total:
        if budget and work >= budget:
            exhausted = True
            break
        trial += 1
        i0 = int(alive_idx[rng.integers(len(alive_idx))])
        nb = near.get(i0)
        if nb is None:  # a point is drawn again and again when the trials run long
            nb = near[i0] = np.asarray(ptree.query_ball_point(P[i0], radius), dtype=np.int64)
        nb = _live_neighbours(nb, alive, i0)
        work += len(nb)
        found = _trial(fixed, i0, nb, alive_idx, rng) if len(nb) >= m_min else []
        for seg in found:
            alive[seg.support] = False
            segments.append(seg)
            trial_of.append(trial)
        if found:
            alive_idx = np.flatnonzero(alive)  # changes only here
            n_alive = int(alive.sum())
            needed = needed_trials(n_alive)
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
    max_vote_radius: float  # the largest error region a vote spreads over, radians


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
    P, C, m_min = fixed.points, fixed.covariances, fixed.m_min
    nb, d, use, vi, ainv = _vote_inputs(P, C, nb, i0, fixed.k2, fixed.max_vote_radius)
    if len(vi) < m_min:
        return []
    if len(vi) > MAX_VOTERS:
        vi = np.sort(rng.choice(vi, MAX_VOTERS, replace=False))
    ok, b, anchor, dir_votes, pos_votes = _hough(
        P, C, nb, d, ainv, use, vi, i0, fixed.lut, fixed.neighbours, fixed.directions,
        fixed.k2, m_min, fixed.max_vote_radius)
    if not ok:
        return []
    inl, T, t = _inliers(P, C, fixed.cov_trace, live, anchor, b, fixed.chi2_2, m_min)
    if len(inl) < m_min:
        return []
    # segments: split at gaps larger than a quarter of the shortest box edge
    gap = max(0.25 * fixed.min_edge, 4.0 * fixed.spacing)
    found: list[_Segment] = []
    along, bounds = _long_groups(t, gap, m_min, 0.5 * fixed.min_edge)
    for lo, hi in bounds:
        idx = inl[along[lo:hi]]
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


# --- the trial's kernels --------------------------------------------------------------------


def vote_granularity(granularity: int, cap_deg: int) -> int:
    """The tessellation a scan's direction votes use: ``granularity`` on a quiet scan, one
    level coarser (cells twice as far apart) for each doubling of the vote cap over
    ``MAX_VOTE_RADIUS``, but never below 2. Each vote then covers about as many cells as
    on a quiet scan (wide error regions over fine cells cost their square and sharpen
    nothing: the peak's direction is refined from the voters that hold it)."""
    steps = int(math.floor(math.log2(max(cap_deg, _QUIET_CAP_DEG) / _QUIET_CAP_DEG)))
    return max(2, min(granularity, granularity - steps))


def vote_radius_cap(cov_trace: np.ndarray, k2: float, radius: float) -> int:
    """The largest error region a direction vote may spread over, whole degrees.

    ``MAX_VOTE_RADIUS`` on a low-noise scan. On a noisy one, the cap is widened so that a
    typical voter beyond ``VOTE_CAP_REACH`` of the vote radius (two thirds of a line's
    voters) still votes: its region, k2 x sqrt(2) x the points' typical standard deviation
    over that distance, as :func:`_vote_inputs` propagates it. Otherwise a sensor whose
    edge points scatter by centimetres (a structured-light camera at 3 m) gets no votes at
    all, however long its edges. At most ``MAX_VOTE_RADIUS_NOISY``. A function of the edge
    points' covariances and the config, so a post-mortem recomputes it from the log.

    Parameters
    ----------
    cov_trace : (N,) float64
        Traces of the edge points' covariances, m^2.
    k2 : float
        The error regions' radius in standard deviations.
    radius : float
        The vote radius, metres.
    """
    if cov_trace.size == 0 or not radius > 0:
        return _QUIET_CAP_DEG
    sd = math.sqrt(max(float(np.median(cov_trace)), 0.0) / 3.0)  # per axis
    need = math.degrees(k2 * math.sqrt(2.0) * sd / (VOTE_CAP_REACH * radius))
    return int(min(max(_QUIET_CAP_DEG, math.ceil(need)), _NOISY_CAP_DEG))


@kernel
def _live_neighbours(nb: np.ndarray, alive: np.ndarray, i0: int) -> np.ndarray:
    """``nb[alive[nb] & (nb != i0)]``, in one pass: the neighbours no segment took."""
    out = np.empty(nb.shape[0], np.int64)
    k = 0
    for j in range(nb.shape[0]):
        i = nb[j]
        if alive[i] and i != i0:
            out[k] = i
            k += 1
    return out[:k]


@kernel
def _vote_inputs(P: np.ndarray, C: np.ndarray, nb: np.ndarray, i0: int, k2: float,
                 max_radius: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The voters' directions from p0 and their error regions.

    Parameters
    ----------
    P : (N, 3) float64, metres; C : (N, 3, 3) their covariances
    nb : (n,) int64
        The neighbours of ``i0``.
    i0 : int
        The distinguished point p0.
    k2 : float
        The regions' radius in standard deviations, sqrt(chi2_2).

    max_radius : float
        The largest error region that votes, radians (:func:`vote_radius_cap`).

    Returns
    -------
    nb : (m,) the neighbours apart from p0 (distance > 0); d : (m, 3) unit directions
    p_i - p0; use : (m,) bool, the error region's short semi-axis (k2 x the smaller sd of
    J (S_i + S_0) J^T, J = (I - d d^T) / l) at most ``max_radius``; vi : the indices where
    ``use`` is true, ascending; ainv : (m, 3) the inverse of J (S_i + S_0) J^T on the
    tangent plane in the basis :func:`_perp` (d): entries 11, 12, 22. The region is the
    ellipse where that quadratic form is at most k2^2: range noise makes it long toward the
    ray and short across it, and a circle of half the trace would spread a direction that
    is sharp across the ray over tens of degrees.
    """
    n = nb.shape[0]
    keep = np.empty(n, np.int64)
    d = np.empty((n, 3))
    ainv = np.empty((n, 3))
    minor = np.empty(n)
    m = 0
    for j in range(n):
        i = nb[j]
        v0 = P[i, 0] - P[i0, 0]
        v1 = P[i, 1] - P[i0, 1]
        v2 = P[i, 2] - P[i0, 2]
        ell = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        if not ell > 0:
            continue
        u0, u1, u2 = v0 / ell, v1 / ell, v2 / ell
        keep[m] = i
        d[m, 0], d[m, 1], d[m, 2] = u0, u1, u2
        # the error region's ellipse on the tangent plane at d: (e1, e2) = _perp(d)
        e1, e2 = _perp(d[m])
        s11 = s12 = s22 = 0.0
        for a in range(3):
            for c in range(3):
                cc = C[i, a, c] + C[i0, a, c]
                s11 += e1[a] * cc * e1[c]
                s12 += e1[a] * cc * e2[c]
                s22 += e2[a] * cc * e2[c]
        s11 /= ell * ell
        s12 /= ell * ell
        s22 /= ell * ell
        det = max(s11 * s22 - s12 * s12, 1e-30)
        ainv[m, 0] = s22 / det
        ainv[m, 1] = -s12 / det
        ainv[m, 2] = s11 / det
        # its minor semi-axis, radians
        half = 0.5 * (s11 + s22)
        disc = math.sqrt(max(half * half - det, 0.0))
        minor[m] = k2 * math.sqrt(max(half - disc, 0.0))
        m += 1
    use = minor[:m] <= max_radius
    return keep[:m], d[:m], use, np.flatnonzero(use), ainv[:m]


@kernel
def _perp(b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors perpendicular to unit b and to each other (as :func:`_perp_basis`)."""
    if abs(b[0]) < 0.9:
        a0, a1, a2 = 1.0, 0.0, 0.0
    else:
        a0, a1, a2 = 0.0, 1.0, 0.0
    e1 = np.array([b[1] * a2 - b[2] * a1, b[2] * a0 - b[0] * a2, b[0] * a1 - b[1] * a0])
    e1 /= math.sqrt(e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2])
    e2 = np.array([b[1] * e1[2] - b[2] * e1[1], b[2] * e1[0] - b[0] * e1[2],
                   b[0] * e1[1] - b[1] * e1[0]])
    return e1, e2


@kernel
def _hough(P: np.ndarray, C: np.ndarray, nb: np.ndarray, d: np.ndarray, ainv: np.ndarray,
           use: np.ndarray, vi: np.ndarray, i0: int, lut: np.ndarray, nbr: np.ndarray,
           D: np.ndarray, k2: float, m_min: int, cap: float
           ) -> tuple[bool, np.ndarray, np.ndarray, float, float]:
    """The two Hough transforms of one trial: the line's direction, then its position.

    HT-1: the voters ``vi`` vote over their error ellipses (:func:`_vote_directions`, at
    most ``cap`` radians out); the points whose ellipse holds the peak refine the direction
    (their mean). HT-2: p0 and
    those points, projected on the plane perpendicular to it, vote for the line's offset
    from p0, each with a Gaussian of its projected error truncated at the chi2(2) region
    (one vote per point; the kernel is separable).

    Returns
    -------
    ok : bool
        False when fewer than ``m_min - 1`` points agree with the peak.
    direction : (3,) unit; anchor : (3,) a point of the line, metres; dir_votes, pos_votes :
    the two peaks' heights.
    """
    z3 = np.zeros(3)
    acc = _vote_directions(d[vi], ainv[vi], k2 * k2, cap, lut, nbr, D)
    peak = int(np.argmax(acc))
    b0 = D[peak]
    dir_votes = acc[peak]
    floor = 2.0 * math.asin(0.5 * 1e-3)
    n = d.shape[0]
    agree = np.zeros(n, np.bool_)
    na = 0
    s0 = s1 = s2 = 0.0
    for j in range(n):
        c = abs(d[j, 0] * b0[0] + d[j, 1] * b0[1] + d[j, 2] * b0[2])
        e1, e2 = _perp(d[j])
        p1 = b0[0] * e1[0] + b0[1] * e1[1] + b0[2] * e1[2]
        p2 = b0[0] * e2[0] + b0[1] * e2[1] + b0[2] * e2[2]
        inside = (ainv[j, 0] * p1 * p1 + 2.0 * ainv[j, 1] * p1 * p2 + ainv[j, 2] * p2 * p2
                  <= k2 * k2)
        if use[j] and (inside or math.acos(min(max(c, -1.0), 1.0)) <= floor):
            agree[j] = True
            na += 1
            dot = d[j, 0] * b0[0] + d[j, 1] * b0[1] + d[j, 2] * b0[2]
            sg = 1.0 if dot > 0 else (-1.0 if dot < 0 else 0.0)
            s0 += d[j, 0] * sg
            s1 += d[j, 1] * sg
            s2 += d[j, 2] * sg
    if na < m_min - 1:
        return False, z3, z3, 0.0, 0.0
    b = np.array([s0 / na, s1 / na, s2 / na])
    b /= math.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2])

    # HT-2: the offset of the line from p0 in the plane perpendicular to b
    e1, e2 = _perp(b)
    m = na + 1
    sel = np.empty(m, np.int64)
    sel[0] = i0
    k = 1
    for j in range(n):
        if agree[j]:
            sel[k] = nb[j]
            k += 1
    O = np.empty((m, 2))
    sig = np.empty(m)
    for q in range(m):
        i = sel[q]
        v0 = P[i, 0] - P[i0, 0]
        v1 = P[i, 1] - P[i0, 1]
        v2 = P[i, 2] - P[i0, 2]
        O[q, 0] = v0 * e1[0] + v1 * e1[1] + v2 * e1[2]
        O[q, 1] = v0 * e2[0] + v1 * e2[1] + v2 * e2[2]
        t11 = 0.0
        t22 = 0.0
        for a in range(3):
            for c in range(3):
                t11 += e1[a] * C[i, a, c] * e1[c]
                t22 += e2[a] * C[i, a, c] * e2[c]
        sig[q] = math.sqrt(max((t11 + t22) / 2.0, 1e-12))
    cell = np.median(sig)
    half = int(math.ceil(3.0 * k2 * sig[0] / cell)) + 1
    G = 2 * half + 1
    g = (np.arange(G) - half) * cell
    # the accumulator is a product of (cells x points) and (points x cells) matrices
    WXt = np.empty((G, m))
    WY = np.empty((m, G))
    for q in range(m):
        sx = 0.0
        sy = 0.0
        for a in range(G):
            WXt[a, q] = math.exp(-0.5 * ((g[a] - O[q, 0]) / sig[q]) ** 2)
            WY[q, a] = math.exp(-0.5 * ((g[a] - O[q, 1]) / sig[q]) ** 2)
            sx += WXt[a, q]
            sy += WY[q, a]
        tot = sx * sy
        scale = 1.0 / max(tot, 1e-300) if tot > 0 else 0.0
        for a in range(G):
            WXt[a, q] *= scale
    acc2 = WXt @ WY
    pk = int(np.argmax(acc2))
    pa, pc = pk // G, pk % G
    anchor = P[i0] + g[pa] * e1 + g[pc] * e2
    return True, b, anchor, dir_votes, acc2[pa, pc]


@kernel
def _on_line_stat(P: np.ndarray, C: np.ndarray, idx: np.ndarray, c: np.ndarray, b: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """chi2(2) statistic of each point ``idx`` against line (c, b), and its position t
    along the line (as :func:`_point_on_line_stat`)."""
    e1, e2 = _perp(b)
    n = idx.shape[0]
    T = np.empty(n)
    t = np.empty(n)
    for j in range(n):
        i = idx[j]
        d0 = P[i, 0] - c[0]
        d1 = P[i, 1] - c[1]
        d2 = P[i, 2] - c[2]
        t[j] = d0 * b[0] + d1 * b[1] + d2 * b[2]
        r0 = d0 * e1[0] + d1 * e1[1] + d2 * e1[2]
        r1 = d0 * e2[0] + d1 * e2[1] + d2 * e2[2]
        s00 = s01 = s11 = 0.0
        for a in range(3):
            for q in range(3):
                s00 += e1[a] * C[i, a, q] * e1[q]
                s01 += e1[a] * C[i, a, q] * e2[q]
                s11 += e2[a] * C[i, a, q] * e2[q]
        det = s00 * s11 - s01 * s01
        T[j] = (s11 * r0 * r0 - 2.0 * s01 * r0 * r1 + s00 * r1 * r1) / max(det, 1e-30)
    return T, t


@kernel
def _inliers(P: np.ndarray, C: np.ndarray, tr: np.ndarray, live: np.ndarray,
             anchor: np.ndarray, b: np.ndarray, crit: float, m_min: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The live points on the line through ``anchor`` along ``b``: the point-on-line test
    (chi2(2) at ``crit``) with two total-least-squares refits of the line.

    Returns
    -------
    inl : (k,) int64, ascending; T : (k,) their statistics; t : (k,) their positions along
    the last fit, metres. Fewer than ``m_min`` points: whatever was left (the trial fails).
    """
    c = anchor.copy()
    bb = b.copy()
    inl = live[:0]
    for _ in range(2):
        cand = _may_lie_on(P, tr, live, c, bb, crit)
        T, _t = _on_line_stat(P, C, cand, c, bb)
        inl = cand[T <= crit]
        k = inl.shape[0]
        if k < m_min:
            return inl, T[:0], T[:0]
        # the total-least-squares line of the inliers
        c = np.zeros(3)
        for j in range(k):
            for a in range(3):
                c[a] += P[inl[j], a]
        c /= k
        M = np.zeros((3, 3))
        for j in range(k):
            for a in range(3):
                for q in range(3):
                    M[a, q] += (P[inl[j], a] - c[a]) * (P[inl[j], q] - c[q])
        _w, V = np.linalg.eigh(M)
        bb = V[:, 2].copy()
    T, t = _on_line_stat(P, C, inl, c, bb)
    keep = T <= crit
    return inl[keep], T[keep], t[keep]


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

"""The peer baseline: box tops from open3d, the way common depalletizing demos find them.

    valid points -> voxel grid -> iterative RANSAC planes (near-horizontal ones kept)
    -> DBSCAN per plane (splits boxes that do not touch) -> minimum-area rectangle per cluster

This is the "region first" counterpart of Katsoulas's "boundary first" method (see
``method-notes.md`` section 6: open3d DBSCAN + ``minAreaRect``; RANSAC ground plane -> cluster
-> top plane -> minimal rectangle). It is meant as a fair peer, so it uses the same priors as
the localizer (box size range, largest tilt, noise model), refits every RANSAC plane by least
squares (so a wide top is not cut in two by a tilted 3-point plane) and rejects clusters that
fill their rectangle poorly (L-shaped merges). Its known limits are by construction: boxes
of equal height that touch (or stand within a DBSCAN radius) form one cluster, a partly
covered top whose visible part is rectangular looks like a smaller box, and visible pieces
of the pallet or floor of box size look like boxes (it knows no support height).

Determinism: open3d's RANSAC is seeded from the scan (``scan.seed``, with
``Config.trial_seed`` as for the localizer's trials) and runs all its
iterations (its early stop depends on thread timing), and each plane is then refitted by
least squares, so the same scan gives the same surfaces.
"""

from __future__ import annotations

import time
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from boxloc.config import Config
from boxloc.products import SurfaceSet
from boxloc.scan import Scan


def surface_set_from_rects(
    centers: npt.ArrayLike,
    normals: npt.ArrayLike,
    x_axis: npt.ArrayLike,
    width: npt.ArrayLike,
    length: npt.ArrayLike,
    *,
    grasp_points: npt.ArrayLike | None = None,
    scores: npt.ArrayLike | None = None,
    covariances: npt.ArrayLike | None = None,
    up: npt.ArrayLike | None = None,
) -> SurfaceSet:
    """Build a :class:`SurfaceSet` from rectangles, in pick order (highest along ``up`` first).

    Parameters
    ----------
    centers, normals, x_axis : array_like, shape (s, 3)
        Sensor frame, metres. ``normals`` are flipped toward the sensor (origin) if needed;
        ``x_axis`` is projected into the plane and normalized.
    width, length : array_like, shape (s,)
        Metres; swapped (with the axes) where width > length.
    grasp_points : array_like, shape (s, 3), optional
        Default: the centres.
    scores : array_like, shape (s,), optional
        Default: 1.
    covariances : array_like, shape (s, 6, 6), optional
        Default: identity * 1e-6 (1 mm, 1 mrad).
    up : array_like, shape (3,), optional
        The world's up in the sensor frame; default ``-z`` (see ``Scan.up``).

    Returns
    -------
    SurfaceSet
        ``y_axis = normal x x_axis`` (right-handed x, y, normal); corners
        ``c - x w/2 - y l/2``, then ``+x``, ``+x+y``, ``+y``; ``hypothesis`` and ``attempt``
        are -1; rows sorted by height along ``up``, ``pick_order = 0..s-1``.
    """
    C = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    s = C.shape[0]
    N = np.asarray(normals, dtype=np.float64).reshape(s, 3)
    X = np.asarray(x_axis, dtype=np.float64).reshape(s, 3)
    w = np.asarray(width, dtype=np.float64).reshape(s).copy()
    ln = np.asarray(length, dtype=np.float64).reshape(s).copy()
    N = N / np.linalg.norm(N, axis=1, keepdims=True).clip(1e-300)
    flip = np.einsum("ij,ij->i", N, C) > 0  # normal must point back toward the origin
    N[flip] *= -1
    X = X - N * np.einsum("ij,ij->i", X, N)[:, None]
    X = X / np.linalg.norm(X, axis=1, keepdims=True).clip(1e-300)
    Y = np.cross(N, X)
    swap = w > ln
    w[swap], ln[swap] = ln[swap].copy(), w[swap].copy()
    X[swap], Y[swap] = Y[swap].copy(), -X[swap].copy()  # keeps x, y, n right-handed
    G = C.copy() if grasp_points is None else np.asarray(grasp_points, np.float64).reshape(s, 3)
    S = np.ones(s) if scores is None else np.asarray(scores, np.float64).reshape(s)
    if covariances is None:
        Cov = np.broadcast_to(np.eye(6) * 1e-6, (s, 6, 6)).copy()
    else:
        Cov = np.asarray(covariances, np.float64).reshape(s, 6, 6)
    a = X * (0.5 * w)[:, None]
    b = Y * (0.5 * ln)[:, None]
    corners = np.stack([C - a - b, C + a - b, C + a + b, C - a + b], axis=1)
    up_v = np.array([0.0, 0.0, -1.0]) if up is None else np.asarray(up, np.float64).reshape(3)
    order = np.argsort(-(C @ up_v), kind="stable")
    return SurfaceSet(
        hypothesis=np.full(s, -1, np.int32),
        attempt=np.full(s, -1, np.int32),
        centers=C[order], normals=N[order], x_axis=X[order], y_axis=Y[order],
        width=w[order], length=ln[order], corners=corners[order], grasp_points=G[order],
        scores=S[order], covariances=Cov[order], pick_order=np.arange(s, dtype=np.int32),
    )


def empty_surface_set() -> SurfaceSet:
    """A SurfaceSet with no surface."""
    z = np.zeros((0, 3))
    return surface_set_from_rects(z, z, z, np.zeros(0), np.zeros(0))


def _plane_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane with normal ``n``."""
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(n, a)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def _fill_ratio(q: np.ndarray, rect: Any, cell: float) -> float:
    """Fraction of the rectangle's area covered by occupied ``cell``-sized grid cells."""
    (cx, cy), (a, b), ang = rect
    area = a * b
    if area <= 0:
        return 0.0
    t = np.radians(ang)
    R = np.array([[np.cos(t), np.sin(t)], [-np.sin(t), np.cos(t)]])
    local = (q - np.array([cx, cy])) @ R.T  # rectangle-aligned coordinates
    ij = np.floor(local / cell).astype(np.int64)
    occupied = np.unique(ij, axis=0).shape[0]
    return float(min(occupied * cell * cell / area, 1.0))


def baseline_surfaces(
    scan: Scan,
    *,
    config: Config | None = None,
    voxel: float = 0.005,
    max_planes: int = 40,
    ransac_iterations: int = 300,
    ransac_points: int = 20_000,
    normal_filter_deg: float = 0.0,
    min_fill: float = 0.75,
    timing: dict[str, float] | None = None,
) -> SurfaceSet:
    """Box top surfaces by RANSAC planes, DBSCAN and minimum-area rectangles (open3d).

    Parameters
    ----------
    scan : Scan
        The range scan (any sensor model); ``scan.up`` gives "up".
    config : Config, optional
        Uses ``noise`` (RANSAC distance = 3 sigma at the median range), ``min_edge`` and
        ``max_edge`` (rectangles with a side outside that range are dropped: the floor, the
        pallet, slivers) and ``max_tilt`` (planes tilted more from up are not tops).
    voxel : float
        Voxel-grid size for downsampling, metres (for speed).
    max_planes : int
        Most RANSAC planes extracted before stopping.
    ransac_iterations : int
        RANSAC iterations per plane.
    ransac_points : int
        RANSAC runs on at most this many of the remaining points (drawn with a generator
        seeded from the scan); the plane is then refitted to all of them.
    normal_filter_deg : float
        If > 0, plane inliers whose local normal (estimated by open3d from 12 neighbours) is
        farther than this from the plane's normal are dropped: box sides or mixed pixels that
        merely cross the plane. Off by default: on 10 simulated scenes it broke the noisy
        floor into box-sized pieces (precision 0.27 instead of 0.65) and doubled the time.
    min_fill : float
        Smallest fraction of a rectangle covered by its cluster's points (on a grid of the
        DBSCAN radius); L-shaped merges of two boxes fail it.
    timing : dict, optional
        Filled with wall-clock ms per step (``downsample, planes, clusters, total``).

    Returns
    -------
    SurfaceSet
        In pick order (highest along ``scan.up`` first); grasp point = centre; score = the
        cluster's point count over the largest cluster's; covariance isotropic from the
        sampling step and the noise at the surface.
    """
    import open3d as o3d  # imported late: heavy, and only the baseline needs it

    cfg = config or Config()
    t0 = time.perf_counter()
    tick = t0
    times: dict[str, float] = {}

    def lap(name: str) -> None:
        nonlocal tick
        now = time.perf_counter()
        times[name] = (now - tick) * 1e3
        tick = now

    valid = scan.valid
    P = scan.points[valid].astype(np.float64)
    up = scan.up
    if P.shape[0] < 50:
        if timing is not None:
            timing.update(total=(time.perf_counter() - t0) * 1e3)
        return empty_surface_set()
    r_med = float(np.median(scan.range[valid]))
    sigma = float(cfg.noise.sigma_range(r_med))
    # Sampling step on the surface: pixel footprint at the median range, or the voxel.
    step = max(voxel, r_med * float(scan.sensor.pixel_angle))
    dist_thr = max(3.0 * sigma, 0.5 * voxel)
    eps = 2.5 * step
    # Smallest cluster worth a rectangle: half the points of the smallest box top.
    min_pts = max(20, int(0.5 * cfg.min_edge**2 / step**2))

    seed = cfg.seed_for(scan.seed)
    o3d.utility.random.seed(int(seed % (2**31 - 1)))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    pcd = pcd.voxel_down_sample(voxel)
    rest_P = np.asarray(pcd.points)
    rest_N = None
    if normal_filter_deg > 0:
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=12))
        rest_N = np.asarray(pcd.normals)
    lap("downsample")

    planes: list[tuple[np.ndarray, np.ndarray]] = []  # (points, normal) of each top plane
    cos_tilt = np.cos(cfg.max_tilt)
    cos_nf = np.cos(np.radians(normal_filter_deg))
    rng = np.random.default_rng(seed)
    for _ in range(max_planes):
        m = rest_P.shape[0]
        if m < min_pts:
            break
        # RANSAC on a random subset finds the same dominant plane far faster; the plane is
        # then refitted on all remaining points.
        pick = np.sort(rng.choice(m, ransac_points, replace=False)) if m > ransac_points \
            else np.arange(m)
        sub = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rest_P[pick]))
        # probability=1 runs every iteration: open3d stops early on a shared counter
        # otherwise, which makes the plane depend on thread timing.
        _model, idx = sub.segment_plane(distance_threshold=dist_thr, ransac_n=3,
                                        num_iterations=ransac_iterations, probability=1.0)
        if len(idx) * m / pick.shape[0] < min_pts:
            break
        inl = _refine_plane(rest_P, pick[np.asarray(idx, dtype=np.int64)], dist_thr)
        c0, n = _fit_plane(rest_P[inl])
        pts = rest_P[inl]
        if rest_N is not None:
            pts = pts[np.abs(rest_N[inl] @ n) >= cos_nf]
        # Remove a wider band than the inliers: the noise tails of a big plane (the floor)
        # would otherwise come back as two thin phantom planes.
        keep = np.abs((rest_P - c0) @ n) > 1.5 * dist_thr
        keep[inl] = False
        rest_P = rest_P[keep]
        rest_N = rest_N[keep] if rest_N is not None else None
        if abs(float(n @ up)) < cos_tilt:
            continue  # a box side or a wall: not a top
        planes.append((pts, n))
    lap("planes")

    rects: list[tuple[np.ndarray, np.ndarray, np.ndarray, float, float, int, float]] = []
    for pts, _n in planes:
        if pts.shape[0] < min_pts:
            continue
        sub = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        labels = np.asarray(sub.cluster_dbscan(eps=eps, min_points=8))
        for lab in range(int(labels.max(initial=-1)) + 1):
            Q = pts[labels == lab]
            if Q.shape[0] < min_pts:
                continue
            rect = _cluster_rectangle(Q, cfg, eps, min_fill)
            if rect is not None:
                rects.append((*rect, Q.shape[0], sigma))
    lap("clusters")

    if not rects:
        out = empty_surface_set()
    else:
        C = np.array([r[0] for r in rects])
        N = np.array([r[1] for r in rects])
        X = np.array([r[2] for r in rects])
        W = np.array([r[3] for r in rects])
        L = np.array([r[4] for r in rects])
        counts = np.array([r[5] for r in rects], dtype=np.float64)
        # Isotropic: the centre is known to about a sampling step (the rectangle's edges are
        # the outermost samples), the rotation to step over the half-width.
        var_c = step**2 / 4.0 + sigma**2
        var_r = (step / (0.5 * W)) ** 2
        cov = np.zeros((len(rects), 6, 6))
        cov[:, :3, :3] = np.eye(3) * var_c
        cov[:, 3:, 3:] = np.eye(3)[None] * var_r[:, None, None]
        out = surface_set_from_rects(
            C, N, X, W, L, scores=counts / counts.max(), covariances=cov, up=up
        )
    if timing is not None:
        timing.update(times)
        timing["total"] = (time.perf_counter() - t0) * 1e3
    return out


def _fit_plane(Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane of points (k, 3): (centroid, unit normal toward the sensor)."""
    c0 = Q.mean(axis=0)
    _, _, Vt = np.linalg.svd(Q - c0, full_matrices=False)
    n = Vt[2]
    return c0, (-n if n @ c0 > 0 else n)


def _refine_plane(P: np.ndarray, idx: np.ndarray, thr: float, rounds: int = 3) -> np.ndarray:
    """Refit RANSAC's plane to its inliers by least squares and re-select, a few rounds.

    A plane from 3 samples is tilted by the noise, so its band cuts off part of a wide
    surface (which would then come back as a second, partial plane); the refit does not.
    """
    for _ in range(rounds):
        c0, n = _fit_plane(P[idx])
        new = np.flatnonzero(np.abs((P - c0) @ n) <= thr)
        if new.shape[0] < 3 or np.array_equal(new, idx):
            break
        idx = new
    return idx


def _cluster_rectangle(
    Q: np.ndarray, cfg: Config, cell: float, min_fill: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float] | None:
    """Least-squares plane and minimum-area rectangle of one cluster (k, 3).

    Returns (center, normal toward the sensor, x_axis along width, width, length), or None
    if a side is outside [min_edge, max_edge] or the cluster fills the rectangle too thinly.

    The rectangle of the samples is not padded by a sampling step (as a clean sampling
    would call for): mixed pixels and the boxes' bevelled edges already reach the edge, and
    padding made the dimensions worse on the simulated scenes (median 7 mm instead of 2 mm).
    """
    c0, n = _fit_plane(Q)
    u, v = _plane_basis(n)
    q = np.stack([(Q - c0) @ u, (Q - c0) @ v], axis=1)
    rect = cv2.minAreaRect(q.astype(np.float32))
    (cx, cy), (a, b), _ang = rect
    if min(a, b) < cfg.min_edge or max(a, b) > cfg.max_edge:
        return None
    if min_fill > 0 and _fill_ratio(q, rect, cell) < min_fill:
        return None
    box = cv2.boxPoints(rect).astype(np.float64)  # (4, 2), consecutive corners
    e1 = box[1] - box[0]
    e2 = box[2] - box[1]
    short = e1 if np.linalg.norm(e1) <= np.linalg.norm(e2) else e2
    short = short / max(np.linalg.norm(short), 1e-300)
    center = c0 + cx * u + cy * v
    x_axis = short[0] * u + short[1] * v
    return center, n, x_axis, float(min(a, b)), float(max(a, b))

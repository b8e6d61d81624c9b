"""Small but valid scans and products for tests that must not depend on the pipeline.

``make_scan`` builds a range image of a few boxes on a floor; ``make_result`` builds one
product of every stage with plausible random content: correct dtypes, shapes, CSR offsets
and cross references (line ids in vertices, attempt ids in the verification, ...), and a
few statistical tests of every kind. Nothing here is geometrically *right*; it is shaped
right, which is what the recorder, the viewers and the diff need.

Everything is seeded: the same arguments give the same products, bit for bit.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np

from boxloc.products import (
    STAGES,
    DimensionSource,
    EdgeKind,
    EdgeMap,
    HypothesisSet,
    LineSet,
    Result,
    Selection,
    SelectReason,
    SurfaceSet,
    Verification,
    VerifyReason,
    VertexSet,
)
from boxloc.scan import PinholeModel, RayTableModel, Scan
from boxloc.stats import TestKind, TestTable

ALPHA = 0.01


def make_scan(
    seed: int = 0,
    shape: tuple[int, int] = (48, 64),
    *,
    raytable: bool = False,
    pose: bool = True,
    index: int | None = None,
    capture_time_ns: int | None = None,
) -> Scan:
    """A scan of two boxes on a floor, seen from ~2 m above, with noise and dropouts.

    Parameters
    ----------
    seed : int
        Seeds the noise, the box placement and the default index/capture time.
    shape : (H, W)
        Image size, pixels.
    raytable : bool
        Use a :class:`RayTableModel` (a slightly bent pinhole) instead of a pinhole.
    pose : bool
        Give the scan a ``sensor_to_base`` pose.
    index, capture_time_ns : int, optional
        Defaults: ``seed`` and ``1.7e18 + seed * 0.1 s``.
    """
    rng = np.random.default_rng(seed)
    H, W = shape
    f = 0.9 * W
    pin = PinholeModel(fx=f, fy=f * 1.01, cx=(W - 1) / 2 + 0.3, cy=(H - 1) / 2 - 0.2,
                       width=W, height=H)
    rays = pin.rays()
    sensor: PinholeModel | RayTableModel = pin
    if raytable:
        # A pinhole with a little radial bend, so it is not a pinhole any more.
        v, u = np.mgrid[0:H, 0:W]
        bend = 1.0 + 0.02 * (((u - W / 2) / W) ** 2 + ((v - H / 2) / H) ** 2)
        t = rays.copy()
        t[..., :2] *= bend[..., None]
        t[0, 0] = np.nan  # a pixel without a ray
        sensor = RayTableModel(t)
        rays = sensor.rays()
    # Depth (z) of a floor at 2 m with two boxes on it, then range along each ray.
    z = np.full((H, W), 2.0)
    for _ in range(2):
        r0, c0 = rng.integers(0, H // 2), rng.integers(0, W // 2)
        h, w = rng.integers(H // 5, H // 2), rng.integers(W // 5, W // 2)
        z[r0 : r0 + h, c0 : c0 + w] = np.minimum(z[r0 : r0 + h, c0 : c0 + w],
                                                 rng.uniform(1.5, 1.8))
    with np.errstate(invalid="ignore"):
        rng_m = z / rays[..., 2] + rng.normal(0, 0.002, (H, W))
    rng_m = rng_m.astype(np.float32)
    rng_m[rng.random((H, W)) < 0.02] = np.nan  # dropouts
    T = None
    if pose:
        a = rng.uniform(-0.3, 0.3)
        c, s = np.cos(a), np.sin(a)
        # sensor looking down: sensor z -> base -z, with a yaw of `a`
        T = np.array([[c, s, 0, 0.1], [s, -c, 0, -0.2], [0, 0, -1, 2.5], [0, 0, 0, 1]],
                     dtype=np.float64)
    return Scan(
        range=rng_m,
        sensor=sensor,
        capture_time_ns=(1_700_000_000_000_000_000 + seed * 100_000_000
                         if capture_time_ns is None else capture_time_ns),
        index=seed if index is None else index,
        sensor_to_base=T,
        source=f"factory:seed={seed}",
        meta={"factory": True, "seed": seed},
    )


# --- helpers -----------------------------------------------------------------------------


def _unit(rng: np.random.Generator, n: int) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _spd(rng: np.random.Generator, n: int, k: int, scale: float) -> np.ndarray:
    """n symmetric positive definite k x k matrices, float64."""
    A = rng.normal(size=(n, k, k)) * scale
    return A @ np.swapaxes(A, 1, 2) + np.eye(k) * scale**2 * 1e-3


def _offsets(counts: np.ndarray) -> np.ndarray:
    return np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)


def _chi2(rng: np.random.Generator, kind: TestKind, n: int, n_entities: int, dof: float,
          scale: float = 1.0) -> TestTable:
    a = rng.integers(0, max(n_entities, 1), n)
    b = rng.integers(0, max(n_entities, 1), n)
    return TestTable.chi2(kind, a, b, rng.chisquare(dof, n) * scale, dof, ALPHA)


def _decision(rng: np.random.Generator, kind: TestKind, n: int, n_entities: int) -> TestTable:
    stat = rng.uniform(0, 1, n)
    crit = 0.5
    return TestTable.decision(kind, rng.integers(0, max(n_entities, 1), n), -1, stat, crit,
                              stat > crit, ALPHA)


# --- products ----------------------------------------------------------------------------


def make_edges(scan: Scan, rng: np.random.Generator, n: int = 60) -> EdgeMap:
    H, W = scan.shape
    flat = rng.choice(H * W, size=min(n, H * W), replace=False)
    r, c = np.divmod(flat, W)
    kinds = rng.integers(1, 4, flat.size).astype(np.uint8)
    labels = np.zeros((H, W), np.uint8)
    labels[r, c] = kinds
    P = np.nan_to_num(scan.points[r, c].astype(np.float64), nan=2.0)
    tests = TestTable.concat(
        [_chi2(rng, TestKind.JUMP, 8, flat.size, 1.0), _chi2(rng, TestKind.CREASE, 7, flat.size,
                                                               1.0)],
        ALPHA,
    )
    return EdgeMap(
        labels=labels,
        pixels=np.stack([r, c], 1).astype(np.int32),
        points=P,
        covariances=_spd(rng, flat.size, 3, 0.002),
        kinds=kinds,
        strength=np.where(kinds == EdgeKind.JUMP, rng.uniform(0.05, 0.4, flat.size),
                          rng.uniform(0.3, 1.6, flat.size)),
        scan_dir=rng.integers(1, 4, flat.size).astype(np.uint8),
        tests=tests,
    )


def make_lines(edges: EdgeMap, rng: np.random.Generator, n: int = 6, seed: int = 0) -> LineSet:
    n_support = rng.integers(3, 10, n).astype(np.int32)
    offs = _offsets(n_support)
    m = int(offs[-1])
    P = rng.uniform(-0.5, 0.5, (n, 3)) + [0, 0, 1.8]
    D = _unit(rng, n)
    half = rng.uniform(0.05, 0.3, (n, 1))
    return LineSet(
        points=P, directions=D, covariances=_spd(rng, n, 6, 0.003),
        starts=P - half * D, ends=P + half * D,
        n_support=n_support, support_offsets=offs,
        support=rng.integers(0, max(len(edges), 1), m).astype(np.int32),
        support_statistic=rng.chisquare(2, m).astype(np.float32),
        kinds=rng.integers(1, 4, n).astype(np.uint8),
        trial=np.sort(rng.integers(0, 40, n)).astype(np.int32),
        direction_votes=rng.uniform(5, 50, n), position_votes=rng.uniform(3, 30, n),
        n_trials=40, epsilon=0.05, p_success=0.9, seed=seed,
        tests=_chi2(rng, TestKind.POINT_ON_LINE, n + 2, n, 2.0),
    )


def make_vertices(lines: LineSet, rng: np.random.Generator, n: int = 4) -> VertexSet:
    d1 = _unit(rng, n)
    d2 = np.cross(d1, _unit(rng, n))
    d2 /= np.linalg.norm(d2, axis=1, keepdims=True)
    nrm = np.cross(d1, d2)
    la = rng.integers(0, len(lines), n).astype(np.int32)
    lb = ((la + 1) % len(lines)).astype(np.int32)
    tests = TestTable.concat(
        [_chi2(rng, TestKind.LINES_MEET, 5, len(lines), 1.0),
         _chi2(rng, TestKind.LINES_ORTHOGONAL, 5, len(lines), 1.0),
         _decision(rng, TestKind.AT_SEGMENT_ENDS, 5, len(lines))],
        ALPHA,
    )
    return VertexSet(points=rng.uniform(-0.5, 0.5, (n, 3)) + [0, 0, 1.7], d1=d1, d2=d2,
                     normals=nrm, covariances=_spd(rng, n, 9, 0.002), line_a=la, line_b=lb,
                     tests=tests)


def make_hypotheses(vertices: VertexSet, rng: np.random.Generator) -> HypothesisSet:
    n = len(vertices)
    # Attempts: 1..3 per hypothesis, the first from vertices, later ones from edges.
    per = rng.integers(1, 4, n)
    att_h = np.repeat(np.arange(n), per).astype(np.int32)
    k = att_h.size
    first = _offsets(per)[:-1]
    att_src = np.full(k, DimensionSource.EDGES, np.uint8)
    att_src[first] = DimensionSource.VERTICES
    att_diag = np.where(att_src == DimensionSource.VERTICES,
                        rng.integers(0, n, k), -1).astype(np.int32)
    att_w, att_l = rng.uniform(0.1, 0.6, k), rng.uniform(0.1, 0.8, k)
    att_ok = rng.random(k) < 0.6
    # The kept attempt: the first verified one of each hypothesis (-1 if none).
    attempt = np.full(n, -1, np.int32)
    for j in range(k - 1, -1, -1):
        if att_ok[j]:
            attempt[att_h[j]] = j
    kept = attempt >= 0
    src = np.where(kept, att_src[np.maximum(attempt, 0)], DimensionSource.NONE).astype(np.uint8)
    width = np.where(kept, att_w[np.maximum(attempt, 0)], np.nan)
    length = np.where(kept, att_l[np.maximum(attempt, 0)], np.nan)
    o, x, y = vertices.points, vertices.d1, vertices.d2
    corners = np.stack([o, o + width[:, None] * x, o + width[:, None] * x + length[:, None] * y,
                        o + length[:, None] * y], 1)
    nx, ny = rng.integers(0, 12, n), rng.integers(0, 12, n)
    npx, npy = rng.integers(0, 3, n), rng.integers(0, 3, n)
    tests = TestTable.concat(
        [_chi2(rng, TestKind.COPLANAR, 4, n, 1.0), _chi2(rng, TestKind.PARALLEL, 4, n, 2.0),
         _decision(rng, TestKind.FIRST_QUADRANT, 3, n),
         _chi2(rng, TestKind.POINT_ON_PLANE, 6, n, 1.0),
         _decision(rng, TestKind.EDGE_SUPPORT, 3, n)],
        ALPHA,
    )
    return HypothesisSet(
        vertex=np.arange(n, dtype=np.int32), source=src, attempt=attempt,
        origins=o.copy(), x_axis=x.copy(), y_axis=y.copy(), normals=vertices.normals.copy(),
        width=width, length=length, corners=corners,
        acc_bin=np.full(n, 0.01),
        acc_x_offsets=_offsets(nx), acc_x=rng.integers(0, 9, int(nx.sum())).astype(np.float32),
        acc_y_offsets=_offsets(ny), acc_y=rng.integers(0, 9, int(ny.sum())).astype(np.float32),
        peaks_x_offsets=_offsets(npx), peaks_x=rng.uniform(0.1, 0.6, int(npx.sum())),
        peaks_y_offsets=_offsets(npy), peaks_y=rng.uniform(0.1, 0.8, int(npy.sum())),
        n_candidates=rng.integers(0, 40, n).astype(np.int32),
        att_hypothesis=att_h, att_source=att_src, att_diagonal=att_diag,
        att_width=att_w, att_length=att_l,
        att_support=rng.uniform(0, 30, k), att_threshold=np.full(k, 9.0),
        att_verified=att_ok, up=np.array([0.0, 0.0, -1.0]), tests=tests,
    )


def make_verification(scan: Scan, hyps: HypothesisSet,
                      rng: np.random.Generator) -> Verification:
    k = hyps.n_attempts
    H, W = scan.shape
    n_inside = rng.integers(20, 200, k).astype(np.int32)
    n_valid = (n_inside * 0.95).astype(np.int32)
    n_in = (n_valid * rng.uniform(0.5, 1.0, k)).astype(np.int32)
    n_front = ((n_valid - n_in) // 2).astype(np.int32)
    n_behind = (n_valid - n_in - n_front).astype(np.int32)
    accepted = hyps.att_verified.copy()
    reason = np.where(accepted, VerifyReason.ACCEPTED,
                      rng.integers(1, len(VerifyReason), k)).astype(np.uint8)
    n_pix = np.minimum(n_in, 15)
    tests = TestTable.concat(
        [_decision(rng, TestKind.VERIFY_INLIERS, k, k),
         _chi2(rng, TestKind.VERIFY_MEAN, k, k, 1.0),
         _decision(rng, TestKind.VERIFY_INTERIOR, k, k),
         _decision(rng, TestKind.VERIFY_TILT, k, k),
         _chi2(rng, TestKind.VERIFY_EXPOSED, k, k, 1.0)]
        # FACE_EXTENT is the hypothesis stage's (and after it: the draws stay as they were)
        + [_decision(rng, kind, k, k) for kind in TestKind
           if TestKind.VERIFY_EXPOSED < kind < TestKind.FACE_EXTENT],
        ALPHA,
    )
    return Verification(
        attempt=np.arange(k, dtype=np.int32), hypothesis=hyps.att_hypothesis.copy(),
        n_inside=n_inside, n_valid=n_valid, n_inliers=n_in, n_front=n_front, n_behind=n_behind,
        inlier_fraction=n_in / np.maximum(n_valid, 1),
        mean_distance=rng.normal(0, 0.001, k), sigma_mean=rng.uniform(1e-4, 1e-3, k),
        n_interior_edges=rng.integers(0, 5, k).astype(np.int32),
        plane_centers=rng.uniform(-0.5, 0.5, (k, 3)) + [0, 0, 1.7],
        plane_normals=_unit(rng, k), plane_covariances=_spd(rng, k, 6, 0.001),
        rms=rng.uniform(5e-4, 3e-3, k), error=rng.uniform(0, 50, k), accepted=accepted,
        reason=reason,
        inlier_offsets=_offsets(n_pix),
        inlier_pixels=rng.integers(0, H * W, int(n_pix.sum())).astype(np.int32),
        tests=tests,
    )


def make_selection(ver: Verification, rng: np.random.Generator) -> Selection:
    cand = np.flatnonzero(ver.accepted).astype(np.int32)
    c = cand.size
    n_points = ver.n_inliers[cand].astype(np.int32)
    err = ver.error[cand].copy()
    Q = -np.abs(rng.normal(0, 5, (c, c)))
    Q = (Q + Q.T) / 2
    Q[np.diag_indices(c)] = n_points - 0.5 * err - 80
    chosen = rng.random(c) < 0.6
    order = np.flatnonzero(chosen).astype(np.int32)
    rng.shuffle(order)
    m = chosen.astype(np.float64)
    beaten = np.where(chosen, -1, order[0] if order.size else -1).astype(np.int32)
    reason = np.where(chosen, SelectReason.CHOSEN,
                      np.where(beaten >= 0, SelectReason.OVERLAPS_CHOSEN, SelectReason.NO_GAIN)
                      ).astype(np.uint8)
    return Selection(candidates=cand, hypothesis=ver.hypothesis[cand].copy(), n_points=n_points,
                     error=err, n_params=np.full(c, 8, np.int32), Q=Q, chosen=chosen,
                     order=order, objective=float(m @ Q @ m), beaten_by=beaten, reason=reason,
                     k1=1.0, k2=0.5, k3=10.0)


def make_surfaces(hyps: HypothesisSet, sel: Selection, rng: np.random.Generator) -> SurfaceSet:
    att = sel.candidates[sel.order]
    s = att.size
    h = hyps.att_hypothesis[att]
    w = np.minimum(hyps.att_width[att], hyps.att_length[att])
    ln = np.maximum(hyps.att_width[att], hyps.att_length[att])
    o, x, y = hyps.origins[h], hyps.x_axis[h], hyps.y_axis[h]
    corners = np.stack([o, o + w[:, None] * x, o + w[:, None] * x + ln[:, None] * y,
                        o + ln[:, None] * y], 1)
    centers = corners.mean(1)
    return SurfaceSet(hypothesis=h.astype(np.int32), attempt=att.astype(np.int32),
                      centers=centers, normals=hyps.normals[h].copy(), x_axis=x.copy(),
                      y_axis=y.copy(), width=w, length=ln, corners=corners,
                      grasp_points=centers.copy(), scores=rng.uniform(0.2, 1.0, s),
                      covariances=_spd(rng, s, 6, 0.001),
                      pick_order=np.arange(s, dtype=np.int32),
                      bulge=rng.uniform(-0.001, 0.01, s),
                      tests=TestTable.chi2(TestKind.SURFACE_BULGE, att, 0,
                                           rng.chisquare(1, s) * 4, 1, ALPHA))


def make_result(scan: Scan, seed: int = 0, *, empty: bool = False) -> Result:
    """One product of every stage for ``scan``, shaped like the pipeline's.

    Parameters
    ----------
    scan : Scan
    seed : int
        Seeds the random content.
    empty : bool
        Return products with no entities at all (a scan where nothing was found).
    """
    from boxloc.config import Config
    from boxloc.stages.scan_noise import estimate_scan_noise

    rng = np.random.default_rng(seed + 1000)
    noise = estimate_scan_noise(scan, Config())
    edges = make_edges(scan, rng, n=0 if empty else 60)
    if empty:
        lines = make_lines(edges, rng, n=0, seed=scan.seed)
        vertices = make_vertices(lines, rng, n=0) if len(lines) else _empty_vertices()
    else:
        lines = make_lines(edges, rng, seed=scan.seed)
        vertices = make_vertices(lines, rng)
    hyps = make_hypotheses(vertices, rng)
    ver = make_verification(scan, hyps, rng)
    sel = make_selection(ver, rng)
    surf = make_surfaces(hyps, sel, rng)
    timing = {k: float(rng.uniform(1, 50)) for k in
              ("edges", "lines", "vertices", "hypotheses", "select", "surfaces")}
    timing["total"] = float(sum(timing.values()))
    return Result(scan_index=scan.index, capture_time_ns=scan.capture_time_ns, seed=scan.seed,
                  config_hash="0123456789abcdef", version="0.1.0", edges=edges, lines=lines,
                  vertices=vertices, hypotheses=hyps, verification=ver, selection=sel,
                  surfaces=surf, timing_ms=timing, noise=noise)


def _empty_vertices() -> VertexSet:
    z3 = np.zeros((0, 3))
    return VertexSet(points=z3, d1=z3, d2=z3, normals=z3, covariances=np.zeros((0, 9, 9)),
                     line_a=np.zeros(0, np.int32), line_b=np.zeros(0, np.int32),
                     tests=TestTable.empty(ALPHA))


def feed(observer: object, scan: Scan, result: Result, config: object = None, *,
         start: bool = True) -> None:
    """Hand ``result``'s products to ``observer`` in pipeline order, as the pipeline would
    (``start=False``: ``on_scan`` was already called)."""
    from boxloc.config import Config

    cfg = config if config is not None else Config()
    if start:
        observer.on_scan(scan, cfg)  # type: ignore[attr-defined]
    for stage in STAGES:
        if getattr(result, stage) is not None:
            getattr(observer, f"on_{stage}")(scan, getattr(result, stage))
    observer.on_result(scan, result)  # type: ignore[attr-defined]


class FullDisk:
    """A file that takes ``limit`` bytes, then fails like a full disk: a partial write, then
    ENOSPC (and ENOSPC for every later write, and for fsync)."""

    def __init__(self, path: Path, limit: int) -> None:
        self.f = open(path, "xb")
        self.limit, self.n, self.full = limit, 0, False

    def write(self, b: bytes) -> int:
        b = bytes(b)
        if self.full or self.n + len(b) > self.limit:
            k = max(0, self.limit - self.n)
            self.f.write(b[:k])
            self.f.flush()
            self.n += k
            self.full = True
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self.f.write(b)
        self.n += len(b)
        return len(b)

    def tell(self) -> int:
        return self.n

    def flush(self) -> None:
        self.f.flush()

    def fileno(self) -> int:
        return self.f.fileno()

    def close(self) -> None:
        self.f.close()

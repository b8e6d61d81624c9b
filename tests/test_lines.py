"""Stage 3: lines by constrained Hough transforms."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from boxloc.config import Config
from boxloc.products import EdgeMap, products_equal
from boxloc.scan import PinholeModel, Scan
from boxloc.stages.lines import (
    ICOSAHEDRON_FACES,
    ICOSAHEDRON_VERTICES,
    find_lines,
    fit_segment,
    hemisphere_directions,
    vote_granularity,
    vote_radius_cap,
)
from boxloc.stats import TestKind, TestTable


@pytest.mark.parametrize("g,n", [(0, 6), (1, 21), (2, 81), (3, 321), (4, 1281)])
def test_hemisphere_tessellation_counts(g, n):
    D = hemisphere_directions(g)
    assert D.shape == (n, 3)
    assert np.allclose(np.linalg.norm(D, axis=1), 1)
    assert (D[:, 2] >= -1e-9).all()


def _subdivided_by_loop(granularity: int) -> np.ndarray:
    """The tessellation as first written: a loop over the faces, midpoints numbered as met."""
    def unit(p: np.ndarray) -> np.ndarray:  # IEEE operations in order: the same bits anywhere
        return p / math.sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2])

    faces = list(ICOSAHEDRON_FACES)
    verts = [unit(np.array(p, float)) for p in ICOSAHEDRON_VERTICES]
    for _ in range(granularity):
        cache: dict[tuple[int, int], int] = {}

        def mid(a: int, b: int, cache: dict[tuple[int, int], int] = cache) -> int:
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = verts[a] + verts[b]
                verts.append(unit(m))
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


@pytest.mark.parametrize("g", range(7))
def test_hemisphere_directions_are_the_loops_bit_for_bit(g: int) -> None:
    """The vectorized subdivision numbers and computes every direction as the loop did: the
    cells' order and bits decide the votes' ties."""
    a, b = hemisphere_directions(g), _subdivided_by_loop(g)
    assert a.shape == b.shape
    assert np.array_equal(a.view(np.uint64), b.view(np.uint64))


@pytest.mark.parametrize("g", range(2, 7))
def test_direction_lut_is_every_bins_nearest_cell(g: int) -> None:
    """The lookup table built from its upper half equals querying every bin's nearest cell,
    for every granularity the config allows."""
    from boxloc.stages.lines import _LUT_AZIMUTH, _LUT_POLAR, _direction_lut

    _, _, hemi, tree, lut = _direction_lut(g)
    th = (np.arange(_LUT_POLAR) + 0.5) * math.pi / _LUT_POLAR
    ph = (np.arange(_LUT_AZIMUTH) + 0.5) * 2 * math.pi / _LUT_AZIMUTH
    T, F = np.meshgrid(th, ph, indexing="ij")
    q = np.stack([np.sin(T) * np.cos(F), np.sin(T) * np.sin(F), np.cos(T)], -1).reshape(-1, 3)
    every = hemi[tree.query(q)[1]].reshape(_LUT_POLAR, _LUT_AZIMUTH)
    assert lut.dtype == np.int32
    np.testing.assert_array_equal(lut, every)


def _same_tables(a: tuple[np.ndarray, ...], b: tuple[np.ndarray, ...]) -> bool:
    return all(x.dtype == y.dtype and np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_saved_direction_tables_are_the_built_ones(tmp_path, monkeypatch) -> None:
    """Set-up's saved tables are read back bit for bit, for every vote cap the default
    configuration can use, and nothing is built where they are."""
    from boxloc.stages import lines as L

    pairs = L.default_direction_tables()
    # every cap from the quiet to the noisy one; the noisiest one level coarser
    assert sorted(c for _, c in pairs) == list(range(L._QUIET_CAP_DEG, L._NOISY_CAP_DEG + 1))
    assert (4, L._QUIET_CAP_DEG) in pairs and (3, L._NOISY_CAP_DEG) in pairs
    some = [(4, L._QUIET_CAP_DEG), (4, L._QUIET_CAP_DEG + 1), (3, L._NOISY_CAP_DEG)]
    path = L.save_direction_tables(tmp_path / "t.npz", some)
    monkeypatch.setattr(L, "DIRECTION_TABLES", path)
    for g, cap in some:
        saved = L._saved_direction_index(g, cap)
        assert saved is not None and _same_tables(saved, L.build_direction_index(g, cap))
    assert L._saved_direction_index(4, L._QUIET_CAP_DEG + 2) is None  # a cap not saved
    L._direction_index.cache_clear()
    try:
        def no_build(*args: object) -> None:
            raise AssertionError("built, not read")

        monkeypatch.setattr(L, "build_direction_index", no_build)
        L._direction_index(*some[0])
    finally:
        L._direction_index.cache_clear()


@pytest.mark.parametrize("damage", ["stale", "truncated", "missing"])
def test_direction_tables_are_built_where_the_saved_ones_cannot_serve(tmp_path, monkeypatch,
                                                                      damage) -> None:
    """A file from other code (its stamp), a damaged one or none: the tables are built, the
    same as ever."""
    from boxloc.stages import lines as L

    path = L.save_direction_tables(tmp_path / "t.npz", [(2, L._QUIET_CAP_DEG)])
    if damage == "stale":
        with np.load(path) as z:
            arrays = {k: z[k] for k in z.files}
        arrays["stamp"] = np.array("0" * 16)
        np.savez(path, **arrays)
    elif damage == "truncated":
        path.write_bytes(path.read_bytes()[:1000])
    else:
        path.unlink()
    monkeypatch.setattr(L, "DIRECTION_TABLES", path)
    assert L._saved_direction_index(2, L._QUIET_CAP_DEG) is None
    L._direction_index.cache_clear()
    try:
        assert _same_tables(L._direction_index(2, L._QUIET_CAP_DEG),
                            L.build_direction_index(2, L._QUIET_CAP_DEG))
    finally:
        L._direction_index.cache_clear()


def _edge_map(P: np.ndarray, sigma: float) -> EdgeMap:
    n = len(P)
    return EdgeMap(
        labels=np.zeros((4, 4), np.uint8), pixels=np.zeros((n, 2), np.int32), points=P,
        covariances=np.broadcast_to(sigma**2 * np.eye(3), (n, 3, 3)).copy(),
        kinds=np.ones(n, np.uint8), strength=np.zeros(n), scan_dir=np.ones(n, np.uint8),
        tests=TestTable.empty(0.01),
    )


def _scan() -> Scan:
    return Scan(range=np.full((480, 640), 1.5, np.float32),
                sensor=PinholeModel(525, 525, 319.5, 239.5, 640, 480))


def _two_lines_and_clutter(seed: int):
    rng = np.random.default_rng(seed)
    s = 0.0015
    t = np.arange(0, 0.4, 0.003)
    a = np.array([0.0, 0.0, 1.5]) + t[:, None] * np.array([1.0, 0, 0])
    b = np.array([0.0, 0.0, 1.5]) + t[:, None] * np.array([0, 0.6, 0.8])
    clutter = rng.uniform([-0.2, -0.2, 1.3], [0.6, 0.4, 1.9], (150, 3))
    P = np.concatenate([a, b, clutter]) + rng.normal(0, s, (len(a) + len(b) + 150, 3))
    return P, s, len(a), len(b)


def test_two_lines_are_found_among_clutter():
    P, s, na, nb = _two_lines_and_clutter(1)
    L = find_lines(_scan(), _edge_map(P, s), config=Config(), rng=np.random.default_rng(0))
    assert len(L) == 2
    dirs = np.abs(L.directions)
    want = np.array([[1.0, 0, 0], [0, 0.6, 0.8]])
    for w in want:
        assert np.max(dirs @ w) > np.cos(np.radians(1.0))
    # most of each line's points are its support; the clutter mostly is not
    assert L.n_support.sum() > 0.85 * (na + nb)
    assert L.n_trials >= 2 and 0 < L.epsilon < 1
    assert len(L.tests.of_kind(TestKind.POINT_ON_LINE)) == 2
    assert len(L.tests.of_kind(TestKind.BUDGET)) == 0  # the work budget was not hit


def _lines_and_clutter(seed: int, k: int = 8, n: int = 40):
    """k straight runs of n points 3 mm apart in random directions, and 300 points of
    clutter: each line found resets the run of failed trials."""
    rng = np.random.default_rng(seed)
    s = 0.0015
    pts = []
    for _ in range(k):
        o = rng.uniform([-0.3, -0.3, 1.3], [0.3, 0.3, 1.7])
        d = rng.normal(size=3)
        pts.append(o + np.arange(n)[:, None] * 0.003 * (d / np.linalg.norm(d)))
    pts.append(rng.uniform([-0.4, -0.4, 1.2], [0.4, 0.4, 1.9], (300, 3)))
    P = np.concatenate(pts)
    return P + rng.normal(0, s, P.shape), s


def test_the_trials_are_olsons_count_in_all():
    # p_success is the chance that each line of m_min points is hit: log(1 - P) /
    # log(1 - m_min / N) draws in all, however many lines are found on the way (a run of
    # that many failures after the last line found drew 109 on seed 0)
    for seed in range(3):
        P, s = _lines_and_clutter(seed)
        L = find_lines(_scan(), _edge_map(P, s), config=Config(), rng=np.random.default_rng(0))
        cap = math.ceil(math.log(1.0 - Config().p_success) / math.log(1.0 - float(L.epsilon)))
        assert len(L) == 8 and L.n_trials <= cap, (seed, len(L), L.n_trials, cap)


def test_same_seed_same_lines():
    P, s, *_ = _two_lines_and_clutter(2)
    a = find_lines(_scan(), _edge_map(P, s), config=Config(), rng=np.random.default_rng(5))
    b = find_lines(_scan(), _edge_map(P, s), config=Config(), rng=np.random.default_rng(5))
    assert len(a) >= 2 and products_equal(a, b) == []  # the two lines, twice the same


def test_no_edges_no_lines():
    L = find_lines(_scan(), _edge_map(np.zeros((0, 3)), 0.001), config=Config(),
                   rng=np.random.default_rng(0))
    assert len(L) == 0 and L.support_offsets.tolist() == [0]


def test_fit_segment_covariance_scales_as_expected():
    rng = np.random.default_rng(3)
    t = np.linspace(-0.2, 0.2, 100)
    P = np.c_[t, np.zeros_like(t), np.full_like(t, 1.5)] + rng.normal(0, 0.002, (100, 3))
    c, b, cov, tt = fit_segment(P, np.broadcast_to(4e-6 * np.eye(3), (100, 3, 3)))
    assert abs(b[0]) > 0.999
    # direction variance ~ sigma^2 / sum t^2 in each perpendicular axis
    assert cov[4, 4] == pytest.approx(4e-6 / (tt**2).sum(), rel=0.5)
    assert cov[1, 1] == pytest.approx(4e-6 / 100, rel=0.5)


def test_trace_prefilter_never_drops_a_point_on_the_line():
    # the pre-filter of the inlier search is a bound, not an approximation: every point the
    # chi2(2) test accepts passes it, and it removes the points far off the line
    from boxloc.stages.lines import _may_lie_on, _point_on_line_stat
    rng = np.random.default_rng(3)
    n = 4000
    c, b = np.array([0.1, -0.2, 1.5]), np.array([0.6, 0.0, 0.8])
    # half of them near the line, half scattered over 10 cm around it
    spread = np.where(np.arange(n) < n // 2, 0.004, 0.03)[:, None]
    P = c + rng.uniform(-0.3, 0.3, n)[:, None] * b + rng.normal(0, 1, (n, 3)) * spread
    A = rng.normal(0, 1, (n, 3, 3))
    # anisotropic covariances, 0.1-3 mm
    C = np.einsum("nij,nkj->nik", A, A) * rng.uniform(1e-8, 9e-6, n)[:, None, None]
    crit = 9.21
    T, _ = _point_on_line_stat(P, C, c, b)
    kept = _may_lie_on(P, np.einsum("nii->n", C), np.arange(n), c, b, crit)
    keep = np.zeros(n, bool)
    keep[kept] = True
    assert np.all(np.diff(kept) > 0)  # the candidates in their order
    assert keep[T <= crit].all()
    assert (T <= crit).sum() > 100 and (~keep).sum() > n // 4


def test_inlier_search_with_the_prefilter_finds_the_same_lines(monkeypatch):
    # the lines of a cluttered set of edges, found with the pre-filter, are the lines of the
    # full test: the pre-filter changes only the time
    import boxloc.stages.lines as L
    P, s, *_ = _two_lines_and_clutter(3)
    a = find_lines(_scan(), _edge_map(P, s), config=Config(), rng=np.random.default_rng(0))
    monkeypatch.setattr(L, "_may_lie_on", lambda P, tr, idx, c, b, crit: idx)
    b_ = find_lines(_scan(), _edge_map(P, s), config=Config(), rng=np.random.default_rng(0))
    assert len(a) >= 2 and products_equal(a, b_) == []


def test_the_line_stage_stops_at_its_work_budget():
    P, s, *_ = _two_lines_and_clutter(1)
    rng = np.random.default_rng
    full = find_lines(_scan(), _edge_map(P, s), config=Config(), rng=rng(0))
    cut = find_lines(_scan(), _edge_map(P, s), config=Config(max_line_work=200), rng=rng(0))
    (row,) = cut.tests.of_kind(TestKind.BUDGET).rows()
    assert not row["accepted"] and row["critical"] == 200 and row["statistic"] >= 200
    assert cut.n_trials < full.n_trials
    # the same budget stops at the same place: a replay reproduces it
    again = find_lines(_scan(), _edge_map(P, s), config=Config(max_line_work=200), rng=rng(0))
    assert again.n_trials == cut.n_trials and len(again) == len(cut)
    # no budget: never hit
    free = find_lines(_scan(), _edge_map(P, s), config=Config(max_line_work=0), rng=rng(0))
    assert len(free.tests.of_kind(TestKind.BUDGET)) == 0 and free.n_trials == full.n_trials


def test_trial_kernels_match_their_numpy_expressions() -> None:
    # the live neighbours and the voters: the NumPy expressions they replaced, exactly
    from boxloc.stages.lines import MAX_VOTE_RADIUS, _live_neighbours, _perp, _vote_inputs

    rng = np.random.default_rng(5)
    P = rng.normal(0.0, 0.2, (400, 3)) + [0.0, 0.0, 1.5]
    # covariances from sharp to broad: some error regions exceed MAX_VOTE_RADIUS
    C = np.diag([1e-6, 1e-6, 4e-6]) * 10.0 ** rng.uniform(0.0, 4.0, 400)[:, None, None]
    P[7] = P[3]  # a duplicate of p0: no direction, dropped
    alive = rng.random(400) < 0.7
    nb = rng.permutation(400).astype(np.int64)
    got = _live_neighbours(nb, alive, 3)
    assert np.array_equal(got, nb[alive[nb] & (nb != 3)])
    keep, d, use, vi, ainv = _vote_inputs(P, C, nb, 3, 3.0, MAX_VOTE_RADIUS)
    assert 3 not in keep and 7 not in keep and len(keep) == 398
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    # the error region's ellipse: the inverse of J (C_i + C_0) J^T on the tangent plane
    # (J = (I - d d^T) / l), in the basis _perp(d); a point votes if its minor semi-axis
    # fits the cap, and the half-trace radius is never below it
    minor = np.empty(len(keep))
    for m, i in enumerate(keep):
        v = P[i] - P[3]
        ell = np.linalg.norm(v)
        e1, e2 = _perp(d[m])
        E = np.stack([e1, e2])
        S2 = E @ (C[i] + C[3]) @ E.T / ell**2
        A = np.linalg.inv(S2)
        np.testing.assert_allclose(ainv[m], [A[0, 0], A[0, 1], A[1, 1]], rtol=1e-6)
        minor[m] = 3.0 * np.sqrt(np.linalg.eigvalsh(S2)[0])
        # never wider than the circle of half the trace (the region's radius before)
        J = (np.eye(3) - np.outer(d[m], d[m])) / ell
        rad = 3.0 * np.sqrt(np.trace(J @ (C[i] + C[3]) @ J.T) / 2.0)
        assert minor[m] <= rad * (1 + 1e-9)
    assert np.array_equal(use, minor <= MAX_VOTE_RADIUS)
    assert np.array_equal(vi, np.flatnonzero(use)) and 0 < len(vi) < len(keep)


def test_the_vote_cap_follows_the_edge_points_noise():
    k2, radius = 3.03, 0.45
    quiet = np.full(100, 3 * 0.002**2)  # 2 mm per axis: the fixed cap
    noisy = np.full(100, 3 * 0.01**2)  # 10 mm per axis (a structured-light camera at 2.5 m)
    wild = np.full(100, 3 * 0.2**2)
    assert vote_radius_cap(quiet, k2, radius) == 8
    assert 8 < vote_radius_cap(noisy, k2, radius) <= 16
    assert vote_radius_cap(wild, k2, radius) == 16
    assert vote_radius_cap(np.zeros(0), k2, radius) == 8


def test_a_long_edge_with_centimetre_scatter_is_a_line():
    # 0.5 m of edge at 3 m, points 4 mm apart, 15 mm of scatter per axis: with the fixed
    # 8 deg cap no voter within the vote radius is sharp enough, and no line is found
    rng = np.random.default_rng(3)
    s = 0.015
    t = np.arange(0, 0.5, 0.004)
    P = np.array([0.0, 0.0, 3.0]) + t[:, None] * np.array([1.0, 0, 0])
    P = P + rng.normal(0, s, P.shape)
    L = find_lines(_scan(), _edge_map(P, s), config=Config(), rng=np.random.default_rng(0))
    assert len(L) >= 1
    assert np.max(np.abs(L.directions @ np.array([1.0, 0, 0]))) > np.cos(np.radians(5.0))
    assert L.n_support.max() > 0.7 * len(P)


def test_an_edge_whose_points_scatter_along_the_rays_is_a_line():
    # active-stereo at 3 m: the edge points' errors are long along the ray (80 mm) and
    # short across it (6 mm). A circular error region of half the trace spans 40 deg at
    # 0.3 m and may not vote; the ellipse's short axis fixes the direction across the ray
    rng = np.random.default_rng(4)
    t = np.arange(0, 0.5, 0.005)
    P = np.array([0.0, 0.0, 3.0]) + t[:, None] * np.array([1.0, 0, 0])
    sd = np.array([0.006, 0.006, 0.08])
    P = P + rng.normal(size=P.shape) * sd
    # false edge points scattered over the surface around it, as noise makes them
    clutter = rng.uniform([-0.2, -0.3, 3.0], [0.7, 0.3, 3.0], (200, 3))
    Q = np.concatenate([P, clutter + rng.normal(size=clutter.shape) * sd])
    e = _edge_map(Q, 0.0)
    e = dataclasses.replace(e, covariances=np.broadcast_to(np.diag(sd**2), (len(Q), 3, 3)).copy())
    L = find_lines(_scan(), e, config=Config(), rng=np.random.default_rng(0))
    # (its tilt in depth is known to a few degrees only: 80 mm of depth error over 0.5 m)
    along = np.abs(L.directions @ np.array([1.0, 0, 0])) > np.cos(np.radians(12.0))
    assert along.any()
    assert L.n_support[along].max() > 0.7 * len(P)


def test_wide_votes_use_a_coarser_tessellation():
    assert vote_granularity(4, 8) == 4
    assert vote_granularity(4, 15) == 4
    assert vote_granularity(4, 16) == 3
    assert vote_granularity(2, 16) == 2

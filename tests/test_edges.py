"""Stage 2: edges by scan-line approximation."""

from __future__ import annotations

import numpy as np
import pytest

from boxloc.config import Config
from boxloc.evaluate.metrics import edge_scores
from boxloc.products import EdgeKind
from boxloc.scan import NoiseModel, PinholeModel, Scan
from boxloc.stages.edges import (
    NO_RETURN_PX,
    STEP_RUN_MAX,
    _split_at_steps,
    _split_merge,
    detect_edges,
    residual_thresholds,
    run_thresholds,
)
from boxloc.stats import TestKind
from tests.scenes import box, scene


@pytest.fixture(scope="module")
def one_box():
    sim = scene([box(0.0, 0.0, 0.40, 0.30, 0.25)], seed=5)
    return sim, detect_edges(sim.scan, config=Config())


def test_box_outline_is_found(one_box):
    sim, e = one_box
    p, r = edge_scores(e.labels, sim.truth.edge_labels)
    assert p > 0.75 and r > 0.8


def test_jump_points_lie_on_the_top_face(one_box):
    sim, e = one_box
    gt = sim.truth
    face = gt.face_ids[e.pixels[:, 0], e.pixels[:, 1]] == 0
    jumps = (e.kinds == EdgeKind.JUMP) & face
    d = (e.points[jumps] - gt.centers[0]) @ gt.normals[0]
    sig = Config().noise.sigma_range(np.linalg.norm(gt.centers[0]))
    assert jumps.sum() > 100
    assert np.median(np.abs(d)) < 2 * sig


def test_covariances_are_symmetric_positive(one_box):
    _, e = one_box
    C = e.covariances
    assert np.allclose(C, np.swapaxes(C, 1, 2))
    assert (np.linalg.eigvalsh(C) > 0).all()
    assert e.labels[e.pixels[:, 0], e.pixels[:, 1]].tolist() == e.kinds.tolist()


def test_every_edge_carries_its_test(one_box):
    _, e = one_box
    kinds = set(np.unique(e.tests.kind).tolist())
    assert kinds <= {TestKind.JUMP, TestKind.CREASE, TestKind.NO_RETURN}
    assert len(e.tests) >= len(e)


def _plane_scan(noise: NoiseModel, seed: int) -> Scan:
    pin = PinholeModel(262.5, 262.5, 159.5, 119.5, 320, 240)
    rays = pin.rays()
    n = np.array([0.0, -0.2, -1.0]) / np.linalg.norm([0.0, -0.2, -1.0])
    r = 1.5 / -(rays @ n)  # plane n.x = 1.5
    rng = np.random.default_rng(seed)
    r = r + rng.normal(size=r.shape) * noise.sigma_range(r)
    return Scan(range=r.astype(np.float32), sensor=pin)


def test_a_noisy_plane_has_almost_no_edges():
    cfg = Config()
    e = detect_edges(_plane_scan(cfg.noise, 3), config=cfg)
    # 560 scan lines each tested at alpha: false edges are a small multiple of alpha per line
    assert len(e) < 0.05 * 560


def _cut(scan: Scan, cols: slice) -> Scan:
    r = scan.range.copy()
    r[:, cols] = np.nan
    return Scan(range=r, sensor=scan.sensor)


def test_a_surface_that_runs_into_no_return_out_to_the_border_ends_there():
    cfg = Config()
    plane = _plane_scan(cfg.noise, 3)
    base = detect_edges(plane, config=cfg)
    # no return from column 250 to the right border (70 px): every row ends in a jump
    e = detect_edges(_cut(plane, slice(250, None)), config=cfg)
    at = (e.pixels[:, 1] == 249) & (e.kinds == EdgeKind.JUMP)
    assert at.sum() >= 0.95 * 240
    # half a pixel past the last return, on the plane, and recorded as a decision
    last = plane.points[e.pixels[at, 0], 249].astype(np.float64)
    step = np.linalg.norm(plane.points[e.pixels[at, 0], 249] - plane.points[e.pixels[at, 0], 248],
                          axis=1)
    assert np.allclose(np.linalg.norm(e.points[at] - last, axis=1), 0.5 * step, rtol=0.5)
    t = e.tests.of_kind(TestKind.NO_RETURN)
    assert len(t) >= 0.95 * 240
    assert (t.statistic == 70).all() and (t.critical == NO_RETURN_PX).all()
    assert (t.dof == 0).all() and t.accepted.all()
    assert set((t.b % 320).tolist()) == {249}  # b = the pixel (row * W + col)
    # a shorter run to the border, or a run with the plane beyond it, is a dropout
    for cols in (slice(320 - NO_RETURN_PX + 1, None), slice(200, 230)):
        d = detect_edges(_cut(plane, cols), config=cfg)
        assert len(d.tests.of_kind(TestKind.NO_RETURN)) == 0
        assert len(d) <= len(base) + 0.05 * 240


def _far_step(seed: int, sigma: float) -> Scan:
    """A top at 3 m, 120 px wide, before a floor at 3.8 m, with 8 px of no return
    between them (stereo holes at a jump), range noise ``sigma`` everywhere."""
    pin = PinholeModel(525.0, 525.0, 319.5, 239.5, 640, 480)
    rays = pin.rays()
    r = 3.8 / rays[..., 2]
    r[:, 100:220] = 3.0 / rays[:, 100:220, 2]
    r[:, 92:100] = np.nan
    r[:, 220:228] = np.nan
    r = r + np.random.default_rng(seed).normal(size=r.shape) * sigma
    return Scan(range=r.astype(np.float32), sensor=pin)


def test_a_far_step_is_a_jump_on_every_row():
    # with noise of 35 mm at 3 m and 6 mm pixels, a total least-squares line through a
    # few of the top's samples and the floor's runs nearly along the rays and fits both:
    # split-and-merge bridged the step on three rows in four before the lines were cut
    # at range steps
    cfg = Config(noise=NoiseModel(sigma0=0.035, k1=0.0, k2=0.0))
    e = detect_edges(_far_step(0, 0.035), config=cfg)
    for col in (100, 219):  # the top's first and last column
        at = (e.pixels[:, 1] == col) & (e.kinds == EdgeKind.JUMP)
        assert at.sum() >= 0.95 * 480
    # nothing else on the two planes but the noise's false alarms (alpha per scan line)
    assert len(e) <= 2 * 480 + 0.05 * (480 + 640)


def _scan_line(r: np.ndarray) -> np.ndarray:
    """Points of one row of rays (0.002 rad apart) at ranges r, (n, 3)."""
    a = (np.arange(len(r)) - len(r) / 2) * 0.002
    return np.stack([np.sin(a) * r, np.zeros_like(r), np.cos(a) * r], -1)


def test_a_change_of_level_is_a_range_step_but_a_blob_or_a_steep_face_is_not():
    rng = np.random.default_rng(1)
    S = np.full(300, 0.002)
    thr = residual_thresholds(300, 0.01)
    plane = 2.0 + rng.normal(size=300) * 0.002
    blob = plane.copy()
    blob[100:100 + STEP_RUN_MAX - 2] += 0.05  # 25 sigma off, then back on the surface

    def bounds(r: np.ndarray, f=_split_at_steps) -> list[list[int]]:
        return f(_scan_line(r), S, thr, np.zeros(1, np.int64))[0].tolist()

    assert bounds(blob) == bounds(blob, _split_merge)  # left to split-and-merge as before
    step = plane.copy()
    step[150:] += 0.3  # a change of level: no segment may span it
    assert all(b[1] < 150 or b[0] >= 150 for b in bounds(step))
    # a face so steep that every sample steps 20 sigma further is no change of level:
    # its increments run on alike (a box side seen at grazing incidence)
    steep = plane.copy()
    steep[150:] += 0.04 * np.arange(150)
    assert bounds(steep) == bounds(steep, _split_merge)


def test_thresholds_grow_with_line_length():
    t = residual_thresholds(640, 0.01)
    assert t[10] < t[100] < t[640]
    assert t[1] == pytest.approx(2.576, abs=1e-3)
    assert run_thresholds(640, 0.01)[640] < t[640]


def test_local_scale_follows_a_noisier_region_and_ignores_edges():
    """The local noise scale: 1 where the noise is at the scan's level (white noise, and
    beside a depth jump), the noise's own ratio where it is 3x (a heavy tail's region)."""
    from boxloc.stages.edges import SCALE_TILE_PX, local_scale

    rng = np.random.default_rng(7)
    H, W = 240, 320
    S = np.full((H, W), 0.002)
    r = 2.0 + rng.normal(0.0, 0.002, (H, W))
    r[:, 160:] += 0.1  # a 10 cm jump down the middle
    loud = (slice(96, 160), slice(32, 96))
    r[loud] += rng.normal(0.0, 0.002 * np.sqrt(8.0), (64, 64))  # 3x the sigma
    g = local_scale(r, S)
    assert g.shape == (H, W) and np.all(g >= 1.0)
    inner = (slice(96 + SCALE_TILE_PX, 160 - SCALE_TILE_PX), slice(32 + SCALE_TILE_PX,
                                                                  96 - SCALE_TILE_PX))
    assert 2.5 < np.median(g[inner]) < 3.5
    quiet = g[:64, 200:]
    assert np.median(quiet) < 1.1 and quiet.max() < 1.3
    assert g[:64, 150:170].max() < 1.3  # the tiles the jump crosses
    # no return: NaN ranges leave the scale at 1
    r2 = np.full((H, W), np.nan)
    assert np.all(local_scale(r2, S) == 1.0)


def test_the_edges_of_a_given_noise_gain_are_those_it_computes_and_the_gain_is_used(one_box):
    """The pipeline computes the local noise gain once (``noise_gain``) and hands it to the
    edge stage and the seam tests: handed in, it gives the edges computed without it, bit
    for bit; and it is used: a gain three times louder gives another edge map."""
    from boxloc.stages.edges import noise_gain
    from boxloc.stages.verify import VerifyContext

    sim, e = one_box
    cfg = Config()
    g = noise_gain(sim.scan, cfg)
    given = detect_edges(sim.scan, config=cfg, gain=g)
    assert np.array_equal(given.labels, e.labels)
    assert np.array_equal(given.points, e.points)
    assert np.array_equal(given.covariances, e.covariances)
    up = sim.scan.up
    assert np.array_equal(VerifyContext.build(sim.scan, e, cfg, up, 1, g).gain,
                          VerifyContext.build(sim.scan, e, cfg, up, 1).gain)
    loud = detect_edges(sim.scan, config=cfg, gain=3.0 * g)
    assert not np.array_equal(loud.labels, e.labels)


def _fuse_one_pixel_at_a_time(flat, pt, cov, kd, stg, sd, chi3):
    """The fusion as a loop over the pixels: the reference :func:`_fuse` must equal."""
    order = np.lexsort((kd, flat))
    uniq, start = np.unique(flat[order], return_index=True)
    stop = np.r_[start[1:], len(order)]
    first = order[start]
    out = [pt[first], cov[first], kd[first], stg[first], sd[first]]
    for gi in range(len(uniq)):
        g = order[start[gi]:stop[gi]]
        d = pt[g] - pt[g[0]]
        T = np.array([d[k] @ np.linalg.solve(cov[g[k]] + cov[g[0]], d[k])
                      for k in range(1, len(g))])
        g = np.concatenate([[g[0]], g[1:][T <= chi3]]).astype(np.int64)
        if len(g) == 1:
            continue
        info = np.linalg.inv(cov[g])
        Cf = np.linalg.inv(info.sum(0))
        out[1][gi] = 0.5 * (Cf + Cf.T)
        out[0][gi] = Cf @ np.einsum("kij,kj->i", info, pt[g])
        out[2][gi], out[3][gi] = kd[g].min(), stg[g].max()
        out[4][gi] = np.bitwise_or.reduce(sd[g])
    return (uniq, *out)


def test_fusing_a_pixels_detections_equals_fusing_them_one_pixel_at_a_time():
    """Pixels with one to four detections, some agreeing with their first and some not
    (a kind's point a centimetre off): the batched fusion gives every array bit for bit
    what a loop over the pixels gives, and fuses what agrees only."""
    from boxloc.stages.edges import _fuse

    rng = np.random.default_rng(3)
    flat = np.repeat(np.arange(0, 3000, 3), rng.integers(1, 5, 1000))
    n = len(flat)
    pt = np.array([0.1, -0.2, 2.0]) + rng.normal(0.0, 1e-3, (n, 3))
    far = rng.random(n) < 0.3
    pt[far] += 0.01  # disagrees with the others of its pixel (sigma ~ 1 mm)
    A = rng.normal(0.0, 1e-3, (n, 3, 3))
    cov = A @ A.transpose(0, 2, 1) + 1e-7 * np.eye(3)
    kd = rng.integers(1, 5, n).astype(np.uint8)
    stg = rng.random(n)
    sd = rng.integers(1, 4, n).astype(np.uint8)
    perm = rng.permutation(n)  # detections arrive in scan order, not by pixel
    args = (flat[perm], pt[perm], cov[perm], kd[perm], stg[perm], sd[perm], 7.815)
    got, want = _fuse(*args), _fuse_one_pixel_at_a_time(*args)
    for g, w in zip(got, want):
        assert g.dtype == w.dtype and g.shape == w.shape
        assert g.tobytes() == w.tobytes()
    # some pixels fused several detections, some kept their first only
    uniq, fused_pt = got[0], got[1]
    counts = np.bincount(np.searchsorted(uniq, flat), minlength=len(uniq))
    first_pt = pt[perm][np.lexsort((kd[perm], flat[perm]))][np.r_[0, np.cumsum(counts)[:-1]]]
    changed = np.any(fused_pt != first_pt, axis=1)
    assert changed.sum() > 100 and (~changed & (counts > 1)).sum() > 50
    assert not changed[counts == 1].any()
    assert len(_fuse(flat[:0], pt[:0], cov[:0], kd[:0], stg[:0], sd[:0], 7.815)[0]) == 0


def test_the_local_scales_tile_medians_are_the_sorted_ones_bit_for_bit():
    # the kernel's per-tile count and median against the arrangement it replaced: the
    # tiles' values side by side, infinities made NaN, nanmedian_last (a sort)
    from boxloc.stages.edges import _tile_medians
    from boxloc.stats import nanmedian_last

    rng = np.random.default_rng(11)
    for H, W, tile in ((48, 64, 16), (50, 70, 16), (37, 29, 8)):
        A = np.abs(rng.standard_t(3, size=(2, H, W)))
        A[rng.random(A.shape) < 0.2] = np.nan
        A[rng.random(A.shape) < 0.01] = np.inf
        A[:, :tile, :tile] = np.nan  # a tile without returns
        A[0, -tile:, -tile:] = np.round(A[0, -tile:, -tile:])  # ties, as quantized depth
        th, tw = H // tile, W // tile
        B = A[:, :th * tile, :tw * tile].reshape(2, th, tile, tw, tile)
        B = B.transpose(1, 3, 0, 2, 4).reshape(th, tw, -1)
        B[~np.isfinite(B)] = np.nan
        n, med = _tile_medians(np.ascontiguousarray(A), th, tw, tile)
        assert n.tolist() == np.sum(np.isfinite(B), axis=2).tolist()
        want = nanmedian_last(B)
        assert np.array_equal(med, want, equal_nan=True)
        assert med.view(np.int64).tolist() == want.view(np.int64).tolist()

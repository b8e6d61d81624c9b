"""Stage 5 and 6: dimensions from vertices and from edges, and verification."""

from __future__ import annotations

import numpy as np
import pytest

from boxloc.config import Config
from boxloc.edges import detect_edges
from boxloc.hypotheses import generate_hypotheses
from boxloc.lines import find_lines
from boxloc.products import DimensionSource, VerifyReason
from boxloc.stats import TestKind
from boxloc.vertices import find_vertices
from tests.scenes import box, scene


def _stages(sim, cfg=None):
    cfg = cfg or Config()
    e = detect_edges(sim.scan, config=cfg)
    L = find_lines(sim.scan, e, config=cfg, rng=np.random.default_rng(sim.scan.seed))
    V = find_vertices(L, config=cfg)
    H, ver = generate_hypotheses(sim.scan, e, V, config=cfg)
    return e, L, V, H, ver


@pytest.fixture(scope="module")
def one_box():
    sim = scene([box(0.0, 0.0, 0.45, 0.30, 0.25, 0.2)], seed=6)
    return sim, _stages(sim)


def test_one_hypothesis_per_vertex_with_recorded_attempts(one_box):
    _, (_, _, V, H, ver) = one_box
    assert len(H) == len(V)
    assert H.n_attempts == len(ver)
    assert (np.diff(H.acc_x_offsets) >= 0).all()
    kept = H.attempt[H.attempt >= 0]
    assert ver.accepted[kept].all()


def test_dimensions_of_a_verified_hypothesis(one_box):
    sim, (_, _, _, H, ver) = one_box
    ok = np.flatnonzero(H.attempt >= 0)
    assert len(ok) >= 2  # several corners of the box verify
    dims = np.sort(np.c_[H.width[ok], H.length[ok]], axis=1)
    assert np.allclose(dims, [0.30, 0.45], atol=0.012)
    assert set(H.source[ok].tolist()) <= {DimensionSource.VERTICES, DimensionSource.EDGES}


def test_diagonal_vertex_tests_are_recorded(one_box):
    _, (_, _, _, H, _) = one_box
    for k in (TestKind.COPLANAR, TestKind.PARALLEL, TestKind.FIRST_QUADRANT):
        assert len(H.tests.of_kind(k)) > 0
    from_vertices = np.flatnonzero(H.att_source == DimensionSource.VERTICES)
    assert (H.att_diagonal[from_vertices] >= 0).all()


def test_dimensions_from_edges_when_no_diagonal_vertex():
    # the far corner is outside the image: only the near corners exist, dimensions come
    # from the edge accumulators (or the hypothesis fails as outside the image)
    sim = scene([box(0.0, 0.0, 0.45, 0.30, 0.25)], seed=6)
    e, L, V, H, ver = _stages(sim, Config())
    src = H.att_source[H.att_source == DimensionSource.EDGES]
    if len(src):
        j = int(np.flatnonzero(H.att_source == DimensionSource.EDGES)[0])
        h = H.att_hypothesis[j]
        assert H.att_support[j] > H.att_threshold[j]  # |P_f| > p
        assert H.peaks_x_offsets[h + 1] > H.peaks_x_offsets[h]
        assert len(H.tests.of_kind(TestKind.EDGE_SUPPORT)) > 0


def test_verification_rejects_a_face_with_a_box_on_it():
    # a small box standing on a big one: the big top is covered, not graspable
    from tests.scenes import TOP

    big = box(0.0, 0.0, 0.6, 0.45, 0.2)
    small = [0.05, 0.02, TOP + 0.2 + 0.075, 0.25, 0.2, 0.15, 0.0]
    sim = scene([big, small], seed=8)
    _, _, _, H, ver = _stages(sim)
    ok = H.attempt[H.attempt >= 0]
    # every verified attempt is the small box's top (about 0.2 x 0.25)
    dims = np.sort(np.c_[H.att_width[ok], H.att_length[ok]], axis=1)
    assert len(dims) > 0
    assert np.allclose(dims, [0.20, 0.25], atol=0.015)
    reasons = set(ver.reason.tolist())
    assert reasons & {VerifyReason.NOT_EXPOSED, VerifyReason.INTERIOR_EDGES,
                      VerifyReason.INLIERS, VerifyReason.BOUNDARY}


def test_dimensions_from_extent_measure_the_face(one_box):
    from boxloc.hypotheses import _Context, _VertexWork, align, dimensions_from_extent
    from boxloc.stats import TestTable

    sim, (e, _, V, H, _) = one_box
    cfg = Config()
    ctx = _Context.build(sim.scan, e, V, cfg, H.up)
    ok = np.flatnonzero(H.attempt >= 0)
    assert len(ok)
    for h in ok:
        work = _VertexWork(vertex=int(h))
        atts = dimensions_from_extent(align(V, int(h), ctx.normal_cov), ctx, work)
        # the extents on both arms are the first candidate: the verified top's size
        assert atts[0].source == DimensionSource.EXTENT
        assert abs(atts[0].width - H.width[h]) < 0.01
        assert abs(atts[0].length - H.length[h]) < 0.01
        rows = TestTable.concat(work.tests, cfg.alpha).of_kind(TestKind.FACE_EXTENT)
        assert list(rows.b) == [0, 1] and rows.accepted.all()
        assert np.allclose(rows.statistic, [atts[0].width, atts[0].length])

"""Stage 5 and 6: dimensions from vertices and from edges, and verification."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from boxloc.config import Config
from boxloc.products import DimensionSource, VerifyReason, VertexSet
from boxloc.stages.edges import detect_edges
from boxloc.stages.hypotheses import generate_hypotheses, neighbour_vertices
from boxloc.stages.lines import find_lines
from boxloc.stages.vertices import find_vertices
from boxloc.stats import TestKind, TestTable
from tests.scenes import box, scene


def _stages(sim, cfg=None):
    cfg = cfg or Config()
    e = detect_edges(sim.scan, config=cfg)
    L = find_lines(sim.scan, e, config=cfg, rng=np.random.default_rng(sim.scan.seed))
    V = find_vertices(L, config=cfg)
    V, H, ver = generate_hypotheses(sim.scan, e, V, config=cfg)
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


def _without_corner(e, corner: np.ndarray, radius: float):  # type: ignore[no-untyped-def]
    """The edge map less its points within ``radius`` of ``corner`` (an occluded corner)."""
    keep = np.linalg.norm(e.points - corner, axis=1) > radius
    labels = e.labels.copy()
    labels[e.pixels[~keep, 0], e.pixels[~keep, 1]] = 0
    return dataclasses.replace(
        e, labels=labels, pixels=e.pixels[keep], points=e.points[keep],
        covariances=e.covariances[keep], kinds=e.kinds[keep], strength=e.strength[keep],
        scan_dir=e.scan_dir[keep])


def test_dimensions_from_edges_when_no_diagonal_vertex():
    # one corner of the top lost (no edge points within 8 cm of it): the vertex diagonal to
    # it has no diagonal vertex, so its dimensions come from the edge accumulators
    sim = scene([box(0.0, 0.0, 0.45, 0.30, 0.25)], seed=6)
    cfg = Config()
    top = int(np.argmax(sim.truth.fully_exposed))
    e = _without_corner(detect_edges(sim.scan, config=cfg), sim.truth.corners[top][0], 0.08)
    L = find_lines(sim.scan, e, config=cfg, rng=np.random.default_rng(sim.scan.seed))
    V = find_vertices(L, config=cfg)
    V, H, ver = generate_hypotheses(sim.scan, e, V, config=cfg)
    from_edges = np.flatnonzero(H.att_source == DimensionSource.EDGES)
    # (was skipped silently when no attempt took its dimensions from the edges)
    assert len(from_edges), "no attempt took its dimensions from the edge accumulators"
    for j in from_edges:
        h = H.att_hypothesis[j]
        assert H.att_support[j] > H.att_threshold[j]  # |P_f| > p
        assert H.peaks_x_offsets[h + 1] > H.peaks_x_offsets[h]
    assert len(H.tests.of_kind(TestKind.EDGE_SUPPORT)) > 0
    # and one of them is the top: its sides' edges are there
    dims = np.sort(np.c_[H.att_width[from_edges], H.att_length[from_edges]], axis=1)
    assert np.any(np.all(np.abs(dims - [0.30, 0.45]) < 0.02, axis=1))


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
    from boxloc.stages.hypotheses import _Context, _VertexWork, align, dimensions_from_extent
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


def _outcome(tests, accepted=True, center=(0.0, 0.0, 1.5), normal=(0.0, 0.0, -1.0)):
    from boxloc.stages.verify import VerifyOutcome
    return VerifyOutcome(
        n_inside=100, n_valid=100, n_inliers=100, n_front=0, n_behind=0,
        inlier_fraction=1.0, mean_distance=0.0, sigma_mean=0.001, n_interior_edges=0,
        plane_center=np.array(center), plane_normal=np.array(normal),
        plane_cov=np.eye(6) * 1e-8, rms=0.001, error=1.0, accepted=accepted,
        reason=VerifyReason.ACCEPTED if accepted else VerifyReason.BOUNDARY,
        inlier_pixels=np.zeros(0, np.int32), tests=TestTable.concat(tests, 0.01))


def _one_vertex(o=(0.0, 0.0, 1.5)):
    # seen from the origin down +z: a face at z = 1.5, normal -z (toward the sensor);
    # d1 x d2 = x x (-y) = -z
    cov = np.eye(9) * 1e-8
    return VertexSet(points=np.array([o]), d1=np.array([[1.0, 0, 0]]),
                     d2=np.array([[0, -1.0, 0]]), normals=np.array([[0, 0, -1.0]]),
                     covariances=cov[None], line_a=np.zeros(1, np.int32),
                     line_b=np.ones(1, np.int32), tests=TestTable.empty(0.01))


def _work(vertex, width, length, seam_sides, runs_on, on_plane=0.95, off_plane=0.0):
    from boxloc.stages.hypotheses import _Attempt, _VertexWork
    seam = TestTable.decision(TestKind.VERIFY_SEAM_SIDE, -1, sorted(seam_sides),
                              [9.0] * len(seam_sides), [3.0] * len(seam_sides),
                              [True] * len(seam_sides), 0.01)
    cont = TestTable.decision(TestKind.VERIFY_CONTINUATION, -1, [0, 1, 2, 3],
                              [on_plane if s in runs_on else off_plane for s in range(4)], 0.8,
                              [True] * 4, 0.01)
    interior = TestTable.decision(TestKind.VERIFY_SEAM_INTERIOR, -1, [0, 1], [1.0, 1.0],
                                  [3.5, 3.5], [True, True], 0.01)
    att = _Attempt(DimensionSource.EDGES, -1, width, length, 0.0, 0.0,
                   outcome=_outcome([seam, interior, cont]))
    return _VertexWork(vertex=vertex, attempts=[att])


def test_neighbour_vertices_are_the_corners_of_a_seam_side():
    V = _one_vertex()
    # side 3 (u = width) is a seam beyond which the plane runs on: the neighbour's corners
    W = neighbour_vertices(V, [_work(0, 0.3, 0.4, {3}, {3})], 0, Config())
    assert len(W) == 3
    assert W.parent.tolist() == [-1, 0, 0] and W.parent_side.tolist() == [-1, 3, 3]
    assert (W.line_a[1:] == -1).all()
    assert np.allclose(W.points[1], [0.3, 0.0, 1.5]) and np.allclose(W.points[2],
                                                                     [0.3, -0.4, 1.5])
    # each new vertex opens onto the neighbour (+x), normal still toward the sensor
    for v in (1, 2):
        assert np.allclose(np.cross(W.d1[v], W.d2[v]), [0, 0, -1.0])
        assert max(W.d1[v] @ [1.0, 0, 0], W.d2[v] @ [1.0, 0, 0]) == pytest.approx(1.0)
    t = W.tests.of_kind(TestKind.NEIGHBOUR_CORNER)
    assert len(t) == 2 and not t.accepted.any()
    # offered again, the same corners are found to be there already
    again = neighbour_vertices(W, [_work(0, 0.3, 0.4, {3}, {3})], 0, Config())
    assert len(again) == 3
    t2 = again.tests.of_kind(TestKind.NEIGHBOUR_CORNER)
    assert t2.accepted[-2:].all() and set(t2.b[-2:].tolist()) == {1, 2}


def test_a_neighbour_with_a_bulged_lid_is_an_equal_neighbour():
    # its middle rises off the plane: 0.65 of the strip beyond the seam on it, short of
    # min_inlier_fraction (0.8) but half or more; a lower neighbour's strip holds a few
    V = _one_vertex()
    bulged = _work(0, 0.3, 0.4, {3}, {3}, on_plane=0.65)
    assert len(neighbour_vertices(V, [bulged], 0, Config())) == 3
    lower = _work(0, 0.3, 0.4, {3}, {3}, on_plane=0.3)
    assert len(neighbour_vertices(V, [lower], 0, Config())) == 1


def test_no_neighbour_corner_where_the_neighbour_is_found_already():
    # vertex 1 is the far corner (0.3, -0.4) of the neighbour beyond side 3, with the
    # neighbour's rectangle verified from it: both corners offered are known (one is
    # vertex 1, the other a corner of its rectangle), so nothing is added
    V0 = _one_vertex()
    V = VertexSet(points=np.r_[V0.points, [[0.6, -0.4, 1.5]]],
                  d1=np.r_[V0.d1, [[-1.0, 0, 0]]], d2=np.r_[V0.d2, [[0, 1.0, 0]]],
                  normals=np.r_[V0.normals, V0.normals],
                  covariances=np.r_[V0.covariances, V0.covariances],
                  line_a=np.zeros(2, np.int32), line_b=np.ones(2, np.int32),
                  tests=TestTable.empty(0.01))
    works = [_work(0, 0.3, 0.4, {3}, {3}), _work(1, 0.3, 0.4, set(), set())]
    W = neighbour_vertices(V, works, 0, Config())
    assert len(W) == 2
    t = W.tests.of_kind(TestKind.NEIGHBOUR_CORNER)
    assert len(t) == 2 and t.accepted.all()


def test_no_neighbour_across_a_seam_to_a_lower_surface():
    # the side is a seam (gap) but the plane does not run on: no equal neighbour there
    V = _one_vertex()
    assert len(neighbour_vertices(V, [_work(0, 0.3, 0.4, {3}, set())], 0, Config())) == 1
    # nor across a seam weaker than the search inside the rectangle had to find
    w = _work(0, 0.3, 0.4, {3}, {3})
    o = w.attempts[0].outcome
    seam = o.tests.of_kind(TestKind.VERIFY_SEAM_SIDE)
    w.attempts[0].outcome = dataclasses.replace(o, tests=TestTable.concat(
        [dataclasses.replace(seam, statistic=np.array([3.0])),
         o.tests.of_kind(TestKind.VERIFY_SEAM_INTERIOR),
         o.tests.of_kind(TestKind.VERIFY_CONTINUATION)], 0.01))
    assert len(neighbour_vertices(V, [w], 0, Config())) == 1
    # nor from a rectangle that was not verified
    w = _work(0, 0.3, 0.4, {3}, {3})
    w.attempts[0].outcome = dataclasses.replace(w.attempts[0].outcome, accepted=False)
    assert len(neighbour_vertices(V, [w], 0, Config())) == 1


def test_a_seam_side_across_another_rectangle_rejects_it():
    # rectangle A spans two boxes (0.6 along x); B, the left box, has a strong seam at
    # u = 0.3 on its side 3, which crosses A's core: A is rejected, B kept
    from boxloc.stages.hypotheses import _seams_across
    V = dataclasses.replace(_one_vertex(), tests=TestTable.empty(0.01))
    V = VertexSet(points=np.r_[V.points, V.points], d1=np.r_[V.d1, V.d1],
                  d2=np.r_[V.d2, V.d2], normals=np.r_[V.normals, V.normals],
                  covariances=np.r_[V.covariances, V.covariances],
                  line_a=np.zeros(2, np.int32), line_b=np.ones(2, np.int32),
                  tests=TestTable.empty(0.01))
    for z, rejected in ((9.0, True), (3.0, False)):  # a weak seam does not
        a = _work(0, 0.6, 0.4, set(), set()).attempts[0]
        b = _work(1, 0.3, 0.4, {3}, {3}).attempts[0]
        seam = b.outcome.tests.of_kind(TestKind.VERIFY_SEAM_SIDE)
        b.outcome = dataclasses.replace(b.outcome, tests=dataclasses.replace(
            seam, statistic=np.array([z])))
        rows = [(0, a), (1, b)]
        _seams_across(rows, V, Config())
        assert a.outcome.accepted is not rejected and b.outcome.accepted
        t = a.outcome.tests.of_kind(TestKind.VERIFY_SEAM_CROSSING)
        assert len(t) == 1
        if rejected:  # most of B's side lies in A's core, beyond the band along its sides
            assert t.b[0] == 1 and t.statistic[0] > 0.6
            assert a.outcome.reason == VerifyReason.INTERIOR_SEAM
        else:  # a weak seam is not counted
            assert t.b[0] == -1 and t.statistic[0] == 0.0


def test_interior_boxes_of_a_neat_layer_are_found_through_their_neighbours():
    # suite scene 7: a partly unloaded neat layer whose seams the edge stage does not see;
    # the interior boxes have no vertex of two lines, only their neighbours' corners
    from boxloc.evaluate.metrics import match_surfaces
    from boxloc.pipeline import find_graspable_surfaces
    from boxloc.simulate import scene_suite, simulate
    sim = simulate(list(scene_suite(60, 0))[7])
    r = find_graspable_surfaces(sim.scan, Config())
    m = match_surfaces(r.surfaces, sim.truth)
    assert m.fp == 0 and m.tp >= 8  # 2 without the neighbours' corners
    hyp = r.hypotheses.att_hypothesis[r.surfaces.attempt]
    assert (r.vertices.parent[hyp] >= 0).sum() >= 4


def test_the_hypothesis_stage_works_on_the_highest_vertices_within_its_budget():
    # a low box and a high one: with room for one vertex, the high box's is worked on
    sim = scene([box(-0.3, 0.0, 0.40, 0.30, 0.15, 0.0), box(0.3, 0.0, 0.40, 0.30, 0.35, 0.0)],
                seed=3)
    _, _, V, H, ver = _stages(sim, Config(max_vertices=1))
    (row,) = H.tests.of_kind(TestKind.BUDGET).rows()
    assert not row["accepted"] and row["critical"] == 1 and row["statistic"] == len(V) > 1
    worked = np.unique(H.att_hypothesis)
    assert len(worked) == 1
    height = V.points @ sim.scan.up
    assert height[worked[0]] == height.max()
    # without the cut every vertex is worked on, and no budget row is recorded
    _, _, V2, H2, _ = _stages(sim)
    assert len(H2.tests.of_kind(TestKind.BUDGET)) == 0 and len(np.unique(H2.att_hypothesis)) > 1


def test_a_packed_box_nearly_max_edge_long_is_parted_at_its_far_seam():
    # four boxes touching (no gap, no edge at the seams): their long side, 0.56 m, is
    # longer than max_edge less a short box edge, so its seam lies beyond the region the
    # first seam search covers; the search near max_edge finds it
    from boxloc.evaluate.metrics import match_surfaces
    from boxloc.pipeline import find_graspable_surfaces
    boxes = [box(sx * 0.1505, sy * 0.2805, 0.30, 0.56, 0.25) for sx in (-1, 1) for sy in (-1, 1)]
    sim = scene(boxes, distance=2.4, tilt=0.1, seed=3)
    r = find_graspable_surfaces(sim.scan, Config(min_edge=0.15, max_edge=0.6))
    m = match_surfaces(r.surfaces, sim.truth)
    assert m.tp == 4 and m.fp == 0
    far = r.hypotheses.tests.of_kind(TestKind.SEAM_PEAK)
    near_max = far.b >= 2
    assert near_max.any() and (far.statistic[near_max] > far.critical[near_max]).all()
    dims = np.sort(np.c_[r.surfaces.width, r.surfaces.length], axis=1)
    assert np.allclose(dims, [0.30, 0.56], atol=0.015)


# --- a vertex of a side face: no search (HYPOTHESIS_TILT) --------------------------------------


@pytest.fixture(scope="module")
def tall_box_at_an_angle():
    # a tall box seen 0.6 rad off vertical: its side faces show, with vertices of their own
    sim = scene([box(0.0, 0.0, 0.40, 0.30, 0.45, 0.3)], tilt=0.6, seed=3)
    return sim, _stages(sim)


def test_a_vertex_tilted_beyond_max_tilt_gets_no_rectangle(tall_box_at_an_angle):
    from boxloc.stages.verify import tilt_from_up

    sim, (_, _, V, H, ver) = tall_box_at_an_angle
    rows = H.tests.of_kind(TestKind.HYPOTHESIS_TILT)
    assert len(rows) >= 1  # the side faces' corners
    cfg = Config()
    for i, t, crit, ok in zip(rows.a, rows.statistic, rows.critical, rows.accepted):
        assert not ok and crit == cfg.max_tilt and t > cfg.max_tilt
        assert t == tilt_from_up(V.normals[i], sim.scan.up)
        assert i not in set(H.att_hypothesis.tolist())  # no attempt from it
    # every other vertex is searched, and none of its attempts fails the tilt prior
    assert not (ver.reason == VerifyReason.TILTED).any()
    assert ver.accepted.any()  # the top is still found


def test_skipping_the_tilted_vertices_changes_no_verified_rectangle(tall_box_at_an_angle,
                                                                    monkeypatch):
    import boxloc.stages.hypotheses as hyp_stage

    sim, (_, _, _, H, ver) = tall_box_at_an_angle
    monkeypatch.setattr(hyp_stage, "_too_tilted", lambda R, ctx: None)  # search them all
    _, _, _, H_all, ver_all = _stages(sim)
    tilted = H.tests.of_kind(TestKind.HYPOTHESIS_TILT).a
    of_tilted = np.isin(H_all.att_hypothesis, tilted)
    assert of_tilted.any()  # searched now: each of their attempts fails the tilt first
    assert (ver_all.reason[of_tilted] == VerifyReason.TILTED).all()

    def accepted(H: object, v: object) -> list[tuple[float, ...]]:
        k = np.flatnonzero(v.accepted)  # type: ignore[attr-defined]
        return sorted((int(H.att_hypothesis[j]), float(H.att_width[j]),  # type: ignore[attr-defined]
                       float(H.att_length[j])) for j in k)  # type: ignore[attr-defined]

    assert accepted(H, ver) == accepted(H_all, ver_all)


def test_explain_at_a_side_face_says_its_vertex_was_tilted(tall_box_at_an_angle, tmp_path):
    from factories import feed

    from boxloc import find_graspable_surfaces
    from recorder.mcap.sink import McapRecorder
    from replay.explain import explain

    sim, _ = tall_box_at_an_angle
    cfg = Config()
    r = find_graspable_surfaces(sim.scan, cfg)
    log = tmp_path / "tilt.mcap"
    with McapRecorder(log) as rec:
        feed(rec, sim.scan, r, cfg)
    V = r.vertices
    said = []
    for i in r.hypotheses.tests.of_kind(TestKind.HYPOTHESIS_TILT).a:
        P = V.points[i] + 0.06 * V.d1[i] + 0.06 * V.d2[i]  # inside the side face's corner
        a = explain(log, 0, at=tuple(float(x) for x in P))["at"]
        said.append(a["stopped_at"] == "dimensions" and re.search(
            rf"vertex V{i}\): no rectangle was sought, its plane is tilted beyond max_tilt "
            rf"from up \(a side face\): HYPOTHESIS_TILT {i},-1: [\d.]+ > 0.7854: REJECTED",
            a["why"]) is not None)
    assert any(said), said


def test_a_candidate_with_a_seam_at_its_middle_is_followed_by_its_half(monkeypatch):
    # a 0.6 x 0.4 candidate whose middle along x shows a seam (two boxes side by side):
    # the 0.3 x 0.4 half at the vertex is verified next, before the other candidates
    import boxloc.stages.hypotheses as hyp
    from boxloc.stages.verify import _failed

    seen: list[tuple[float, float, DimensionSource]] = []

    def fake_verify(R, att, ctx, size_sides=frozenset(), family=1):
        seen.append((att.width, att.length, att.source))
        if att.width > 0.5:  # the pair: its midline along x rejects it
            mid = TestTable.decision(TestKind.VERIFY_SEAM_MIDLINE, -1, [0, 1], [4.7, 1.0],
                                     [2.9, 2.9], [False, True], 0.01)
            att.outcome = _failed(VerifyReason.INTERIOR_SEAM, [mid], 0.01)
        else:
            att.outcome = _outcome([], accepted=att.width == 0.3)

    monkeypatch.setattr(hyp, "_verify", fake_verify)
    monkeypatch.setattr(hyp, "_verified_pixels", lambda R, att, ctx: 0.0)
    work = hyp._VertexWork(vertex=0)
    cands = [hyp._Attempt(DimensionSource.VERTICES, 1, 0.6, 0.4, 0.0, 0.0),
             hyp._Attempt(DimensionSource.EDGES, -1, 0.2, 0.4, 0.0, 0.0)]
    ok, tried = hyp._try_in_turn(None, None, work, cands, 6)  # type: ignore[arg-type]
    assert ok and tried == 2
    assert seen == [(0.6, 0.4, DimensionSource.VERTICES), (0.3, 0.4, DimensionSource.MIDLINE)]
    half = work.attempts[1]
    assert (half.support, half.threshold) == (4.7, 2.9)  # the midline's z and critical
    # within the budget: with one verification left, the half is not tried
    seen.clear()
    cands = [hyp._Attempt(DimensionSource.VERTICES, 1, 0.6, 0.4, 0.0, 0.0)]
    ok, tried = hyp._try_in_turn(None, None, hyp._VertexWork(vertex=0), cands, 1)  # type: ignore[arg-type]
    assert not ok and tried == 1 and len(seen) == 1
    # a candidate rejected otherwise (its midline shows nothing) is not halved
    assert hyp._midline_half(hyp._Attempt(DimensionSource.EDGES, -1, 0.6, 0.4, 0.0, 0.0,
                                          outcome=_outcome([], accepted=False))) is None

    def part_after(width: float, length: float, b: list[int], z: list[float]
                   ) -> hyp._Attempt | None:
        """_midline_half of a candidate whose midline rows b (z each) all rejected but
        those at z 1.0."""
        rows = TestTable.decision(TestKind.VERIFY_SEAM_MIDLINE, -1, b, z, [2.9] * len(b),
                                  [v == 1.0 for v in z], 0.01)
        return hyp._midline_half(hyp._Attempt(
            DimensionSource.EDGES, -1, width, length, 0.0, 0.0,
            outcome=_failed(VerifyReason.INTERIOR_SEAM, [rows], 0.01)))

    # one rejected by the seams at its thirds along x (b = 2) is followed by its third
    part = part_after(0.45, 0.4, [0, 2], [1.0, 4.7])
    assert part is not None and (part.width, part.length) == (0.15, 0.4)
    # the middle and the quarters along y both showing: halved (the fewest parts), and the
    # half is halved again when its own middle shows
    part = part_after(0.3, 0.6, [1, 5], [5.0, 4.0])
    assert part is not None and (part.width, part.length) == (0.3, 0.3)
    # its support is the middle's z, the row that chose the parts, even where the
    # quarters' sum is the stronger
    part = part_after(0.3, 0.6, [1, 5], [4.0, 5.0])
    assert part is not None and (part.width, part.length, part.support) == (0.3, 0.3, 4.0)

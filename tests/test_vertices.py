"""Stage 4: vertices from pairs of lines."""

from __future__ import annotations

import numpy as np
import pytest

from boxloc.config import Config
from boxloc.stages.vertices import find_vertices
from boxloc.stats import TestKind
from tests.test_stats import _line, _lineset

X, Y, Z = np.eye(3)


def _fits(*specs, seed=0):
    rng = np.random.default_rng(seed)
    return _lineset([_line(np.asarray(c, float), np.asarray(d, float), 60, ln, 0.0015, rng)
                     for c, d, ln in specs])


def test_an_L_of_two_lines_gives_one_vertex():
    corner = np.array([0.0, 0.0, 1.5])
    L = _fits((corner + 0.15 * X, X, 0.3), (corner + 0.1 * Y, Y, 0.2))
    V = find_vertices(L, config=Config())
    assert len(V) == 1
    assert np.linalg.norm(V.points[0] - corner) < 0.003
    # arms point into the segments; the normal points toward the sensor (the origin)
    assert {tuple(np.round(V.d1[0])), tuple(np.round(V.d2[0]))} == {(1, 0, 0), (0, 1, 0)}
    assert V.normals[0] @ V.points[0] < 0
    assert np.allclose(np.cross(V.d1[0], V.d2[0]), V.normals[0], atol=1e-9)
    assert V.covariances.shape == (1, 9, 9)


def test_a_T_gives_two_vertices_and_a_cross_four():
    c = np.array([0.0, 0.0, 1.5])
    T = _fits((c, X, 0.6), (c + 0.15 * Y, Y, 0.3))
    assert len(find_vertices(T, config=Config())) == 2
    plus = _fits((c, X, 0.6), (c, Y, 0.6))
    assert len(find_vertices(plus, config=Config())) == 4


def test_parallel_skew_and_far_apart_lines_give_no_vertex():
    c = np.array([0.0, 0.0, 1.5])
    par = _fits((c, X, 0.3), (c + 0.1 * Y, X, 0.3))
    assert len(find_vertices(par, config=Config())) == 0
    skew = _fits((c + 0.15 * X, X, 0.3), (c + 0.1 * Y + 0.05 * Z, Y, 0.2))  # 5 cm apart
    V = find_vertices(skew, config=Config())
    assert len(V) == 0
    assert not V.tests.of_kind(TestKind.LINES_MEET).accepted[0]
    far = _fits((c + 0.15 * X, X, 0.3), (c + 0.6 * X + 0.3 * Y, Y, 0.2))  # meet far away
    assert not find_vertices(far, config=Config()).tests.of_kind(
        TestKind.AT_SEGMENT_ENDS).accepted[0]


@pytest.mark.parametrize("end_tolerance", [None, 0.5, 1.0])
def test_a_segment_may_stop_short_of_its_corner_by_end_tolerance_of_the_shortest_edge(
        end_tolerance):
    # rounded and dented cardboard corners: the edge down the front starts a gap g below
    # the corner; the gap is allowed up to end_tolerance * min_edge, and not beyond
    corner = np.array([0.0, 0.0, 1.5])
    cfg = Config() if end_tolerance is None else Config(end_tolerance=end_tolerance)
    for frac, found in ((cfg.end_tolerance - 0.1, True), (cfg.end_tolerance + 0.1, False)):
        g = frac * cfg.min_edge
        L = _fits((corner + 0.15 * X, X, 0.3), (corner + (g + 0.1) * Y, Y, 0.2))
        V = find_vertices(L, config=cfg)
        ends = V.tests.of_kind(TestKind.AT_SEGMENT_ENDS)
        assert ends.accepted[0] == found
        assert abs(ends.statistic[0] - g) < 0.005  # the gap, metres
        assert ends.critical[0] == pytest.approx(cfg.end_tolerance * cfg.min_edge)
        assert (len(V) == 1) == found
        if found:
            assert np.linalg.norm(V.points[0] - corner) < 0.003


def test_end_tolerance_is_recorded_at_its_default_too():
    assert Config().to_dict()["end_tolerance"] == 0.75
    assert Config(end_tolerance=0.75).hash == Config().hash
    c = Config(end_tolerance=0.5)
    assert c.to_dict()["end_tolerance"] == 0.5 and c.hash != Config().hash
    assert Config.from_toml(c.to_toml()) == c
    assert "end_tolerance = 0.75" in Config().to_toml()
    assert Config().with_overrides(["end_tolerance=0.6"]).end_tolerance == 0.6


def test_every_pair_is_tested_and_recorded():
    c = np.array([0.0, 0.0, 1.5])
    L = _fits((c, X, 0.3), (c, Y, 0.3), (c + 0.5 * Y, X, 0.3))
    t = find_vertices(L, config=Config()).tests
    for kind in (TestKind.LINES_MEET, TestKind.LINES_ORTHOGONAL, TestKind.AT_SEGMENT_ENDS):
        assert len(t.of_kind(kind)) == 3


def test_a_vertex_set_from_a_log_before_neighbours_reads_back_as_lines():
    # logs of schema 1.0 have no parent columns: every vertex is then one of two lines
    from boxloc.products import VertexSet, from_arrays, to_arrays
    corner = np.array([0.0, 0.0, 1.5])
    V = find_vertices(_fits((corner + 0.15 * X, X, 0.3), (corner + 0.1 * Y, Y, 0.2)),
                      config=Config())
    assert len(V) == 1 and V.parent.tolist() == [-1]
    arrays = {k: v for k, v in to_arrays(V).items() if "parent" not in k}
    W = from_arrays(VertexSet, arrays)
    assert W.parent.tolist() == [-1] and W.parent_side.tolist() == [-1]


def _crease_corner(kind_a: int) -> tuple:
    """A box corner seen from the origin: line a (kind ``kind_a``) along x where the top
    meets the front face, line b down the front face along y; the box lies toward +z."""
    import dataclasses
    corner = np.array([0.0, 0.0, 1.5])
    L = _fits((corner + 0.15 * X, X, 0.3), (corner + 0.1 * Y, Y, 0.2))
    return corner, dataclasses.replace(L, kinds=np.array([kind_a, 1], np.uint8))


def test_a_convex_crease_corner_is_also_a_vertex_of_the_face_across_it():
    from boxloc.products import EdgeKind
    from boxloc.stages.vertices import THIRD_EDGE
    corner, L = _crease_corner(EdgeKind.CREASE_CONVEX)
    V = find_vertices(L, config=Config())
    assert len(V) == 2
    assert V.parent.tolist() == [-1, 0] and V.parent_side.tolist() == [-1, THIRD_EDGE]
    # the new vertex: same point, arms along the crease (+x) and into the box (+z, away
    # from the sensor, against the front face's normal), normal toward the sensor
    assert np.allclose(V.points[1], V.points[0])
    arms = {tuple(np.round(V.d1[1])), tuple(np.round(V.d2[1]))}
    assert arms == {(1, 0, 0), (0, 0, 1)}
    assert V.normals[1] @ V.points[1] < 0
    assert np.allclose(np.cross(V.d1[1], V.d2[1]), V.normals[1], atol=1e-9)
    # the crease keeps its line id, the implied third edge has none
    assert sorted([int(V.line_a[1]), int(V.line_b[1])]) == [-1, 0]
    # the third edge's direction is as uncertain as the front face's normal
    k = 3 if V.line_a[1] == -1 else 6
    assert np.trace(V.covariances[1][k:k + 3, k:k + 3]) > 0


def test_no_box_corner_vertex_without_a_convex_crease():
    from boxloc.products import EdgeKind
    for kind in (EdgeKind.JUMP, EdgeKind.CREASE_CONCAVE, EdgeKind.GROOVE):
        _, L = _crease_corner(kind)
        V = find_vertices(L, config=Config())
        assert len(V) == 1 and V.parent.tolist() == [-1]


def test_a_T_on_a_crease_gives_its_box_corner_vertex_once():
    import dataclasses

    from boxloc.products import EdgeKind
    c = np.array([0.0, 0.0, 1.5])
    T = _fits((c, X, 0.6), (c + 0.15 * Y, Y, 0.3))  # the crease runs on both ways
    T = dataclasses.replace(T, kinds=np.array([1, EdgeKind.CREASE_CONVEX], np.uint8))
    V = find_vertices(T, config=Config())
    # two vertices of lines; the crease (along y) gives one corner per arm pair, but both
    # of the T's vertices share its arm: one box corner vertex
    assert (V.parent >= 0).sum() == 1


def test_a_box_corner_is_offered_only_where_its_face_can_be_a_top():
    from boxloc.products import EdgeKind
    _, L = _crease_corner(EdgeKind.CREASE_CONVEX)
    # the face across the crease has normal -y (y is down): a top when up is -y, a side
    # face when the sensor looks straight down (up -z)
    for up, offered in (((0.0, -1.0, 0.0), True), ((0.0, 0.0, -1.0), False)):
        V = find_vertices(L, config=Config(), up=np.array(up))
        t = V.tests.of_kind(TestKind.BOX_CORNER)
        assert len(t) == 1 and t.a[0] == 0 and t.b[0] == 0
        assert bool(t.accepted[0]) is offered
        assert len(V) == (2 if offered else 1)
        assert bool(t.statistic[0] < 0) is offered  # n.up above cos(max_tilt), or below

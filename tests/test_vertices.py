"""Stage 4: vertices from pairs of lines."""

from __future__ import annotations

import numpy as np

from boxloc.config import Config
from boxloc.stats import TestKind
from boxloc.vertices import find_vertices
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

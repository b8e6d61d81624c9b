"""Tests of boxloc.evaluate.metrics: rectangle IoU, surface matching, edge scores, pooling."""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import pytest

from boxloc.evaluate.baseline import empty_surface_set, surface_set_from_rects
from boxloc.evaluate.metrics import (
    FalseKind,
    PredStatus,
    WrongReason,
    aggregate_edges,
    aggregate_matches,
    edge_report,
    edge_scores,
    false_kind_counts,
    false_kinds,
    height_errors,
    match_surfaces,
    prf,
    rect_iou_in_plane,
    rect_overlap_in_plane,
    region_cover,
    true_box_heights,
    wrong_rectangles,
)
from boxloc.products import EdgeKind

# --- helpers -----------------------------------------------------------------------------


def _rot(axis: str, deg: float) -> np.ndarray:
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _corners(c: np.ndarray, x: np.ndarray, y: np.ndarray, w: float, length: float) -> np.ndarray:
    a, b = 0.5 * w * x, 0.5 * length * y
    return np.array([c - a - b, c + a - b, c + a + b, c - a + b])


# A face frame that is deliberately not axis-aligned with the sensor, to catch frame bugs.
R0 = _rot("z", 17.0) @ _rot("x", 160.0)
EX, EY, EN = R0[:, 0], R0[:, 1], R0[:, 2]
C0 = np.array([0.1, -0.2, 1.9])


@dataclass
class FakeTruth:
    """The face arrays of a GroundTruth, for scoring without the simulator."""

    centers: np.ndarray
    normals: np.ndarray
    x_axis: np.ndarray
    y_axis: np.ndarray
    width: np.ndarray
    length: np.ndarray
    fully_exposed: np.ndarray


def _truth(faces: list[tuple[tuple[float, float, float], float, float, bool]]) -> FakeTruth:
    """Horizontal faces (normal -z, toward a sensor looking down +z) at the given centres."""
    F = len(faces)
    return FakeTruth(
        centers=np.array([f[0] for f in faces], dtype=float).reshape(F, 3),
        normals=np.tile([0.0, 0.0, -1.0], (F, 1)),
        x_axis=np.tile([1.0, 0.0, 0.0], (F, 1)),
        y_axis=np.tile([0.0, -1.0, 0.0], (F, 1)),
        width=np.array([f[1] for f in faces], dtype=float),
        length=np.array([f[2] for f in faces], dtype=float),
        fully_exposed=np.array([f[3] for f in faces], dtype=bool),
    )


def _preds(rects: list[tuple[tuple[float, float, float], float, float]],
           normals: list[np.ndarray] | None = None) -> object:
    s = len(rects)
    C = np.array([r[0] for r in rects], dtype=float).reshape(s, 3)
    N = np.tile([0.0, 0.0, -1.0], (s, 1)) if normals is None else np.array(normals)
    X = np.tile([1.0, 0.0, 0.0], (s, 1))
    return surface_set_from_rects(C, N, X, [r[1] for r in rects], [r[2] for r in rects])


# --- rect_iou_in_plane -------------------------------------------------------------------


def test_iou_identical_is_one() -> None:
    P = _corners(C0, EX, EY, 0.3, 0.5)
    assert rect_iou_in_plane(P, EN, C0, EX, EY, 0.3, 0.5) == pytest.approx(1.0, abs=1e-12)


def test_iou_corner_order_does_not_matter() -> None:
    P = _corners(C0, EX, EY, 0.3, 0.5)[[0, 2, 1, 3]]  # a self-crossing order
    assert rect_iou_in_plane(P, EN, C0, EX, EY, 0.3, 0.5) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize(
    ("dx", "dy", "expected"),
    [
        (0.15, 0.0, 1.0 / 3.0),  # half the width: inter = wl/2, union = 3wl/2
        (0.0, 0.25, 1.0 / 3.0),  # half the length
        (0.15, 0.25, 1.0 / 7.0),  # a quarter overlaps: inter = wl/4, union = 7wl/4
        (0.3, 0.0, 0.0),  # touching
        (1.0, 1.0, 0.0),  # far
    ],
)
def test_iou_shifted(dx: float, dy: float, expected: float) -> None:
    P = _corners(C0 + dx * EX + dy * EY, EX, EY, 0.3, 0.5)
    assert rect_iou_in_plane(P, EN, C0, EX, EY, 0.3, 0.5) == pytest.approx(expected, abs=1e-9)


def test_iou_square_rotated_45_in_plane() -> None:
    # The overlap of a square and the same square turned by 45 degrees is a regular octagon:
    # each cut corner is a right triangle with legs s (1 - 1/sqrt2), so
    # inter = s^2 (1 - 2 (1 - 1/sqrt2)^2) and IoU = inter / (2 s^2 - inter).
    s = 0.4
    k = 2 * (1 - 1 / np.sqrt(2)) ** 2
    expected = (1 - k) / (1 + k)
    R = np.array([np.cos(np.pi / 4) * EX + np.sin(np.pi / 4) * EY,
                  -np.sin(np.pi / 4) * EX + np.cos(np.pi / 4) * EY])
    P = _corners(C0, R[0], R[1], s, s)
    assert rect_iou_in_plane(P, EN, C0, EX, EY, s, s) == pytest.approx(expected, abs=1e-9)
    assert expected == pytest.approx(1 / np.sqrt(2), abs=1e-9)  # a neat identity


def test_iou_rectangle_rotated_90_in_plane() -> None:
    # 0.3 x 0.5 turned by 90 degrees about its centre: the overlap is 0.3 x 0.3.
    P = _corners(C0, EY, -EX, 0.3, 0.5)
    expected = 0.09 / (0.15 + 0.15 - 0.09)
    assert rect_iou_in_plane(P, EN, C0, EX, EY, 0.3, 0.5) == pytest.approx(expected, abs=1e-9)


def test_iou_tilted_plane_projects() -> None:
    # The same rectangle tilted by 60 degrees about the width axis projects to half its
    # length, centred: IoU = 0.5.
    y_t = np.cos(np.radians(60)) * EY + np.sin(np.radians(60)) * EN
    n_t = np.cross(EX, y_t)
    P = _corners(C0, EX, y_t, 0.3, 0.5)
    assert rect_iou_in_plane(P, n_t, C0, EX, EY, 0.3, 0.5) == pytest.approx(0.5, abs=1e-9)


def test_iou_ignores_offset_along_normal() -> None:
    P = _corners(C0 + 0.2 * EN, EX, EY, 0.3, 0.5)
    assert rect_iou_in_plane(P, EN, C0, EX, EY, 0.3, 0.5) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize(
    "corners",
    [
        np.full((4, 3), np.nan),
        np.zeros((4, 3)),  # a point
        np.array([[0, 0, 2], [0.1, 0, 2], [0.2, 0, 2], [0.3, 0, 2]], dtype=float),  # a line
        np.zeros((2, 3)),  # too few corners
    ],
)
def test_iou_degenerate_prediction_is_zero(corners: np.ndarray) -> None:
    v = rect_iou_in_plane(corners, EN, C0, EX, EY, 0.3, 0.5)
    assert v == 0.0


def test_iou_degenerate_truth_is_zero() -> None:
    P = _corners(C0, EX, EY, 0.3, 0.5)
    assert rect_iou_in_plane(P, EN, C0, EX, EY, 0.0, 0.5) == 0.0
    assert rect_iou_in_plane(P, EN, C0, EX, EX, 0.3, 0.5) == 0.0  # parallel axes
    assert rect_iou_in_plane(P, EN, C0, EX, EY, np.nan, 0.5) == 0.0


def test_iou_perpendicular_prediction_is_zero() -> None:
    P = _corners(C0, EX, EN, 0.3, 0.5)  # stands on edge in the face's plane
    assert rect_iou_in_plane(P, EY, C0, EX, EY, 0.3, 0.5) == pytest.approx(0.0, abs=1e-9)


# --- match_surfaces ----------------------------------------------------------------------


def test_match_tp_fp_fn_and_not_exposed() -> None:
    truth = _truth([
        ((0.0, 0.0, 2.0), 0.3, 0.4, True),  # 0: found exactly
        ((0.6, 0.0, 2.0), 0.3, 0.4, True),  # 1: missed
        ((0.0, 0.6, 2.3), 0.3, 0.4, False),  # 2: partly covered, yet "found"
    ])
    pred = _preds([
        ((0.0, 0.0, 2.0), 0.3, 0.4),
        ((0.0, 0.6, 2.3), 0.3, 0.4),
        ((-1.5, -1.5, 2.0), 0.3, 0.4),  # nothing there
    ])
    m = match_surfaces(pred, truth)
    assert (m.tp, m.fp, m.fn) == (1, 2, 1)
    assert (m.n_pred, m.n_exposed, m.n_faces) == (3, 2, 3)
    assert m.precision == pytest.approx(1 / 3)
    assert m.recall == pytest.approx(1 / 2)
    assert m.f1 == pytest.approx(2 * (1 / 3) * (1 / 2) / (1 / 3 + 1 / 2))
    # rows are in pick order (highest = smallest z first, up = -z): find them by centre
    by_x = {round(float(c[0]), 3) + 10 * round(float(c[1]), 3): i
            for i, c in enumerate(pred.centers)}
    i_tp, i_cov, i_far = by_x[0.0], by_x[6.0], by_x[-1.5 - 15.0]
    assert m.status[i_tp] == PredStatus.TP
    assert m.status[i_cov] == PredStatus.NOT_EXPOSED
    assert m.status[i_far] == PredStatus.UNMATCHED
    assert m.pred_face[i_tp] == 0 and m.pred_face[i_cov] == 2 and m.pred_face[i_far] == -1
    assert m.tp_pairs.tolist() == [[i_tp, 0]]
    np.testing.assert_allclose(m.grasp_err, [0.0], atol=1e-12)
    np.testing.assert_allclose(m.normal_err_deg, [0.0], atol=1e-6)


def test_match_errors_are_measured() -> None:
    truth = _truth([((0.0, 0.0, 2.0), 0.3, 0.4, True)])
    pred = _preds([((0.003, 0.004, 2.0), 0.302, 0.395)])
    m = match_surfaces(pred, truth)
    assert m.tp == 1
    np.testing.assert_allclose(m.grasp_err, [0.005], atol=1e-12)  # 3-4-5
    np.testing.assert_allclose(m.center_err, [0.005], atol=1e-12)
    np.testing.assert_allclose(m.width_err, [0.002], atol=1e-12)
    np.testing.assert_allclose(m.length_err, [0.005], atol=1e-12)
    np.testing.assert_allclose(np.sort(m.dim_err), [0.002, 0.005], atol=1e-12)
    d = m.to_dict()
    assert d["grasp_err_mm"] == [pytest.approx(5.0)]
    assert d["status"] == ["TP"]


def test_match_grasp_point_differs_from_centre() -> None:
    truth = _truth([((0.0, 0.0, 2.0), 0.3, 0.4, True)])
    base = _preds([((0.0, 0.0, 2.0), 0.3, 0.4)])
    pred = surface_set_from_rects(base.centers, base.normals, base.x_axis, base.width,
                                  base.length, grasp_points=base.centers + [0.0, 0.01, 0.0])
    m = match_surfaces(pred, truth)
    np.testing.assert_allclose(m.grasp_err, [0.01], atol=1e-12)
    np.testing.assert_allclose(m.center_err, [0.0], atol=1e-12)


def test_match_low_iou_and_bad_normal_are_fp() -> None:
    truth = _truth([((0.0, 0.0, 2.0), 0.3, 0.4, True), ((1.0, 0.0, 2.0), 0.3, 0.4, True)])
    tilt = _rot("x", 20.0) @ np.array([0.0, 0.0, -1.0])
    pred = _preds(
        [((0.2, 0.0, 2.0), 0.3, 0.4),  # overlaps 1/3 of face 0 -> IoU 1/5
         ((1.0, 0.0, 2.0), 0.3, 0.4)],  # right place, 20 degrees off
        normals=[np.array([0.0, 0.0, -1.0]), tilt],
    )
    m = match_surfaces(pred, truth)
    assert (m.tp, m.fp, m.fn) == (0, 2, 2)
    st = {round(float(c[0]), 1): PredStatus(int(s)) for c, s in zip(pred.centers, m.status)}
    assert st[0.2] == PredStatus.LOW_IOU
    assert st[1.0] == PredStatus.NORMAL
    assert match_surfaces(pred, truth, max_normal_deg=25.0).tp == 1
    assert match_surfaces(pred, truth, iou_min=0.1, max_normal_deg=25.0).tp == 2


def test_false_surfaces_are_told_apart_by_what_they_would_make_a_robot_do() -> None:
    truth = _truth([
        ((0.0, 0.0, 2.0), 0.3, 0.4, True),  # 0: found
        ((1.0, 0.0, 2.0), 0.3, 0.4, True),  # 1: a sliver of it reported
        ((0.0, 1.0, 2.0), 0.3, 0.4, False),  # 2: a box rests on it
        ((1.0, 1.0, 2.0), 0.3, 0.4, False),  # 3: free, seen in part, reported whole
        ((2.0, 1.0, 2.0), 0.3, 0.4, False),  # 4: free, seen in part, a sliver reported
        ((2.0, 0.0, 2.0), 0.3, 0.4, True),  # 5: the right rectangle, tilted 20 degrees
    ])
    tilt = _rot("x", 20.0) @ np.array([0.0, 0.0, -1.0])
    up = np.array([0.0, 0.0, -1.0])
    rects = [((0.0, 0.0, 2.0), 0.3, 0.4), ((1.1, 0.0, 2.0), 0.1, 0.4),
             ((0.0, 1.0, 2.0), 0.3, 0.4), ((1.0, 1.0, 2.0), 0.3, 0.4),
             ((2.1, 1.0, 2.0), 0.1, 0.4), ((2.0, 0.0, 2.0), 0.3, 0.4),
             ((-3.0, -3.0, 2.0), 0.3, 0.4)]  # 6: nothing there
    pred = _preds(rects, normals=[up, up, up, up, up, tilt, up])
    m = match_surfaces(pred, truth)
    covered = np.array([False, False, True, False, False, False])
    kinds = false_kinds(m, covered)
    by_x = {(round(float(c[0]), 1), round(float(c[1]), 1)): FalseKind(int(k))
            for c, k in zip(pred.centers, kinds)}
    assert by_x == {(0.0, 0.0): FalseKind.NONE, (1.1, 0.0): FalseKind.WRONG_RECTANGLE,
                    (0.0, 1.0): FalseKind.COVERED, (1.0, 1.0): FalseKind.SEEN_IN_PART,
                    (2.1, 1.0): FalseKind.WRONG_RECTANGLE, (2.0, 0.0): FalseKind.NORMAL,
                    (-3.0, -3.0): FalseKind.NO_TOP}
    counts = false_kind_counts([kinds, kinds[:1]])
    assert counts == {"no_top": 1, "covered": 1, "seen_in_part": 1, "wrong_rectangle": 2,
                      "normal": 1}
    assert sum(counts.values()) == m.fp
    assert false_kind_counts([]) == dict.fromkeys(counts, 0)


def test_match_is_one_to_one() -> None:
    truth = _truth([((0.0, 0.0, 2.0), 0.3, 0.4, True)])
    pred = _preds([((0.0, 0.0, 2.0), 0.3, 0.4), ((0.01, 0.0, 2.0), 0.3, 0.4)])
    m = match_surfaces(pred, truth)
    assert (m.tp, m.fp, m.fn) == (1, 1, 0)
    # the better of the two (exact) is the TP
    i_tp = int(m.tp_pairs[0, 0])
    np.testing.assert_allclose(pred.centers[i_tp], [0.0, 0.0, 2.0])


def test_match_covered_face_takes_its_own_prediction() -> None:
    # A prediction that sits mostly on a covered face, a little on an exposed neighbour,
    # is paired with the covered face (max IoU), not credited to the neighbour.
    truth = _truth([((0.0, 0.0, 2.0), 0.3, 0.4, True), ((0.3, 0.0, 2.0), 0.3, 0.4, False)])
    pred = _preds([((0.25, 0.0, 2.0), 0.3, 0.4)])
    m = match_surfaces(pred, truth)
    assert m.pred_face.tolist() == [1]
    assert m.status.tolist() == [PredStatus.NOT_EXPOSED]
    assert (m.tp, m.fp, m.fn) == (0, 1, 1)


def test_match_plane_offset_gate() -> None:
    truth = _truth([((0.0, 0.0, 2.0), 0.3, 0.4, True)])
    pred = _preds([((0.0, 0.0, 1.9), 0.3, 0.4)])  # a phantom 10 cm above
    assert match_surfaces(pred, truth).tp == 0
    assert match_surfaces(pred, truth).status.tolist() == [PredStatus.UNMATCHED]
    assert match_surfaces(pred, truth, max_plane_offset=None).tp == 1
    assert match_surfaces(pred, truth, max_plane_offset=0.2).tp == 1


def test_match_empty_conventions() -> None:
    truth = _truth([((0.0, 0.0, 2.0), 0.3, 0.4, True)])
    m = match_surfaces(empty_surface_set(), truth)
    assert (m.tp, m.fp, m.fn, m.precision, m.recall, m.f1) == (0, 0, 1, 1.0, 0.0, 0.0)
    none = _truth([])
    m = match_surfaces(empty_surface_set(), none)
    assert (m.precision, m.recall, m.f1) == (1.0, 1.0, 1.0)
    m = match_surfaces(_preds([((0.0, 0.0, 2.0), 0.3, 0.4)]), none)
    assert (m.tp, m.fp, m.fn, m.precision, m.recall) == (0, 1, 0, 0.0, 1.0)
    covered = _truth([((0.0, 0.0, 2.0), 0.3, 0.4, False)])
    m = match_surfaces(empty_surface_set(), covered)
    assert (m.n_exposed, m.recall, m.precision) == (0, 1.0, 1.0)


def test_prf() -> None:
    assert prf(0, 0, 0) == (1.0, 1.0, 1.0)
    assert prf(0, 3, 0) == (0.0, 1.0, 0.0)
    assert prf(2, 4, 2) == pytest.approx((0.5, 1.0, 2 / 3))


def test_aggregate_matches_pools_counts_and_errors() -> None:
    truth = _truth([((0.0, 0.0, 2.0), 0.3, 0.4, True), ((0.6, 0.0, 2.0), 0.3, 0.4, True)])
    m1 = match_surfaces(_preds([((0.001, 0.0, 2.0), 0.3, 0.4),
                                ((0.603, 0.0, 2.0), 0.3, 0.4)]), truth)
    m2 = match_surfaces(_preds([((0.0, 0.005, 2.0), 0.3, 0.4),
                                ((3.0, 0.0, 2.0), 0.3, 0.4)]), truth)
    agg = aggregate_matches([m1, m2])
    assert (agg["tp"], agg["fp"], agg["fn"], agg["n_scans"]) == (3, 1, 1, 2)
    assert agg["precision"] == pytest.approx(0.75)
    assert agg["recall"] == pytest.approx(0.75)
    assert agg["grasp_err_median_mm"] == pytest.approx(3.0)  # of 1, 3, 5 mm
    assert agg["dim_err_median_mm"] == pytest.approx(0.0, abs=1e-9)
    empty = aggregate_matches([])
    assert empty["grasp_err_median_mm"] is None and empty["precision"] == 1.0


# --- edges -------------------------------------------------------------------------------


def _line(col: int, value: int, shape: tuple[int, int] = (7, 9)) -> np.ndarray:
    a = np.zeros(shape, np.uint8)
    a[:, col] = value
    return a


def test_edge_scores_tolerance() -> None:
    gt = _line(3, 1)
    pred = _line(4, EdgeKind.JUMP)  # one pixel off
    assert edge_scores(pred, gt, tol_px=1) == (1.0, 1.0)
    assert edge_scores(pred, gt, tol_px=0) == (0.0, 0.0)
    assert edge_scores(_line(5, EdgeKind.JUMP), gt, tol_px=1) == (0.0, 0.0)
    assert edge_scores(_line(5, EdgeKind.JUMP), gt, tol_px=2) == (1.0, 1.0)


def test_edge_scores_counts() -> None:
    gt = _line(3, 1)
    pred = gt.copy()
    pred[0, 8] = EdgeKind.JUMP  # a stray pixel
    pred[6, 3] = 0  # one true pixel missed, but its neighbour is within 1 px
    p, r = edge_scores(pred, gt)
    assert p == pytest.approx(6 / 7)
    assert r == pytest.approx(1.0)
    pred[4:, 3] = 0  # rows 4..6 missed: row 4 is next to row 3, rows 5, 6 are not
    p, r = edge_scores(pred, gt)
    assert p == pytest.approx(4 / 5)
    assert r == pytest.approx(5 / 7)


def test_edge_scores_kinds() -> None:
    gt = _line(2, 1) | _line(6, 2)  # a jump at column 2, a crease at column 6
    pred = np.zeros_like(gt)
    pred[:, 2] = EdgeKind.CREASE_CONVEX  # right place, wrong kind
    pred[:4, 6] = EdgeKind.CREASE_CONVEX
    pred[4:, 6] = EdgeKind.CREASE_CONCAVE  # both crease kinds count as crease
    assert edge_scores(pred, gt, kind="any") == (1.0, 1.0)
    assert edge_scores(pred, gt, kind="jump") == (1.0, 0.0)  # no predicted jump: p = 1
    assert edge_scores(pred, gt, kind="crease") == (0.5, 1.0)
    rep = edge_report(pred, gt)
    assert rep["crease"]["n_pred"] == 14 and rep["crease"]["n_gt"] == 7
    assert rep["jump"]["recall"] == 0.0


def test_edge_scores_empty_and_errors() -> None:
    z = np.zeros((5, 5), np.uint8)
    assert edge_scores(z, z) == (1.0, 1.0)
    assert edge_scores(z, _line(2, 1, (5, 5))) == (1.0, 0.0)
    with pytest.raises(ValueError, match="equal shape"):
        edge_scores(z, np.zeros((5, 6), np.uint8))
    with pytest.raises(ValueError, match="edge kind"):
        edge_scores(z, z, kind="groove")


def test_aggregate_edges_pools_pixels() -> None:
    gt = _line(3, 1)
    r1 = edge_report(gt, gt)
    r2 = edge_report(np.zeros_like(gt), gt)
    agg = aggregate_edges([r1, r2])
    assert agg["any"]["precision"] == pytest.approx(1.0)
    assert agg["any"]["recall"] == pytest.approx(0.5)
    assert agg["n_scans"] == 2


def test_edge_scores_groove_counts_as_any_edge_only() -> None:
    groove = int(getattr(EdgeKind, "GROOVE", 4))
    gt = _line(3, 1)
    pred = _line(3, groove)
    assert edge_scores(pred, gt, kind="any") == (1.0, 1.0)
    assert edge_scores(pred, gt, kind="jump") == (1.0, 0.0)
    assert edge_scores(pred, gt, kind="crease") == (1.0, 1.0)  # neither side has a crease


# --- packed layers: wrong rectangles, ambiguous regions, heights --------------------------

#: Four touching 0.3 x 0.4 m tops in a 2 x 2 block at 2 m (a packed layer, no gaps).
BLOCK = [((-0.15, -0.2, 2.0), 0.3, 0.4, True), ((0.15, -0.2, 2.0), 0.3, 0.4, True),
         ((-0.15, 0.2, 2.0), 0.3, 0.4, True), ((0.15, 0.2, 2.0), 0.3, 0.4, True)]


def test_overlap_areas() -> None:
    P = _corners(C0, EX, EY, 0.3, 0.5)
    inter, a_pred, a_gt = rect_overlap_in_plane(P, C0 + 0.1 * EX, EX, EY, 0.3, 0.5)
    assert (inter, a_pred, a_gt) == pytest.approx((0.2 * 0.5, 0.15, 0.15), abs=1e-12)
    assert rect_overlap_in_plane(P[:2], C0, EX, EY, 0.3, 0.5) == (0.0, 0.0, 0.0)


def test_wrong_rectangles_on_a_packed_block() -> None:
    truth = _truth(BLOCK)
    pred = _preds([
        ((-0.15, -0.2, 2.0), 0.3, 0.4),   # right: exactly top 0
        ((0.15, -0.2, 2.0), 0.3, 0.3),    # 3/4 of top 1: IoU 0.75, a match
        ((-0.06, 0.2, 2.0), 0.48, 0.4),   # top 2 and 60 % of top 3: IoU 0.625, spans
        ((0.0, 0.0, 2.0), 0.6, 0.8),      # the whole block: IoU 0.25 with each
        ((0.075, -0.2, 2.0), 0.15, 0.1),  # a sliver across the seam of 0 and 1
        ((3.0, 3.0, 2.0), 0.3, 0.4),      # off every top: the pallet, say
        ((-0.15, -0.2, 2.2), 0.3, 0.4),   # 20 cm below top 0: the plane gate keeps it off
    ])
    w = wrong_rectangles(pred, truth)
    by_c = {tuple(np.round(c, 3)): i for i, c in enumerate(pred.centers)}

    def of(c: tuple[float, float, float]) -> int:
        return int(w.reason[by_c[tuple(np.round(c, 3))]])

    assert of((-0.15, -0.2, 2.0)) == WrongReason.RIGHT
    assert of((0.15, -0.2, 2.0)) == WrongReason.RIGHT
    assert of((-0.06, 0.2, 2.0)) == WrongReason.SPANS
    assert of((0.0, 0.0, 2.0)) == WrongReason.NO_MATCH
    assert of((0.075, -0.2, 2.0)) == WrongReason.NO_MATCH
    assert of((3.0, 3.0, 2.0)) == WrongReason.OFF_TOP
    assert of((-0.15, -0.2, 2.2)) == WrongReason.OFF_TOP
    i_whole = by_c[(0.0, 0.0, 2.0)]
    assert w.max_iou[i_whole] == pytest.approx(0.25, abs=1e-9)
    assert w.n_covered[i_whole] == 4
    assert w.max_iou[by_c[(-0.06, 0.2, 2.0)]] == pytest.approx(0.625, abs=1e-9)
    # two equal tops as one: IoU exactly 0.5 with each, called wrong either way
    two = wrong_rectangles(_preds([((0.0, 0.2, 2.0), 0.6, 0.4)]), truth)
    assert two.n_wrong == 1 and two.n_covered[0] == 2
    assert w.best_face[by_c[(3.0, 3.0, 2.0)]] == -1
    assert (w.n_pred, w.n_wrong) == (7, 3)
    assert w.rate == pytest.approx(3 / 7)
    d = w.to_dict()
    assert (d["spans"], d["no_match"], d["off_top"], d["right"]) == (1, 2, 2, 2)
    # every surface is judged alone: a duplicate of a top is a right rectangle here
    dup = wrong_rectangles(_preds([BLOCK[0][0:3], BLOCK[0][0:3]]), truth)
    assert dup.n_wrong == 0 and dup.rate == 0.0
    assert wrong_rectangles(empty_surface_set(), truth).rate == 0.0
    with pytest.raises(ValueError, match="span_cover"):
        wrong_rectangles(pred, truth, span_cover=0.0)


def test_region_cover_of_an_ambiguous_outline() -> None:
    truth = _truth(BLOCK + [((1.0, 0.0, 2.0), 0.3, 0.4, True)])
    X, Y = np.array([1.0, 0.0, 0.0]), np.array([0.0, -1.0, 0.0])
    # the left half of the block (tops 0 and 2), and a quarter of the far top
    regions = np.stack([_corners(np.array([-0.15, 0.0, 2.0]), X, Y, 0.3, 0.8),
                        _corners(np.array([0.925, -0.1, 2.0]), X, Y, 0.15, 0.2)])
    cov = region_cover(regions, truth)
    assert cov.shape == (2, 5)
    np.testing.assert_allclose(cov[0], [1.0, 0.0, 1.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(cov[1], [0.0, 0.0, 0.0, 0.0, 0.25], atol=1e-9)
    assert region_cover(np.zeros((0, 4, 3)), truth).shape == (0, 5)


def test_height_errors_of_true_positives_with_a_measured_height() -> None:
    truth = _truth(BLOCK[:3])
    truth_h = SimpleNamespace(centers=truth.centers, box_index=np.array([2, 0, 1]),
                              boxes=np.array([[0, 0, 0, 0.3, 0.4, 0.25, 0],
                                              [0, 0, 0, 0.3, 0.4, 0.30, 0],
                                              [0, 0, 0, 0.3, 0.4, 0.20, 0]]))
    th = true_box_heights(truth_h)
    np.testing.assert_allclose(th, [0.20, 0.25, 0.30])
    assert np.isnan(true_box_heights(SimpleNamespace(centers=np.zeros((2, 3))))).all()
    pred = _preds([BLOCK[0][0:3], BLOCK[1][0:3], BLOCK[2][0:3],
                   ((3.0, 3.0, 2.0), 0.3, 0.4)])
    m = match_surfaces(pred, truth)
    face_of = {int(p): int(f) for p, f in m.tp_pairs}
    # surface -> height and source: side (1), step (2), sku (3); the false one has a side
    est = {0: (0.205, 1), 1: (0.24, 2), 2: (0.30, 3)}
    h, src = np.full(4, np.nan), np.zeros(4, np.int8)
    for p, f in face_of.items():
        h[p], src[p] = est[f]
    fp = next(i for i in range(4) if i not in face_of)
    h[fp], src[fp] = 0.5, 1
    e = height_errors(h, src, m, th, sigma=np.full(4, 0.002))
    assert len(e) == 2  # the sku height and the false surface are not scored
    got = {int(f): float(err) for f, err in zip(e.face, e.error)}
    assert got == pytest.approx({0: 0.005, 1: 0.01}, abs=1e-12)
    assert set(e.source.tolist()) == {1, 2} and np.all(e.sigma == 0.002)
    assert len(height_errors(h, src, m, th, sources=(3,))) == 1
    with pytest.raises(ValueError, match="shape"):
        height_errors(h[:3], src, m, th)

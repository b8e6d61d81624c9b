"""Scoring: match found surfaces to ground-truth faces, score edge maps, pool many scans.

A predicted surface is a *true positive* when the optimal one-to-one assignment (Hungarian,
on rectangle IoU) pairs it with a **fully exposed** ground-truth face, the IoU of the two
rectangles in the face's plane is at least ``iou_min`` (0.5) and the normals agree within
``max_normal_deg`` (15 degrees). Everything else predicted is a false positive, every fully
exposed face left without a true positive is a false negative. Partly covered faces are
never graspable, so a surface put on one is a false positive, not a "don't care".

Frames and units: the sensor frame, metres, as everywhere in boxloc. The pooled figures of
:func:`aggregate_matches` are reported in millimetres and degrees (their names say so).

The ground truth is duck-typed: anything with the :class:`boxloc.simulate.GroundTruth` face
arrays (``centers``, ``normals``, ``x_axis``, ``y_axis``, ``width``, ``length``,
``fully_exposed``) works, so this module does not import the simulator.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, Protocol

import cv2
import numpy as np
import numpy.typing as npt
from scipy.optimize import linear_sum_assignment

from boxloc.products import EdgeKind, HeightSource, SurfaceSet


class FaceTruth(Protocol):
    """The face arrays of a ground truth (see ``boxloc.simulate.GroundTruth``), read-only."""

    @property
    def centers(self) -> np.ndarray: ...
    @property
    def normals(self) -> np.ndarray: ...
    @property
    def x_axis(self) -> np.ndarray: ...
    @property
    def y_axis(self) -> np.ndarray: ...
    @property
    def width(self) -> np.ndarray: ...
    @property
    def length(self) -> np.ndarray: ...
    @property
    def fully_exposed(self) -> np.ndarray: ...


class PredStatus(IntEnum):
    """Why a predicted surface was or was not a true positive (first failing reason)."""

    TP = 0
    #: not paired with any face (no overlap with any face in its plane)
    UNMATCHED = 1
    #: paired with a face that is partly covered (not graspable)
    NOT_EXPOSED = 2
    #: paired with an exposed face, but IoU < iou_min
    LOW_IOU = 3
    #: paired with an exposed face with IoU >= iou_min, but the normal is off
    NORMAL = 4


# --- rectangle IoU in a plane ------------------------------------------------------------


def _clip_halfplane(poly: np.ndarray, axis: int, bound: float, keep_below: bool) -> np.ndarray:
    """One Sutherland-Hodgman step: keep the part of ``poly`` (k, 2) with x[axis] <= bound
    (or >= bound)."""
    if poly.shape[0] == 0:
        return poly
    sign = 1.0 if keep_below else -1.0
    d = sign * (poly[:, axis] - bound)  # <= 0 inside
    out: list[np.ndarray] = []
    k = poly.shape[0]
    for i in range(k):
        p, q = poly[i], poly[(i + 1) % k]
        dp, dq = d[i], d[(i + 1) % k]
        if dp <= 0:
            out.append(p)
        if (dp < 0 < dq) or (dq < 0 < dp):
            t = dp / (dp - dq)
            out.append(p + t * (q - p))
    return np.array(out, dtype=np.float64).reshape(-1, 2)


def _area(poly: np.ndarray) -> float:
    """Shoelace area of a simple polygon (k, 2), >= 0."""
    if poly.shape[0] < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def _convex_hull(pts: np.ndarray) -> np.ndarray:
    """Convex hull (k, 2) of 2-D points, counter-clockwise (Andrew's monotone chain)."""
    pts = np.unique(pts, axis=0)
    if pts.shape[0] < 3:
        return pts
    order = np.lexsort((pts[:, 1], pts[:, 0]))
    pts = pts[order]

    def half(seq: np.ndarray) -> list[np.ndarray]:
        h: list[np.ndarray] = []
        for p in seq:
            while len(h) >= 2:
                a, b = h[-2], h[-1]
                if (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]) > 0:
                    break
                h.pop()
            h.append(p)
        return h

    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1], dtype=np.float64).reshape(-1, 2)


def rect_overlap_in_plane(
    pred_corners: npt.ArrayLike,
    gt_center: npt.ArrayLike,
    gt_x: npt.ArrayLike,
    gt_y: npt.ArrayLike,
    gt_w: float,
    gt_l: float,
) -> tuple[float, float, float]:
    """Areas of a predicted polygon and a ground-truth face, and of their overlap, in the
    face's plane.

    Parameters
    ----------
    pred_corners : array_like, shape (k, 3), metres, sensor frame
        Predicted polygon corners (a rectangle: k = 4), in order around it.
    gt_center : array_like, shape (3,), metres
    gt_x, gt_y : array_like, shape (3,)
        Unit axes of the face: ``gt_x`` along its width, ``gt_y`` along its length.
    gt_w, gt_l : float
        Face width and length, metres.

    Returns
    -------
    (intersection, pred_area, face_area) : tuple of float, m^2
        All 0.0 for degenerate or non-finite input (never NaN); ``pred_area`` is the area of
        the prediction's projection into the face plane.

    Notes
    -----
    The predicted corners are projected orthogonally into the face plane and expressed in
    the face's 2-D frame, where the face is the axis-aligned box ``[-w/2, w/2] x [-l/2, l/2]``.
    The convex hull of the projected corners (a parallelogram for a planar rectangle) is
    clipped against that box (Sutherland-Hodgman), so the result is exact for convex input.
    """
    try:
        P = np.asarray(pred_corners, dtype=np.float64).reshape(-1, 3)
        c = np.asarray(gt_center, dtype=np.float64).reshape(3)
        ex = np.asarray(gt_x, dtype=np.float64).reshape(3)
        ey = np.asarray(gt_y, dtype=np.float64).reshape(3)
        w, length = float(gt_w), float(gt_l)
    except (ValueError, TypeError):
        return 0.0, 0.0, 0.0
    vals = (P, c, ex, ey, np.array([w, length]))
    if P.shape[0] < 3 or not all(np.isfinite(v).all() for v in vals):
        return 0.0, 0.0, 0.0
    if w <= 0 or length <= 0:
        return 0.0, 0.0, 0.0
    # Re-orthonormalize the face axes so slightly sloppy truth does not bias the areas.
    ex = ex / max(float(np.linalg.norm(ex)), 1e-300)
    ey = ey - ex * float(ey @ ex)
    ny = np.linalg.norm(ey)
    if ny < 1e-9:
        return 0.0, 0.0, 0.0
    ey = ey / ny
    q = np.stack([(P - c) @ ex, (P - c) @ ey], axis=1)
    hull = _convex_hull(q)
    a_pred = _area(hull)
    a_gt = w * length
    if a_pred <= 1e-9 * a_gt:  # collinear or coincident corners (up to rounding)
        return 0.0, 0.0, a_gt
    clip = hull
    clip = _clip_halfplane(clip, 0, 0.5 * w, keep_below=True)
    clip = _clip_halfplane(clip, 0, -0.5 * w, keep_below=False)
    clip = _clip_halfplane(clip, 1, 0.5 * length, keep_below=True)
    clip = _clip_halfplane(clip, 1, -0.5 * length, keep_below=False)
    return min(_area(clip), a_pred, a_gt), a_pred, a_gt


def rect_iou_in_plane(
    pred_corners: npt.ArrayLike,
    pred_normal: npt.ArrayLike,
    gt_center: npt.ArrayLike,
    gt_x: npt.ArrayLike,
    gt_y: npt.ArrayLike,
    gt_w: float,
    gt_l: float,
) -> float:
    """IoU of a predicted rectangle and a ground-truth face, measured in the face's plane.

    Parameters
    ----------
    pred_corners : array_like, shape (4, 3), metres, sensor frame
        Predicted rectangle corners, in order around the rectangle.
    pred_normal : array_like, shape (3,)
        Predicted unit normal. A prediction seen edge-on from the face (normals at
        90 degrees) projects to a sliver and scores ~0.
    gt_center : array_like, shape (3,), metres
    gt_x, gt_y : array_like, shape (3,)
        Unit axes of the face: ``gt_x`` along its width, ``gt_y`` along its length.
    gt_w, gt_l : float
        Face width and length, metres.

    Returns
    -------
    float
        Area of intersection over area of union, in [0, 1]. 0.0 for degenerate or
        non-finite input (never NaN).

    Notes
    -----
    The areas are those of :func:`rect_overlap_in_plane` (the prediction projected into
    the face plane, clipped against the face). How far the prediction lies off the plane is
    not part of the IoU; see :func:`match_surfaces` (``max_plane_offset``).
    """
    try:
        n = np.asarray(pred_normal, dtype=np.float64).reshape(3)
    except (ValueError, TypeError):
        return 0.0
    if not np.isfinite(n).all():
        return 0.0
    inter, a_pred, a_gt = rect_overlap_in_plane(pred_corners, gt_center, gt_x, gt_y, gt_w,
                                                gt_l)
    if a_pred <= 0.0:
        return 0.0
    union = a_pred + a_gt - inter
    if union <= 0.0:
        return 0.0
    return float(np.clip(inter / union, 0.0, 1.0))


# --- matching ----------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Match:
    """Result of :func:`match_surfaces` for one scan.

    Attributes
    ----------
    tp, fp, fn : int
        True positives, false positives, false negatives (fully exposed faces missed).
    n_pred, n_exposed, n_faces : int
        Predictions, fully exposed faces, all faces.
    precision, recall, f1 : float
        ``precision = 1`` when there are no predictions, ``recall = 1`` when there is no
        exposed face; ``f1`` is their harmonic mean (0 if both are 0).
    pairs : (K, 2) int64
        (prediction index, face index) of every assigned pair, TP or not.
    pair_iou : (K,) float64
    status : (n_pred,) uint8
        :class:`PredStatus` of each prediction.
    pred_face : (n_pred,) int64
        The face each prediction was assigned to, -1 if none.
    tp_pairs : (tp, 2) int64
        (prediction index, face index) of the true positives.
    tp_iou : (tp,) float64
    grasp_err : (tp,) float64, metres
        ``|pred.grasp_point - gt.center|``.
    center_err : (tp,) float64, metres
        ``|pred.center - gt.center|``.
    width_err, length_err : (tp,) float64, metres
        ``|w - w_gt|``, ``|l - l_gt|`` (both sides sorted, width <= length).
    normal_err_deg : (tp,) float64, degrees
        Angle between the predicted and the true normal (signed: a flipped normal is 180).
    """

    tp: int
    fp: int
    fn: int
    n_pred: int
    n_exposed: int
    n_faces: int
    precision: float
    recall: float
    f1: float
    pairs: np.ndarray
    pair_iou: np.ndarray
    status: np.ndarray
    pred_face: np.ndarray
    tp_pairs: np.ndarray
    tp_iou: np.ndarray
    grasp_err: np.ndarray
    center_err: np.ndarray
    width_err: np.ndarray
    length_err: np.ndarray
    normal_err_deg: np.ndarray

    @property
    def dim_err(self) -> np.ndarray:
        """Width and length errors pooled, (2 * tp,), metres."""
        return np.concatenate([self.width_err, self.length_err])

    def to_dict(self, *, digits: int = 4) -> dict[str, Any]:
        """JSON-ready summary: counts, scores, and per-TP errors in mm / degrees."""

        def mm(a: np.ndarray) -> list[float]:
            return [round(float(v) * 1e3, digits) for v in a]

        return {
            "tp": self.tp, "fp": self.fp, "fn": self.fn,
            "n_pred": self.n_pred, "n_exposed": self.n_exposed, "n_faces": self.n_faces,
            "precision": round(self.precision, 6), "recall": round(self.recall, 6),
            "f1": round(self.f1, 6),
            "status": [PredStatus(int(s)).name for s in self.status],
            "pred_face": [int(v) for v in self.pred_face],
            "tp_iou": [round(float(v), 6) for v in self.tp_iou],
            "grasp_err_mm": mm(self.grasp_err),
            "center_err_mm": mm(self.center_err),
            "width_err_mm": mm(self.width_err),
            "length_err_mm": mm(self.length_err),
            "normal_err_deg": [round(float(v), digits) for v in self.normal_err_deg],
        }


class FalseKind(IntEnum):
    """What a false positive of :func:`match_surfaces` would make a robot do
    (:func:`false_kinds`): the precision counts them alike, a post-mortem does not."""

    #: a true positive
    NONE = 0
    #: paired with no top: the floor, a pallet's plane, a phantom
    NO_TOP = 1
    #: paired with a top something rests on: gripping it disturbs the box above
    COVERED = 2
    #: paired, at IoU >= ``iou_min``, with a top nothing rests on that the scan saw less of
    #: than a graspable face needs (``visible_fraction`` < 0.9): the right box, which the
    #: benchmark does not count as graspable (its normal is not checked)
    SEEN_IN_PART = 3
    #: paired with a top at IoU < ``iou_min``: a sliver of it or a rectangle over several
    WRONG_RECTANGLE = 4
    #: the right rectangle on a graspable top, its normal off by more than the match's bound
    NORMAL = 5


def false_kinds(match: Match, covered: npt.ArrayLike, *, iou_min: float = 0.5) -> np.ndarray:
    """The :class:`FalseKind` of each prediction of a match.

    Parameters
    ----------
    match : Match
        :func:`match_surfaces`' result, with the same ``iou_min``.
    covered : (F,) bool
        The faces something rests on (:func:`boxloc.simulate.truth.resting_on`).
    iou_min : float
        The match's smallest IoU of a true positive.

    Returns
    -------
    (n_pred,) int8
        :class:`FalseKind` values; ``NONE`` for the true positives.
    """
    covered = np.asarray(covered, dtype=bool)
    iou = np.zeros(len(match.status))
    if len(match.pairs):
        iou[match.pairs[:, 0]] = match.pair_iou
    out = np.full(len(match.status), FalseKind.NO_TOP, dtype=np.int8)
    for i, (st, f) in enumerate(zip(match.status, match.pred_face)):
        if st == PredStatus.TP:
            out[i] = FalseKind.NONE
        elif st == PredStatus.LOW_IOU:
            out[i] = FalseKind.WRONG_RECTANGLE
        elif st == PredStatus.NORMAL:
            out[i] = FalseKind.NORMAL
        elif st == PredStatus.NOT_EXPOSED:
            out[i] = (FalseKind.COVERED if covered[f] else FalseKind.SEEN_IN_PART
                      if iou[i] >= iou_min else FalseKind.WRONG_RECTANGLE)
    return out


def false_kind_counts(kinds: Iterable[np.ndarray]) -> dict[str, int]:
    """The predictions of many scans counted by :class:`FalseKind` name (``NONE`` left out):
    lower-case names, every kind present, 0 where none."""
    ks = [np.asarray(k, dtype=np.int64) for k in kinds]
    flat = np.concatenate(ks) if ks else np.zeros(0, np.int64)
    counts = np.bincount(flat, minlength=len(FalseKind))
    return {k.name.lower(): int(counts[k]) for k in FalseKind if k != FalseKind.NONE}


def prf(tp: int, n_pred: int, n_true: int) -> tuple[float, float, float]:
    """Precision, recall, F1 with the conventions of :class:`Match` for empty denominators."""
    precision = tp / n_pred if n_pred > 0 else 1.0
    recall = tp / n_true if n_true > 0 else 1.0
    s = precision + recall
    f1 = 2.0 * precision * recall / s if s > 0 else 0.0
    return float(precision), float(recall), float(f1)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between rows of unit-ish vectors a and b, degrees (NaN-safe: NaN -> 180)."""
    na = np.linalg.norm(a, axis=-1)
    nb = np.linalg.norm(b, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.einsum("...k,...k->...", a, b) / (na * nb)
    cos = np.where(np.isfinite(cos), cos, -1.0)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def iou_matrix(
    pred: SurfaceSet, truth: FaceTruth, *, max_plane_offset: float | None = None
) -> np.ndarray:
    """IoU of every prediction with every face, shape (n_pred, n_faces).

    With ``max_plane_offset`` (metres), a pair whose predicted centre lies farther than that
    from the face's plane scores 0: a rectangle floating above a box is not that box's top.
    """
    return rect_iou_matrix(pred.centers, pred.corners, pred.normals, truth,
                           max_plane_offset=max_plane_offset)


def rect_iou_matrix(
    centers: npt.ArrayLike, corners: npt.ArrayLike, normals: npt.ArrayLike, truth: FaceTruth,
    *, max_plane_offset: float | None = None
) -> np.ndarray:
    """:func:`iou_matrix` of rectangles given as arrays: centres (P, 3), corners (P, 4, 3)
    and normals (P, 3), metres, sensor frame (a rectangle with a NaN corner scores 0)."""
    corners = np.asarray(corners, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    P, F = corners.shape[0], int(np.asarray(truth.centers).shape[0])
    M = np.zeros((P, F), dtype=np.float64)
    gc = np.asarray(truth.centers, dtype=np.float64).reshape(F, 3)
    gn = np.asarray(truth.normals, dtype=np.float64).reshape(F, 3)
    gx = np.asarray(truth.x_axis, dtype=np.float64).reshape(F, 3)
    gy = np.asarray(truth.y_axis, dtype=np.float64).reshape(F, 3)
    gw = np.asarray(truth.width, dtype=np.float64).reshape(F)
    gl = np.asarray(truth.length, dtype=np.float64).reshape(F)
    if P == 0 or F == 0:
        return M
    pc = np.asarray(centers, dtype=np.float64).reshape(P, 3)
    # A cheap bounding-sphere test avoids clipping pairs that cannot overlap.
    corners = corners.reshape(P, -1, 3)
    pr = np.max(np.linalg.norm(corners - pc[:, None, :], axis=2), axis=1)  # NaN -> never near
    gr = 0.5 * np.hypot(gw, gl)
    dist = np.linalg.norm(pc[:, None, :] - gc[None, :, :], axis=-1)
    near = dist <= (pr[:, None] + gr[None, :]) * 1.001
    if max_plane_offset is not None:
        off = np.abs(np.einsum("pfk,fk->pf", pc[:, None, :] - gc[None, :, :], gn))
        near &= off <= max_plane_offset
    for i, j in zip(*np.nonzero(near)):
        M[i, j] = rect_iou_in_plane(corners[i], normals[i], gc[j], gx[j], gy[j], gw[j], gl[j])
    return M


def match_surfaces(
    pred: SurfaceSet,
    truth: FaceTruth,
    *,
    iou_min: float = 0.5,
    max_normal_deg: float = 15.0,
    max_plane_offset: float | None = 0.03,
    iou: npt.ArrayLike | None = None,
) -> Match:
    """Match predicted surfaces one-to-one to ground-truth faces and score them.

    Parameters
    ----------
    pred : SurfaceSet
        Predicted surfaces (any order).
    truth : GroundTruth-like
        Faces in the sensor frame: ``centers (F, 3)``, ``normals (F, 3)``, ``x_axis``,
        ``y_axis (F, 3)``, ``width``, ``length (F,)`` metres, ``fully_exposed (F,)`` bool.
    iou_min : float
        Smallest in-plane IoU of a true positive.
    max_normal_deg : float
        Largest angle between predicted and true normal of a true positive, degrees.
    max_plane_offset : float or None
        A prediction whose centre lies farther than this from a face's plane (metres) cannot
        be paired with that face; None disables the gate. 3 cm is ~5 sigma of range noise at
        3 m and far below any box height, so it only removes phantom planes.
    iou : array_like, shape (n_pred, n_faces), optional
        A precomputed IoU matrix to use instead of :func:`iou_matrix` (e.g. the image IoU
        of :func:`boxloc.evaluate.real.real_iou_matrix`); ``max_plane_offset`` is then not applied.

    Returns
    -------
    Match

    Notes
    -----
    The assignment maximizes the summed IoU over all faces, exposed or not
    (``scipy.optimize.linear_sum_assignment``), so a prediction on a covered face is
    paired with that face and counted as a false positive instead of being credited to an
    overlapping exposed neighbour. Pairs with zero IoU are not pairs.
    """
    P = len(pred)
    F = int(np.asarray(truth.centers).shape[0])
    exposed = np.asarray(truth.fully_exposed, dtype=bool).reshape(F)
    n_exposed = int(exposed.sum())
    if iou is None:
        M = iou_matrix(pred, truth, max_plane_offset=max_plane_offset)
    else:
        M = np.asarray(iou, dtype=np.float64)
        if M.shape != (P, F):
            raise ValueError(f"iou must have shape ({P}, {F}), got {M.shape}")
    pred_face = np.full(P, -1, dtype=np.int64)
    status = np.full(P, PredStatus.UNMATCHED, dtype=np.uint8)
    pairs = np.zeros((0, 2), dtype=np.int64)
    pair_iou = np.zeros(0)
    if P and F:
        rows, cols = linear_sum_assignment(M, maximize=True)
        keep = M[rows, cols] > 0.0
        rows, cols = rows[keep], cols[keep]
        pairs = np.stack([rows, cols], axis=1).astype(np.int64)
        pair_iou = M[rows, cols]
        pred_face[rows] = cols
        gn = np.asarray(truth.normals, dtype=np.float64).reshape(F, 3)
        ang = _angle_deg(np.asarray(pred.normals, dtype=np.float64)[rows], gn[cols])
        for r, c, iou, a in zip(rows, cols, pair_iou, ang):
            if not exposed[c]:
                status[r] = PredStatus.NOT_EXPOSED
            elif iou < iou_min:
                status[r] = PredStatus.LOW_IOU
            elif not a <= max_normal_deg:
                status[r] = PredStatus.NORMAL
            else:
                status[r] = PredStatus.TP
    tp_mask = status[pairs[:, 0]] == PredStatus.TP if len(pairs) else np.zeros(0, bool)
    tp_pairs = pairs[tp_mask]
    tp_iou = pair_iou[tp_mask]
    tp = int(tp_pairs.shape[0])
    pi, fi = tp_pairs[:, 0], tp_pairs[:, 1]
    gc = np.asarray(truth.centers, dtype=np.float64).reshape(F, 3)
    grasp_err = np.linalg.norm(np.asarray(pred.grasp_points, np.float64)[pi] - gc[fi], axis=1)
    center_err = np.linalg.norm(np.asarray(pred.centers, np.float64)[pi] - gc[fi], axis=1)
    width_err = np.abs(np.asarray(pred.width, np.float64)[pi]
                       - np.asarray(truth.width, np.float64).reshape(F)[fi])
    length_err = np.abs(np.asarray(pred.length, np.float64)[pi]
                        - np.asarray(truth.length, np.float64).reshape(F)[fi])
    normal_err = _angle_deg(np.asarray(pred.normals, np.float64)[pi],
                            np.asarray(truth.normals, np.float64).reshape(F, 3)[fi])
    precision, recall, f1 = prf(tp, P, n_exposed)
    return Match(
        tp=tp, fp=P - tp, fn=n_exposed - tp, n_pred=P, n_exposed=n_exposed, n_faces=F,
        precision=precision, recall=recall, f1=f1,
        pairs=pairs, pair_iou=pair_iou, status=status, pred_face=pred_face,
        tp_pairs=tp_pairs, tp_iou=tp_iou, grasp_err=grasp_err, center_err=center_err,
        width_err=width_err, length_err=length_err, normal_err_deg=normal_err,
    )


# --- packed layers: wrong rectangles, ambiguous regions, heights --------------------------


def overlap_matrix(
    corners: npt.ArrayLike,
    truth: FaceTruth,
    *,
    centers: npt.ArrayLike | None = None,
    max_plane_offset: float | None = 0.03,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Overlap areas of every polygon with every face, in the face's plane.

    Parameters
    ----------
    corners : array_like, shape (P, k, 3), metres, sensor frame
        Polygons (rectangles: k = 4), corners in order around each.
    truth : GroundTruth-like
        ``centers``, ``normals``, ``x_axis``, ``y_axis`` (F, 3), ``width``, ``length`` (F,).
    centers : array_like, shape (P, 3), optional
        The polygons' centres for the plane gate; default the mean of their corners.
    max_plane_offset : float or None
        As in :func:`match_surfaces`: a polygon whose centre lies farther than this from a
        face's plane (metres) does not overlap it; None disables the gate.

    Returns
    -------
    (inter, pred_area, face_area) : ndarrays, shape (P, F), m^2
        :func:`rect_overlap_in_plane` of each pair; zeros where the pair cannot overlap.
    """
    C = np.asarray(corners, dtype=np.float64)
    P = int(C.shape[0]) if C.ndim == 3 else 0
    F = int(np.asarray(truth.centers).shape[0])
    inter, a_pred, a_gt = (np.zeros((P, F)) for _ in range(3))
    if P == 0 or F == 0:
        return inter, a_pred, a_gt
    C = C.reshape(P, -1, 3)
    gc = np.asarray(truth.centers, dtype=np.float64).reshape(F, 3)
    gn = np.asarray(truth.normals, dtype=np.float64).reshape(F, 3)
    gx = np.asarray(truth.x_axis, dtype=np.float64).reshape(F, 3)
    gy = np.asarray(truth.y_axis, dtype=np.float64).reshape(F, 3)
    gw = np.asarray(truth.width, dtype=np.float64).reshape(F)
    gl = np.asarray(truth.length, dtype=np.float64).reshape(F)
    pc = C.mean(axis=1) if centers is None else np.asarray(centers, np.float64).reshape(P, 3)
    # The bounding-sphere test of iou_matrix: pairs that cannot overlap are not clipped.
    pr = np.max(np.linalg.norm(C - pc[:, None, :], axis=2), axis=1)  # NaN -> never near
    gr = 0.5 * np.hypot(gw, gl)
    near = np.linalg.norm(pc[:, None, :] - gc[None, :, :], axis=-1) <= (pr[:, None]
                                                                       + gr[None, :]) * 1.001
    if max_plane_offset is not None:
        off = np.abs(np.einsum("pfk,fk->pf", pc[:, None, :] - gc[None, :, :], gn))
        near &= off <= max_plane_offset
    for i, j in zip(*np.nonzero(near)):
        inter[i, j], a_pred[i, j], a_gt[i, j] = rect_overlap_in_plane(
            C[i], gc[j], gx[j], gy[j], gw[j], gl[j])
    return inter, a_pred, a_gt


class WrongReason(IntEnum):
    """How a reported surface stands to the box tops (:func:`wrong_rectangles`)."""

    #: matches a top with IoU >= iou_min and covers no second top by half
    RIGHT = 0
    #: overlaps no box top (a plane of the pallet, the floor, a phantom): a false
    #: surface, but not a wrong rectangle on a box
    OFF_TOP = 1
    #: overlaps a top but matches none with IoU >= iou_min: a sliver of one top, or a
    #: rectangle spanning several
    NO_MATCH = 2
    #: matches a top with IoU >= iou_min, but covers at least ``span_cover`` of two or
    #: more tops: it spans a seam (one that covers exactly two equal tops has IoU 0.5
    #: with each, so the IoU alone cannot be trusted to call it)
    SPANS = 3


@dataclass(frozen=True, eq=False)
class WrongRectangles:
    """Result of :func:`wrong_rectangles` for one scan.

    Attributes
    ----------
    max_iou : (n_pred,) float64
        The best in-plane IoU of each surface with any top (exposed or not).
    best_face : (n_pred,) int64
        The top of that IoU, -1 if the surface overlaps none.
    n_covered : (n_pred,) int64
        Tops of which the surface covers at least ``span_cover`` of the area.
    reason : (n_pred,) uint8
        :class:`WrongReason` of each surface.
    """

    max_iou: np.ndarray
    best_face: np.ndarray
    n_covered: np.ndarray
    reason: np.ndarray

    @property
    def n_pred(self) -> int:
        return int(self.reason.shape[0])

    @property
    def wrong(self) -> np.ndarray:
        """(n_pred,) bool: the wrong rectangles (NO_MATCH or SPANS)."""
        return (self.reason == WrongReason.NO_MATCH) | (self.reason == WrongReason.SPANS)

    @property
    def n_wrong(self) -> int:
        return int(self.wrong.sum())

    def count(self, reason: WrongReason) -> int:
        return int((self.reason == reason).sum())

    @property
    def rate(self) -> float:
        """Wrong rectangles per reported surface (0 with no surface)."""
        return self.n_wrong / self.n_pred if self.n_pred else 0.0

    def to_dict(self, *, digits: int = 4) -> dict[str, Any]:
        """JSON-ready: counts per reason and each surface's reason, best IoU and top."""
        return {"n_pred": self.n_pred, "n_wrong": self.n_wrong,
                **{r.name.lower(): self.count(r) for r in WrongReason},
                "reason": [WrongReason(int(r)).name for r in self.reason],
                "max_iou": [round(float(v), digits) for v in self.max_iou],
                "best_face": [int(v) for v in self.best_face]}


def wrong_rectangles(
    pred: SurfaceSet,
    truth: FaceTruth,
    *,
    iou_min: float = 0.5,
    span_cover: float = 0.5,
    max_plane_offset: float | None = 0.03,
) -> WrongRectangles:
    """Find the reported surfaces that would make a robot grip the wrong thing.

    A surface is a *wrong rectangle* when it overlaps a box top (any top, exposed or
    not, in its plane) and either matches none with IoU >= ``iou_min`` (issue 21's
    definition: a sliver of a top, or a union of tops), or covers at least ``span_cover``
    of the area of two or more tops (it spans a seam). A surface that overlaps no top is
    a false surface of another kind (``OFF_TOP``) and is not counted here.

    Parameters
    ----------
    pred : SurfaceSet
        Reported surfaces (``corners`` (s, 4, 3), ``centers`` (s, 3), sensor frame, metres).
    truth : GroundTruth-like
        The faces (see :func:`match_surfaces`).
    iou_min : float
        The IoU of a match, as in :func:`match_surfaces`.
    span_cover : float
        Fraction of a top's area a surface must cover to count as lying on it, in (0, 1].
        At 0.5, a surface that takes in half of a neighbour is called: its grasp point is
        a quarter of a box off and a suction cup can straddle the seam.
    max_plane_offset : float or None
        The plane gate of :func:`match_surfaces` (metres).

    Returns
    -------
    WrongRectangles

    Notes
    -----
    Unlike the one-to-one assignment of :func:`match_surfaces`, every surface is judged on
    its own: two surfaces on the same top are both right rectangles here (the second one is
    a duplicate, a false positive of the match).
    """
    if not 0.0 < span_cover <= 1.0:
        raise ValueError(f"span_cover must be in (0, 1], got {span_cover}")
    P = len(pred)
    inter, a_pred, a_gt = overlap_matrix(pred.corners, truth, centers=pred.centers,
                                         max_plane_offset=max_plane_offset)
    # a surface without a finite normal overlaps nothing (rect_iou_in_plane scores it 0)
    normals_ok = np.asarray(
        np.isfinite(np.asarray(pred.normals, np.float64).reshape(P, 3)).all(axis=1), bool)
    inter = np.where(normals_ok[:, None], inter, 0.0)
    union = a_pred + a_gt - inter
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.where((union > 0) & (a_pred > 0), inter / np.where(union > 0, union, 1.0), 0.0)
        cover = np.where(a_gt > 0, inter / np.where(a_gt > 0, a_gt, 1.0), 0.0)
    F = iou.shape[1]
    max_iou = iou.max(axis=1) if F else np.zeros(P)
    best = np.where(inter.max(axis=1) > 0, iou.argmax(axis=1), -1) if F else np.full(P, -1)
    n_cov = (cover >= span_cover).sum(axis=1) if F else np.zeros(P, np.int64)
    reason = np.full(P, WrongReason.RIGHT, dtype=np.uint8)
    reason[best < 0] = WrongReason.OFF_TOP
    reason[(best >= 0) & (max_iou < iou_min)] = WrongReason.NO_MATCH
    reason[(best >= 0) & (max_iou >= iou_min) & (n_cov >= 2)] = WrongReason.SPANS
    return WrongRectangles(max_iou=max_iou.astype(np.float64),
                           best_face=best.astype(np.int64), n_covered=n_cov.astype(np.int64),
                           reason=reason)


def region_cover(corners: npt.ArrayLike, truth: FaceTruth, *,
                 max_plane_offset: float | None = 0.03) -> np.ndarray:
    """Fraction of each face's area that each region covers, shape (K, F), in [0, 1].

    Parameters
    ----------
    corners : array_like, shape (K, 4, 3), metres, sensor frame
        Region outlines (e.g. ``Result.ambiguous.corners``).
    truth : GroundTruth-like
    max_plane_offset : float or None
        The plane gate of :func:`match_surfaces` (metres), on the outline's centre.
    """
    inter, _, a_gt = overlap_matrix(corners, truth, max_plane_offset=max_plane_offset)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(a_gt > 0, inter / np.where(a_gt > 0, a_gt, 1.0), 0.0)


def true_box_heights(truth: Any) -> np.ndarray:
    """The height of each face's box, shape (F,), metres; NaN where the truth has no boxes.

    Reads the simulator's ``boxes`` (B, 7: size z at column 5) through ``box_index`` (F,).
    """
    F = int(np.asarray(truth.centers).shape[0])
    boxes, idx = getattr(truth, "boxes", None), getattr(truth, "box_index", None)
    if boxes is None or idx is None:
        return np.full(F, np.nan)
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    i = np.asarray(idx, dtype=np.int64).reshape(F)
    out = np.full(F, np.nan)
    ok = (i >= 0) & (i < b.shape[0])
    out[ok] = b[i[ok], 5]
    return out


#: The height sources of a measured height: a side face, a step (not a listed size's).
MEASURED_HEIGHT_SOURCES: tuple[int, ...] = (int(HeightSource.SIDE), int(HeightSource.STEP))


@dataclass(frozen=True, eq=False)
class HeightErrors:
    """Result of :func:`height_errors`: one row per true positive with a measured height.

    Attributes
    ----------
    pred, face : (k,) int64
        The surface and the face it matched.
    source : (k,) int8
        The surface's height source (``boxloc.products.HeightSource``).
    estimate, sigma, truth : (k,) float64, metres
        The reported height, its reported standard deviation, the box's true height.
    error : (k,) float64, metres
        ``|estimate - truth|``.
    """

    pred: np.ndarray
    face: np.ndarray
    source: np.ndarray
    estimate: np.ndarray
    sigma: np.ndarray
    truth: np.ndarray
    error: np.ndarray

    def __len__(self) -> int:
        return int(self.error.shape[0])


def height_errors(
    height: npt.ArrayLike,
    source: npt.ArrayLike,
    match: Match,
    true_height: npt.ArrayLike,
    *,
    sigma: npt.ArrayLike | None = None,
    sources: Sequence[int] = MEASURED_HEIGHT_SOURCES,
) -> HeightErrors:
    """The height error of each true positive whose height was measured.

    Parameters
    ----------
    height : array_like, shape (n_pred,), metres
        Reported box heights (``SurfaceSet.height``; NaN: none).
    source : array_like, shape (n_pred,), int
        Their sources (``SurfaceSet.height_source``).
    match : Match
        :func:`match_surfaces` of the same surfaces: only its true positives are scored
        (a wrong rectangle has no true height).
    true_height : array_like, shape (F,), metres
        The true height of each face's box (:func:`true_box_heights`).
    sigma : array_like, shape (n_pred,), optional
        Reported standard deviations (``SurfaceSet.height_sigma``), carried along.
    sources : sequence of int
        The sources scored; default side and step (a height copied from a listed size
        measures the list, not the scan).

    Returns
    -------
    HeightErrors
        Rows in the order of ``match.tp_pairs``; a finite estimate and truth only.
    """
    h = np.asarray(height, dtype=np.float64).reshape(-1)
    src = np.asarray(source).astype(np.int64).reshape(-1)
    n = match.n_pred
    if h.shape[0] != n or src.shape[0] != n:
        raise ValueError(f"height and source must have shape ({n},), got {h.shape} and "
                         f"{src.shape}")
    sg = np.full(n, np.nan) if sigma is None else np.asarray(sigma, np.float64).reshape(n)
    th = np.asarray(true_height, dtype=np.float64).reshape(-1)
    pi = match.tp_pairs[:, 0].astype(np.int64)
    fi = match.tp_pairs[:, 1].astype(np.int64)
    est, tru = h[pi], th[fi]
    keep = np.asarray(np.isin(src[pi], np.asarray(list(sources), np.int64))
                      & np.isfinite(est) & np.isfinite(tru), dtype=bool)
    pi, fi, est, tru = pi[keep], fi[keep], est[keep], tru[keep]
    return HeightErrors(pred=pi, face=fi, source=src[pi].astype(np.int8), estimate=est,
                        sigma=sg[pi], truth=tru, error=np.abs(est - tru))


# --- edges -------------------------------------------------------------------------------

#: Ground-truth edge label values (``GroundTruth.edge_labels``).
GT_JUMP = 1
GT_CREASE = 2

EDGE_CLASSES: tuple[str, ...] = ("any", "jump", "crease")


def _masks(labels_pred: np.ndarray, labels_gt: np.ndarray, kind: str) -> tuple[np.ndarray, ...]:
    lp = np.asarray(labels_pred)
    lg = np.asarray(labels_gt)
    if lp.shape != lg.shape or lp.ndim != 2:
        raise ValueError(
            f"edge label images must be 2-D and of equal shape, got {lp.shape} and {lg.shape}"
        )
    if kind == "any":
        return lp != EdgeKind.NONE, lg != 0
    if kind == "jump":
        return lp == EdgeKind.JUMP, lg == GT_JUMP
    if kind == "crease":
        return (lp == EdgeKind.CREASE_CONVEX) | (lp == EdgeKind.CREASE_CONCAVE), lg == GT_CREASE
    raise ValueError(f"edge kind must be one of {EDGE_CLASSES}, got {kind!r}")


def _dilate(mask: np.ndarray, tol_px: int) -> np.ndarray:
    if tol_px <= 0:
        return mask
    k = np.ones((2 * tol_px + 1, 2 * tol_px + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), k).astype(bool)


def edge_counts(
    labels_pred: npt.ArrayLike, labels_gt: npt.ArrayLike, tol_px: int = 1, kind: str = "any"
) -> tuple[int, int, int, int]:
    """Counts behind :func:`edge_scores`: (pred correct, pred, gt found, gt), for pooling."""
    mp, mg = _masks(np.asarray(labels_pred), np.asarray(labels_gt), kind)
    tol = int(tol_px)
    correct = int((mp & _dilate(mg, tol)).sum())
    found = int((mg & _dilate(mp, tol)).sum())
    return correct, int(mp.sum()), found, int(mg.sum())


def edge_scores(
    labels_pred: npt.ArrayLike, labels_gt: npt.ArrayLike, tol_px: int = 1, kind: str = "any"
) -> tuple[float, float]:
    """Pixel precision and recall of an edge map within a tolerance.

    Parameters
    ----------
    labels_pred : array_like, shape (H, W), uint8
        :class:`boxloc.products.EdgeKind` per pixel (``EdgeMap.labels``).
    labels_gt : array_like, shape (H, W), uint8
        Ground truth: 0 none, 1 jump, 2 crease (``GroundTruth.edge_labels``).
    tol_px : int
        A predicted edge pixel is correct if a ground-truth edge pixel of the same class is
        within ``tol_px`` (Chebyshev distance, i.e. a (2 tol + 1)^2 square); a ground-truth
        pixel is found if a predicted one is within ``tol_px``.
    kind : {"any", "jump", "crease"}
        Which class to score. "any" ignores the kind (the headline figure, and the only class
        that counts ``EdgeKind.GROOVE``, which the ground truth does not label separately);
        "crease" pools convex and concave creases.

    Returns
    -------
    (precision, recall) : tuple of float
        precision = 1 with no predicted pixel, recall = 1 with no true pixel.
    """
    c, n_p, f, n_g = edge_counts(labels_pred, labels_gt, tol_px, kind)
    return (c / n_p if n_p else 1.0, f / n_g if n_g else 1.0)


def edge_report(
    labels_pred: npt.ArrayLike, labels_gt: npt.ArrayLike, tol_px: int = 1
) -> dict[str, dict[str, float]]:
    """Counts, precision and recall for each of :data:`EDGE_CLASSES`.

    Returns ``{"any": {"correct", "n_pred", "found", "n_gt", "precision", "recall"}, ...}``.
    """
    out: dict[str, dict[str, float]] = {}
    for kind in EDGE_CLASSES:
        c, n_p, f, n_g = edge_counts(labels_pred, labels_gt, tol_px, kind)
        out[kind] = {
            "correct": c, "n_pred": n_p, "found": f, "n_gt": n_g,
            "precision": c / n_p if n_p else 1.0, "recall": f / n_g if n_g else 1.0,
        }
    return out


# --- pooling -----------------------------------------------------------------------------


def _stat(a: np.ndarray, q: float, scale: float = 1.0) -> float | None:
    """Percentile ``q`` of ``a`` times ``scale``; None (JSON null) for an empty array."""
    a = a[np.isfinite(a)]
    if a.size == 0:
        return None
    return float(np.percentile(a, q) * scale)


def aggregate_matches(matches: Iterable[Match]) -> dict[str, Any]:
    """Pool the matches of many scans.

    Counts are summed before precision/recall/F1 (micro-average); the errors of all true
    positives are pooled before their median and 95th percentile.

    Returns
    -------
    dict
        ``n_scans, tp, fp, fn, n_pred, n_exposed, precision, recall, f1,
        grasp_err_median_mm, grasp_err_p95_mm, center_err_median_mm, dim_err_median_mm,
        dim_err_p95_mm, normal_err_median_deg, normal_err_p95_deg, iou_median``; a figure
        over no true positive is None.
    """
    ms = list(matches)
    tp = sum(m.tp for m in ms)
    n_pred = sum(m.n_pred for m in ms)
    n_exposed = sum(m.n_exposed for m in ms)
    precision, recall, f1 = prf(tp, n_pred, n_exposed)

    def cat(name: str) -> np.ndarray:
        arrs = [np.asarray(getattr(m, name), dtype=np.float64) for m in ms]
        return np.concatenate(arrs) if arrs else np.zeros(0)

    grasp, center, dim = cat("grasp_err"), cat("center_err"), cat("dim_err")
    normal, iou = cat("normal_err_deg"), cat("tp_iou")
    return {
        "n_scans": len(ms), "tp": tp, "fp": n_pred - tp, "fn": n_exposed - tp,
        "n_pred": n_pred, "n_exposed": n_exposed,
        "precision": precision, "recall": recall, "f1": f1,
        "grasp_err_median_mm": _stat(grasp, 50, 1e3),
        "grasp_err_p95_mm": _stat(grasp, 95, 1e3),
        "center_err_median_mm": _stat(center, 50, 1e3),
        "dim_err_median_mm": _stat(dim, 50, 1e3),
        "dim_err_p95_mm": _stat(dim, 95, 1e3),
        "normal_err_median_deg": _stat(normal, 50),
        "normal_err_p95_deg": _stat(normal, 95),
        "iou_median": _stat(iou, 50),
    }


def aggregate_edges(reports: Sequence[dict[str, dict[str, float]]]) -> dict[str, Any]:
    """Pool :func:`edge_report` outputs of many scans (pixel counts summed per class)."""
    out: dict[str, Any] = {"n_scans": len(reports)}
    for kind in EDGE_CLASSES:
        c = sum(int(r[kind]["correct"]) for r in reports)
        n_p = sum(int(r[kind]["n_pred"]) for r in reports)
        f = sum(int(r[kind]["found"]) for r in reports)
        n_g = sum(int(r[kind]["n_gt"]) for r in reports)
        p = c / n_p if n_p else 1.0
        r_ = f / n_g if n_g else 1.0
        out[kind] = {"precision": p, "recall": r_,
                     "f1": 2 * p * r_ / (p + r_) if p + r_ > 0 else 0.0,
                     "n_pred": n_p, "n_gt": n_g}
    return out


def percentiles_ms(values: Sequence[float]) -> dict[str, float | None]:
    """Median and 95th percentile of durations (ms), None when empty."""
    a = np.asarray([v for v in values if v is not None and math.isfinite(v)], dtype=np.float64)
    return {"median": _stat(a, 50), "p95": _stat(a, 95)}

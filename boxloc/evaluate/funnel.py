"""The loss funnel: at which stage of the pipeline each exposed box top was lost.

:func:`loss_stages` takes one scan's :class:`boxloc.products.Result` and its ground truth
and follows every fully exposed face down the pipeline (edges, lines, vertices, hypotheses,
verification, selection), each stage's product tested against the face's true rectangle:

======== ==================================================================================
stage    the face is lost there when
======== ==================================================================================
edges    fewer than :data:`MIN_SIDES` of its sides show edge points (``result.edges``
         labels within :data:`EDGE_TOL_PX` of the projected side along at least
         :data:`SIDE_SHOWN` of it)
lines    edges are there, but fewer than :data:`MIN_SIDES` sides have a 3D line along them
         (within :data:`LINE_ANGLE_DEG` and :data:`LINE_DIST` m, overlapping
         :data:`LINE_OVERLAP` of the side)
vertex   lines are there, but no vertex lies within :data:`VERTEX_DIST` m of a corner
hyp      a vertex is there, but no dimension attempt (a row of ``HypothesisSet.att_*``)
         has IoU >= :data:`IOU_MIN` with the face
verify   such an attempt exists, but none passed verification (the
         :class:`~boxloc.products.VerifyReason` of the best one says why)
select   a verified attempt has IoU >= :data:`IOU_MIN`, but no surface is a true positive
         on the face (MDL chose another, or the match paired it elsewhere)
found    a surface is a true positive on the face (:func:`~boxloc.evaluate.metrics.match_surfaces`)
======== ==================================================================================

The stage is decided from the end: a face found is ``found`` whatever its edges looked
like; otherwise the latest stage whose product still holds the face names the stage after
it as the one that lost it (a face with a neighbour's corner as its vertex but no lines of
its own is a ``hyp`` loss, not a ``lines`` loss).

Each face is also tested for being *separable* (:func:`separable_faces`): no side of it
is a flush seam that the noise-free render cannot show. Two equal-height boxes touching with
no gap and sharp, flat lids make one smooth plane in the range image, and no method can
split it without a list of box sizes.

Frames and units: the sensor frame, metres; pixels are (column u, row v) as
``scan.sensor.project`` returns them.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np

from boxloc.distributions import norm_isf
from boxloc.evaluate.metrics import Match, match_surfaces, rect_iou_matrix
from boxloc.products import DimensionSource, EdgeKind, VerifyReason

__all__ = [
    "EDGE_TOL_PX", "SIDE_SHOWN", "SIDE_SAMPLES", "SIDE_SPAN", "MIN_SIDES", "LINE_ANGLE_DEG",
    "LINE_DIST", "LINE_OVERLAP", "VERTEX_DIST", "FLUSH_ANGLE_DEG", "FLUSH_STEP", "IOU_MIN",
    "MAX_PLANE_OFFSET", "LossStage",
    "STAGE_NAMES", "NO_PRODUCTS", "FaceLosses", "loss_stages", "sides_shown",
    "separable_faces", "funnel_figures", "vertex_normal_chi2", "vertex_normal_figures",
    "line_direction_z", "line_direction_figures", "LINE_GROUPS", "Z_MEDIAN", "Z_P99",
    "CHI2_2_MEDIAN", "CHI2_2_P99",
]

#: Edge pixels within this many pixels (a square window) of the projected side count as
#: the side's: a jump is labelled on its nearer surface (up to 1 px off the true outline)
#: and the sensors' edge blur (``noise.edge_px``) moves a detected edge by about 1 px more.
EDGE_TOL_PX = 2
#: A side shows when at least this fraction of its samples have an edge pixel near: half
#: a side is enough for a line to be found along it (the Hough stage needs support, not
#: completeness), and an occluder or a mixed-pixel gap may hide the rest.
SIDE_SHOWN = 0.5
#: Samples along each side, evenly spaced over :data:`SIDE_SPAN` of its length.
SIDE_SAMPLES = 25
#: The part of a side that is sampled (fractions of its length): its middle 80 %, so that
#: the edges of the two sides meeting it at the corners do not count for it.
SIDE_SPAN = (0.1, 0.9)
#: Sides a face needs at a stage: a vertex is two sides meeting (an L), so a face with
#: fewer than two sides with edges (lines) cannot get a vertex of its own.
MIN_SIDES = 2
#: A line lies along a side when its direction is within this angle of the side's, degrees,
#: ... (the line tests are generous on purpose: they ask whether the Hough stage found the
#: side at all, not how well; these are the thresholds of the first hand-run funnel)
LINE_ANGLE_DEG = 6.0
#: ... the side's midpoint is within this distance of the line, metres (far below the
#: smallest box side, 0.15 m, so a line never counts for the parallel side across) ...
LINE_DIST = 0.02
#: ... and its segment overlaps at least this fraction of the side's length.
LINE_OVERLAP = 0.3
#: Largest distance from a true corner to a vertex that counts as that corner's, metres
#: (1.5 x :data:`LINE_DIST`: a vertex is where two such lines meet).
VERTEX_DIST = 0.03
#: Two tops are flush (one plane) when their normals agree within this angle, degrees, ...
FLUSH_ANGLE_DEG = 0.5
#: ... and their planes are this close along the normal, metres: far above the rounding of
#: boxes drawn to one height (``touching`` and ``layered`` tops share theirs exactly) and
#: no more than the smallest range-noise floor of the simulator's sensor models (the ToF's
#: ``TOF_SIGMA0``, 0.5 mm), so no sensor here resolves such a step.
FLUSH_STEP = 0.0005
#: Smallest IoU of an attempt (or a verified attempt) with the face: the bench's true
#: positive IoU (:func:`boxloc.evaluate.metrics.match_surfaces`).
IOU_MIN = 0.5
#: An attempt whose centre lies farther than this from the face's plane is not the face's,
#: metres: the same gate as the bench's match.
MAX_PLANE_OFFSET = 0.03


class LossStage(IntEnum):
    """The stage that lost an exposed face (``FOUND``: none did)."""

    EDGES = 0
    LINES = 1
    VERTEX = 2
    HYP = 3
    VERIFY = 4
    SELECT = 5
    FOUND = 6


#: The stages' names in the report, in pipeline order (``LossStage(i)`` is ``STAGE_NAMES[i]``).
STAGE_NAMES: tuple[str, ...] = tuple(s.name.lower() for s in LossStage)
#: The bench's name for a missed face of a scan without stage products (timed out, crashed,
#: or a localizer that returns surfaces only).
NO_PRODUCTS = "none"


@dataclass(frozen=True, eq=False)
class FaceLosses:
    """Where each fully exposed face of one scan was lost (:func:`loss_stages`).

    Attributes
    ----------
    face : (n,) int64
        The face (row of the ground truth) of each entry: the fully exposed ones, in order.
    stage : (n,) uint8
        :class:`LossStage`.
    edge_sides, line_sides : (n,) int8
        Sides (0-4) that show edge points of ``result.edges``; sides with a 3D line along.
    vertices : (n,) int8
        Corners (0-4) with a vertex within :data:`VERTEX_DIST`.
    best_iou : (n,) float64
        The largest IoU of any dimension attempt with the face (0 if none overlaps).
    best_reason : (n,) int16
        :class:`~boxloc.products.VerifyReason` of that attempt's verification; -1 if no
        attempt overlaps the face or the attempt was not verified.
    best_source : (n,) int16
        :class:`~boxloc.products.DimensionSource` of that attempt; -1 if none overlaps.
    separable : (n,) bool
        No side is a flush seam the noise-free render cannot show (:func:`separable_faces`).
    """

    face: np.ndarray
    stage: np.ndarray
    edge_sides: np.ndarray
    line_sides: np.ndarray
    vertices: np.ndarray
    best_iou: np.ndarray
    best_reason: np.ndarray
    best_source: np.ndarray
    separable: np.ndarray

    def __len__(self) -> int:
        return int(self.face.shape[0])

    def stage_names(self) -> list[str]:
        """The stage of each face by name (:data:`STAGE_NAMES`)."""
        return [STAGE_NAMES[int(s)] for s in self.stage]

    def counts(self) -> dict[str, int]:
        """Faces per stage, every stage of :data:`STAGE_NAMES` present (0 if none)."""
        n = np.bincount(self.stage.astype(np.int64), minlength=len(STAGE_NAMES))
        return {name: int(n[i]) for i, name in enumerate(STAGE_NAMES)}

    def verify_reasons(self) -> dict[str, int]:
        """The :class:`~boxloc.products.VerifyReason` of the ``verify`` losses, by name
        (``none``: the best attempt has no verification row)."""
        sel = self.best_reason[self.stage == LossStage.VERIFY]
        out: dict[str, int] = {}
        for r in sel:
            name = NO_PRODUCTS if r < 0 else _enum_name(VerifyReason, int(r))
            out[name] = out.get(name, 0) + 1
        return dict(sorted(out.items()))

    def hyp_sources(self) -> dict[str, int]:
        """The :class:`~boxloc.products.DimensionSource` of the best overlapping attempt of
        each ``hyp`` loss, by name (``none``: no attempt overlaps the face). ``REGION``: the
        face's plane was followed as one flat region over several tops."""
        out: dict[str, int] = {}
        for r in self.best_source[self.stage == LossStage.HYP]:
            name = NO_PRODUCTS if r < 0 else _enum_name(DimensionSource, int(r))
            out[name] = out.get(name, 0) + 1
        return dict(sorted(out.items()))

    def why(self) -> dict[str, dict[str, int]]:
        """:meth:`verify_reasons` and :meth:`hyp_sources`, for :func:`funnel_figures`."""
        return {"verify": self.verify_reasons(), "hyp": self.hyp_sources()}

    def to_dict(self, *, digits: int = 4) -> dict[str, Any]:
        """JSON-ready, one list per attribute; enums by name (null for -1)."""
        return {
            "face": [int(f) for f in self.face],
            "stage": self.stage_names(),
            "edge_sides": [int(v) for v in self.edge_sides],
            "line_sides": [int(v) for v in self.line_sides],
            "vertices": [int(v) for v in self.vertices],
            "best_iou": [round(float(v), digits) for v in self.best_iou],
            "best_reason": [None if r < 0 else _enum_name(VerifyReason, int(r))
                            for r in self.best_reason],
            "best_source": [None if s < 0 else _enum_name(DimensionSource, int(s))
                            for s in self.best_source],
            "separable": [bool(v) for v in self.separable],
        }


def _enum_name(enum: Any, value: int) -> str:
    try:
        return str(enum(value).name)
    except ValueError:  # a value from a newer log than this code
        return str(value)


# --- the side tests ------------------------------------------------------------------------


def _side_pixels(corners: np.ndarray, sensor: Any, shape: tuple[int, int]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The samples along every side, projected: their 3D points (F, 4, S, 3), pixel columns
    and rows (F, 4, S) int64, and whether each lies in the image (F, 4, S) bool."""
    a, b = corners, np.roll(corners, -1, axis=1)  # side k: corner k -> k + 1
    t = np.linspace(SIDE_SPAN[0], SIDE_SPAN[1], SIDE_SAMPLES)[:, None]
    pts = a[:, :, None] * (1.0 - t) + b[:, :, None] * t  # (F, 4, S, 3)
    u, v, inside = _pixels(np.asarray(sensor.project(pts), dtype=np.float64), shape)
    return pts, u, v, inside


def _pixels(uv: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray,
                                                             np.ndarray]:
    """Nearest pixel (column, row) of projected points (..., 2), and whether it is in the
    image (a NaN projection is not)."""
    H, W = shape
    ok = np.isfinite(uv).all(axis=-1)
    with np.errstate(invalid="ignore"):
        ok &= (np.abs(uv) < 1e9).all(axis=-1)
    u = np.where(ok, np.rint(np.where(ok, uv[..., 0], 0.0)), -1).astype(np.int64)
    v = np.where(ok, np.rint(np.where(ok, uv[..., 1], 0.0)), -1).astype(np.int64)
    return u, v, (u >= 0) & (u < W) & (v >= 0) & (v < H)


def _near(mask: np.ndarray, u: np.ndarray, v: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """Whether ``mask`` (H, W) is set within :data:`EDGE_TOL_PX` (a square window, clipped
    to the image) of each pixel; False outside the image. Cheaper than dilating the image:
    a few hundred samples against a megapixel."""
    H, W = mask.shape
    off = np.arange(-EDGE_TOL_PX, EDGE_TOL_PX + 1)
    uu = np.clip(u[inside][:, None, None] + off[None, None, :], 0, W - 1)
    vv = np.clip(v[inside][:, None, None] + off[None, :, None], 0, H - 1)
    hit = np.zeros(inside.shape, dtype=bool)
    hit[inside] = mask[vv, uu].any(axis=(1, 2))
    return hit


def _shown(hit: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """(F, 4) bool: at least :data:`SIDE_SHOWN` of a side's samples in the image hit."""
    n = inside.sum(axis=-1)
    frac = hit.sum(axis=-1) / np.maximum(n, 1)
    return np.asarray((n > 0) & (frac >= SIDE_SHOWN), dtype=bool)


def _check_corners(corners: Any) -> np.ndarray:
    c = np.asarray(corners, dtype=np.float64)
    if c.ndim != 3 or c.shape[1:] != (4, 3):
        raise ValueError(f"corners must have shape (F, 4, 3), got {c.shape}")
    return c


def sides_shown(labels: np.ndarray, corners: np.ndarray, sensor: Any) -> np.ndarray:
    """Which sides of each rectangle show edge pixels in a label image.

    Parameters
    ----------
    labels : ndarray, shape (H, W)
        Edge labels; any non-zero pixel is an edge.
    corners : ndarray, shape (F, 4, 3), float, metres, sensor frame
        Each rectangle's corners in order around it; side k runs from corner k to k + 1.
    sensor : PinholeModel or RayTableModel
        The scan's sensor model (its ``project``).

    Returns
    -------
    ndarray, shape (F, 4), bool
        Side k shows: at least :data:`SIDE_SHOWN` of its :data:`SIDE_SAMPLES` samples that
        project into the image have an edge pixel within :data:`EDGE_TOL_PX`. A side with
        no sample in the image does not show.

    Raises
    ------
    ValueError
        If ``labels`` is not 2-D or ``corners`` not (F, 4, 3).

    Examples
    --------
    >>> from boxloc.scan import PinholeModel
    >>> cam = PinholeModel(fx=100.0, fy=100.0, cx=50.0, cy=50.0, width=100, height=100)
    >>> labels = np.zeros((100, 100), np.uint8)
    >>> labels[30, 30:71] = 1  # the top side of the square below, and nothing else
    >>> sq = np.array([[[-0.2, -0.2, 1.0], [0.2, -0.2, 1.0], [0.2, 0.2, 1.0], [-0.2, 0.2, 1.0]]])
    >>> sides_shown(labels, sq, cam)
    array([[ True, False, False, False]])
    """
    lab = np.asarray(labels)
    if lab.ndim != 2:
        raise ValueError(f"labels must have shape (H, W), got {lab.shape}")
    c = _check_corners(corners)
    if c.shape[0] == 0:
        return np.zeros((0, 4), dtype=bool)
    _, u, v, inside = _side_pixels(c, sensor, lab.shape)
    return _shown(_near(lab != 0, u, v, inside), inside)


def _flush(truth: Any, faces: np.ndarray, pts: np.ndarray, sensor: Any,
           shape: tuple[int, int]) -> np.ndarray:
    """(F, 4, S) bool: just beyond the side sample (:data:`EDGE_TOL_PX` + 1 px outward in
    the image) the noise-free render sees another top face in the same plane (within
    :data:`FLUSH_ANGLE_DEG` and :data:`FLUSH_STEP`)."""
    c = np.asarray(truth.centers, dtype=np.float64).reshape(-1, 3)
    nrm = np.asarray(truth.normals, dtype=np.float64).reshape(-1, 3)
    corners = np.asarray(truth.corners, dtype=np.float64).reshape(-1, 4, 3)[faces]
    side = np.roll(corners, -1, axis=1) - corners  # (F, 4, 3)
    out = np.cross(side, nrm[faces][:, None, :])
    mid = 0.5 * (corners + np.roll(corners, -1, axis=1))
    sign = np.sign(np.einsum("fkc,fkc->fk", mid - c[faces][:, None], out))
    out *= (sign / np.maximum(np.linalg.norm(out, axis=-1), 1e-12))[..., None]
    # the outward direction in the image, from the projection of a point 1 cm beyond
    uv0 = np.asarray(sensor.project(pts), dtype=np.float64)
    uv1 = np.asarray(sensor.project(pts + 0.01 * out[:, :, None, :]), dtype=np.float64)
    step = uv1 - uv0
    with np.errstate(invalid="ignore", divide="ignore"):
        step /= np.linalg.norm(step, axis=-1, keepdims=True)
    u, v, inside = _pixels(uv0 + (EDGE_TOL_PX + 1) * step, shape)
    ids = np.asarray(truth.face_ids)
    other = np.full(inside.shape, -1, dtype=np.int64)
    other[inside] = ids[v[inside], u[inside]]
    me = faces[:, None, None]
    cand = (other >= 0) & (other != me)
    o = np.where(cand, other, 0)
    same_dir = np.einsum("fksc,fc->fks", nrm[o], nrm[faces]) >= math.cos(
        math.radians(FLUSH_ANGLE_DEG))
    step_m = np.abs(np.einsum("fksc,fc->fks", c[o] - c[faces][:, None, None], nrm[faces]))
    return np.asarray(cand & same_dir & (step_m <= FLUSH_STEP), dtype=bool)


def separable_faces(truth: Any, sensor: Any, faces: Sequence[int] | np.ndarray | None = None,
                    *, flush_seams_show: bool = False) -> np.ndarray:
    """Whether each face can be told from its neighbours in the noise-free render: no
    side of it is a flush seam that the render cannot show.

    Parameters
    ----------
    truth : GroundTruth-like
        ``corners (F, 4, 3)``, ``centers``, ``normals (F, 3)`` metres, and the noise-free
        render's ``edge_labels`` and ``face_ids (H, W)``.
    sensor : PinholeModel or RayTableModel
    faces : sequence of int, optional
        The faces to test; default the fully exposed ones, in order.
    flush_seams_show : bool
        Whether a seam between two flush tops (neighbours in the same plane) has relief in
        the noise-free scene: True when the lids have a bevel (a groove along the seam) or
        a bulge (a valley), and then every face is separable; False for sharp, flat lids
        (``SceneSpec.bevel == 0`` and ``bulge == 0``).

    Returns
    -------
    ndarray, shape (len(faces),), bool

    Notes
    -----
    A side sample (as in :func:`sides_shown`) is *hidden* when just beyond it (
    :data:`EDGE_TOL_PX` + 1 px outward in the image) the render sees another top face in
    the same plane and no jump label (a ray through a gap) lies within
    :data:`EDGE_TOL_PX` of it. A side is a hidden seam when more than 1 - :data:`SIDE_SHOWN`
    of its samples in the image are hidden; a face with a hidden seam is not separable: two
    equal-height boxes touching with no gap (or one narrower than the rays' spacing) and no
    bevel make one smooth plane in the range image, and no method can split it without a
    list of box sizes (``Config.box_sizes``).

    ``truth.edge_labels != 0`` alone cannot say this: the render labels every boundary
    between two objects, a flush seam included (as a crease). A side that is occluded or
    out of the image is not a seam and does not make a face inseparable.
    """
    if faces is None:
        faces = np.flatnonzero(np.asarray(truth.fully_exposed, dtype=bool))
    idx = np.asarray(faces, dtype=np.int64).reshape(-1)
    if idx.size == 0 or flush_seams_show:
        return np.ones(idx.size, dtype=bool)
    corners = np.asarray(truth.corners, dtype=np.float64).reshape(-1, 4, 3)[idx]
    lab = np.asarray(truth.edge_labels)
    pts, u, v, inside = _side_pixels(corners, sensor, lab.shape)
    hidden = _flush(truth, idx, pts, sensor, lab.shape) & inside & ~_near(lab == 1, u, v, inside)
    n = inside.sum(axis=-1)
    seam = hidden.sum(axis=-1) > (1.0 - SIDE_SHOWN) * n
    return np.asarray(~seam.any(axis=1), dtype=bool)


def _lines_along(lines: Any, corners: np.ndarray) -> np.ndarray:
    """(F, 4) bool: side k of face f has a 3D line along it (see the module docstring)."""
    return (_line_side_pairs(lines, corners) >= 0.0).any(axis=0).reshape(corners.shape[0], 4)


def _line_side_pairs(lines: Any, corners: np.ndarray) -> np.ndarray:
    """(L, 4F): |cos| of the angle between line l and side k of face f (index 4f + k)
    where the line lies along that side (within :data:`LINE_ANGLE_DEG` and
    :data:`LINE_DIST`, overlapping :data:`LINE_OVERLAP` of it); -1 elsewhere."""
    F = corners.shape[0]
    dirs = np.asarray(lines.directions, dtype=np.float64).reshape(-1, 3)
    if F == 0 or dirs.shape[0] == 0:
        return np.full((dirs.shape[0], 4 * F), -1.0)
    a = corners.reshape(-1, 3)
    b = np.roll(corners, -1, axis=1).reshape(-1, 3)
    length = np.linalg.norm(b - a, axis=1)  # (K,)
    d = (b - a) / np.maximum(length, 1e-12)[:, None]
    mid = 0.5 * (a + b)
    lp = np.asarray(lines.points, dtype=np.float64).reshape(-1, 3)
    ls = np.asarray(lines.starts, dtype=np.float64).reshape(-1, 3)
    le = np.asarray(lines.ends, dtype=np.float64).reshape(-1, 3)
    cos = np.abs(dirs @ d.T)  # (L, K)
    parallel = cos >= math.cos(math.radians(LINE_ANGLE_DEG))
    r = mid[None, :, :] - lp[:, None, :]  # (L, K, 3)
    along = np.einsum("lkc,lc->lk", r, dirs)
    perp = np.linalg.norm(r - along[..., None] * dirs[:, None, :], axis=-1)
    s = np.einsum("lkc,kc->lk", ls[:, None, :] - a[None], d)
    e = np.einsum("lkc,kc->lk", le[:, None, :] - a[None], d)
    lo, hi = np.minimum(s, e), np.maximum(s, e)
    overlap = np.minimum(hi, length[None]) - np.maximum(lo, 0.0)
    along_side = parallel & (perp <= LINE_DIST) & (overlap > LINE_OVERLAP * length[None])
    return np.where(along_side, cos, -1.0)


def _attempt_corners(hyps: Any) -> tuple[np.ndarray, np.ndarray]:
    """Every dimension attempt's rectangle, (k, 4, 3) metres (origin, + x w, + x w + y l,
    + y l in its hypothesis's frame), and its hypothesis's normal, (k, 3)."""
    h = np.asarray(hyps.att_hypothesis, dtype=np.int64)
    o = np.asarray(hyps.origins, dtype=np.float64).reshape(-1, 3)[h]
    x = np.asarray(hyps.x_axis, dtype=np.float64).reshape(-1, 3)[h]
    y = np.asarray(hyps.y_axis, dtype=np.float64).reshape(-1, 3)[h]
    w = np.asarray(hyps.att_width, dtype=np.float64)[:, None]
    ln = np.asarray(hyps.att_length, dtype=np.float64)[:, None]
    c = np.stack([o, o + x * w, o + x * w + y * ln, o + y * ln], axis=1)
    return c, np.asarray(hyps.normals, dtype=np.float64).reshape(-1, 3)[h]


# --- the funnel ---------------------------------------------------------------------------


def loss_stages(result: Any, truth: Any, sensor: Any, *, match: Match | None = None,
                flush_seams_show: bool = False,
                separable: Sequence[bool] | np.ndarray | None = None) -> FaceLosses:
    """Follow every fully exposed face of one scan down the pipeline's products.

    Parameters
    ----------
    result : Result
        :func:`boxloc.find_graspable_surfaces`' result: ``edges``, ``lines``, ``vertices``,
        ``hypotheses``, ``verification`` and ``surfaces`` are read.
    truth : GroundTruth-like
        The faces (``centers``, ``normals``, ``x_axis``, ``y_axis``, ``width``, ``length``,
        ``corners``, ``fully_exposed``) and the noise-free render's ``edge_labels`` and
        ``face_ids (H, W)`` (for :func:`separable_faces`).
    sensor : PinholeModel or RayTableModel
        The scan's sensor model (``scan.sensor``), for projecting the faces' sides.
    match : Match, optional
        ``match_surfaces(result.surfaces, truth)``, if already computed (the bench's).
    flush_seams_show : bool
        The lids have a bevel or a bulge (see :func:`separable_faces`).
    separable : (n_exposed,) bool, optional
        :func:`separable_faces` of the exposed faces, if already computed (the bench's).

    Returns
    -------
    FaceLosses
        One entry per fully exposed face, in face order.

    Notes
    -----
    The stages, their tests and thresholds are in the module docstring. The tests are
    diagnostics, not the pipeline's own statistical tests: a face counted as having lines
    along two sides may still have failed the vertex stage's tests for a good reason.

    Examples
    --------
    >>> import boxloc, boxloc.simulate as sim
    >>> s = sim.simulate(sim.SceneSpec(kind="single", seed=2, width=320, height=240, f=262.5))
    >>> res = boxloc.find_graspable_surfaces(s.scan, boxloc.Config(min_edge=0.15, max_edge=0.6))
    >>> loss_stages(res, s.truth, s.scan.sensor).stage_names()
    ['found']
    """
    exposed = np.flatnonzero(np.asarray(truth.fully_exposed, dtype=bool))
    n = exposed.size
    corners = np.asarray(truth.corners, dtype=np.float64).reshape(-1, 4, 3)[exposed]
    if match is None:
        match = match_surfaces(result.surfaces, truth)
    found = np.isin(exposed, np.asarray(match.tp_pairs, dtype=np.int64).reshape(-1, 2)[:, 1])

    edge_sides = sides_shown(np.asarray(result.edges.labels), corners, sensor).sum(axis=1)
    line_sides = _lines_along(result.lines, corners).sum(axis=1)
    vpts = np.asarray(result.vertices.points, dtype=np.float64).reshape(-1, 3)
    if vpts.shape[0] and n:
        dist = np.linalg.norm(vpts[:, None, None, :] - corners[None], axis=-1)  # (V, n, 4)
        vertices = (dist.min(axis=0) <= VERTEX_DIST).sum(axis=1)
    else:
        vertices = np.zeros(n, dtype=np.int64)

    hyps, ver = result.hypotheses, result.verification
    n_att = int(np.asarray(hyps.att_hypothesis).shape[0])
    best_iou = np.zeros(n)
    best_reason = np.full(n, -1, dtype=np.int16)
    best_source = np.full(n, -1, dtype=np.int16)
    verified = np.zeros(n, dtype=bool)
    if n_att and n:
        corners, normals = _attempt_corners(hyps)
        with np.errstate(invalid="ignore"):  # an attempt without dimensions: NaN corners
            M = rect_iou_matrix(corners.mean(axis=1), corners, normals, truth,
                                max_plane_offset=MAX_PLANE_OFFSET)[:, exposed]  # (n_att, n)
        # the verification of each attempt (rows are by attempt id; -1: not verified)
        reason = np.full(n_att, -1, dtype=np.int16)
        accepted = np.zeros(n_att, dtype=bool)
        att = np.asarray(ver.attempt, dtype=np.int64)
        keep = (att >= 0) & (att < n_att)
        reason[att[keep]] = np.asarray(ver.reason)[keep]
        accepted[att[keep]] = np.asarray(ver.accepted, dtype=bool)[keep]
        best = np.argmax(M, axis=0)
        best_iou = M[best, np.arange(n)]
        some = best_iou > 0
        best_reason = np.where(some, reason[best], -1).astype(np.int16)
        src = np.asarray(hyps.att_source).astype(np.int16)
        best_source = np.where(some, src[best], -1).astype(np.int16)
        verified = np.asarray(((M >= IOU_MIN) & accepted[:, None]).any(axis=0), dtype=bool)

    stage = np.select(
        [found, verified, best_iou >= IOU_MIN, vertices >= 1, line_sides >= MIN_SIDES,
         edge_sides >= MIN_SIDES],
        [LossStage.FOUND, LossStage.SELECT, LossStage.VERIFY, LossStage.HYP,
         LossStage.VERTEX, LossStage.LINES],
        default=LossStage.EDGES).astype(np.uint8)
    return FaceLosses(
        face=exposed.astype(np.int64), stage=stage,
        edge_sides=edge_sides.astype(np.int8), line_sides=line_sides.astype(np.int8),
        vertices=vertices.astype(np.int8), best_iou=best_iou.astype(np.float64),
        best_reason=best_reason, best_source=best_source,
        separable=(separable_faces(truth, sensor, exposed, flush_seams_show=flush_seams_show)
                   if separable is None else np.asarray(separable, dtype=bool)))


def vertex_normal_chi2(vertices: Any, truth: Any) -> np.ndarray:
    """How far each vertex's normal is from its true face's, over its own covariance.

    A calibration check of the statistic every coplanarity test in the hypothesis stage
    rests on. A vertex counts where it lies within :data:`VERTEX_DIST` of a corner of a
    fully exposed face and its normal is within 45 degrees of that face's (a side face's
    vertex at the same corner is another face's); of several such faces, the one whose
    normal is nearest. The error is the true normal's component across the vertex's, and
    the statistic its Mahalanobis square under :func:`boxloc.stages.vertices.normal_covariance`
    (rank 2): chi2(2) if the lines' covariances are the true ones.

    Parameters
    ----------
    vertices : VertexSet
        ``result.vertices`` (``points``, ``normals``, ``d1``, ``d2``, ``covariances``).
    truth : GroundTruth-like
        ``corners``, ``normals`` and ``fully_exposed`` of the faces.

    Returns
    -------
    chi2 : (k,) float64
        One per vertex that counts, in vertex order.
    """
    from boxloc.stages.vertices import normal_covariance

    pts = np.asarray(vertices.points, dtype=np.float64).reshape(-1, 3)
    exposed = np.flatnonzero(np.asarray(truth.fully_exposed, dtype=bool))
    if not pts.shape[0] or not exposed.size:
        return np.zeros(0)
    corners = np.asarray(truth.corners, dtype=np.float64).reshape(-1, 4, 3)[exposed]
    fn = np.asarray(truth.normals, dtype=np.float64).reshape(-1, 3)[exposed]
    vn = np.asarray(vertices.normals, dtype=np.float64).reshape(-1, 3)
    near = np.linalg.norm(pts[:, None, None, :] - corners[None], axis=-1).min(axis=2)
    cos = np.abs(vn @ fn.T)  # (V, n)
    cos = np.where(near <= VERTEX_DIST, cos, -1.0)
    face = np.argmax(cos, axis=1)
    keep = cos[np.arange(len(pts)), face] >= math.cos(math.radians(45.0))
    if not keep.any():
        return np.zeros(0)
    S = normal_covariance(vertices)[keep]
    n, f = vn[keep], fn[face[keep]]
    f = f * np.sign(np.einsum("ij,ij->i", n, f))[:, None]
    # in a basis across the vertex's normal (the covariance's rank-2 part: a pseudo-inverse
    # in 3-D would blow up the rounding along n)
    a = np.cross(n, np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]]))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    B = np.stack([a, np.cross(n, a)], axis=1)  # (k, 2, 3)
    e = np.einsum("nij,nj->ni", B, f)
    S2 = np.einsum("nij,njk,nlk->nil", B, S, B)
    return np.einsum("ni,nij,nj->n", e, np.linalg.inv(S2), e)


#: The chi2(2) quantiles :func:`vertex_normal_figures` compares with: the median, and the
#: value a calibrated statistic passes 1 % of the time.
CHI2_2_MEDIAN = 2.0 * math.log(2.0)
CHI2_2_P99 = -2.0 * math.log(0.01)


def vertex_normal_figures(chi2: Sequence[float] | np.ndarray) -> dict[str, Any]:
    """Pool :func:`vertex_normal_chi2` over scans: ``n``, ``median`` (chi2(2): 1.386) and
    ``beyond_p99``, the fraction beyond chi2(2)'s 99th percentile (calibrated: 0.01);
    null medians and rates without a vertex."""
    return _tail_figures(np.asarray(chi2, dtype=np.float64), CHI2_2_P99, "median")


def _tail_figures(x: np.ndarray, limit: float, median_key: str) -> dict[str, Any]:
    """``n``, the median (under ``median_key``) and the fraction beyond ``limit`` of x;
    null figures for none."""
    return {"n": int(x.size),
            median_key: float(np.median(x)) if x.size else None,
            "beyond_p99": float(np.mean(x > limit)) if x.size else None}


#: Line kinds :func:`line_direction_figures` pools apart: jump lines (a depth
#: discontinuity, the edge on the nearer surface) and crease lines (a fold, either way).
LINE_GROUPS: dict[str, tuple[int, ...]] = {
    "jump": (EdgeKind.JUMP,), "crease": (EdgeKind.CREASE_CONVEX, EdgeKind.CREASE_CONCAVE)}
#: |z| a calibrated N(0, 1) statistic exceeds half the time, and 1 % of the time.
Z_MEDIAN = float(norm_isf(0.25))
Z_P99 = float(norm_isf(0.005))


def line_direction_z(lines: Any, truth: Any) -> tuple[np.ndarray, np.ndarray]:
    """How far each line along a true top's side leaves the top's plane, over its sigma.

    The vertex normals are cross products of line directions, so a line direction's error
    out of the face's plane is what turns a normal. A line counts where it lies along a
    side of a fully exposed face as the funnel's ``lines`` stage counts it
    (:data:`LINE_ANGLE_DEG`, :data:`LINE_DIST`, :data:`LINE_OVERLAP`); of several faces,
    the one whose side is nearest in angle. The statistic is the direction's component
    along the face's normal over its standard deviation under the line's direction
    covariance: N(0, 1) if that covariance is the true one (a true side lies in the plane).

    Parameters
    ----------
    lines : LineSet
        ``result.lines`` (``points``, ``directions``, ``starts``, ``ends``,
        ``covariances``, ``kinds``).
    truth : GroundTruth-like
        ``corners``, ``normals`` and ``fully_exposed`` of the faces.

    Returns
    -------
    z : (k,) float64
        One per line that counts, in line order.
    kinds : (k,) uint8
        Their :class:`~boxloc.products.EdgeKind` (the support's majority).
    """
    exposed = np.flatnonzero(np.asarray(truth.fully_exposed, dtype=bool))
    dirs = np.asarray(lines.directions, dtype=np.float64).reshape(-1, 3)
    if not dirs.shape[0] or not exposed.size:
        return np.zeros(0), np.zeros(0, np.uint8)
    corners = np.asarray(truth.corners, dtype=np.float64).reshape(-1, 4, 3)[exposed]
    cos = _line_side_pairs(lines, corners)  # (L, 4F)
    best = np.argmax(cos, axis=1)
    keep = cos[np.arange(len(dirs)), best] >= 0.0
    if not keep.any():
        return np.zeros(0), np.zeros(0, np.uint8)
    fn = np.asarray(truth.normals, dtype=np.float64).reshape(-1, 3)[exposed]
    n = fn[best[keep] // 4]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    Sd = np.asarray(lines.covariances, dtype=np.float64).reshape(-1, 6, 6)[keep, 3:, 3:]
    var = np.einsum("ni,nij,nj->n", n, Sd, n)
    z = np.einsum("ni,ni->n", dirs[keep], n) / np.sqrt(np.maximum(var, 1e-300))
    return z, np.asarray(lines.kinds, dtype=np.uint8).reshape(-1)[keep]


def line_direction_figures(z: Sequence[float] | np.ndarray, kinds: Sequence[int] | np.ndarray
                           ) -> dict[str, Any]:
    """Pool :func:`line_direction_z` over scans, per :data:`LINE_GROUPS`: ``n``, the median
    |z| (N(0, 1): 0.674) and ``beyond_p99``, the fraction with |z| beyond 2.576 (0.01)."""
    az = np.abs(np.asarray(z, dtype=np.float64).reshape(-1))
    k = np.asarray(kinds, dtype=np.int64).reshape(-1)
    return {name: _tail_figures(az[np.isin(k, members)], Z_P99, "median_abs")
            for name, members in LINE_GROUPS.items()}


# --- pooled over scans ----------------------------------------------------------------------


def funnel_figures(scans: Iterable[tuple[Sequence[str], Sequence[bool], Sequence[bool],
                                         dict[str, dict[str, int]]]]) -> dict[str, Any]:
    """Pool the funnels of many scans into a group's figures.

    Parameters
    ----------
    scans : iterable of (stages, separable, found, why)
        Per scan, per exposed face: its stage name (:data:`STAGE_NAMES` or
        :data:`NO_PRODUCTS`), whether it is separable, whether it is a true positive; and
        the scan's :meth:`FaceLosses.why` (``verify`` reasons and ``hyp`` sources).

    Returns
    -------
    dict
        ``faces`` (exposed faces), ``stages`` (faces per stage name, pipeline order,
        :data:`NO_PRODUCTS` last), ``verify_reasons`` (the reasons of the ``verify``
        losses, by name), ``hyp_sources`` (the dimension source of the best overlapping
        attempt of the ``hyp`` losses, ``none`` without one), ``separable`` (separable
        faces), ``separable_tp`` (true positives among them), ``separable_recall`` (their
        ratio; null without a separable face) and ``inseparable_misses`` (missed faces that
        are not separable).
    """
    stages = {name: 0 for name in (*STAGE_NAMES, NO_PRODUCTS)}
    why_all: dict[str, dict[str, int]] = {"verify": {}, "hyp": {}}
    faces = sep = sep_tp = insep_miss = 0
    for names, separable, found, why in scans:
        for name, s, f in zip(names, separable, found, strict=True):
            faces += 1
            stages[name] += 1
            sep += bool(s)
            sep_tp += bool(s) and bool(f)
            insep_miss += (not s) and (not f)
        for stage, counts in why.items():
            pooled = why_all[stage]
            for k, v in counts.items():
                pooled[k] = pooled.get(k, 0) + int(v)
    return {"faces": faces, "stages": stages,
            "verify_reasons": dict(sorted(why_all["verify"].items())),
            "hyp_sources": dict(sorted(why_all["hyp"].items())),
            "separable": sep, "separable_tp": sep_tp,
            "separable_recall": sep_tp / sep if sep else None,
            "inseparable_misses": insep_miss}

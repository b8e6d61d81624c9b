"""Ground truth and scoring on real, labelled scans (mOSD: Kinect frames of boxes on a table).

The mOSD frames carry a per-pixel segment ``label``: 0 for no return, 1-9 for (parts of) the
supporting table, ``10 k + j`` for part ``j`` of object ``k`` (k >= 2; parts are *disjoint
pieces* of one object, split by occlusion, not its faces). There are no box poses, so the
top faces are derived from the labels here.

Ground truth (:func:`top_faces`)
--------------------------------
1. The table plane is fitted robustly to the table pixels (RANSAC, then least squares on
   the inliers); its normal, turned toward the sensor, is "up".
2. Each object's valid pixels are cut into planes by sequential RANSAC with the noise
   model's threshold (every point then goes to its nearest plane within the threshold).
3. The object's top face is its plane whose normal is closest to the table normal, if that
   is within ``max_top_tilt`` (an object seen only from the side has no visible top). Its
   region is that plane's pixels (connected pieces smaller than a tenth of the largest are
   dropped: stray points of a side face that happen to lie on the top's plane).
4. The face's centre is the centroid of its region (points weighted by the surface area
   each pixel covers), its normal the region's plane;
   a minimum-area rectangle of the region's points in that plane gives axes and size (used
   for the perfect-prediction check and, indicatively, for dimension errors).

Exposure rule
-------------
A top face of object A is *covered* (not exposed, not graspable) when another object B
rests on it, which is decided in the table's frame (heights along the table normal):

* B lies above the face: B's median height exceeds the face's height by ``cover_margin``;
* B reaches no lower than the face: B's 2nd-percentile height is above the face's height
  minus ``contact_tolerance`` (a box standing on the table next to A shows points down to
  the table, unless A hides them; a box resting on A does not);
* B stands over A: at least ``min_cover_points`` of B's points, projected along the table
  normal, fall inside A's footprint (the convex hull of A's plane points projected the same
  way) by more than ``footprint_inset``. A neighbour that merely touches A's side stays
  outside the inset footprint.

All three are needed: "taller and adjacent in the image" alone would call a rear box's top
covered by a taller box in front of it, which only hides it from the sensor.
On the 25 mOSD learn frames this gives every visible top of learn0-16 as exposed and the
supporting boxes of learn17-24 as covered.

Scoring (:func:`score_real`)
----------------------------
A predicted rectangle is projected into the image (its sides densified, so it also works
for ray-table sensors) and rasterized. Pixels where the scene is seen *in front of* the
rectangle's plane (by more than ``occlusion_margin``, 2 cm) or that have no return are
dropped from it: those parts cannot be seen, and the region only holds seen pixels. The
intersection with a region counts only pixels whose point lies on the rectangle's plane
(within the same margin), so a rectangle floating above a face does not overlap it. The
IoU then enters the same one-to-one assignment as the synthetic benchmark
(:func:`boxloc.evaluate.metrics.match_surfaces`): a true positive needs IoU >= 0.5 with an exposed
face and a normal within 15 degrees. Centre error is against the region's centroid (which
is not the face centre when part of the face is hidden). The faces' own fitted rectangles
score IoU 0.83-0.98 on the mOSD learn frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from boxloc.errors import InputError
from boxloc.evaluate.metrics import Match, match_surfaces
from boxloc.products import SurfaceSet
from boxloc.scan import NoiseModel, Scan

__all__ = [
    "RealTruth",
    "object_masks",
    "table_mask",
    "table_normal",
    "top_faces",
    "real_iou_matrix",
    "rasterize_rectangle",
    "score_real",
    "frame_group",
]

#: Labels of the table after the README's merge rule (2-9 -> 1, and 10-19 // 10 == 1).
_TABLE_MAX_LABEL = 19
#: Smallest label of an object (object k >= 2 has labels 10 k .. 10 k + 9).
_FIRST_OBJECT_LABEL = 20


# --- labels ------------------------------------------------------------------------------


def _check_labels(labels: npt.ArrayLike, shape: tuple[int, int] | None = None) -> np.ndarray:
    L = np.asarray(labels)
    if L.ndim != 2:
        raise InputError(f"labels must have shape (H, W), got {L.shape}")
    if L.dtype.kind not in "iu":
        raise InputError(f"labels must be an integer array, got dtype {L.dtype}")
    if shape is not None and L.shape != shape:
        raise InputError(f"labels must have the scan's shape {shape}, got {L.shape}")
    if L.size and int(L.min()) < 0:
        raise InputError("labels must be >= 0, found negative values")
    return L.astype(np.int64, copy=False)


def object_masks(labels: npt.ArrayLike) -> dict[int, np.ndarray]:
    """The pixels of each object, by object id.

    Parameters
    ----------
    labels : array_like, shape (H, W), int
        mOSD labels: 0 no return, 1-9 table, ``10 k + j`` part ``j`` of object ``k`` (k >= 2).

    Returns
    -------
    dict of int -> ndarray, shape (H, W), bool
        ``{k: labels // 10 == k}`` for every object k >= 2 present, in increasing k; all
        parts ``j`` of an object are merged (they are disjoint pieces of one object).

    Raises
    ------
    InputError
        If ``labels`` is not a 2-D integer array of non-negative values.
    """
    L = _check_labels(labels)
    obj = np.where(L >= _FIRST_OBJECT_LABEL, L // 10, 0)
    return {int(k): obj == k for k in np.unique(obj[obj > 0])}


def table_mask(labels: npt.ArrayLike) -> np.ndarray:
    """Pixels of the supporting table (labels 1-19, i.e. object 1 after merging parts)."""
    L = _check_labels(labels)
    return (L >= 1) & (L <= _TABLE_MAX_LABEL)


def frame_group(name: str) -> str:
    """The mOSD category of a frame by its file stem: ``boxes`` (learn0-16, test0-15),
    ``stacked`` (learn17-24, test16-23), else ``other``."""
    import re

    m = re.fullmatch(r"(learn|test)(\d+)", name)
    if m is None:
        return "other"
    k = int(m.group(2))
    last_box = 16 if m.group(1) == "learn" else 15
    if k <= last_box:
        return "boxes"
    if k <= last_box + 8:
        return "stacked"
    return "other"


# --- planes ------------------------------------------------------------------------------


def _fit_plane(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane of points (k, 3): (centroid, unit normal toward the sensor)."""
    c = P.mean(axis=0)
    _, _, vt = np.linalg.svd(P - c, full_matrices=False)
    n = vt[2]
    if float(n @ c) > 0:  # the sensor is at the origin: the normal points back at it
        n = -n
    return c, n


def _ransac_plane(P: np.ndarray, thr: float, rng: np.random.Generator, *,
                  iterations: int = 200, max_sample: int = 2000) -> np.ndarray:
    """Inlier mask (k,) of the dominant plane of P: RANSAC on a subsample, then least
    squares refits on all points."""
    S = P if P.shape[0] <= max_sample else P[rng.choice(P.shape[0], max_sample, replace=False)]
    tri = rng.integers(0, S.shape[0], size=(iterations, 3))
    a, b, c = S[tri[:, 0]], S[tri[:, 1]], S[tri[:, 2]]
    N = np.cross(b - a, c - a)
    nn = np.linalg.norm(N, axis=1)
    good = nn > 1e-12
    if not good.any():
        return np.zeros(P.shape[0], dtype=bool)
    N, a = N[good] / nn[good, None], a[good]
    d = np.abs(S @ N.T - np.einsum("ik,ik->i", a, N)[None, :])  # (samples, hypotheses)
    best = int(np.argmax((d < thr).sum(axis=0)))
    inl = np.abs((P - a[best]) @ N[best]) < thr
    for _ in range(3):
        if inl.sum() < 3:
            break
        c0, n = _fit_plane(P[inl])
        new = np.abs((P - c0) @ n) < thr
        if np.array_equal(new, inl):
            break
        inl = new
    return inl


@dataclass(frozen=True)
class _Plane:
    center: np.ndarray  # (3,)
    normal: np.ndarray  # (3,), toward the sensor


def _segment_planes(P: np.ndarray, thr: float, rng: np.random.Generator, *,
                    min_points: int, max_planes: int = 6) -> tuple[list[_Plane], np.ndarray]:
    """Planes of an object's points by sequential RANSAC; returns the planes and, per point,
    the index of its nearest plane within ``thr`` (-1: none)."""
    rest = np.ones(P.shape[0], dtype=bool)
    planes: list[_Plane] = []
    for _ in range(max_planes):
        idx = np.flatnonzero(rest)
        if idx.size < min_points:
            break
        inl = _ransac_plane(P[idx], thr, rng)
        if inl.sum() < min_points:
            break
        c, n = _fit_plane(P[idx[inl]])
        planes.append(_Plane(c, n))
        rest[idx[inl]] = False
    assign = np.full(P.shape[0], -1, dtype=np.int64)
    if planes:
        D = np.abs(np.stack([(P - p.center) @ p.normal for p in planes], axis=1))
        near = np.argmin(D, axis=1)
        ok = D[np.arange(P.shape[0]), near] < thr
        assign[ok] = near[ok]
    return planes, assign


def _table_plane(scan: Scan, labels: np.ndarray, noise: NoiseModel,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    m = table_mask(labels) & scan.valid
    if m.sum() < 100:
        raise InputError(f"too few table pixels with a return ({int(m.sum())}) to fit the "
                         "table plane")
    P = np.asarray(scan.points, dtype=np.float64)[m]
    r_med = float(np.median(scan.range[m]))
    # Generous: a table is warped by a few mm over a metre, and Kinect depth is distorted
    # toward the image corners. The inliers only feed a least-squares normal.
    thr = max(5.0 * float(noise.sigma_range(r_med, 0.5)), 0.01)
    inl = _ransac_plane(P, thr, rng, iterations=300)
    if inl.sum() < 3:
        raise InputError("cannot fit the table plane (its pixels are not planar)")
    return _fit_plane(P[inl])


def table_normal(scan: Scan, labels: npt.ArrayLike, *,
                 noise: NoiseModel | None = None) -> np.ndarray:
    """Unit normal of the table plane, toward the sensor, shape (3,), sensor frame.

    Parameters
    ----------
    scan : Scan
    labels : array_like, shape (H, W), int
        mOSD labels (table = 1-9).
    noise : NoiseModel, optional
        Sets the RANSAC threshold (at least 1 cm); default ``NoiseModel()``.

    Raises
    ------
    InputError
        If the labels do not match the scan or the table has fewer than 100 valid pixels.
    """
    _check_scan(scan)
    L = _check_labels(labels, scan.shape)
    return _table_plane(scan, L, noise or NoiseModel(), np.random.default_rng(scan.seed))[1]


def support_plane_pose(scan: Scan, *, noise: NoiseModel | None = None) -> np.ndarray:
    """``sensor_to_base`` (4, 4) from the scan's dominant plane, without labels.

    For a fixed camera over a table (mOSD) the dominant plane is the table: its normal,
    turned toward the sensor, becomes the base's +z ("up"), and the base origin is the foot
    of the perpendicular from the sensor onto it, so ``base z`` is the height above the
    table. The base x axis is the sensor's x projected into the plane. This stands in for
    the hand-eye calibration a robot cell has; it uses no ground truth.

    Raises
    ------
    InputError
        If the scan has fewer than 100 valid points or no plane is found.
    """
    _check_scan(scan)
    valid = scan.valid
    if valid.sum() < 100:
        raise InputError(f"too few valid points ({int(valid.sum())}) to find a support plane")
    noise = noise or NoiseModel()
    P = np.asarray(scan.points, dtype=np.float64)[valid]
    rng = np.random.default_rng(scan.seed)
    thr = max(5.0 * float(noise.sigma_range(float(np.median(scan.range[valid])), 0.5)), 0.01)
    inl = _ransac_plane(P, thr, rng, iterations=300)
    if inl.sum() < 3:
        raise InputError("no support plane found in the scan")
    c, n = _fit_plane(P[inl])
    x = np.array([1.0, 0.0, 0.0]) - n * n[0]
    if np.linalg.norm(x) < 1e-6:  # looking along the plane's x: take the sensor's y
        x = np.array([0.0, 1.0, 0.0]) - n * n[1]
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(n, x), n])  # rows: base axes in the sensor frame
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = [0.0, 0.0, -float(n @ c)]  # the sensor's height above the plane
    return T


def _check_scan(scan: Scan) -> None:
    if not isinstance(scan, Scan):
        raise TypeError(f"scan must be a boxloc.scan.Scan, got {type(scan).__name__}")


# --- the ground truth --------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class RealTruth:
    """Top faces of the objects of one labelled scan (see the module docstring).

    Attributes
    ----------
    object_id : (F,) int64
        The object (mOSD ``k``) of each face; at most one face per object.
    regions : (F, H, W) bool
        The face's pixels (the region).
    n_pixels : (F,) int64
    centers : (F, 3) float64, metres, sensor frame
        Centroid of the region: its points weighted by the surface area each pixel sees
        (so the sensor's denser sampling of near parts does not bias it).
    normals : (F, 3) float64
        Unit normal of the region's plane, toward the sensor.
    x_axis, y_axis : (F, 3) float64
        Axes of the region's minimum-area rectangle (x along the width).
    width, length : (F,) float64, metres
        Sides of that rectangle, ``width <= length``.
    rect_centers : (F, 3) float64
        Centre of that rectangle (in the plane; differs from ``centers``).
    heights : (F,) float64, metres
        Height of the face's centroid above the table plane.
    tilt_deg : (F,) float64
        Angle between the face's normal and the table normal, degrees.
    exposed : (F,) bool
        No other object rests on the face.
    covered_by : (F,) int64
        The object resting on the face, or -1.
    visible_fraction : (F,) float64
        Fraction of the rectangle's area covered by region points (on a grid a few pixel
        footprints wide): low when the face is seen in part.
    table_point, table_normal : (3,) float64
        The table plane (a point and its unit normal toward the sensor).
    objects : (K,) int64
        Every object id in the labels.
    objects_without_top : (M,) int64
        Objects with no plane within ``max_top_tilt`` of the table normal (seen from the
        side only) or too few pixels.
    """

    object_id: np.ndarray
    regions: np.ndarray
    n_pixels: np.ndarray
    centers: np.ndarray
    normals: np.ndarray
    x_axis: np.ndarray
    y_axis: np.ndarray
    width: np.ndarray
    length: np.ndarray
    rect_centers: np.ndarray
    heights: np.ndarray
    tilt_deg: np.ndarray
    exposed: np.ndarray
    covered_by: np.ndarray
    visible_fraction: np.ndarray
    table_point: np.ndarray
    table_normal: np.ndarray
    objects: np.ndarray
    objects_without_top: np.ndarray

    def __len__(self) -> int:
        return int(self.object_id.shape[0])

    @property
    def fully_exposed(self) -> np.ndarray:
        """``exposed``, under the name :func:`boxloc.evaluate.metrics.match_surfaces` reads."""
        return self.exposed

    @property
    def n_exposed(self) -> int:
        return int(self.exposed.sum())

    def rectangles(self) -> SurfaceSet:
        """The faces' fitted rectangles as a SurfaceSet (a "perfect" prediction)."""
        from boxloc.evaluate.baseline import surface_set_from_rects

        return surface_set_from_rects(self.rect_centers, self.normals, self.x_axis,
                                      self.width, self.length, up=self.table_normal)

    def to_dict(self, *, digits: int = 4) -> dict[str, Any]:
        """JSON-ready summary: one row per face (lengths in mm), no masks."""
        faces = []
        for i in range(len(self)):
            faces.append({
                "object": int(self.object_id[i]),
                "exposed": bool(self.exposed[i]),
                "covered_by": int(self.covered_by[i]),
                "n_pixels": int(self.n_pixels[i]),
                "height_mm": round(float(self.heights[i]) * 1e3, 1),
                "width_mm": round(float(self.width[i]) * 1e3, 1),
                "length_mm": round(float(self.length[i]) * 1e3, 1),
                "tilt_deg": round(float(self.tilt_deg[i]), 2),
                "visible_fraction": round(float(self.visible_fraction[i]), 3),
                "center": [round(float(v), digits) for v in self.centers[i]],
            })
        return {"n_faces": len(self), "n_exposed": self.n_exposed,
                "objects": [int(k) for k in self.objects],
                "objects_without_top": [int(k) for k in self.objects_without_top],
                "table_normal": [round(float(v), 6) for v in self.table_normal],
                "faces": faces}


def _plane_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(n, a)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def _pixel_solid_angle(rays: np.ndarray) -> np.ndarray:
    """Solid angle of each pixel, steradians, (H, W), from its neighbours' rays (works for
    pinhole and ray-table sensors; 0 where a ray is missing)."""
    du = np.gradient(rays, axis=1)
    dv = np.gradient(rays, axis=0)
    om = np.linalg.norm(np.cross(du, dv), axis=-1)
    return np.where(np.isfinite(om), om, 0.0)


def _clean_region(pix: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Drop connected pieces (8-connected) smaller than a tenth of the largest."""
    mask = np.zeros(shape, np.uint8)
    mask.reshape(-1)[pix] = 1
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n <= 2:
        return pix
    areas = stats[1:, cv2.CC_STAT_AREA]
    keep = np.flatnonzero(areas >= 0.1 * areas.max()) + 1
    return pix[np.isin(lab.reshape(-1)[pix], keep)]


def _rectangle(Q: np.ndarray, c: np.ndarray, n: np.ndarray,
               cell: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float, float]:
    """Minimum-area rectangle of points Q (k, 3) in the plane (c, n): centre, x axis, y axis,
    width, length (width <= length) and the fraction of it covered by occupied grid cells."""
    u, v = _plane_basis(n)
    q = np.stack([(Q - c) @ u, (Q - c) @ v], axis=1)
    (rx, ry), (a, b), ang = cv2.minAreaRect(q.astype(np.float32))
    t = np.radians(ang)
    ex = np.cos(t) * u + np.sin(t) * v
    ey = np.cross(n, ex)
    center = c + rx * u + ry * v
    if a > b:
        a, b = b, a
        ex, ey = ey, -ex
    # Coverage: occupied cells of a grid in the rectangle's frame over its area.
    local = np.stack([(Q - center) @ ex, (Q - center) @ ey], axis=1)
    occ = np.unique(np.floor(local / cell).astype(np.int64), axis=0).shape[0]
    area = float(a) * float(b)
    frac = float(min(occ * cell * cell / area, 1.0)) if area > 0 else 0.0
    return center, ex, ey, float(a), float(b), frac


def _inset_depth(hull: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Signed distance (m) of 2-D points q (k, 2) inside a convex polygon (h, 2), CCW:
    > 0 inside, the distance to the nearest side."""
    e = np.roll(hull, -1, axis=0) - hull
    inward = np.stack([-e[:, 1], e[:, 0]], axis=1)  # left normal of a CCW polygon's sides
    inward /= np.maximum(np.linalg.norm(inward, axis=1, keepdims=True), 1e-300)
    return np.min(np.einsum("khd,hd->kh", q[:, None, :] - hull[None], inward), axis=1)


def _footprint(Q2: np.ndarray) -> np.ndarray | None:
    """Convex hull (h, 2), counter-clockwise, of 2-D points; None if degenerate."""
    if Q2.shape[0] < 3:
        return None
    hull = cv2.convexHull(Q2.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    if hull.shape[0] < 3:
        return None
    x, y = hull[:, 0], hull[:, 1]
    if float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))) < 0:
        hull = hull[::-1]
    return hull


def top_faces(
    scan: Scan,
    labels: npt.ArrayLike,
    *,
    noise: NoiseModel | None = None,
    min_pixels: int = 100,
    max_top_tilt: float = np.radians(20.0),
    flatness: float = 0.003,
    cover_margin: float = 0.01,
    contact_tolerance: float = 0.02,
    footprint_inset: float = 0.015,
    min_cover_points: int = 30,
) -> RealTruth:
    """Derive the objects' top faces, and which are exposed, from a labelled scan.

    Parameters
    ----------
    scan : Scan
    labels : array_like, shape (H, W), int
        mOSD labels (0 none, 1-9 table, ``10 k + j`` part j of object k).
    noise : NoiseModel, optional
        Range noise; the plane threshold is ``3 sigma`` (at the object's median range and a
        60 degree incidence) plus ``flatness``, clipped to [4, 20] mm. Default
        ``NoiseModel()``.
    min_pixels : int
        Smallest plane, and smallest top region, in pixels.
    max_top_tilt : float
        Largest angle between a top face's normal and the table normal, radians.
    flatness : float
        Allowance for cardboard bulge in the plane threshold, metres.
    cover_margin, contact_tolerance, footprint_inset : float
        Metres; the exposure rule (module docstring).
    min_cover_points : int
        Points of another object inside the inset footprint that make it "over" this one.

    Returns
    -------
    RealTruth

    Raises
    ------
    InputError
        If the labels do not match the scan, or the table cannot be fitted.

    Notes
    -----
    Deterministic: the RANSAC draws come from a generator seeded with ``scan.seed``.
    """
    _check_scan(scan)
    L = _check_labels(labels, scan.shape)
    noise = noise or NoiseModel()
    H, W = scan.shape
    rng = np.random.default_rng(scan.seed)
    c_t, n_t = _table_plane(scan, L, noise, rng)
    u_t, v_t = _plane_basis(n_t)
    P_all = np.asarray(scan.points, dtype=np.float64).reshape(-1, 3)
    rng_all = scan.range.reshape(-1)
    valid = scan.valid.reshape(-1)
    pixel_angle = float(scan.sensor.pixel_angle)
    rays = np.asarray(scan.sensor.rays(), dtype=np.float64)
    omega = _pixel_solid_angle(rays).reshape(-1)
    rays = rays.reshape(-1, 3)

    masks = object_masks(L)
    # Per object: its plane points (for footprints and heights) and its top face, if any.
    plane_pts: dict[int, np.ndarray] = {}
    tops: list[dict[str, Any]] = []
    no_top: list[int] = []
    for k, mask in masks.items():
        pix = np.flatnonzero(mask.reshape(-1) & valid)
        if pix.size < min_pixels:
            no_top.append(k)
            continue
        P = P_all[pix]
        r_med = float(np.median(rng_all[pix]))
        thr = float(np.clip(3.0 * noise.sigma_range(r_med, 0.5) + flatness, 0.004, 0.02))
        planes, assign = _segment_planes(P, thr, rng, min_points=min_pixels)
        plane_pts[k] = P[assign >= 0]
        if not planes:
            no_top.append(k)
            continue
        cos_up = np.array([abs(float(p.normal @ n_t)) for p in planes])
        best = int(np.argmax(cos_up))
        if cos_up[best] < np.cos(max_top_tilt):
            no_top.append(k)
            continue
        region = _clean_region(pix[assign == best], (H, W))
        if region.size < min_pixels:
            no_top.append(k)
            continue
        Q = P_all[region]
        _, n = _fit_plane(Q)
        # Area-weighted centroid: near pixels sample a surface more densely than far ones,
        # so the plain mean of the points is pulled toward the sensor (by ~2 cm over a 30 cm
        # top seen at 50 degrees).
        d = rays[region]
        wt = omega[region] * rng_all[region].astype(np.float64) ** 2 / np.maximum(
            np.abs(d @ n), 0.1)
        c = (wt[:, None] * Q).sum(axis=0) / wt.sum()
        cell = 3.0 * r_med * pixel_angle / max(abs(float(n @ (c / np.linalg.norm(c)))), 0.3)
        rc, ex, ey, w, ln, frac = _rectangle(Q, c, n, cell)
        tops.append({"k": k, "region": region, "c": c, "n": n, "rc": rc, "ex": ex, "ey": ey,
                     "w": w, "l": ln, "frac": frac, "h": float((c - c_t) @ n_t)})

    def height(Q: np.ndarray) -> np.ndarray:
        return (Q - c_t) @ n_t

    def flat(Q: np.ndarray) -> np.ndarray:
        return np.stack([(Q - c_t) @ u_t, (Q - c_t) @ v_t], axis=1)

    footprints = {k: _footprint(flat(Q)) for k, Q in plane_pts.items()}
    F = len(tops)
    covered_by = np.full(F, -1, dtype=np.int64)
    for i, t in enumerate(tops):
        hull = footprints.get(t["k"])
        if hull is None:
            continue
        for b, QB in plane_pts.items():
            if b == t["k"] or QB.shape[0] < min_cover_points:
                continue
            hB = height(QB)
            if not np.median(hB) > t["h"] + cover_margin:
                continue
            if not np.percentile(hB, 2) > t["h"] - contact_tolerance:
                continue
            inside = _inset_depth(hull, flat(QB)) > footprint_inset
            if inside.sum() >= min_cover_points:
                covered_by[i] = b
                break

    regions = np.zeros((F, H, W), dtype=bool)
    for i, t in enumerate(tops):
        regions[i].reshape(-1)[t["region"]] = True

    def stack(key: str, shape: tuple[int, ...]) -> np.ndarray:
        return (np.array([t[key] for t in tops], dtype=np.float64).reshape(shape)
                if F else np.zeros(shape))

    normals = stack("n", (F, 3))
    tilt = np.degrees(np.arccos(np.clip(np.abs(normals @ n_t), 0.0, 1.0)))
    return RealTruth(
        object_id=np.array([t["k"] for t in tops], dtype=np.int64),
        regions=regions,
        n_pixels=np.array([t["region"].size for t in tops], dtype=np.int64),
        centers=stack("c", (F, 3)), normals=normals,
        x_axis=stack("ex", (F, 3)), y_axis=stack("ey", (F, 3)),
        width=stack("w", (F,)), length=stack("l", (F,)), rect_centers=stack("rc", (F, 3)),
        heights=stack("h", (F,)), tilt_deg=tilt.reshape(F),
        exposed=covered_by < 0, covered_by=covered_by,
        visible_fraction=stack("frac", (F,)),
        table_point=c_t, table_normal=n_t,
        objects=np.array(sorted(masks), dtype=np.int64),
        objects_without_top=np.array(sorted(no_top), dtype=np.int64),
    )


# --- scoring -----------------------------------------------------------------------------


def rasterize_rectangle(
    corners: npt.ArrayLike,
    scan: Scan,
    *,
    occlusion_margin: float = 0.02,
    rays: np.ndarray | None = None,
    samples_per_side: int = 16,
) -> np.ndarray:
    """The pixels where a 3-D rectangle is seen, shape (H, W), bool.

    Parameters
    ----------
    corners : array_like, shape (4, 3), metres, sensor frame
        In order around the rectangle.
    scan : Scan
        Gives the sensor model (projection) and the measured ranges.
    occlusion_margin : float
        Pixels whose measured range is shorter than the rectangle's plane along that ray by
        more than this (metres) see something in front of it and are dropped; pixels
        without a return are dropped too.
    rays : ndarray, shape (H, W, 3), optional
        ``scan.sensor.rays()``, if the caller already has it.
    samples_per_side : int
        Points per side projected (sides of a rectangle are not straight in the image of a
        non-pinhole sensor).

    Returns
    -------
    ndarray, shape (H, W), bool
        Empty if any corner is behind the sensor or not finite.
    """
    return _rect_pixels(corners, scan, occlusion_margin, rays, samples_per_side)[0]


def _rect_pixels(corners: npt.ArrayLike, scan: Scan, margin: float, rays: np.ndarray | None,
                 samples_per_side: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """(seen, on): the rectangle's seen pixels, and those whose point lies on its plane
    (within ``margin`` along the ray)."""
    C = np.asarray(corners, dtype=np.float64).reshape(4, 3)
    H, W = scan.shape
    seen = np.zeros((H, W), dtype=bool)
    on = np.zeros((H, W), dtype=bool)
    if not np.isfinite(C).all():
        return seen, on
    s = np.linspace(0.0, 1.0, samples_per_side, endpoint=False)[:, None]
    edge_pts = np.concatenate([C[i] + s * (C[(i + 1) % 4] - C[i]) for i in range(4)])
    uv = scan.sensor.project(edge_pts)
    if not np.isfinite(uv).all():
        return seen, on
    uv = np.clip(uv, -4.0 * max(H, W), 4.0 * max(H, W))  # keep cv2's fixed point in range
    img = np.zeros((H, W), np.uint8)
    cv2.fillPoly(img, [np.round(uv * 16).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=4)
    inside = img.astype(bool) & scan.valid
    n = np.cross(C[1] - C[0], C[3] - C[0])
    nn = np.linalg.norm(n)
    if not inside.any() or nn < 1e-12:
        return seen, on
    n /= nn
    R = scan.sensor.rays() if rays is None else rays
    d = R[inside]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = float(n @ C[0]) / (d @ n)  # range of the plane along each ray
    r = scan.range[inside].astype(np.float64)
    ok = np.isfinite(t) & (t > 0)
    seen[inside] = ok & ~(r < t - margin)
    on[inside] = ok & (np.abs(r - t) <= margin)
    return seen, on


def real_iou_matrix(pred: SurfaceSet, truth: RealTruth, scan: Scan, *,
                    occlusion_margin: float = 0.02) -> np.ndarray:
    """Image IoU of every predicted rectangle with every face region, (n_pred, n_faces).

    The union is that of the rectangle's seen pixels (:func:`rasterize_rectangle`) and the
    region; the intersection counts only region pixels whose point lies on the rectangle's
    plane (within ``occlusion_margin``), so a rectangle floating above a face, which
    projects onto it, does not overlap it.
    """
    P, F = len(pred), len(truth)
    M = np.zeros((P, F), dtype=np.float64)
    if P == 0 or F == 0:
        return M
    if truth.regions.shape[1:] != scan.shape:
        raise InputError(f"truth regions {truth.regions.shape[1:]} do not match the scan "
                         f"{scan.shape}")
    rays = scan.sensor.rays()
    G = truth.regions.reshape(F, -1)
    g_area = G.sum(axis=1)
    for i in range(P):
        seen, on = _rect_pixels(pred.corners[i], scan, occlusion_margin, rays)
        seen, on = seen.reshape(-1), on.reshape(-1)
        if not seen.any():
            continue
        inter = (G & on[None, :]).sum(axis=1)
        union = g_area + int(seen.sum()) - (G & seen[None, :]).sum(axis=1)
        M[i] = np.where(union > 0, inter / np.maximum(union, 1), 0.0)
    return M


def score_real(
    pred: SurfaceSet,
    truth: RealTruth,
    scan: Scan,
    *,
    iou_min: float = 0.5,
    max_normal_deg: float = 15.0,
    occlusion_margin: float = 0.02,
) -> Match:
    """Score predicted surfaces against the top faces of a labelled real scan.

    Parameters
    ----------
    pred : SurfaceSet
    truth : RealTruth
        From :func:`top_faces` on the same scan.
    scan : Scan
    iou_min : float
        Smallest image IoU (seen pixels of the rectangle vs the region) of a true positive.
    max_normal_deg : float
        Largest normal error of a true positive, degrees.
    occlusion_margin : float
        See :func:`rasterize_rectangle`, metres.

    Returns
    -------
    Match
        As :func:`boxloc.evaluate.metrics.match_surfaces`: one-to-one assignment maximizing the
        summed IoU over all faces (a prediction on a covered face is a false positive);
        ``center_err`` and ``grasp_err`` are against the region's centroid; ``width_err``
        and ``length_err`` against the region's fitted rectangle (indicative only: a face
        seen in part has a smaller rectangle).
    """
    M = real_iou_matrix(pred, truth, scan, occlusion_margin=occlusion_margin)
    return match_surfaces(pred, truth, iou_min=iou_min, max_normal_deg=max_normal_deg,
                          iou=M)

"""Ground truth: each box's top face in the sensor frame, how much of it is seen, and the
per-pixel face and edge maps of the noise-free render.

A face is *fully exposed* (graspable, the paper's target) when no box rests on it and at
least 90 % of its area is seen. Edges of the noise-free render are labelled 1 (jump, on the
nearer side) or 2 (crease, where two surfaces meet).
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass
from typing import Any

import numpy as np

from boxloc.simulate.boxes import _rests_on
from boxloc.simulate.raycast import _FACE_PLANES, _K, _World

__all__ = ["GroundTruth", "resting_on"]

#: Surfaces of different objects whose meeting line is within this of both (plus the bevel)
#: are in contact: a gap of a few mm is below what a range sensor resolves as a jump.
_CONTACT_TOL = 0.005
_FULLY_SEEN = 0.9  # the visible fraction above which a free face is graspable


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """The exact answer for one simulated scan (sensor frame, metres).

    Attributes
    ----------
    centers : (F, 3) float64
        Centre of each box's top face.
    normals : (F, 3) float64
        Unit normal, pointing toward the sensor.
    x_axis, y_axis : (F, 3) float64
        Unit axes along the width and the length; ``x_axis x y_axis == normals``.
    width, length : (F,) float64
        Face dimensions, ``width <= length``.
    corners : (F, 4, 3) float64
        ``c - x w/2 - y l/2``, then ``+x``, ``+x+y``, ``+y``: counter-clockwise seen from the
        sensor.
    visible_fraction : (F,) float64
        Fraction of the face area the sensor sees (``face_ids`` of the noise-free render,
        each pixel weighted by its footprint on the face plane); 0..1. Emitter shadows,
        dropouts and noise do not lower it: they are the sensor's, not the pile's.
    fully_exposed : (F,) bool
        Nothing rests on the face and ``visible_fraction >= 0.9``: the graspable faces.
    box_index : (F,) int32
        The box (row of ``boxes``) of each face.
    face_ids : (H, W) int32
        Top face seen at each pixel by the noise-free render (bevel band included), else -1.
    edge_labels : (H, W) uint8
        0 none, 1 jump (on the nearer side), 2 crease, from the noise-free render.
    boxes : (B, 7) float64
        Base frame: centre x, y, z, size x, y, z, yaw about z.
    sensor_to_base : (4, 4) float64
    """

    centers: np.ndarray
    normals: np.ndarray
    x_axis: np.ndarray
    y_axis: np.ndarray
    width: np.ndarray
    length: np.ndarray
    corners: np.ndarray
    visible_fraction: np.ndarray
    fully_exposed: np.ndarray
    box_index: np.ndarray
    face_ids: np.ndarray
    edge_labels: np.ndarray
    boxes: np.ndarray
    sensor_to_base: np.ndarray

    _DTYPES: typing.ClassVar[dict[str, Any]] = {
        "fully_exposed": np.bool_, "box_index": np.int32, "face_ids": np.int32,
        "edge_labels": np.uint8,
    }

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            a = np.array(getattr(self, f.name), dtype=self._DTYPES.get(f.name, np.float64),
                         order="C", copy=True)
            a.flags.writeable = False
            object.__setattr__(self, f.name, a)

    def __len__(self) -> int:
        return int(self.centers.shape[0])


def resting_on(truth: GroundTruth) -> np.ndarray:
    """``covered[f]``: some box rests on face f's top, shape (F,), bool. A face that is
    not fully exposed is covered, or free but seen less than 90 %."""
    return _rests_on(np.asarray(truth.boxes, dtype=np.float64).reshape(-1, 7))


def _ground_truth(world: _World, boxes: np.ndarray, T: np.ndarray, rays: np.ndarray,
                  r0: np.ndarray, surf_t: np.ndarray, shape: tuple[int, int], f: float,
                  bevel: float) -> tuple[GroundTruth, np.ndarray]:
    """The ground truth of the noise-free render, and the pixels on either side of a jump.

    Parameters
    ----------
    world : _World
        The scene in the sensor frame.
    boxes : (B, 7) float64
        The boxes, base frame.
    T : (4, 4) float64
        sensor_to_base.
    rays : (N, 3) float64
        Unit rays of the pixels, sensor frame.
    r0 : (N,) float64
        Noise-free range of each pixel, metres (NaN: nothing hit).
    surf_t : (N,) int64
        Surface seen at each pixel (decorations replaced by their lid, ``_as_host_top``).
    shape : (H, W)
        Image size, pixels.
    f : float
        Focal length, pixels.
    bevel : float
        The boxes' bevel, metres.

    Returns
    -------
    truth : GroundTruth
    at_jump : (H, W) bool
        Both pixels of every jump pair (where the sensors' mixed pixels happen).
    """
    labels, at_jump = _edge_labels(world, rays, r0, surf_t, shape, bevel)
    B = len(boxes)
    obj, k = surf_t // _K, surf_t % _K
    face_ids = np.where((surf_t >= 0) & (obj < B) & np.isin(k, _FACE_PLANES), obj, -1)
    faces = _faces(boxes, T)
    seen = np.isfinite(r0)
    vis = _visible_fraction(faces, face_ids, seen, rays, f)
    exposed = ~_rests_on(boxes) & (vis >= _FULLY_SEEN)
    truth = GroundTruth(
        centers=faces.centers, normals=faces.normals, x_axis=faces.x_axis, y_axis=faces.y_axis,
        width=faces.width, length=faces.length, corners=faces.corners, visible_fraction=vis,
        fully_exposed=exposed, box_index=np.arange(B, dtype=np.int32),
        face_ids=face_ids.reshape(shape), edge_labels=labels, boxes=boxes, sensor_to_base=T,
    )
    return truth, at_jump


@dataclass(frozen=True)
class _Faces:
    """The nominal top rectangles, sensor frame: the face fields of :class:`GroundTruth`."""

    centers: np.ndarray
    normals: np.ndarray
    x_axis: np.ndarray
    y_axis: np.ndarray
    width: np.ndarray
    length: np.ndarray
    corners: np.ndarray


def _faces(boxes: np.ndarray, T: np.ndarray) -> _Faces:
    """The nominal top rectangle of every box, in the sensor frame."""
    R, C = T[:3, :3], T[:3, 3]
    B = len(boxes)
    yaw = boxes[:, 6]
    ex = np.stack([np.cos(yaw), np.sin(yaw), np.zeros(B)], 1)
    ey = np.stack([-np.sin(yaw), np.cos(yaw), np.zeros(B)], 1)
    swap = boxes[:, 3] > boxes[:, 4]
    x_b = np.where(swap[:, None], ey, ex)  # the width runs along the shorter side
    w = np.minimum(boxes[:, 3], boxes[:, 4])
    l = np.maximum(boxes[:, 3], boxes[:, 4])
    c_b = boxes[:, :3] + np.c_[np.zeros((B, 2)), boxes[:, 5] / 2]
    c = (c_b - C) @ R
    n = np.tile(np.array([0.0, 0.0, 1.0]) @ R, (B, 1))
    x = x_b @ R
    away = (n * -c).sum(1) < 0  # the sensor is below the face: the normal must face it
    n[away] *= -1
    y = np.cross(n, x)
    c0 = c - x * w[:, None] / 2 - y * l[:, None] / 2
    corners = np.stack([c0, c0 + x * w[:, None], c0 + x * w[:, None] + y * l[:, None],
                        c0 + y * l[:, None]], 1)
    return _Faces(c, n, x, y, w, l, corners.reshape(B, 4, 3))


def _visible_fraction(faces: _Faces, face_ids: np.ndarray, seen: np.ndarray,
                      rays: np.ndarray, f: float) -> np.ndarray:
    """Sum of the seeing pixels' footprints on each face plane over the face area, (F,)."""
    F = len(faces.width)
    if F == 0:
        return np.zeros(0)
    sel = (face_ids >= 0) & seen
    fid = face_ids[sel]
    u = rays[sel]
    n, c = faces.normals[fid], faces.centers[fid]
    nu = np.abs((n * u).sum(1))
    r = np.abs((n * c).sum(1)) / nu
    # Pixel solid angle u_z^3 / f^2, projected on the plane at range r.
    area = r**2 * u[:, 2] ** 3 / (f * f * nu)
    sums = np.bincount(fid, weights=area, minlength=F)
    return np.clip(sums / (faces.width * faces.length), 0.0, 1.0)


def _edge_pairs(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices (p, q) of every horizontal and vertical pair of neighbouring pixels."""
    H, W = shape
    idx = np.arange(H * W).reshape(H, W)
    p = np.concatenate([idx[:, :-1].ravel(), idx[:-1, :].ravel()])
    q = np.concatenate([idx[:, 1:].ravel(), idx[1:, :].ravel()])
    return p, q


def _edge_labels(world: _World, rays: np.ndarray, r0: np.ndarray, surf: np.ndarray,
                 shape: tuple[int, int], bevel: float) -> tuple[np.ndarray, np.ndarray]:
    """Edge labels of the noise-free render, and the pixels on either side of a jump.

    Two neighbouring pixels on different surfaces are a *crease* when the surfaces meet
    between them: the same (convex) box, or two objects whose planes meet, along the rays
    between the two pixels, within ``_CONTACT_TOL + bevel`` of both. Otherwise, or when one
    pixel sees nothing, they are a *jump*. A jump is labelled on the nearer pixel, a crease on
    the pixel nearer the meeting line.

    Returns
    -------
    labels : (H, W) uint8
    at_jump : (H, W) bool
        Both pixels of every jump pair (where mixed pixels happen).
    """
    p, q = _edge_pairs(shape)
    d = surf[p] != surf[q]
    p, q = p[d], q[d]
    sp, sq = surf[p], surf[q]
    vp, vq = sp >= 0, sq >= 0
    crease = np.zeros(p.size, bool)
    s_star = np.full(p.size, 0.5)
    both = vp & vq
    bi = np.flatnonzero(both)
    if bi.size:
        pl = world.flat_planes
        A, Bp = pl[sp[bi]], pl[sq[bi]]
        up, uq = rays[p[bi]], rays[q[bi]]
        # Along w(s) = (1-s) u_p + s u_q the planes are at lam = d / (n . w); they meet where
        # d_A (n_B . w) = d_B (n_A . w), linear in s.
        al0 = A[:, 3] * (Bp[:, :3] * up).sum(1) - Bp[:, 3] * (A[:, :3] * up).sum(1)
        al1 = A[:, 3] * (Bp[:, :3] * uq).sum(1) - Bp[:, 3] * (A[:, :3] * uq).sum(1)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            s = al0 / (al0 - al1)
            w = (1 - s)[:, None] * up + s[:, None] * uq
            lam = A[:, 3] / (A[:, :3] * w).sum(1)
            X = lam[:, None] * w
        X[~np.isfinite(X).all(1)] = 0.0  # no meeting point; rejected by the s and lam tests
        tol = _CONTACT_TOL + bevel
        oa, ob = sp[bi] // _K, sq[bi] // _K
        inside_a = (np.einsum("mkj,mj->mk", world.planes[oa, :, :3], X)
                    - world.planes[oa, :, 3]).max(1) <= tol
        inside_b = (np.einsum("mkj,mj->mk", world.planes[ob, :, :3], X)
                    - world.planes[ob, :, 3]).max(1) <= tol
        meet = (np.isfinite(s) & (s >= -0.5) & (s <= 1.5) & np.isfinite(lam) & (lam > 0)
                & inside_a & inside_b)
        coplanar = ((np.abs(A[:, :3] - Bp[:, :3]).max(1) < 1e-9)
                    & (np.abs(A[:, 3] - Bp[:, 3]) <= tol))
        same_obj = oa == ob
        crease[bi] = same_obj | meet | coplanar
        s_star[bi] = np.where(meet & np.isfinite(s), np.clip(s, 0, 1), 0.5)
    jump = ~crease & (vp | vq)
    near_p = np.where(both, r0[p] <= r0[q], vp)
    labels = np.zeros(shape[0] * shape[1], np.uint8)
    c_pix = np.where(s_star[crease] < 0.5, p[crease], q[crease])
    labels[c_pix] = 2
    j_pix = np.where(near_p[jump], p[jump], q[jump])
    labels[j_pix] = 1
    at_jump = np.zeros(shape[0] * shape[1], bool)
    at_jump[p[jump]] = True
    at_jump[q[jump]] = True
    return labels.reshape(shape), at_jump.reshape(shape)

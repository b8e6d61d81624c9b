"""The scene as half-spaces in the sensor frame, and rays cast at it analytically.

Every box is a convex polyhedron (six faces plus four 45-degree bevels along its top edges),
a decoration a thin slab on its lid, the pallet a slab and the floor a plane. :func:`_cast`
finds each ray's first hit, visiting solids from the highest top down and only the rays of
an image tile that can reach them (:class:`_RayIndex`); :func:`_bulge` moves top-face hits
onto the bulged lid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from boxloc.simulate.boxes import _PALLET_TOP, PALLET_SIZE, _footprint_corners

#: Half-spaces per object: 6 faces and 4 top-edge bevels (padded with always-true rows).
_K = 10
_TOP = 4  # index of the top face among an object's half-spaces
_FACE_PLANES = (4, 6, 7, 8, 9)  # a box's top and its bevels: the nominal top rectangle
_TILE = 16  # ray-index tile size, pixels


@dataclass(frozen=True)
class _World:
    """Every object as half-spaces ``n . X <= d`` in the sensor frame.

    ``planes`` (O, K, 4) rows (n, d): boxes 0..B-1 (+x, -x, +y, -y, top, bottom, then the
    bevels of the +x, -x, +y, -y top edges), the decorations (tape, labels) B..B+D-1, the
    pallet P = B+D, the floor P+1 (its top only). ``host`` (O,): the box of each box or
    decoration (-1 for the pallet and the floor); ``lift`` (O,): a decoration's thickness;
    ``material`` (O,): 0 tape, 1 label, -1 else.
    ``verts`` (P+1, 8, 3): nominal corners, for culling. ``top_*``: each box's top-centre
    and local axes, for the bulge. ``n_rows`` (B+1,): real rows of each solid (the rest is
    padding). ``z_max`` (B+1,): top of each solid in the base frame; ``up`` (3,) and ``c_z``
    give a sensor-frame point's base height ``up . X + c_z``.
    """

    planes: np.ndarray
    verts: np.ndarray
    top_c: np.ndarray
    top_x: np.ndarray
    top_y: np.ndarray
    top_z: np.ndarray
    half: np.ndarray
    n_boxes: int
    bulge: float
    n_rows: np.ndarray
    z_max: np.ndarray
    up: np.ndarray
    c_z: float
    n_deco: int
    host: np.ndarray
    lift: np.ndarray
    material: np.ndarray

    @property
    def flat_planes(self) -> np.ndarray:
        return self.planes.reshape(-1, 4)

    @property
    def floor(self) -> int:
        """Object index of the floor."""
        return self.n_boxes + self.n_deco + 1


def _build_world(boxes: np.ndarray, T: np.ndarray, bevel: float, bulge: float,
                 deco: np.ndarray | None = None, pallet_on: bool = True) -> _World:
    """The scene in the sensor frame; ``deco`` (D, 9): decoration slabs (box columns, host,
    material); ``pallet_on`` False leaves the pallet out (it is never hit)."""
    R, C = T[:3, :3], T[:3, 3]
    B = len(boxes)
    dec = np.zeros((0, 9)) if deco is None else deco
    D = len(dec)
    P = B + D
    pallet = np.array([0.0, 0.0, _PALLET_TOP / 2, *PALLET_SIZE, 0.0])
    planes = np.zeros((P + 2, _K, 4))
    planes[:, :, 3] = 1.0
    for i, b in enumerate(boxes):
        planes[i] = _box_halfspaces(b, bevel)
    for j, dj in enumerate(dec):
        planes[B + j] = _box_halfspaces(dj[:7], 0.0)
    planes[P] = _box_halfspaces(pallet, 0.0)
    planes[P + 1, _TOP] = [0.0, 0.0, 1.0, 0.0]  # the floor: z <= 0
    # Base half-space n.X_b <= d with X_b = R X_s + C becomes (R^T n).X_s <= d - n.C.
    n_s = planes[..., :3] @ R
    d_s = planes[..., 3] - planes[..., :3] @ C
    pad = (planes[..., :3] == 0).all(-1)
    planes = np.concatenate([n_s, d_s[..., None]], -1)
    planes[pad] = [0.0, 0.0, 0.0, 1.0]
    verts = np.stack([_box_verts(b) for b in [*boxes, *dec[:, :7], pallet]])
    verts = (verts - C) @ R
    yaw = boxes[:, 6] if B else np.zeros(0)
    ex = np.stack([np.cos(yaw), np.sin(yaw), np.zeros(B)], 1)
    ey = np.stack([-np.sin(yaw), np.cos(yaw), np.zeros(B)], 1)
    ez = np.tile([0.0, 0.0, 1.0], (B, 1))
    top = boxes[:, :3] + np.c_[np.zeros((B, 2)), boxes[:, 5] / 2] if B else np.zeros((0, 3))
    n_rows = np.full(P + 1, _K if bevel > 0 else 6)
    n_rows[B:] = 6
    z_max = np.concatenate([boxes[:, 2] + boxes[:, 5] / 2 if B else np.zeros(0),
                            dec[:, 2] + dec[:, 5] / 2,
                            [_PALLET_TOP if pallet_on else -np.inf]])
    host = np.concatenate([np.arange(B), dec[:, 7].astype(np.int64), [-1, -1]])
    lift = np.concatenate([np.zeros(B), dec[:, 5], [0.0, 0.0]])
    material = np.concatenate([np.full(B, -1), dec[:, 8].astype(np.int64), [-1, -1]])
    return _World(planes=planes, verts=verts, top_c=(top - C) @ R, top_x=ex @ R, top_y=ey @ R,
                  top_z=ez @ R, half=boxes[:, 3:5] / 2 if B else np.zeros((0, 2)),
                  n_boxes=B, bulge=bulge, n_rows=n_rows, z_max=z_max, up=R[2].copy(),
                  c_z=float(C[2]), n_deco=D, host=host, lift=lift,
                  material=material)


def _box_halfspaces(box: np.ndarray, bevel: float) -> np.ndarray:
    """(K, 4) half-spaces of a box with 45-degree bevels of size ``bevel`` on its top edges."""
    cx, cy, cz, sx, sy, sz, yaw = box
    ex = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    ey = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    ez = np.array([0.0, 0.0, 1.0])
    c = np.array([cx, cy, cz])
    hx, hy, hz = sx / 2, sy / 2, sz / 2
    rows = np.zeros((_K, 4))
    rows[:, 3] = 1.0  # padding: 0 . X <= 1 always holds
    for k, (n, h) in enumerate(((ex, hx), (-ex, hx), (ey, hy), (-ey, hy), (ez, hz), (-ez, hz))):
        rows[k] = [*n, n @ c + h]
    if bevel > 0:
        for k, (e, h) in enumerate(((ex, hx), (-ex, hx), (ey, hy), (-ey, hy))):
            n = (e + ez) / math.sqrt(2)
            rows[6 + k] = [*n, n @ c + (h + hz - bevel) / math.sqrt(2)]
    return rows


def _box_verts(box: np.ndarray) -> np.ndarray:
    """(8, 3) corners of a box in the base frame: the bottom four, then the top four."""
    c = _footprint_corners(box)
    lo, hi = box[2] - box[5] / 2, box[2] + box[5] / 2
    return np.concatenate([np.c_[c, np.full(4, lo)], np.c_[c, np.full(4, hi)]])


def _as_host_top(world: _World, surf: np.ndarray) -> np.ndarray:
    """``surf`` with every decoration hit replaced by its host box's top face."""
    if world.n_deco == 0:
        return surf
    o = surf // _K
    deco = (surf >= 0) & (o >= world.n_boxes) & (o < world.n_boxes + world.n_deco)
    return np.where(deco, world.host[np.maximum(o, 0)] * _K + _TOP, surf)


class _RayIndex:
    """Finds the rays whose direction falls in an image-plane box, by tiles of the image."""

    def __init__(self, D: np.ndarray, shape: tuple[int, int] | None) -> None:
        with np.errstate(divide="ignore", invalid="ignore"):
            a, b = D[:, 0] / D[:, 2], D[:, 1] / D[:, 2]
        ok = (D[:, 2] > 0) & np.isfinite(a) & np.isfinite(b)
        self.a, self.b = np.where(ok, a, np.nan), np.where(ok, b, np.nan)
        self.ok = ok
        self.tiles: np.ndarray | None = None
        if shape is not None:
            H, W = shape
            th, tw = -(-H // _TILE), -(-W // _TILE)
            idx = np.full((th * _TILE, tw * _TILE), -1, np.int64)
            idx[:H, :W] = np.arange(H * W).reshape(H, W)
            tiles = idx.reshape(th, _TILE, tw, _TILE).transpose(0, 2, 1, 3).reshape(th * tw, -1)
            valid = tiles >= 0
            valid[valid] = ok[tiles[valid]]
            ta = np.where(valid, a[np.maximum(tiles, 0)], np.nan)
            tb = np.where(valid, b[np.maximum(tiles, 0)], np.nan)
            self.amin = np.where(valid, ta, np.inf).min(1)
            self.amax = np.where(valid, ta, -np.inf).max(1)
            self.bmin = np.where(valid, tb, np.inf).min(1)
            self.bmax = np.where(valid, tb, -np.inf).max(1)
            self.tiles = tiles
        for v in vars(self).values():  # shared through the camera cache: never modified
            if isinstance(v, np.ndarray):
                v.flags.writeable = False

    def candidates(self, bbox: tuple[float, float, float, float] | None) -> np.ndarray:
        """Flat indices of the rays inside ``bbox`` = (a0, a1, b0, b1); all rays for None."""
        if bbox is None:
            return np.flatnonzero(self.ok)
        a0, a1, b0, b1 = bbox
        if self.tiles is not None:
            sel = (self.amax >= a0) & (self.amin <= a1) & (self.bmax >= b0) & (self.bmin <= b1)
            idx = self.tiles[sel].ravel()
            idx = idx[idx >= 0]
        else:
            idx = np.flatnonzero(self.ok)
        a, b = self.a[idx], self.b[idx]
        return idx[(a >= a0) & (a <= a1) & (b >= b0) & (b <= b1)]


def _bbox(verts: np.ndarray, O: np.ndarray) -> tuple[float, float, float, float] | None:
    """Image-plane box (x/z, y/z) of an object seen from ``O``; None if it reaches behind."""
    rel = verts - O
    if (rel[:, 2] <= 1e-6).any():
        return None
    a, b = rel[:, 0] / rel[:, 2], rel[:, 1] / rel[:, 2]
    eps = 1e-9
    return float(a.min() - eps), float(a.max() + eps), float(b.min() - eps), float(b.max() + eps)


def _cast(world: _World, O: np.ndarray, D: np.ndarray, index: _RayIndex, *,
          floor: bool = True, t_max: np.ndarray | None = None,
          normals: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Cast rays ``O + t D`` (``D`` (N, 3) unit, sensor frame) at the world.

    Parameters
    ----------
    t_max : (N,) float64, optional
        Only hits nearer than this count (default: any).
    normals : bool
        Also return the normals.

    Returns
    -------
    t : (N,) float64
        Distance to the first hit, metres; inf (or ``t_max``) for none.
    surf : (N,) int64
        ``object * K + half-space`` of the hit surface, -1 for none.
    normal : (N, 3) float64 or None
        Outward unit normal at the hit (bulge included), NaN for none.

    Notes
    -----
    Solids are visited from the highest top down. A ray going down (in the base frame) whose
    best hit so far is above a solid's top cannot meet that solid any nearer, so it is not
    tested: lower layers and the pallet cost only the rays that pass between the boxes above.
    """
    N = D.shape[0]
    best = np.full(N, np.inf) if t_max is None else np.array(t_max, dtype=np.float64)
    surf = np.full(N, -1, np.int64)
    DT = np.ascontiguousarray(D.T)
    dz = world.up @ DT  # base-frame vertical component of each ray
    down = dz < 0
    oz = float(world.up @ O) + world.c_z
    with np.errstate(invalid="ignore"):
        h_best = np.where(down, oz + best * dz, -np.inf)  # base height of the best hit
    h_best[np.isnan(h_best)] = -np.inf
    for o in np.argsort(-world.z_max, kind="stable"):
        cand = index.candidates(_bbox(world.verts[o], O))
        # A ray whose best hit is at or above this solid's top meets it no nearer.
        cand = cand[h_best[cand] < world.z_max[o] - 1e-9]
        if cand.size == 0:
            continue
        pl = world.planes[o, : world.n_rows[o]]
        dn = pl[:, :3] @ DT[:, cand]  # (k, M): rows are contiguous, reductions run along them
        num = pl[:, 3] - pl[:, :3] @ O
        with np.errstate(divide="ignore", invalid="ignore"):
            t = num[:, None] / dn
        zero = dn == 0
        if zero.any():  # parallel to a face: outside it never inside (-inf), inside unbounded
            t[zero] = np.where(np.broadcast_to(num[:, None], t.shape)[zero] < 0, -np.inf, np.inf)
        M = cand.size
        t_in, t_out = np.full(M, -np.inf), np.full(M, np.inf)
        k = np.zeros(M, np.int64)
        for row in range(dn.shape[0]):
            tr, enter = t[row], dn[row] < 0
            upd = enter & (tr > t_in)
            np.copyto(t_in, tr, where=upd)
            k[upd] = row
            np.minimum(t_out, np.where(enter, np.inf, tr), out=t_out)
        hit = (t_in <= t_out) & (t_in > 1e-9) & (t_in < best[cand])
        sel = cand[hit]
        best[sel] = t_in[hit]
        surf[sel] = o * _K + k[hit]
        h_best[sel] = np.where(down[sel], oz + t_in[hit] * dz[sel], -np.inf)
    if floor:
        fl = world.floor
        n, d = world.planes[fl, _TOP, :3], world.planes[fl, _TOP, 3]
        idx = np.flatnonzero(down & (h_best < -1e-9) & index.ok)
        dn = n @ DT[:, idx]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (d - n @ O) / dn
        hit = (dn < 0) & (t > 1e-9) & (t < best[idx])
        best[idx[hit]] = t[hit]
        surf[idx[hit]] = fl * _K + _TOP
    if not normals:
        return best, surf, None
    # Row -1 (no hit) of the table is NaN.
    table = np.vstack([world.flat_planes[:, :3], np.full((1, 3), np.nan)])
    normal = np.take(table, surf, axis=0)
    if world.bulge > 0 and world.n_boxes:
        _bulge(world, O, D, best, surf, normal)
    return best, surf, normal


def _bulge(world: _World, O: np.ndarray, D: np.ndarray, t: np.ndarray, surf: np.ndarray,
           normal: np.ndarray) -> None:
    """Move top-face hits onto the bulged surface z = bulge (1-(u/hx)^2)(1-(v/hy)^2), in place
    (a decoration's top follows its lid's bulge, raised by its thickness)."""
    host = np.where(surf >= 0, world.host[np.maximum(surf, 0) // _K], -1)
    idx = np.flatnonzero((host >= 0) & (surf % _K == _TOP))
    if idx.size == 0:
        return
    lift = world.lift[surf[idx] // _K]
    o = host[idx]
    c, ex, ey, ez = world.top_c[o], world.top_x[o], world.top_y[o], world.top_z[o]
    hx, hy = world.half[o, 0], world.half[o, 1]
    d = D[idx]
    q0 = O - c
    z0, dz = (q0 * ez).sum(1), (d * ez).sum(1)
    ti = t[idx]
    for _ in range(5):  # a contraction: the bulge's slope is small
        p = q0 + ti[:, None] * d
        u, v = (p * ex).sum(1), (p * ey).sum(1)
        fu, fv = 1 - (u / hx) ** 2, 1 - (v / hy) ** 2
        h = world.bulge * np.maximum(fu, 0) * np.maximum(fv, 0) + lift
        ti = (h - z0) / dz
    p = q0 + ti[:, None] * d
    u, v = (p * ex).sum(1), (p * ey).sum(1)
    fu, fv = 1 - (u / hx) ** 2, 1 - (v / hy) ** 2
    inside = (fu > 0) & (fv > 0)
    gu = np.where(inside, world.bulge * (-2 * u / hx**2) * fv, 0.0)
    gv = np.where(inside, world.bulge * (-2 * v / hy**2) * fu, 0.0)
    n = ez - gu[:, None] * ex - gv[:, None] * ey
    t[idx] = ti
    normal[idx] = n / np.linalg.norm(n, axis=1, keepdims=True)

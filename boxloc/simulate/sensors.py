"""What the sensor measures: the default sensor's noisy range image, and the render handed
to a physical sensor model of :mod:`boxloc.simulate.zoo`.

The default sensor adds range noise from :class:`boxloc.scan.NoiseModel` (growing with range
and incidence), beam pointing jitter, mixed pixels at depth jumps, emitter shadows and random
dropouts. The zoo's sensors carry their own artefacts; they get a :class:`Rendered` with the
materials and callbacks (shadows, footprints) they need.
"""

from __future__ import annotations

import math

import numpy as np

from boxloc.scan import PinholeModel
from boxloc.simulate.layouts import _LABEL, _TAPE
from boxloc.simulate.raycast import _K, _cast, _RayIndex, _World
from boxloc.simulate.spec import SceneSpec
from boxloc.simulate.truth import _edge_pairs
from boxloc.simulate.zoo import Rendered

#: A shadow is cast only by an occluder this much in front of the lit point, metres.
_SHADOW_EPS = 1e-4
#: Diffuse reflectivity of each material: cardboard, tape, label, pallet wood, concrete floor.
_RHO_BOX, _RHO_TAPE, _RHO_LABEL, _RHO_PALLET, _RHO_FLOOR = 0.45, 0.35, 0.8, 0.4, 0.25


def _measure(spec: SceneSpec, world: _World, sensor: PinholeModel, rays: np.ndarray,
             r0: np.ndarray, normal: np.ndarray, at_jump: np.ndarray, shadow: np.ndarray,
             rng: np.random.Generator) -> np.ndarray:
    """The noisy range image, (N,) float64 (NaN = no return), from the noise-free render."""
    N = r0.size
    # Draw every stream in full and in a fixed order, so options never shift other pixels.
    g = rng.standard_normal((2, N))
    z_range = rng.standard_normal(N)
    u_drop = rng.random(N)
    u_mixed = rng.random(N)
    hit = np.isfinite(r0)
    nu = np.where(hit, np.einsum("ij,ij->i", np.nan_to_num(normal), rays), -1.0)
    # Beam pointing jitter: a ray off by delta (perpendicular to it, sigma_angle per axis)
    # meets the hit's tangent plane at r0 (n.u) |u + delta| / (n.u + n.delta); n.delta only
    # sees the component along n's projection perpendicular to the ray.
    sa = spec.noise.sigma_angle
    n_perp = np.sqrt(np.maximum(1.0 - nu * nu, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        den = nu + sa * g[0] * n_perp * np.sign(nu)
        rj = r0 * nu * np.sqrt(1.0 + sa * sa * (g[0] ** 2 + g[1] ** 2)) / den
    r = np.where(hit & (np.abs(den) > 1e-6) & (rj > 0), rj, r0)
    if spec.mixed_pixels and spec.mixed_fraction > 0:
        pix = np.flatnonzero(at_jump.ravel() & (u_mixed < spec.mixed_fraction))
        if pix.size:
            rm = _supersampled_range(world, pix, sensor)
            good = np.isfinite(rm)
            r[pix[good]] = rm[good]
    sigma = spec.noise.sigma_range(np.where(hit, r0, 1.0), np.abs(nu))
    rho = spec.noise.row_corr
    if rho > 0:
        # an offset shared by each image row (drawn last, and only then: a model without
        # it renders the same scan as before it existed)
        z_row = rng.standard_normal(sensor.height)
        z_range = np.sqrt(1.0 - rho) * z_range + np.sqrt(rho) * z_row[np.arange(N) // sensor.width]
    r = r + z_range * sigma
    bad = ~hit | ~(r > 0) | (u_drop < spec.dropout)
    if spec.shadows:
        bad |= shadow
    return np.where(bad, np.nan, r)


def _shadowed(world: _World, X: np.ndarray, surf: np.ndarray, baseline: float, f: float,
              shape: tuple[int, int], everywhere: bool = False) -> np.ndarray:
    """Points (N, 3) that the emitter at (baseline, 0, 0) cannot see, (N,) bool.

    Notes
    -----
    The emitter sits on the sensor's x axis, so the occluder of a point at column u lies on
    the same image row at u + f b (1/z_occluder - 1/z_point) (depth z along the axis), where
    the camera sees another surface (or on a neighbouring row, for an occluder thinner than a
    pixel). Only pixels with a surface change that near on their right are cast (all of them
    with ``everywhere``, which the tests use to check this).
    """
    H, W = shape
    ok = np.isfinite(X).all(1)
    if baseline <= 0 or not ok.any():
        return np.zeros(X.shape[0], bool)
    if not everywhere:
        z = X[ok, 2]
        reach = int(math.ceil(f * baseline * (1.0 / z.min() - 1.0 / z.max()))) + 2
        s2 = surf.reshape(H, W)
        cols = np.broadcast_to(np.arange(W), (H, W))
        change = np.full((H, W), W)
        change[:, :-1] = np.where(s2[:, 1:] != s2[:, :-1], cols[:, :-1] + 1, W)
        nxt = np.minimum.accumulate(change[:, ::-1], axis=1)[:, ::-1]  # next change at or right
        # An occluder thinner than a pixel may show on a neighbouring row only.
        nxt[1:] = np.minimum(nxt[1:], nxt[:-1].copy())
        nxt[:-1] = np.minimum(nxt[:-1], nxt[1:].copy())
        ok &= ((nxt - cols) <= reach).ravel()
    idx = np.flatnonzero(ok)
    E = np.array([baseline, 0.0, 0.0])
    D = X[idx] - E
    dist = np.sqrt(np.einsum("ij,ij->i", D, D))
    D /= dist[:, None]
    index = _RayIndex(D, None) if idx.size < ok.size // 4 else _RayIndex(
        np.where(ok[:, None], X - E, np.nan), shape)
    if index.tiles is not None:  # many candidates: cast on the full grid, with its tiles
        full = np.full(X.shape, np.nan)
        full[idx] = D
        t_max = np.zeros(ok.size)
        t_max[idx] = dist - _SHADOW_EPS
        _, hit, _ = _cast(world, E, full, index, floor=False, t_max=t_max, normals=False)
        return ok & (hit >= 0)
    _, hit, _ = _cast(world, E, D, index, floor=False, t_max=dist - _SHADOW_EPS, normals=False)
    out = np.zeros(ok.size, bool)
    out[idx] = hit >= 0
    return out


def _supersampled_range(world: _World, pix: np.ndarray, sensor: PinholeModel) -> np.ndarray:
    """Mean range over a 2x2 grid of sub-pixel rays at each pixel (flat index), NaN if any miss."""
    v, u = np.divmod(pix, sensor.width)
    off = np.array([[-0.25, -0.25], [-0.25, 0.25], [0.25, -0.25], [0.25, 0.25]])
    uu = u[:, None] + off[None, :, 0]
    vv = v[:, None] + off[None, :, 1]
    d = np.stack([(uu - sensor.cx) / sensor.fx, (vv - sensor.cy) / sensor.fy,
                  np.ones_like(uu)], -1).reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, _, _ = _cast(world, np.zeros(3), d, _RayIndex(d, None), normals=False)
    t = t.reshape(-1, 4)
    return np.where(np.isfinite(t).all(1), t.mean(1), np.nan)


def _rendered(spec: SceneSpec, world: _World, sensor: PinholeModel, rays: np.ndarray,
              r0: np.ndarray, surf: np.ndarray, surf_t: np.ndarray, normal: np.ndarray | None,
              at_jump: np.ndarray) -> Rendered:
    """What a zoo sensor measures: the render with its materials and callbacks."""
    H, W = spec.height, spec.width
    assert normal is not None
    B, D = world.n_boxes, world.n_deco
    rho_obj = np.full(B + D + 3, _RHO_BOX)
    shiny_obj = np.zeros(B + D + 3, bool)
    tape = world.material[: B + D + 2] == _TAPE
    rho_obj[: B + D + 2][tape] = _RHO_TAPE
    rho_obj[: B + D + 2][world.material[: B + D + 2] == _LABEL] = _RHO_LABEL
    shiny_obj[: B + D + 2][tape] = True
    rho_obj[B + D], rho_obj[B + D + 1], rho_obj[-1] = _RHO_PALLET, _RHO_FLOOR, 0.0

    def per_pixel(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        o = np.where(s >= 0, s // _K, -1)
        return rho_obj[o], shiny_obj[o]

    rho, shiny = per_pixel(surf)
    cos_i = np.abs(np.einsum("ij,ij->i", normal, rays))
    X = r0[:, None] * rays

    def shadow(baseline: float) -> np.ndarray:
        return _shadowed(world, X, surf, baseline, spec.f, (H, W))

    def footprint(pix: np.ndarray, off: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        v, u = np.divmod(pix, W)
        uu = u[:, None] + off[None, :, 0]
        vv = v[:, None] + off[None, :, 1]
        d = np.stack([(uu - sensor.cx) / sensor.fx, (vv - sensor.cy) / sensor.fy,
                      np.ones_like(uu)], -1).reshape(-1, 3)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        t, s, n = _cast(world, np.zeros(3), d, _RayIndex(d, None))
        assert n is not None
        c = np.abs(np.einsum("ij,ij->i", np.nan_to_num(n), d))
        rr, _ = per_pixel(s)
        shape = (pix.size, off.shape[0])
        return (np.where(np.isfinite(t), t, np.nan).reshape(shape), c.reshape(shape),
                rr.reshape(shape))

    return Rendered(shape=(H, W), f=float(spec.f), rays=rays, r0=r0, cos_i=cos_i,
                    reflectivity=rho, shiny=shiny, at_jump=at_jump.ravel(),
                    concave=_concave_pixels(world, rays, r0, surf_t, (H, W), spec.f),
                    shadow=shadow, footprint=footprint)


def _concave_pixels(world: _World, rays: np.ndarray, r0: np.ndarray, surf: np.ndarray,
                    shape: tuple[int, int], f: float) -> np.ndarray:
    """Pixels on an inside corner, (N,) bool: two neighbours on different surfaces, each
    outside the other's half-space by > 1 mm, and close in space (a crease, not a jump)."""
    p, q = _edge_pairs(shape)
    sel = (surf[p] != surf[q]) & (surf[p] >= 0) & (surf[q] >= 0)
    p, q = p[sel], q[sel]
    X = r0[:, None] * rays
    A, Bp = world.flat_planes[surf[p]], world.flat_planes[surf[q]]
    out_a = (A[:, :3] * X[q]).sum(1) - A[:, 3]
    out_b = (Bp[:, :3] * X[p]).sum(1) - Bp[:, 3]
    close = np.linalg.norm(X[p] - X[q], axis=1) < 0.01 + 3 * r0[p] / f
    c = (out_a > 1e-3) & (out_b > 1e-3) & close
    m = np.zeros(r0.size, bool)
    m[p[c]] = True
    m[q[c]] = True
    return m

"""Estimate the sensor's range-noise model from real scans of flat surfaces.

The residuals come from small local plane fits (tiles of ``patch`` x ``patch`` pixels), not
from one plane per surface, so cardboard bulge, table warp and plane misfit do not inflate
them. A tile is used only when it is genuinely flat and whole: nearly all its pixels have a
return, few points are outliers of its robust plane fit, and a quadratic surface does not fit
it markedly better than the plane (which rejects creases, curved objects and edges that the
outlier test lets through). The residual standard deviation is then binned by range and the
model of :class:`boxloc.scan.NoiseModel`,

    sigma(r) = sqrt(sigma0**2 + (k1 r)**2 + (k2 r**2)**2),

is fitted to the binned (robust) standard deviations by non-negative least squares on
sigma**2, which is linear in (sigma0**2, k1**2, k2**2).

The same tiles give ``row_corr``, the share of the noise variance that is an offset common
to one image row (one-way ANOVA per tile, rows as groups: the intraclass correlation,
averaged over the tiles). Structured-light sensors have one; a scanner with independent
samples gives ~0. Two diagnostics say how far that model reaches: ``correlation``, the
correlation of two residuals of a tile at 1, 2, 4 and 8 pixels apart along a row and along
a column (how long the shared part is: a whole-row offset keeps its correlation at every
lag), and ``tails``, how often a residual of the accepted tiles (their plane-fit outliers
included) is beyond 3, 4 and 5 model sigmas, against a normal distribution's rate.

The NoiseModel divides the range noise by ``max(cos_incidence, min_cos)``; the residual of
each point along its ray is multiplied by the same factor before binning, so the fitted model
predicts the observed along-ray scatter at the incidences seen in the data.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from boxloc.errors import InputError
from boxloc.kernels import kernel
from boxloc.scan import NoiseModel, Scan

__all__ = ["plane_residuals", "tile_residuals", "TileResiduals", "estimate_noise", "fit_residuals",
           "noise_toml", "nnls_few", "NOISE_TERMS"]

NOISE_TERMS = ("sigma0", "k1", "k2")
#: Pixel lags of the residual correlation diagnostic (within a tile).
CORRELATION_LAGS = (1, 2, 4, 8)
#: Incidence exponents ``incidence="fit"`` chooses from (1/cos**g; 0: laser, time of
#: flight; 1: triangulation).
INCIDENCE_EXPONENTS = (0.0, 0.5, 1.0, 1.5)
#: Model sigmas of the tail diagnostic.
TAIL_SIGMAS = (3.0, 4.0, 5.0)
_MAD_TO_STD = 1.4826  # 1 / Phi^-1(3/4): MAD of a normal distribution -> its std


@dataclass(frozen=True)
class TileResiduals:
    """Per-point residuals of accepted tiles (every valid point, the robust plane fit's
    outliers included), plus bookkeeping for the report."""

    range: np.ndarray  # (N,) metres
    cos_incidence: np.ndarray  # (N,)
    residual: np.ndarray  # (N,) metres, along the ray
    depth: np.ndarray  # (N,) metres, the points' z (their quantization shows in it)
    tile: np.ndarray  # (N,) int, tile id (unique within one scan)
    inlier: np.ndarray  # (N,) bool: kept by the robust plane fit
    row_share: np.ndarray  # (n_accepted,) per tile: row-offset variance / total (ANOVA)
    # (2, len(CORRELATION_LAGS), 3): along rows / columns, per lag, sums of a*b, a*a, b*b
    # over the pairs of inlier residuals that far apart
    lag_sums: np.ndarray
    n_tiles: int  # tiles considered (enough valid pixels)
    n_accepted: int  # tiles that passed every test
    rejected: dict[str, int]  # tiles rejected, by reason


def plane_residuals(
    scan: Scan,
    mask: npt.ArrayLike | None = None,
    *,
    patch: int = 16,
    labels: npt.ArrayLike | None = None,
    min_valid: float = 0.9,
    max_outliers: float = 0.05,
    max_curvature_ratio: float = 1.5,
    min_cos: float = 0.3,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residuals of the scan's points from robust local plane fits.

    The image is cut into ``patch`` x ``patch`` pixel tiles; each tile that is nearly full,
    flat and not seen at a grazing angle gets a robust plane fit (least squares with
    iterative 3.5-sigma MAD rejection), and its inliers' residuals along their rays are
    returned.

    Parameters
    ----------
    scan : Scan
    mask : ndarray, shape (H, W), bool, optional
        Pixels that may be used (e.g. the known-flat region of a calibration target).
    patch : int
        Tile side, pixels (>= 4). Small enough that real surfaces are flat over a tile,
        large enough to span several quantization steps of the sensor.
    labels : ndarray, shape (H, W), int, optional
        Segment labels (e.g. mOSD ground truth); tiles that cover more than one label are
        skipped, so no tile straddles two surfaces.
    min_valid : float
        Smallest fraction of a tile's pixels that must have a return (and be in ``mask``).
    max_outliers : float
        Largest fraction of a tile's valid points rejected by the robust fit; more means the
        tile holds two surfaces or mixed pixels.
    max_curvature_ratio : float
        Largest ratio of the plane fit's residual variance to a quadratic fit's; more means
        the tile is curved or folded.
    min_cos : float
        Smallest cosine of the incidence angle of a tile (grazing tiles carry mixed pixels).

    Returns
    -------
    range : ndarray, shape (N,), float64, metres
        Range of each inlier point.
    cos_incidence : ndarray, shape (N,), float64
        |cos| of the angle between the point's ray and its tile's plane normal.
    residual : ndarray, shape (N,), float64, metres
        Signed distance along the ray from the fitted plane, scaled by sqrt(n / (n - 3)) for
        the tile's n inliers so that its variance is unbiased for independent noise.

    Raises
    ------
    InputError
        If ``mask`` or ``labels`` do not have the scan's shape, or a parameter is out of range.
    """
    t = tile_residuals(scan, mask, patch=patch, labels=labels, min_valid=min_valid,
                        max_outliers=max_outliers, max_curvature_ratio=max_curvature_ratio,
                        min_cos=min_cos)
    return t.range[t.inlier], t.cos_incidence[t.inlier], t.residual[t.inlier]


def _check_image(a: npt.ArrayLike | None, shape: tuple[int, int], name: str) -> np.ndarray | None:
    if a is None:
        return None
    arr = np.asarray(a)
    if arr.shape != shape:
        raise InputError(f"{name} must have the scan's shape {shape}, got {arr.shape}")
    return arr


def _tiles(a: np.ndarray, patch: int, step: int = 1) -> np.ndarray:
    """(H, W, ...) -> (T, patch*patch, ...) for the whole tiles of the image, row-major;
    every ``step``-th tile along rows and columns."""
    H, W = a.shape[:2]
    ty, tx = H // patch, W // patch
    rest = a.shape[2:]
    a = a[: ty * patch, : tx * patch].reshape(ty, patch, tx, patch, *rest)[::step, :, ::step]
    return a.swapaxes(1, 2).reshape(-1, patch * patch, *rest)


def tile_residuals(
    scan: Scan,
    mask: npt.ArrayLike | None,
    *,
    patch: int,
    labels: npt.ArrayLike | None,
    min_valid: float,
    max_outliers: float,
    max_curvature_ratio: float,
    min_cos: float,
    step: int = 1,
) -> TileResiduals:
    """Residuals of the flat tiles of ``scan`` (see :func:`plane_residuals` for the
    parameters); ``step`` > 1 examines every step-th tile along rows and columns only."""
    if not isinstance(scan, Scan):
        raise TypeError(f"scan must be a boxloc.scan.Scan, got {type(scan).__name__}")
    if not isinstance(patch, int) or patch < 4:
        raise InputError(f"patch must be an integer >= 4, got {patch!r}")
    for name, v, lo, hi in (("min_valid", min_valid, 0, 1), ("max_outliers", max_outliers, 0, 1),
                            ("min_cos", min_cos, 0, 1)):
        if not lo <= v <= hi:
            raise InputError(f"{name} must be in [{lo}, {hi}], got {v}")
    if not max_curvature_ratio >= 1:
        raise InputError(f"max_curvature_ratio must be >= 1, got {max_curvature_ratio}")
    m = _check_image(mask, scan.shape, "mask")
    lab = _check_image(labels, scan.shape, "labels")
    valid = scan.valid if m is None else scan.valid & m.astype(bool)

    def nothing(n_tiles: int, rejected: dict[str, int]) -> TileResiduals:
        z = np.zeros(0)
        return TileResiduals(
            range=z, cos_incidence=z, residual=z, depth=z, tile=np.zeros(0, dtype=np.int64),
            inlier=np.zeros(0, dtype=bool), row_share=z,
            lag_sums=np.zeros((2, len(CORRELATION_LAGS), 3)), n_tiles=n_tiles, n_accepted=0,
            rejected=rejected)

    if scan.shape[0] < patch or scan.shape[1] < patch:
        return nothing(0, {})
    # cut (and subsample) the tiles first: float64 for the tiles examined only
    P = _tiles(scan.points, patch, step).astype(np.float64)  # (T, n, 3)
    V = _tiles(valid, patch, step)  # (T, n)
    rejected: dict[str, int] = {}
    keep = V.mean(1) >= min_valid
    rejected["too few returns"] = int((~keep).sum())
    if lab is not None:
        L = _tiles(lab, patch, step).astype(np.float64)
        Lv = np.where(V, L, np.nan)
        with np.errstate(invalid="ignore"), _quiet_nan():
            one = np.nanmin(Lv, 1) == np.nanmax(Lv, 1)
        rejected["several labels"] = int((keep & ~one).sum())
        keep &= one
    ids = np.flatnonzero(keep)
    n_tiles = int(keep.sum() + rejected.get("several labels", 0))
    if ids.size == 0:
        return nothing(n_tiles, rejected)
    P, V = P[ids], V[ids]
    P0 = np.where(V[..., None], P, 0.0)

    # robust plane per tile, fitted along the rays: refit on the points within 3.5 sigma
    # (MAD), at most 4 rounds; h is each point's range residual
    mean, normal, h, w, ratio = _ray_planes(P0, V, 4)
    n_in = w.sum(1)
    outl = 1.0 - n_in / V.sum(1)
    ok = (outl <= max_outliers) & (n_in >= 10)
    rejected["outliers (edge or mixed pixels)"] = int((~ok).sum())

    # Flatness: does a quadratic surface explain the tile markedly better than the plane?
    # (``ratio``, from the same kernel)
    # On correlated noise every tile's quadratic absorbs a share of the noise (a stereo
    # camera's tiles have a median ratio of 1.2-1.3, a quarter above 1.5): the bound is
    # relative to the scan's own typical tile, or the noisier tiles would be dropped as
    # curved and the noise underestimated
    typical = float(np.nanmedian(ratio[ok])) if ok.any() else 1.0
    bound = max(max_curvature_ratio, 1.0 + CURVATURE_EXCESS * (typical - 1.0))
    curved = ok & ~(ratio <= bound)
    rejected["curved or folded"] = int(curved.sum())
    ok &= ~curved

    # Incidence at the tile's centroid, from the normal of the surface around the tile (see
    # _incidence_normals: a noisy tile's own normal is biased toward grazing).
    # each tile's robust scale, for the incidence window's band and the lag correlations
    # (a tile's own: computed once for the tiles both take)
    scale = np.full(ok.shape, np.nan)
    scale[ok] = _tile_scale(h[ok], w[ok] > 0)
    normal = _incidence_normals(scan, valid, ids, step, patch, mean, normal, ok, scale[ok])
    d_mean = mean / np.linalg.norm(mean, axis=1, keepdims=True)
    cos_tile = np.abs(np.einsum("tk,tk->t", d_mean, normal))
    grazing = ok & (cos_tile < min_cos)
    rejected["grazing incidence"] = int(grazing.sum())
    ok &= ~grazing

    sel = np.flatnonzero(ok)
    wi = w[sel] > 0
    Ps, hs = P0[sel], h[sel]
    r = _norms(Ps)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = Ps / r[..., None]
    ndot = np.einsum("tnk,tk->tn", d, normal[sel])
    dof = np.sqrt(n_in[sel] / (n_in[sel] - 3.0))[:, None]
    e_ray = hs * dof
    tile = np.broadcast_to(ids[sel][:, None], wi.shape)
    vi = V[sel]  # the inliers are among them (the fit's weights are zero elsewhere)
    return TileResiduals(
        range=r[vi], cos_incidence=np.abs(ndot[vi]), residual=e_ray[vi],
        depth=Ps[..., 2][vi],
        tile=tile[vi].astype(np.int64), inlier=wi[vi], row_share=_row_share(hs, wi, patch),
        lag_sums=_lag_sums(hs / scale[sel][:, None], wi, patch),
        n_tiles=n_tiles, n_accepted=int(sel.size),
        rejected=rejected,
    )


def _tile_scale(h: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Each tile's robust residual scale (1.4826 x the median |h| of its inliers), so that
    the pooled correlation weighs every tile alike: otherwise a few tiles of large, folded
    residuals (a box's side at grazing incidence) decide it."""
    mad = _abs_medians(h, w)
    return np.maximum(_MAD_TO_STD * np.nan_to_num(mad), 1e-12)


def _norms(P: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(P, axis=2)`` of (T, n, 3) float64 points, bit for bit: NumPy's
    reduction over the short last axis adds the squares left to right, ``(x*x + y*y) +
    z*z`` (an implementation detail, so a test holds this to NumPy's result), then takes
    the square root; a kernel does that without the (T, n, 3) squares and NumPy's
    per-point loop overhead."""
    return _norms_kernel(np.ascontiguousarray(P, dtype=np.float64))


@kernel
def _norms_kernel(P: np.ndarray) -> np.ndarray:
    T, n = P.shape[0], P.shape[1]
    out = np.empty((T, n))
    for t in range(T):
        for i in range(n):
            x, y, z = P[t, i, 0], P[t, i, 1], P[t, i, 2]
            out[t, i] = math.sqrt((x * x + y * y) + z * z)
    return out


def _lag_sums(h: np.ndarray, w: np.ndarray, patch: int) -> np.ndarray:
    """Sums for the correlation of two inlier residuals of a tile ``lag`` pixels apart,
    along a row and along a column: (2, len(CORRELATION_LAGS), 3) of sum a*b, a*a, b*b."""
    T = h.shape[0]
    H = np.ascontiguousarray(h, dtype=np.float64).reshape(T, patch, patch)
    M = np.ascontiguousarray(w, dtype=np.bool_).reshape(T, patch, patch)
    out = np.zeros((2, len(CORRELATION_LAGS), 3))
    for j, lag in enumerate(CORRELATION_LAGS):
        if lag >= patch:
            continue
        for i in range(2):
            # the products of the pairs in NumPy's order, summed by NumPy as before
            prod = _lag_products(H, M, lag, i == 0)
            out[i, j] = (prod[0].sum(), prod[1].sum(), prod[2].sum())
    return out


@kernel
def _lag_products(H: np.ndarray, M: np.ndarray, lag: int, along_rows: bool) -> np.ndarray:
    """The pairs of inliers ``lag`` pixels apart in (T, p, p) tiles ``H`` (inliers ``M``),
    along rows or along columns: (3, pairs) of a*b, a*a, b*b in C order of the pairs'
    first pixel, bit for bit ``(a * b)[both]`` of :func:`_lag_sums`' slices (without the
    masks and products of every pixel)."""
    T, p = H.shape[0], H.shape[1]
    dr, dc = (0, lag) if along_rows else (lag, 0)
    out = np.empty((3, T * p * p))
    m = 0
    for t in range(T):
        for r in range(p - dr):
            for c in range(p - dc):
                if M[t, r, c] and M[t, r + dr, c + dc]:
                    a, b = H[t, r, c], H[t, r + dr, c + dc]
                    out[0, m] = a * b
                    out[1, m] = a * a
                    out[2, m] = b * b
                    m += 1
    return out[:, :m]


def _row_share(h: np.ndarray, w: np.ndarray, patch: int) -> np.ndarray:
    """Per tile, the share of the residual variance that is an offset common to an image
    row: one-way ANOVA with the tile's rows as groups (the intraclass correlation).

    ``h`` (T, patch*patch) are the residuals in row-major order, ``w`` the inliers. The
    plane fit takes one of the between-row degrees of freedom (its tilt along the
    columns) and one within (its tilt along the rows).
    """
    T = h.shape[0]
    H = np.where(w, h, 0.0).reshape(T, patch, patch)
    n_r = w.reshape(T, patch, patch).sum(2)
    with np.errstate(invalid="ignore", divide="ignore"):
        m_r = H.sum(2) / n_r
        m = H.sum((1, 2)) / n_r.sum(1)
        has = n_r > 0
        R = has.sum(1)
        N = n_r.sum(1)
        ssb = np.sum(np.where(has, n_r * (m_r - m[:, None]) ** 2, 0.0), 1)
        ssw = np.sum(np.where(w.reshape(T, patch, patch),
                              (H - np.where(has, m_r, 0.0)[..., None]) ** 2, 0.0), (1, 2))
        msb = ssb / np.maximum(R - 2, 1)
        msw = ssw / np.maximum(N - R - 1, 1)
        n0 = N / np.maximum(R, 1)  # rows are (nearly) full in an accepted tile
        s_row = (msb - msw) / n0
        share = s_row / (s_row + msw)
    return np.where(np.isfinite(share), share, np.nan)


#: The incidence normal's window: this many tiles on a side, centred on the tile; every
#: INCIDENCE_STRIDE-th pixel along rows and columns.
INCIDENCE_TILES = 3
INCIDENCE_STRIDE = 3
#: Points within this many of the tile's robust sigmas of a plane are on it.
INCIDENCE_BAND = 3.5
#: A tile whose robust scatter exceeds this many times its neighbours' is not a plane of
#: the surface around it (it spans a step) and keeps its own normal.
INCIDENCE_SCATTER = 3.0


def _incidence_normals(scan: Scan, valid: np.ndarray, ids: np.ndarray, step: int, patch: int,
                       mean: np.ndarray, normal: np.ndarray, ok: np.ndarray, sig: np.ndarray
                       ) -> np.ndarray:
    """Each accepted tile's surface normal, fitted over a window INCIDENCE_TILES tiles wide.

    A tile's own plane has 256 points. Where the range noise is large against the tile's
    width (an active-stereo floor at 5 m: 110 mm of noise over 180 mm, correlated over 4
    px), its normal's error is tens of degrees, and in every direction away from the true
    normal: the incidence it gives is biased toward grazing (median cos 0.61 on a floor
    seen at cos 0.8-1, and a seventh of the tiles rejected as grazing). The noise model's
    1 / cos**g then explains the noise away with a small sigma and a large g, and every
    test downstream sees half the true noise. The window is three times as wide, sampled
    as many times, every INCIDENCE_STRIDE-th pixel (less correlated than neighbours): its
    slope errors are a third of the tile's or less. It takes only the window's
    points within INCIDENCE_BAND of the tile's robust sigmas of the tile's plane, then of
    its own plane, so another surface joins it only within the noise of this one (a
    precise tile's band is millimetres wide). Where the window does not fit in the image
    or holds fewer points than the tile, or the tile scatters more than INCIDENCE_SCATTER
    times the median of its accepted neighbours (or has none), the tile's own normal stays.

    ``sig`` (accepted tiles,) are the accepted tiles' robust scales (:func:`_tile_scale`).
    Returns (T, 3) unit normals toward the sensor (``normal`` with the accepted tiles'
    rows replaced).
    """
    H, W = valid.shape
    side = INCIDENCE_TILES * patch
    sel = np.flatnonzero(ok)
    if sel.size == 0 or H < side or W < side:
        return normal
    ty, tx = -(-(H // patch) // step), -(-(W // patch) // step)  # the examined tile grid
    gy, gx = np.divmod(ids[sel], tx)
    r0 = np.clip(gy * step * patch - patch * (INCIDENCE_TILES // 2), 0, H - side)
    c0 = np.clip(gx * step * patch - patch * (INCIDENCE_TILES // 2), 0, W - side)
    P, V = _window_points(scan.points, valid, r0, c0, side, INCIDENCE_STRIDE)
    dist = _norms(P)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = P / dist[..., None]
    Zs = np.where(V, P[..., 2], 1.0)
    x, y, q = P[..., 0] / Zs, P[..., 1] / Zs, 1.0 / Zs
    A = _design(x, y, False)  # (x, y, 1)
    n, c = normal[sel], np.einsum("tk,tk->t", normal[sel], mean[sel])
    for _ in range(2):
        with np.errstate(invalid="ignore", divide="ignore"):
            t_hit = c[:, None] / np.einsum("tnk,tk->tn", u, n)
        inl = V & (np.abs(dist - t_hit) <= INCIDENCE_BAND * sig[:, None])
        wt = inl.astype(np.float64)
        AwT = (A * wt[..., None]).transpose(0, 2, 1)
        M = AwT @ A + 1e-12 * np.eye(3)
        abc = np.linalg.solve(M, AwT @ q[..., None])[..., 0]
        # a x + b y + c = 1 / Z is the plane (a, b, c) . P = 1: normal (a, b, c), offset 1
        nn = np.linalg.norm(abc, axis=1)
        good = (inl.sum(1) >= patch * patch // (INCIDENCE_STRIDE**2)) & (nn > 0)
        good &= np.all(np.isfinite(abc), axis=1)
        cand = abc / np.maximum(nn, 1e-300)[:, None]
        cof = 1.0 / np.maximum(nn, 1e-300)
        away = np.einsum("tk,tk->t", cand, mean[sel]) > 0  # orient toward the sensor
        cand = np.where(away[:, None], -cand, cand)
        n = np.where(good[:, None], cand, n)
        c = np.where(good, np.where(away, -cof, cof), c)
    # The window's normal replaces the tile's only where the tile's scatter is its
    # neighbours' (the surface's noise): a tile across a step fits one plane through both
    # levels, grazing, with a scatter far above its neighbours', and stays grazing.
    grid = np.full((ty + 2, tx + 2), np.nan)
    grid[gy + 1, gx + 1] = sig
    nb = np.stack([grid[gy + 1 + dy, gx + 1 + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)
                   if dy or dx], 1)
    # np.nanmedian(nb, 1): the scales are positive (at least 1e-12), their |x| is x
    typical = _abs_medians(nb, nb > 0)
    same = sig <= INCIDENCE_SCATTER * typical  # False without a neighbour (NaN)
    out = normal.copy()
    out[sel] = np.where(same[:, None], n, normal[sel])
    return out


@kernel
def _window_points(points: np.ndarray, valid: np.ndarray, r0: np.ndarray, c0: np.ndarray,
                   side: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """The incidence windows' points: every ``stride``-th pixel of the ``side`` x ``side``
    window from (r0[t], c0[t]), row-major; (T, m, 3) float64, 0 where no return, and (T,
    m) which have one (valid and in front of the sensor), as NumPy's gather of the pixels
    (``points[rr, cc]``, converted, masked) gives them, without its index arrays."""
    T = r0.shape[0]
    k = (side + stride - 1) // stride
    P = np.zeros((T, k * k, 3))
    V = np.zeros((T, k * k), np.bool_)
    for t in range(T):
        for a in range(k):
            for b in range(k):
                r, c = r0[t] + a * stride, c0[t] + b * stride
                z = np.float64(points[r, c, 2])
                if valid[r, c] and z > 0:
                    i = a * k + b
                    V[t, i] = True
                    P[t, i, 0] = np.float64(points[r, c, 0])
                    P[t, i, 1] = np.float64(points[r, c, 1])
                    P[t, i, 2] = z
    return P, V


@contextlib.contextmanager
def _quiet_nan() -> Iterator[None]:
    """Silence numpy's all-NaN-slice warnings: an empty tile is expected here."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        yield


#: A tile is curved or folded when the plane leaves this many times the typical tile's
#: excess residual variance (over a quadratic's), or ``max_curvature_ratio``, whichever is
#: larger.
CURVATURE_EXCESS = 4.0


def _ray_planes(
    P0: np.ndarray, V: np.ndarray, rounds: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Robust plane of each tile fitted along the sensor's rays, and its flatness.

    A range sensor's noise lies along its rays. A total-least-squares plane (the least
    variance of the points) is the wrong fit for it: on a far tile whose range noise is
    comparable to its width, the least variance turns across the ray, and the tile's
    normal with it (a structured-light camera's fronto-parallel floor at 3.5 m came out
    grazing on every tile). Here the inverse depth, linear in the normalized image
    coordinates for any plane (``a x + b y + c = 1 / Z``), is fitted by least squares, and
    each point's residual is its range minus the plane's range along its ray. Then the
    points within 3.5 robust sigmas (1.4826 x the median |residual| of the current
    inliers) become the inliers, until they do not change, at most ``rounds`` times.

    Parameters
    ----------
    P0 : ndarray, shape (T, n, 3), float64, metres
        The tiles' points, 0 where no return.
    V : ndarray, shape (T, n), bool
        Which points have a return.
    rounds : int

    Returns
    -------
    mean : (T, 3) centroids of the inliers; normal : (T, 3) unit normals toward the sensor;
    h : (T, n) range residuals (measured minus plane, along each ray), metres, 0 where no
    return; w : (T, n) float64, 1 for the final inliers; ratio : (T,) the residual variance
    of the plane over that of a quadratic in the image coordinates (each per degree of
    freedom), over the final inliers: much above 1 for a curved or folded tile.
    """
    T, n = V.shape
    Z = P0[..., 2]
    ok = V & (Z > 0)
    Zs = np.where(ok, Z, 1.0)
    x, y = P0[..., 0] / Zs, P0[..., 1] / Zs
    ray = np.sqrt(1.0 + x * x + y * y)
    q = 1.0 / Zs
    # centred, scaled image coordinates keep the normal equations well conditioned
    cnt = np.maximum(ok.sum(1, keepdims=True), 1)
    xm = np.where(ok, x, 0.0).sum(1, keepdims=True) / cnt
    ym = np.where(ok, y, 0.0).sum(1, keepdims=True) / cnt
    sc = np.sqrt((np.where(ok, (x - xm) ** 2 + (y - ym) ** 2, 0.0)).sum(1, keepdims=True)
                 / cnt) + 1e-12
    u, v = (x - xm) / sc, (y - ym) / sc
    A3 = _design(u, v, False)  # (u, v, 1)
    A6 = _design(u, v, True)  # (u, v, 1, u u, u v, v v)

    def fit(A: np.ndarray, wt: np.ndarray, t: slice | np.ndarray = slice(None)
            ) -> tuple[np.ndarray, np.ndarray]:
        """The tiles ``t``'s planes (``A``, ``wt``: theirs already) and residuals; each
        tile's from its own rows only, whichever others are fitted with it."""
        AwT = (A * wt[..., None]).transpose(0, 2, 1)  # batched matmul: BLAS, not einsum
        M = AwT @ A + 1e-12 * np.eye(A.shape[-1])
        beta = np.linalg.solve(M, AwT @ q[t][..., None])
        with np.errstate(divide="ignore", invalid="ignore"):
            zfit = 1.0 / (A @ beta)[..., 0]
        beta = beta[..., 0]
        return beta, np.where(ok[t], (Z[t] - zfit) * ray[t], 0.0)

    wt = ok.astype(np.float64)
    beta, h = fit(A3, wt)
    # A tile whose inliers did not change has its final fit: only the others are refitted
    # (most tiles settle in one round), the same rounds as refitting all until none changes
    active = np.arange(T)
    for _ in range(rounds):
        mad = _abs_medians(h[active], wt[active])
        lim = 3.5 * np.maximum(_MAD_TO_STD * np.nan_to_num(mad), 1e-9)
        nw = (ok[active] & (np.abs(h[active]) <= lim[:, None])).astype(np.float64)
        moved = np.any(nw != wt[active], axis=1)
        if not moved.any():
            break
        active = active[moved]
        wt[active] = nw[moved]
        beta[active], h[active] = fit(A3[active], wt[active], active)
    # beta in (u, v, 1) -> the plane a x + b y + c = 1 / Z in normalized coordinates
    a = beta[:, 0] / sc[:, 0]
    b = beta[:, 1] / sc[:, 0]
    c = beta[:, 2] - a * xm[:, 0] - b * ym[:, 0]
    normal = np.stack([a, b, c], 1)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    sw = np.maximum(wt.sum(1, keepdims=True), 1e-12)
    mean = np.einsum("tn,tnk->tk", wt, P0) / sw
    normal = np.where((np.einsum("tk,tk->t", normal, mean) > 0)[:, None], -normal, normal)
    _, hq = fit(A6, wt)
    ns = wt.sum(1)
    vp = (wt * h * h).sum(1) / np.maximum(ns - 3.0, 1.0)
    vq = (wt * hq * hq).sum(1) / np.maximum(ns - 6.0, 1.0)
    ratio = vp / np.maximum(vq, 1e-30)
    return mean, normal, np.where(ok, h, 0.0), wt, ratio


@kernel
def _design(u: np.ndarray, v: np.ndarray, quadratic: bool) -> np.ndarray:
    """The (T, n) coordinates' design matrices, (T, n, 3) ``(u, v, 1)`` or (T, n, 6) ``(u,
    v, 1, u*u, u*v, v*v)``, C-contiguous: ``np.stack`` of those columns, without the
    columns as arrays."""
    T, n = u.shape
    k = 6 if quadratic else 3
    A = np.empty((T, n, k))
    for t in range(T):
        for i in range(n):
            a, b = u[t, i], v[t, i]
            A[t, i, 0] = a
            A[t, i, 1] = b
            A[t, i, 2] = 1.0
            if quadratic:
                A[t, i, 3] = a * a
                A[t, i, 4] = a * b
                A[t, i, 5] = b * b
    return A


# --- the fit ------------------------------------------------------------------------------


#: Distinct depths closer than this (relative) are one reported level.
QUANTUM_TOL = 1e-6


def quantization_floor(r: np.ndarray, z: np.ndarray) -> float:
    """The range noise a sensor that reports depth in steps has at least: the step (the
    median gap between the distinct depths of the points) over sqrt(12), along the ray.

    A structured-light camera reports disparity in eighths of a pixel: at 4 m with a
    1160 px focal length, depth steps of 18 mm. A flat tile that spans less than one step
    reads nearly one value, and a robust std of its residuals collapses (a 4-tile bin read
    2.4 mm among bins of 9-15 mm, and the fit, which weighs a bin by its inverse
    variance, followed it to 4.7 mm: every step then passed for an edge). The steps'
    own spread, step / sqrt(12), is what the tests must expect between neighbours. For a
    sensor without steps the distinct depths are as many as the points and the floor is
    negligible (a tenth of a millimetre over a 0.1 m bin of 1000 points).
    """
    r, z = np.asarray(r), np.asarray(z)
    if r.dtype == z.dtype == np.float64 and r.ndim == z.ndim == 1 and r.shape == z.shape:
        return float(_floor_kernel(r, z, np.sort(z)))  # the same, without the overheads
    u = np.unique(z)
    # one level stored at several roundings (z = range x ray in float32) is one level
    gaps = np.diff(u)
    gaps = gaps[gaps > QUANTUM_TOL * float(np.median(np.abs(u)))] if u.size > 1 else gaps
    if gaps.size == 0:
        return 0.0
    step = float(np.median(gaps))
    with np.errstate(invalid="ignore", divide="ignore"):
        ray = float(np.median(r / z))
    return step / math.sqrt(12.0) * (ray if math.isfinite(ray) else 1.0)


def _bin_std(row: dict[str, Any], estimator: str) -> float:
    """A range bin's std: the estimator's, at least the bin's quantization floor."""
    return max(row["std_mad"] if estimator == "mad" else row["std_clipped"], row["floor"])


def _robust_std(y: np.ndarray) -> float:
    return float(_MAD_TO_STD * _mad(np.asarray(y, dtype=np.float64)))


def median(x: np.ndarray) -> float:
    """``float(np.median(x))`` of a 1-D float64 array, bit for bit, by selection: NumPy's
    per-call overhead (tens of microseconds) is most of a small median's cost, and the
    noise stage takes hundreds per scan."""
    return float(_median(np.asarray(x, dtype=np.float64)))


def unique_runs(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``np.unique(t, return_inverse=True, return_counts=True)`` of 1-D integers, the
    same arrays; from the runs of equal values when ``t`` is sorted (the tiles' points:
    each tile's together, the tiles in ascending order), without NumPy's hashing."""
    t = np.asarray(t)
    if t.ndim == 1 and t.size and t.dtype.kind in "iu" and bool(np.all(t[1:] >= t[:-1])):
        first = np.flatnonzero(np.concatenate([[True], t[1:] != t[:-1]]))
        counts = np.diff(np.append(first, t.size))
        return t[first], np.repeat(np.arange(first.size), counts), counts
    return np.unique(t, return_inverse=True, return_counts=True)


def stable_order(keys: np.ndarray) -> np.ndarray:
    """``np.argsort(keys, kind="stable")`` of 1-D int64 ``keys``, the same permutation (a
    stable sort's is unique): by counting when their range is small (range bins), several
    times faster than NumPy's merge sort."""
    keys = np.asarray(keys)
    if keys.ndim == 1 and keys.size and keys.dtype == np.int64:
        lo, hi = int(keys.min()), int(keys.max())
        if hi - lo <= 4 * keys.size + 1024:
            return _counting_order(keys, lo, hi - lo + 1)
    return np.argsort(keys, kind="stable")


@kernel
def _counting_order(keys: np.ndarray, lo: int, span: int) -> np.ndarray:
    """The stable sorting permutation of ``keys`` (all in [lo, lo + span)) by counting."""
    start = np.zeros(span + 1, np.int64)
    for i in range(keys.shape[0]):
        start[keys[i] - lo + 1] += 1
    for v in range(span):
        start[v + 1] += start[v]
    out = np.empty(keys.shape[0], np.int64)
    for i in range(keys.shape[0]):
        v = keys[i] - lo
        out[start[v]] = i
        start[v] += 1
    return out


# --- exact medians by selection -------------------------------------------------------------
# A median is an order statistic (or the mean of two), so any exact selection gives NumPy's
# value. NumPy's ``np.median`` returns ``mean`` of the middle one or two values: the sum
# starts from 0.0, so ``0.0 + a`` (odd n) or ``(0.0 + a + b) / 2`` (even n), never -0.0; the
# kernels below compute exactly that, and NaN for a NaN anywhere (NumPy's nan check) or no
# values (its mean of nothing).


@kernel
def _select(a: np.ndarray, k: int, lo: int, hi: int) -> float:
    """The value of rank ``k`` in ``a[lo:hi + 1]`` (no NaN), reordering that range in place
    so that no value before ``k`` is above it and none after below (Hoare's selection, a
    median-of-three pivot: ties, common in quantized depths, split evenly)."""
    while True:
        if hi <= lo + 1:
            if hi == lo + 1 and a[hi] < a[lo]:
                a[lo], a[hi] = a[hi], a[lo]
            return a[k]
        mid = (lo + hi) >> 1
        a[mid], a[lo + 1] = a[lo + 1], a[mid]
        if a[lo] > a[hi]:
            a[lo], a[hi] = a[hi], a[lo]
        if a[lo + 1] > a[hi]:
            a[lo + 1], a[hi] = a[hi], a[lo + 1]
        if a[lo] > a[lo + 1]:
            a[lo], a[lo + 1] = a[lo + 1], a[lo]
        i, j = lo + 1, hi
        pivot = a[lo + 1]
        while True:
            i += 1
            while a[i] < pivot:
                i += 1
            j -= 1
            while a[j] > pivot:
                j -= 1
            if j < i:
                break
            a[i], a[j] = a[j], a[i]
        a[lo + 1] = a[j]
        a[j] = pivot
        if j >= k:
            hi = j - 1
        if j <= k:
            lo = i


#: Values from which a median first narrows the values down to a band around it
#: (:func:`_band`); fewer are selected among directly.
BAND_MIN = 1024


@kernel
def _median_inplace(a: np.ndarray, n: int) -> float:
    """``np.median(a[:n])`` bit for bit, reordering ``a[:n]``."""
    if n == 0:
        return np.nan
    for i in range(n):
        if np.isnan(a[i]):
            return np.nan
    k = (n - 1) // 2
    if n >= BAND_MIN:
        band, below = _band(a, n, k)
        j = k - below
        # the band holds ranks k (and k + 1 for even n): select there, else among all
        if 0 <= j and j + 1 - n % 2 < band.shape[0]:
            a, k, n_sel = band, j, band.shape[0]
        else:
            n_sel = n
    else:
        n_sel = n
    m = _select(a, k, 0, n_sel - 1)
    if n % 2 == 1:
        return 0.0 + m
    return (0.0 + m + _least_after(a, k, n_sel)) / 2.0


@kernel
def _least_after(a: np.ndarray, k: int, n: int) -> float:
    """The order statistic after rank ``k`` once :func:`_select` has placed it: the least
    of ``a[k + 1:n]``."""
    up = a[k + 1]
    for i in range(k + 2, n):
        up = min(up, a[i])
    return up


@kernel
def _band(a: np.ndarray, n: int, k: int) -> tuple[np.ndarray, int]:
    """The values of ``a[:n]`` (no NaN) between two pivots that likely bracket rank
    ``k``, and how many are below the band (Floyd and Rivest's sampling: the pivots are
    ranks about 3 standard errors either side of ``k`` in an evenly spaced sample of
    ``6 sqrt(n)``; the band is a tenth to a fifth of the values). Whether it brackets
    rank ``k`` is the caller's check. A pass without branches on the values' order:
    selecting among all costs a mispredicted branch per value and step."""
    s = min(n, int(6.0 * math.sqrt(n)))
    sample = np.empty(s)
    for j in range(s):
        sample[j] = a[(j * n) // s]
    ks = (k * s) // n
    d = int(1.5 * math.sqrt(s)) + 1
    i_lo, i_hi = max(ks - d, 0), min(ks + 1 + d, s - 1)
    p_lo = _select(sample, i_lo, 0, s - 1)
    p_hi = _select(sample, i_hi, i_lo, s - 1)
    band = np.empty(n)
    m = 0
    below = 0
    for i in range(n):
        x = a[i]
        below += x < p_lo
        band[m] = x
        m += (x >= p_lo) & (x <= p_hi)
    return band[:m], below


@kernel
def _median(x: np.ndarray) -> float:
    """``np.median(x)`` of a 1-D float64 array, bit for bit (``x`` is not changed)."""
    return _median_inplace(x.copy(), x.shape[0])


@kernel
def _mad(y: np.ndarray) -> float:
    """``np.median(np.abs(y - np.median(y)))`` of a 1-D float64 array, bit for bit."""
    n = y.shape[0]
    buf = y.copy()
    m = _median_inplace(buf, n)
    for i in range(n):
        buf[i] = abs(y[i] - m)
    return _median_inplace(buf, n)


@kernel
def _group_medians(x: np.ndarray, order: np.ndarray, starts: np.ndarray, stops: np.ndarray,
                   mad: bool) -> np.ndarray:
    """Per group g, the median of ``x[order[starts[g]:stops[g]]]`` (``mad``: the median of
    the absolute deviations from it, :func:`_mad`), bit for bit; NaN for an empty group."""
    out = np.empty(starts.shape[0])
    buf = np.empty(x.shape[0])
    dev = np.empty(x.shape[0])
    for g in range(starts.shape[0]):
        n = stops[g] - starts[g]
        for i in range(n):
            buf[i] = x[order[starts[g] + i]]
        m = _median_inplace(buf, n)
        if mad:
            for i in range(n):
                dev[i] = abs(x[order[starts[g] + i]] - m)
            m = _median_inplace(dev, n)
        out[g] = m
    return out


@kernel
def _abs_medians(h: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Per row t of (T, n) ``h``, the median of ``|h[t]|`` over ``w[t] > 0`` (NaN values
    skipped), NaN where none: ``nanmedian_last(np.where(w > 0, np.abs(h), np.nan))`` bit
    for bit (the values are never -0.0, so any exact selection gives its value)."""
    T, n = h.shape
    out = np.empty(T)
    buf = np.empty(n)
    for t in range(T):
        m = 0
        for i in range(n):
            if w[t, i] > 0 and not np.isnan(h[t, i]):
                buf[m] = abs(h[t, i])
                m += 1
        if m == 0:
            out[t] = np.nan
            continue
        k = (m - 1) // 2
        lo = _select(buf, k, 0, m - 1)
        # nanmedian_last's mean of the middle two, (lo + up) / 2 (not np.median's 0.0 + ...)
        out[t] = lo if m % 2 == 1 else (lo + _least_after(buf, k, m)) / 2.0
    return out


@kernel
def _lower_medians(x: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The lower median of each group ``x[starts[k]:starts[k] + counts[k]]``, (K,): the
    element of rank (count - 1) // 2 as a sort would place it (NaN last), an order
    statistic, so exact (found by selection, not a sort)."""
    out = np.empty(starts.shape[0])
    for k in range(starts.shape[0]):
        g = x[starts[k]:starts[k] + counts[k]].copy()
        m = 0  # the non-NaN values first, as a sort puts them
        for i in range(g.shape[0]):
            if not np.isnan(g[i]):
                g[m] = g[i]
                m += 1
        rank = (counts[k] - 1) // 2
        out[k] = _select(g, rank, 0, m - 1) if rank < m else np.nan
    return out


@kernel
def _group_distinct(t: np.ndarray, order: np.ndarray, starts: np.ndarray,
                    stops: np.ndarray) -> np.ndarray:
    """Per group g, ``np.unique(t[order[starts[g]:stops[g]]]).size`` (integers)."""
    out = np.zeros(starts.shape[0], np.int64)
    for g in range(starts.shape[0]):
        n = stops[g] - starts[g]
        if n == 0:
            continue
        v = t[order[starts[g]:stops[g]]]
        for i in range(1, n):
            if v[i] < v[i - 1]:  # in order already where a tile's points are together
                v = np.sort(v)
                break
        k = 1
        for i in range(1, n):
            if v[i] != v[i - 1]:
                k += 1
        out[g] = k
    return out


@kernel(error_model="numpy")
def _floor_kernel(r: np.ndarray, z: np.ndarray, u: np.ndarray) -> float:
    """:func:`quantization_floor` of 1-D float64 ``r``, ``z``, bit for bit, given ``u``,
    ``z`` sorted (NumPy's sort, vectorized, is several times numba's; ``u`` is reused)."""
    n = z.shape[0]
    for i in range(n):
        if np.isnan(z[i]):
            return 0.0  # np.unique keeps one NaN: the median |u| and every gap test are NaN
    m = 0  # the distinct depths, ascending, in u[:m]
    for i in range(n):
        if m == 0 or u[i] != u[m - 1]:
            u[m] = u[i]
            m += 1
    if m < 2:
        return 0.0
    buf = np.empty(m)
    if u[0] >= 0:  # |u| is u, ascending: its median by index
        h = (m - 1) // 2
        mid = 0.0 + abs(u[h]) if m % 2 else (0.0 + abs(u[h]) + abs(u[h + 1])) / 2.0
    else:
        for i in range(m):
            buf[i] = abs(u[i])
        mid = _median_inplace(buf, m)
    tol = QUANTUM_TOL * mid
    k = 0
    for i in range(m - 1):
        gap = u[i + 1] - u[i]
        if gap > tol:
            buf[k] = gap
            k += 1
    if k == 0:
        return 0.0
    step = _median_inplace(buf, k)
    q = np.empty(r.shape[0])
    for i in range(r.shape[0]):
        q[i] = r[i] / z[i]
    ray = _median_inplace(q, q.shape[0])
    return step / math.sqrt(12.0) * (ray if math.isfinite(ray) else 1.0)


def _group_floors(r: np.ndarray, z: np.ndarray, order: np.ndarray, starts: np.ndarray,
                  stops: np.ndarray) -> np.ndarray:
    """Per group g, :func:`quantization_floor` of the points ``order[starts[g]:stops[g]]``
    (1-D float64 ``r``, ``z``), bit for bit."""
    out = np.empty(len(starts))
    for g, (a, b) in enumerate(zip(starts, stops)):
        idx = order[a:b]
        rg, zg = r[idx], z[idx]
        out[g] = _floor_kernel(rg, zg, np.sort(zg))
    return out


def _clipped_std(y: np.ndarray, k: float = 3.0, iters: int = 10) -> float:
    """Standard deviation after iterative k-sigma clipping (starting from the MAD)."""
    s = _robust_std(y)
    keep = np.ones(y.size, dtype=bool)
    for _ in range(iters):
        c = float(np.mean(y[keep]))
        new = np.abs(y - c) <= k * max(s, 1e-12)
        if new.sum() < 3:
            break
        s = float(np.std(y[new], ddof=1))
        if np.array_equal(new, keep):
            break
        keep = new
    return s


def estimate_noise(
    scans: Sequence[Scan],
    masks: Sequence[npt.ArrayLike | None] | None = None,
    *,
    labels: Sequence[npt.ArrayLike | None] | None = None,
    bin_width: float = 0.1,
    min_points: int = 2000,
    min_tiles: int = 4,
    estimator: str = "mad",
    incidence: str = "model",
    terms: Sequence[str] = NOISE_TERMS,
    base: NoiseModel | None = None,
    patch: int = 16,
) -> tuple[NoiseModel, dict[str, Any]]:
    """Fit the range-noise model to the residuals of flat surfaces in real scans.

    Parameters
    ----------
    scans : sequence of Scan
        Scans with flat surfaces (walls, tables, box faces) over a spread of ranges.
    masks : sequence of (H, W) bool arrays or None, optional
        Per scan, the pixels that may be used.
    labels : sequence of (H, W) int arrays or None, optional
        Per scan, segment labels; tiles spanning two labels are skipped.
    bin_width : float
        Width of the range bins, metres.
    min_points, min_tiles : int
        A bin enters the fit only with at least this many points from this many tiles.
    estimator : {"mad", "clipped"}
        Per-bin standard deviation: 1.4826 * MAD (robust, exact for Gaussian noise; it
        overestimates uniform quantization noise by ~28 %), or the 3-sigma-clipped sample
        standard deviation. Both are reported.
    incidence : {"model", "ignore", "fit"}
        "model": each residual along the ray is multiplied by ``max(cos_incidence,
        min_cos)`` before binning, matching the NoiseModel's ``1 / cos`` factor, so the
        fitted model predicts the along-ray scatter at every incidence. "ignore": the raw
        along-ray residuals are binned (the model then over-predicts at oblique incidence,
        by ``1 / cos``); useful to compare with sensor data sheets quoted along the ray.
        "fit": the factor is ``max(cos_incidence, min_cos)**g`` with g of
        :data:`INCIDENCE_EXPONENTS` whose fitted model leaves the least scatter of the
        bins' stds around it (ties keep the smaller g); the returned model carries it.
    terms : sequence of {"sigma0", "k1", "k2"}
        Which terms of the model to fit; the others are 0.
    base : NoiseModel, optional
        Supplies ``sigma_angle`` and ``min_cos``, which are not estimated here.
    patch : int
        Tile side of the local plane fits, pixels.

    Returns
    -------
    model : NoiseModel
    report : dict
        ``bins`` (edges, metres), and per used bin ``range`` (median, m), ``count``,
        ``tiles``, ``std`` (the estimator's, m, at least ``floor``), ``std_mad``,
        ``std_clipped``, ``floor`` (:func:`quantization_floor`, m), ``mean_cos``,
        ``model_std`` (fitted, m, at cos = 1), ``used`` (entered the fit); ``fit_rel_rms``
        (RMS of std/model - 1 over the fitted bins), ``incidence_exponent`` (see Notes),
        ``row_corr`` (``value``, ``tiles``, ``median``, ``std_error``), ``correlation``
        (``lags_px``, ``along_rows``, ``along_columns``: the residual correlation at those
        pixel lags, within tiles), ``tails`` (``sigmas``, ``observed`` and ``normal`` rates
        of |residual| beyond them, ``n_points``),
        ``n_points``, ``n_tiles``, ``n_tiles_used``, ``tiles_rejected`` (by reason),
        ``n_scans``, ``estimator``, ``incidence``, ``terms``, ``underdetermined``, ``model``.

    Raises
    ------
    InputError
        If there are no scans, the masks/labels do not match, a parameter is out of range, or
        no range bin holds enough flat surface.

    Notes
    -----
    The model is linear in (sigma0**2, k1**2, k2**2), so the fit is a non-negative least
    squares on the binned variances, each row weighted by sqrt(count) / std**2 (the inverse
    of the relative standard error of a variance estimate). Over a short span of ranges the
    three terms are nearly collinear: NNLS then keeps the fewest terms that explain the
    data; pass ``terms`` to choose.

    ``incidence_exponent`` is g in std(along-ray residual) ~ cos_incidence**-g, measured
    within range bins: the model assumes g = 1. Far from 1 means the ``1 / cos`` factor of
    :class:`NoiseModel` does not describe this sensor.
    """
    scans = list(scans)
    if not scans:
        raise InputError("estimate_noise needs at least one scan")
    masks_l = list(masks) if masks is not None else [None] * len(scans)
    labels_l = list(labels) if labels is not None else [None] * len(scans)
    if len(masks_l) != len(scans) or len(labels_l) != len(scans):
        raise InputError(f"got {len(scans)} scans but {len(masks_l)} masks and "
                         f"{len(labels_l)} label images")
    if estimator not in ("mad", "clipped"):
        raise InputError(f"estimator must be 'mad' or 'clipped', got {estimator!r}")
    if incidence not in ("model", "ignore", "fit"):
        raise InputError(f"incidence must be 'model', 'ignore' or 'fit', got {incidence!r}")
    terms = tuple(terms)
    if not terms or any(t not in NOISE_TERMS for t in terms) or len(set(terms)) != len(terms):
        raise InputError(f"terms must be a non-empty subset of {NOISE_TERMS}, got {terms}")
    if not (np.isfinite(bin_width) and bin_width > 0):
        raise InputError(f"bin_width must be finite and > 0, got {bin_width}")
    base = base or NoiseModel()

    tiles = [tile_residuals(scan, m, patch=patch, labels=lab, min_valid=0.9,
                             max_outliers=0.05, max_curvature_ratio=1.5, min_cos=0.3)
             for scan, m, lab in zip(scans, masks_l, labels_l)]
    return fit_residuals(tiles, bin_width=bin_width, min_points=min_points,
                         min_tiles=min_tiles, estimator=estimator, incidence=incidence,
                         terms=terms, base=base)


def fit_residuals(
    tiles: Sequence[TileResiduals],
    *,
    bin_width: float = 0.1,
    min_points: int = 2000,
    min_tiles: int = 4,
    estimator: str = "mad",
    incidence: str = "model",
    terms: Sequence[str] = NOISE_TERMS,
    base: NoiseModel | None = None,
    diagnostics: bool = True,
) -> tuple[NoiseModel, dict[str, Any]]:
    """:func:`estimate_noise` on flat tiles already cut (one :func:`tile_residuals` per
    scan); same parameters and returns.

    ``diagnostics=False`` leaves out what only the calibration report reads (the rows'
    ``std_clipped`` when ``estimator="mad"``, ``incidence_exponent``, ``correlation``,
    ``tails``, ``fit_rel_rms``: None), for the per-scan model of the pipeline; the model
    is the same, bit for bit.
    """
    terms = tuple(terms)
    base = base or NoiseModel()
    rs, ys, cs, ts, ds, shares = [], [], [], [], [], []
    lag_sums = np.zeros((2, len(CORRELATION_LAGS), 3))
    all_r, all_c, all_e = [], [], []  # every point of the accepted tiles, for the tails
    n_tiles = 0
    rejected: dict[str, int] = {}
    for i, t in enumerate(tiles):
        inl = t.inlier
        rs.append(t.range[inl])
        cs.append(t.cos_incidence[inl])
        # The model divides range noise by max(cos, min_cos); undo that per point.
        f = np.maximum(t.cos_incidence[inl], base.min_cos) if incidence == "model" else 1.0
        ys.append(t.residual[inl] * f)
        ts.append(t.tile[inl] + (i << 32))
        ds.append(t.depth[inl])
        shares.append(t.row_share)
        lag_sums += t.lag_sums
        all_r.append(t.range)
        all_c.append(t.cos_incidence)
        all_e.append(t.residual)
        n_tiles += t.n_tiles
        for k, v in t.rejected.items():
            rejected[k] = rejected.get(k, 0) + v
    r, y, c, tile, d = (np.concatenate(a) for a in (rs, ys, cs, ts, ds))
    ok = np.isfinite(r) & np.isfinite(y)
    r, y, c, tile, d = r[ok], y[ok], c[ok], tile[ok], d[ok]
    report: dict[str, Any] = {
        "n_scans": len(tiles), "n_points": int(r.size), "n_tiles": n_tiles,
        "n_tiles_used": int(unique_runs(tile)[0].size), "tiles_rejected": rejected,
        "estimator": estimator, "incidence": incidence, "terms": list(terms),
        "bin_width": float(bin_width),
    }
    if r.size == 0:
        raise InputError("no flat surface found to estimate the noise from "
                         f"({n_tiles} tiles examined)")

    lo = np.floor(r.min() / bin_width) * bin_width
    nb = int(np.ceil((r.max() - lo) / bin_width)) or 1
    edges = lo + bin_width * np.arange(nb + 1)
    which = np.clip(((r - lo) / bin_width).astype(np.int64), 0, nb - 1)
    # each bin's points, in their order (the same selection as ``which == b``, found once)
    order = stable_order(which)
    cuts = np.searchsorted(which[order], np.arange(nb + 1))
    members = [order[cuts[b]:cuts[b + 1]] for b in range(nb)]
    clipped = estimator == "clipped" or diagnostics
    # the bins' medians, tile counts and floors in one pass each (bit for bit the per-bin
    # NumPy calls: a few hundred small medians per scan cost more in overhead than work)
    starts, stops = cuts[:-1], cuts[1:]
    r_med = _group_medians(r, order, starts, stops, False)
    mad = _group_medians(y, order, starts, stops, True)
    n_tile = _group_distinct(tile, order, starts, stops)
    floors = _group_floors(r, d, order, starts, stops)
    rows = []
    for b in range(nb):
        sel = members[b]
        if not sel.size:
            continue
        yb = y[sel]
        tiles_b = int(n_tile[b])
        row: dict[str, Any] = {
            "lo": float(edges[b]), "hi": float(edges[b + 1]),
            "range": float(r_med[b]), "count": int(sel.size), "tiles": tiles_b,
            "std_mad": float(_MAD_TO_STD * mad[b]),
            "std_clipped": _clipped_std(yb) if clipped else None,
            "mean_cos": float(np.mean(c[sel])),
            "floor": float(floors[b]),
        }
        row["std"] = _bin_std(row, estimator)
        row["used"] = bool(row["count"] >= min_points and tiles_b >= min_tiles
                           and row["std"] > 0)
        rows.append(row)
    report["bins"] = [float(e) for e in edges]
    report["rows"] = rows
    used = [row for row in rows if row["used"]]
    if not used:
        raise InputError(
            f"not enough flat surface to estimate the noise: no range bin has {min_points} "
            f"points from {min_tiles} flat tiles ({r.size} points in total)"
        )
    e_ray = y / np.maximum(c, base.min_cos) if incidence == "model" else y
    report["incidence_exponent"] = _incidence_exponent(r, c, e_ray, used) if diagnostics else None
    g = 1.0
    if incidence == "fit":
        # The incidence law that explains the binned scatter best. The within-bin slope
        # (the report's incidence_exponent) is too noisy to use: range and incidence go
        # together on a tilted plane.
        best = math.inf
        c_min = np.maximum(c, base.min_cos)
        for g_try in INCIDENCE_EXPONENTS:
            y_try = e_ray * c_min ** g_try
            # g = 0 on residuals binned as they are (incidence="fit") gives the same bits
            # as the bins above: their MADs are those
            same = np.array_equal(y_try.view(np.uint64), y.view(np.uint64))
            mad_try = mad if same else _group_medians(y_try, order, starts, stops, True)
            rows_try = [dict(row) for row in rows]
            for row in rows_try:
                b = int(round((row["lo"] - lo) / bin_width))
                row["std_mad"] = float(_MAD_TO_STD * mad_try[b])
                row["std_clipped"] = _clipped_std(y_try[members[b]]) if clipped else None
                row["std"] = _bin_std(row, estimator)
            used_try = [row for row in rows_try if row["used"] and row["std"] > 0]
            if not used_try:
                continue
            m_try, _ = fit_bins(used_try, terms, base)
            # scatter of a bin around the model, in ln, weighted by its points
            s = np.array([row["std"] for row in used_try])
            w = np.array([row["count"] for row in used_try], dtype=np.float64)
            r_b = np.array([row["range"] for row in used_try])
            cost = float(np.sum(w * np.log(s / m_try.sigma_range(r_b)) ** 2) / w.sum())
            if cost < best - 1e-12:
                best, g, rows, used = cost, g_try, rows_try, used_try
    model, x = fit_bins(used, terms, base)
    model = dataclasses.replace(model, incidence_exponent=g)
    # the row-shared share of the variance: the mean of the tiles' ANOVA estimates (each
    # noisy, some negative; a little low: scans simulated with 0.276 give 0.26)
    share = np.concatenate(shares)
    share = share[np.isfinite(share)]
    row_corr = float(np.clip(share.mean(), 0.0, 0.95)) if share.size else 0.0
    model = dataclasses.replace(model, row_corr=row_corr)
    report["row_corr"] = {"value": row_corr, "tiles": int(share.size),
                          "median": float(np.median(share)) if share.size else None,
                          "std_error": float(share.std() / np.sqrt(share.size))
                          if share.size > 1 else None}
    if not diagnostics:
        report.update(correlation=None, tails=None, fit_rel_rms=None,
                      underdetermined=len(used) < len(terms), model=model.to_dict())
        return model, report
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = lag_sums[..., 0] / np.sqrt(lag_sums[..., 1] * lag_sums[..., 2])
    report["correlation"] = {
        "lags_px": list(CORRELATION_LAGS),
        "along_rows": [None if not np.isfinite(v) else float(v) for v in corr[0]],
        "along_columns": [None if not np.isfinite(v) else float(v) for v in corr[1]],
    }
    ra, ca, ea = (np.concatenate(a) for a in (all_r, all_c, all_e))
    fin = np.isfinite(ea)
    ra, ca, ea = ra[fin], ca[fin], ea[fin]
    za = np.abs(ea) / model.sigma_range(ra, ca if incidence != "ignore" else 1.0)
    report["tails"] = {
        "sigmas": list(TAIL_SIGMAS), "n_points": int(za.size),
        "observed": [float(np.mean(za > k)) for k in TAIL_SIGMAS] if za.size else None,
        "normal": [math.erfc(k / math.sqrt(2.0)) for k in TAIL_SIGMAS],
    }
    for row in rows:
        row["model_std"] = float(model.sigma_range(row["range"]) * 1.0)
    rel = np.array([row["std"] / row["model_std"] - 1.0 for row in used])
    report["fit_rel_rms"] = float(np.sqrt(np.mean(rel**2)))
    report["underdetermined"] = len(used) < len(terms)
    report["model"] = model.to_dict()
    return model, report


def _incidence_exponent(
    r: np.ndarray, c: np.ndarray, e_ray: np.ndarray, used: list[dict[str, Any]],
    min_points: int = 500,
) -> float | None:
    """Exponent g of std(along-ray residual) ~ cos_incidence**-g, pooled over range bins.

    A diagnostic: the NoiseModel assumes g = 1; structured-light sensors often show less
    (their noise is mostly along the ray whatever the surface's slant). None when no range
    bin spans enough incidences.
    """
    xs, ys = [], []
    for row in used:
        in_bin = (r >= row["lo"]) & (r < row["hi"])
        lx, ly = [], []
        for clo in np.arange(0.0, 1.0, 0.15):
            q = in_bin & (c >= clo) & (c < clo + 0.15)
            if q.sum() >= min_points:
                s = _robust_std(e_ray[q])
                if s > 0:
                    lx.append(np.log(np.median(c[q])))
                    ly.append(np.log(s))
        if len(lx) >= 2:  # remove the bin's own level: only the slope is pooled
            xs += list(np.asarray(lx) - np.mean(lx))
            ys += list(np.asarray(ly) - np.mean(ly))
    x, yv = np.asarray(xs), np.asarray(ys)
    if x.size < 2 or not np.any(x != 0):
        return None
    return float(-(x @ yv) / (x @ x))


def nnls_few(A: np.ndarray, b: np.ndarray, rtol: float = 1e-10) -> np.ndarray:
    """Non-negative least squares, ``argmin ||A x - b||`` over ``x >= 0``, exactly, for a
    few unknowns: the least-squares solution on the support where it is optimal.

    What ``scipy.optimize.nnls`` returns (to rounding: ``tests/test_noise.py`` compares
    them), without importing ``scipy.optimize``, which costs the first scan of every process
    0.15 s. The minimum is the least-squares solution on its own support (its gradient
    vanishes there), so it is among the supports' solutions. The supports are tried from
    the largest down, and the first feasible solution whose gradient points out of the
    feasible set on every other unknown (the KKT conditions, to rounding) is it: usually
    after two or three of the seven supports of three unknowns. Where rounding fails every
    such check, the feasible solution with the least residual is returned, the same point.

    Parameters
    ----------
    A : (m, n) float64, n <= 6 (2**n supports)
    b : (m,) float64
    rtol : float
        A gradient component within ``rtol`` of its scale (``|A|^T |b|``) is zero.

    Returns
    -------
    x : (n,) float64, x >= 0
    """
    n = A.shape[1]
    if n > 6:
        raise ValueError(f"nnls_few: {n} unknowns, at most 6")
    tol = rtol * (np.abs(A).T @ np.abs(b)) + 1e-300
    best, best_r = np.zeros(n), float(b @ b)
    if (A.T @ b <= tol).all():  # x = 0 is optimal
        return best
    for cols, out in _supports(n):
        sol = np.linalg.lstsq(A[:, cols], b, rcond=None)[0]
        if sol.min() < 0:
            continue
        x = np.zeros(n)
        x[cols] = sol
        res = A @ x - b
        if not len(out) or (A[:, out].T @ res >= -tol[out]).all():
            return x
        r = float(res @ res)
        if r < best_r:
            best, best_r = x, r
    return best


@functools.lru_cache(maxsize=8)
def _supports(n: int) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """The non-empty supports of n unknowns, largest first: (in, out) column indices."""
    masks = sorted(range(1, 1 << n), key=lambda k: (-k.bit_count(), k))
    return tuple((np.array([j for j in range(n) if k >> j & 1]),
                  np.array([j for j in range(n) if not k >> j & 1], dtype=np.intp))
                 for k in masks)


def fit_bins(
    used: list[dict[str, Any]], terms: tuple[str, ...], base: NoiseModel
) -> tuple[NoiseModel, np.ndarray]:
    """The range terms fitted to per-bin stds (rows with ``range``, ``std``, ``count``) by
    non-negative least squares on the variances; ``base`` supplies the other terms."""
    r = np.array([row["range"] for row in used])
    s = np.array([row["std"] for row in used])
    n = np.array([row["count"] for row in used], dtype=np.float64)
    cols = {"sigma0": np.ones_like(r), "k1": r**2, "k2": r**4}
    A = np.stack([cols[t] for t in terms], 1)
    wt = np.sqrt(n) / s**2
    x = nnls_few(A * wt[:, None], s**2 * wt)
    params = dict.fromkeys(NOISE_TERMS, 0.0)
    for t, v in zip(terms, x):
        params[t] = float(np.sqrt(v))
    if params["sigma0"] == params["k1"] == params["k2"] == 0:
        raise InputError("the measured range noise is zero; cannot fit a noise model")
    model = NoiseModel(sigma0=params["sigma0"], k1=params["k1"], k2=params["k2"],
                       sigma_angle=base.sigma_angle, min_cos=base.min_cos)
    return model, x


def noise_toml(model: NoiseModel) -> str:
    """The model as a TOML ``[noise]`` table, loadable with ``boxloc --config``."""
    import tomli_w

    return tomli_w.dumps({"noise": model.to_dict()})

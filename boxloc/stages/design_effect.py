"""How much a count of noise exceedances over a face varies more than a binomial count,
where the scan's noise is spatially correlated (its model's ``row_corr``,
``corr_px_rows``, ``corr_px_cols``).

A test that counts the points beyond ``k`` standard deviations (``VERIFY_EXPOSED``: points
in front of a face's plane) takes them as independent draws. Structured-light and stereo
sensors match windows of pixels and share an offset along each image row: on the
development pallets a quarter to a third of the noise variance was common to a row. Then
the points beyond ``k`` come in runs along rows, and a face's count of them varies several
times more than a binomial's: a flat layer of four tops at 2.3 m had 0.6 % of its core's
points in front and 0.4 % behind, and the sign test called it covered.

The *design effect* D of a set of n points is the variance of their count over the
binomial's, 1 + (1/n) sum over ordered pairs i != j of c(rho_ij), with c the correlation of
two points' exceedance indicators (:func:`exceedance_correlation`)
and rho_ij the noise model's correlation of their ranges:

* in one image row, ``dc`` pixels apart: r + (1 - r) exp(-dc / L_rows);
* ``dr`` rows apart: (1 - r) exp(-dr / L_cols) exp(-dc / L_rows) (the row offset r is
  the row's own),

with r = ``row_corr`` and a length of 0 meaning no correlation along that axis. A count
of x exceedances over n points then weighs as x / D of n / D independent ones.

The sum runs over each row's points as if they were contiguous (a face's holes make it an
overestimate: the test errs toward exposed). Rows of different groups (a face's cells) do
not pair. White noise (all three 0) gives D = 1 exactly.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt
from scipy import special

from boxloc.scan import NoiseModel

#: Correlations below this are left out of the sums (their pairs' exceedance correlation
#: is below 1e-4 at the levels used).
MIN_RHO = 1e-3


def _reach(length: float, scale: float) -> int:
    """Pixels within which scale * exp(-d / length) stays above :data:`MIN_RHO`."""
    if not (length > 0 and scale > MIN_RHO):
        return 0
    return int(math.ceil(length * math.log(scale / MIN_RHO)))


def _decay(d: np.ndarray, length: float) -> np.ndarray:
    """exp(-d / length), or 1 at d = 0 and 0 beyond for a length of 0."""
    if length > 0:
        return np.exp(-d / length)
    return (d == 0).astype(np.float64)


def _pair_sum(n: np.ndarray, x: np.ndarray) -> np.ndarray:
    """sum_{d=1}^{n-1} (n - d) x[d-1] for each n (x zero beyond its end)."""
    if not len(x):
        return np.zeros(len(n))
    d = np.arange(1, len(x) + 1, dtype=np.float64)
    X1 = np.concatenate([[0.0], np.cumsum(x)])
    X2 = np.concatenate([[0.0], np.cumsum(d * x)])
    m = np.minimum(np.maximum(n - 1, 0), len(x)).astype(np.int64)
    return n * X1[m] - X2[m]


def exceedance_correlation(k: float, rho: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """How two standard normal samples of correlation ``rho`` exceed ``k`` together.

    With p = P(z > k) and U(rho) = P(z1 > k, z2 > k), from Owen's T function as
    U(rho) = p - 2 T(k, sqrt((1 - rho) / (1 + rho))) (so U(0) = p^2, U(1) = p), and
    P(z1 > k, z2 < -k) = U(-rho):

    * ``front``: the correlation of the indicators 1[z > k], (U(rho) - p^2) / (p (1 - p));
    * ``sign``: that of 1[z > k] - 1[z < -k] (variance 2 p, mean 0),
      (U(rho) - U(-rho)) / p.

    A count of exceedances over n samples of mean pair correlation c has n (1 + (n - 1) c)
    times the variance of one sample's indicator; both are far below rho (at k 2.576, rho
    0.27 gives 0.027 and 0.031), which is why they are needed: rho itself would overstate it.

    Parameters
    ----------
    k : float
        The level, > 0 (standard deviations).
    rho : array_like
        Correlations in [0, 1].

    Returns
    -------
    front, sign : ndarray
        Float64 of the shape of ``rho``, in [0, 1].
    """
    r = np.clip(np.asarray(rho, dtype=np.float64), 0.0, 1.0)
    p = float(special.ndtr(-k))

    def upper(c: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore"):
            a = np.sqrt((1.0 - c) / np.maximum(1.0 + c, 1e-300))
        return np.asarray(p - 2.0 * special.owens_t(k, a))

    u, v = upper(r), upper(-r)
    front = np.clip((u - p * p) / (p * (1.0 - p)), 0.0, 1.0)
    sign = np.clip((u - v) / p, 0.0, 1.0)
    return front, sign


def exceedance_design_effects(rows: np.ndarray, groups: np.ndarray, n_groups: int,
                              k: float, noise: NoiseModel) -> tuple[np.ndarray, np.ndarray]:
    """The design effects of exceedance counts over groups of pixels.

    Parameters
    ----------
    rows : (n,) int
        Image row of each point.
    groups : (n,) int
        Group of each point, in [0, n_groups).
    n_groups : int
    k : float
        The level the points are counted beyond, standard deviations.
    noise : NoiseModel
        Its ``row_corr``, ``corr_px_rows`` and ``corr_px_cols``.

    Returns
    -------
    front, sign : (n_groups,) float64
        >= 1: for a count of points beyond +k, and for the difference of the counts
        beyond +k and below -k (the sign test's). 1 for a group without points.
    """
    one = np.ones(n_groups)
    r = float(noise.row_corr)
    Lr, Lc = float(noise.corr_px_rows), float(noise.corr_px_cols)
    if not (r > 0 or noise.correlated) or not len(rows):
        return one, one.copy()
    rows = np.asarray(rows, np.int64)
    groups = np.asarray(groups, np.int64)
    Kc = _reach(Lc, 1.0 - r)
    span = int(rows.max()) + 2 + Kc  # a row dr below never reaches the next group's keys
    key = groups * span + rows
    # np.unique(key, return_counts=True), the keys being small integers: a count per key
    counts = np.bincount(key, minlength=n_groups * span)
    uk = np.flatnonzero(counts)
    n = counts[uk]
    g = uk // span
    n = n.astype(np.float64)
    n_g = np.bincount(g, weights=n, minlength=n_groups)
    tot_f = np.zeros(n_groups)
    tot_s = np.zeros(n_groups)
    # pairs in one row: the row offset r between all of them, and the short range on top
    cf_r, cs_r = exceedance_correlation(k, r)
    K = _reach(Lr, 1.0 - r)
    d = np.arange(1, K + 1, dtype=np.float64)
    cf, cs = exceedance_correlation(k, r + (1.0 - r) * _decay(d, Lr))
    within_f = n * (n - 1) * cf_r + 2.0 * _pair_sum(n, cf - cf_r)
    within_s = n * (n - 1) * cs_r + 2.0 * _pair_sum(n, cs - cs_r)
    tot_f += np.bincount(g, weights=within_f, minlength=n_groups)
    tot_s += np.bincount(g, weights=within_s, minlength=n_groups)
    # pairs dr rows apart, over the overlap of the two rows' runs
    for dr in range(1, Kc + 1):
        scale = (1.0 - r) * math.exp(-dr / Lc)
        K2 = _reach(Lr, scale)
        d = np.arange(0, K2 + 1, dtype=np.float64)
        yf, ys = exceedance_correlation(k, scale * _decay(d, Lr))
        j = np.searchsorted(uk, uk + dr)
        j = np.minimum(j, len(uk) - 1)
        has = uk[j] == uk + dr
        if not has.any():
            continue
        m = np.minimum(n[has], n[j[has]])
        cross_f = 2.0 * (m * yf[0] + 2.0 * _pair_sum(m, yf[1:]))
        cross_s = 2.0 * (m * ys[0] + 2.0 * _pair_sum(m, ys[1:]))
        tot_f += np.bincount(g[has], weights=cross_f, minlength=n_groups)
        tot_s += np.bincount(g[has], weights=cross_s, minlength=n_groups)
    with np.errstate(invalid="ignore", divide="ignore"):
        D_f = np.where(n_g > 0, 1.0 + tot_f / np.maximum(n_g, 1.0), 1.0)
        D_s = np.where(n_g > 0, 1.0 + tot_s / np.maximum(n_g, 1.0), 1.0)
    return np.maximum(D_f, 1.0), np.maximum(D_s, 1.0)


#: Side of the tiles over which the scan's noise measured how its exceedances vary and
#: correlate, pixels (:data:`boxloc.stages.scan_noise.PATCH_PX`).
EXCEED_TILE_PX = 16


def patch_factor(rows: np.ndarray, cols: np.ndarray, noise: NoiseModel) -> float:
    """How many times more a count over the pixels (rows, cols) varies than
    ``noise.exceed_dispersion`` says per tile, where the tiles' counts correlate
    (``noise.exceed_corr_px``): 1 + sum over pairs of distinct :data:`EXCEED_TILE_PX` tiles
    s != t of exp(-d_st / L) sqrt(n_s n_t) / n, with n_t the pixels in tile t and d_st the
    distance of the tiles' centres in pixels.

    ``exceed_dispersion`` is measured tile by tile, so it holds for a count over one tile;
    a face's core spans many, and where the noise's patches are larger than a tile the
    core's count varies more (a count x of the tiles' Var(x_t) = D n_t p (1 - p) and
    correlation rho_st has Var = D p (1 - p) (n + sum_{s != t} rho_st sqrt(n_s n_t))).
    1 without a correlation or pixels.
    """
    length = float(noise.exceed_corr_px)
    if not length > 0 or rows.size == 0:
        return 1.0
    ty = np.asarray(rows, np.int64) // EXCEED_TILE_PX
    tx = np.asarray(cols, np.int64) // EXCEED_TILE_PX
    ty, tx = ty - ty.min(), tx - tx.min()
    H, W = int(ty.max()) + 1, int(tx.max()) + 1
    n = np.bincount(ty * W + tx, minlength=H * W).astype(np.float64).reshape(H, W)
    if np.count_nonzero(n) < 2:
        return 1.0
    # the pair sum as one filtering of the tiles' sqrt(n) by the correlation over every
    # offset the grid holds (zero at offset 0): O(grid + kernel) memory, where the pairs
    # of a 1280x960 face's 4,800 tiles would take 23 million
    w = np.sqrt(n)
    dy, dx = np.arange(-(H - 1), H), np.arange(-(W - 1), W)
    rho = np.exp(-EXCEED_TILE_PX * np.hypot(dy[:, None], dx[None, :]) / length)
    rho[H - 1, W - 1] = 0.0
    s = cv2.filter2D(w, -1, rho, borderType=cv2.BORDER_CONSTANT)
    return 1.0 + float(np.sum(w * s)) / float(n.sum())

"""The scan's own noise model: estimated from its flat regions before the edge stage.

Every test of the pipeline scales its statistic by the range-noise model. A model
configured for one sensor and used on another makes every test fire at the wrong rate
(with the true noise at 2x the model a chi-square(1) test at alpha = 0.01 fires at 0.20), so
by default (``Config.noise_auto``) each scan gets the model fitted to its own flat tiles
(:func:`boxloc.calibrate.noise.tile_residuals`,
:func:`boxloc.calibrate.noise.fit_residuals`): the range terms
``sigma0``, ``k1``, ``k2``, the incidence law (``incidence_exponent``) and the row-shared
share ``row_corr``. The terms a single scan
cannot measure (``sigma_angle``, ``min_cos``, ``edge_px``) come from the config's model.

Whatever the source, the scan's residuals are tested against the model in use
(``NOISE_FIT``), so a log says when a pinned model is wrong for the scan. How heavy the
tails are is recorded (``tails``) but not tested: flat tiles that hold a few pixels of a
neighbouring surface put outliers beyond 4 sigma even under Gaussian noise (the simulator's
give 3x a normal's rate), so a tail test would not keep its level.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from boxloc.calibrate.noise import (
    CORRELATION_LAGS,
    NOISE_TERMS,
    TAIL_SIGMAS,
    TileResiduals,
    _group_floors,
    _lower_medians,
    fit_bins,
    fit_residuals,
    median,
    stable_order,
    tile_residuals,
    unique_runs,
)
from boxloc.config import Config
from boxloc.distributions import chi2_isf, norm_isf, t_sf
from boxloc.errors import InputError
from boxloc.kernels import kernel
from boxloc.products import NOISE_FIELDS, NoiseEstimate, NoiseSource
from boxloc.scan import NoiseModel, Scan
from boxloc.stats import TestKind, TestTable

__all__ = ["estimate_scan_noise", "exceedance", "fit_warning", "scale_margin", "MIN_FLAT_TILES",
           "PATCH_PX"]

#: Side of the flat tiles, pixels: small enough that box tops and floors are flat over a
#: tile at the resolutions seen (320x240 to 1280x960), large enough for a robust std.
PATCH_PX = 16
#: Flat tiles a scan needs for its own model (24 tiles of 16x16: ~6000 residuals); fewer
#: and the config's model is used.
MIN_FLAT_TILES = 24
#: Tiles examined at most (every k-th tile along rows and columns beyond it): the estimate
#: needs hundreds, not the 1200 of a 640x480 scan.
MAX_TILES = 400
#: Flat tiles a range bin needs to enter the fit and the NOISE_FIT test.
MIN_BIN_TILES = 4
#: Flat tiles a range bin needs to enter the NOISE_FIT test (its standard error comes from
#: their spread).
MIN_TEST_TILES = 10
#: Width of the range bins, metres.
BIN_WIDTH = 0.1


def estimate_scan_noise(scan: Scan, config: Config) -> NoiseEstimate:
    """The noise model for this scan and the tests of its residuals against it.

    Parameters
    ----------
    scan : Scan
    config : Config
        ``noise_auto`` chooses estimation; ``noise`` is the fallback (and the pinned model),
        and supplies ``sigma_angle``, ``min_cos`` and ``edge_px``.

    Returns
    -------
    NoiseEstimate
        Deterministic: a function of the scan's ranges and the config only.
    """
    nominal = config.noise
    H, W = scan.shape
    step = max(1, math.ceil(math.sqrt((H // PATCH_PX) * (W // PATCH_PX) / MAX_TILES)))
    tiles = tile_residuals(scan, None, patch=PATCH_PX, labels=None, min_valid=0.9,
                           max_outliers=0.05, max_curvature_ratio=1.5, min_cos=0.3,
                           step=step)
    corr = _correlation(tiles)
    model, source, reason = nominal, NoiseSource.CONFIG, "the config pins the noise model"
    if config.noise_auto:
        model, source, reason = _auto(scan, tiles, corr, nominal, config.alpha)
    z = _z(tiles, model)  # the flat tiles' points in the model's sigmas (their outliers too)
    grid_width = -(-(W // PATCH_PX) // step)
    if source == NoiseSource.SCAN:
        rate, dispersion, corr_px = exceedance(
            z, tiles.tile[np.isfinite(tiles.residual)], config.alpha, grid_width,
            PATCH_PX * step)
        model = dataclasses.replace(model, exceed_rate=rate, exceed_dispersion=dispersion,
                                    exceed_corr_px=corr_px)
    bins, tile_corr, pooled, tests = _fit_tests(tiles, model, config.alpha, grid_width)
    tails = _tail_rates(z)
    return NoiseEstimate(
        source=int(source), reason=reason,
        model=_as_array(model), nominal=_as_array(nominal),
        n_tiles=int(tiles.n_tiles), n_tiles_used=int(tiles.n_accepted),
        n_points=int(tiles.inlier.sum()),
        bin_range=bins[0], bin_tiles=bins[1], bin_std=bins[2], bin_model_std=bins[3],
        bin_z=bins[4], correlation=corr, tails=tails, tests=tests, bin_design=bins[5],
        bin_dof=bins[6], tile_correlation=tile_corr, fit_all=pooled,
    )


def fit_warning(noise: NoiseEstimate) -> str | None:
    """A one-line warning when the scan's residuals reject the model in use, else None."""
    fit = noise.tests.of_kind(TestKind.NOISE_FIT)
    if len(fit) == 0 or bool(fit.accepted.all()):
        return None
    i = int(np.argmax(noise.bin_z))
    ratio = noise.bin_std[i] / noise.bin_model_std[i]
    advice = ("set noise_auto = true, or calibrate the sensor (boxloc calibrate-noise)"
              if noise.source == NoiseSource.CONFIG else "the scan's own model does not fit "
              "its flat regions either: its noise is not a function of range alone")
    return (f"the noise model does not fit this scan (NOISE_FIT z = {fit.statistic[0]:.1f} > "
            f"{fit.critical[0]:.1f}): at {noise.bin_range[i]:.2f} m its flat surfaces scatter "
            f"{ratio:.2f}x the model's sigma, so every test fires at the wrong rate; {advice}")


def _as_array(model: NoiseModel) -> np.ndarray:
    return np.array([getattr(model, k) for k in NOISE_FIELDS], dtype=np.float64)


def _auto(scan: Scan, tiles: TileResiduals, corr: np.ndarray, nominal: NoiseModel,
          alpha: float) -> tuple[NoiseModel, NoiseSource, str]:
    if tiles.n_accepted < MIN_FLAT_TILES:
        few = (f"{tiles.n_accepted} flat tiles of {PATCH_PX}x{PATCH_PX} px, fewer than "
               f"{MIN_FLAT_TILES}")
        model = _from_differences(scan, nominal)
        if model is None:
            return nominal, NoiseSource.FALLBACK, (
                f"{few}, and too few smooth scan lines: the config's model")
        return model, NoiseSource.DIFFERENCES, f"{few}: fitted to second differences"
    try:
        fitted, report = fit_residuals([tiles], bin_width=BIN_WIDTH,
                                       min_points=MIN_BIN_TILES * PATCH_PX**2 // 2,
                                       min_tiles=MIN_BIN_TILES, base=nominal,
                                       incidence="fit", diagnostics=False)
    except InputError as e:
        return nominal, NoiseSource.FALLBACK, f"no fit ({e}): the config's model"
    # a row-shared share the tiles cannot tell from 0 (one-sided z at alpha) is 0: the
    # seam tests' row term costs time and an estimate of 0.01 is the ANOVA's noise
    rc = report["row_corr"]
    se = rc["std_error"]
    row_corr = fitted.row_corr if se and fitted.row_corr > norm_isf(alpha) * se else 0.0
    along_rows, along_cols = corr
    model = NoiseModel(sigma0=fitted.sigma0, k1=fitted.k1, k2=fitted.k2,
                       sigma_angle=nominal.sigma_angle, min_cos=nominal.min_cos,
                       edge_px=nominal.edge_px, row_corr=row_corr,
                       incidence_exponent=fitted.incidence_exponent,
                       corr_px_rows=correlation_length(along_rows),
                       corr_px_cols=correlation_length(along_cols))
    used = sum(1 for row in report["rows"] if row["used"])
    return model, NoiseSource.SCAN, (
        f"fitted to {tiles.n_accepted} flat tiles ({report['n_points']} points, "
        f"{used} range bins)")


def exceedance(z: np.ndarray, tile: np.ndarray, alpha: float, grid_width: int = 0,
               step_px: float = PATCH_PX) -> tuple[float, float, float]:
    """How often a flat surface's points lie beyond the point test's critical value, how
    patchy those points are, and how far the patches reach: :attr:`NoiseModel.exceed_rate`,
    :attr:`NoiseModel.exceed_dispersion` and :attr:`NoiseModel.exceed_corr_px`.

    ``z`` (n,) are the flat tiles' points (their plane-fit outliers too: a heavy tail is
    such points) as |residual| over the model's sigma, ``tile`` (n,) their tiles; a point
    beyond the normal's z at ``alpha / 2`` exceeds. Robust over the tiles: a few tiles
    that hold a neighbouring surface's pixels put many exceedances in one place on any
    sensor (a development laser pile: a mean two-sided share of 6.4 % and a variance ratio
    of 180, against the median tile's 1.6 % and an interquartile ratio of 2.2), so the
    rate is the median tile's, and the dispersion the counts' interquartile range (as a
    normal's sigma) squared over their binomial variance at that rate.

    The reach is from the correlation rho of neighbouring tiles' counts (on the tile grid
    of ``grid_width`` tiles a row, ``step_px`` pixels apart; along rows and columns
    pooled; the counts' deviations winsorized at 3 of their robust sigmas):
    ``-step_px / ln rho`` where rho is significant at ``alpha`` (above
    z_{1 - alpha} / sqrt(pairs)), else 0. One step's correlation, no fit of its decay:
    the counts are small and their correlations at two or more steps mostly noise.

    Returns
    -------
    rate : float
        One side's share, half the median tile's two-sided share; at least ``alpha / 2``.
    dispersion : float
        At least 1.
    corr_px : float
        Pixels, 0 for none.
    """
    if z.size < MIN_FLAT_TILES * PATCH_PX**2 // 2:
        return alpha / 2.0, 1.0, 0.0
    k = float(norm_isf(alpha / 2.0))
    ids, inv, _ = unique_runs(tile)
    count = np.bincount(inv, weights=(z > k).astype(np.float64))
    n = np.bincount(inv).astype(np.float64)
    p = median(count / n)
    if not p > 0:
        return alpha / 2.0, 1.0, 0.0
    q25, q75 = np.percentile(count - n * p, [25.0, 75.0])
    binomial = float(np.mean(n * p * (1.0 - p)))
    dispersion = max(1.0, ((q75 - q25) / 1.349) ** 2 / binomial)
    corr_px = 0.0
    if grid_width > 0:
        dev = (count - n * p) / np.sqrt(n * p * (1.0 - p))
        lim = 3.0 * math.sqrt(dispersion)
        dev = np.clip(dev - median(dev), -lim, lim)
        rho, pairs = _lag_correlation(_on_grid(*np.divmod(ids, grid_width), dev), 1, (0, 1))
        if pairs >= MIN_TILE_PAIRS and norm_isf(alpha) / math.sqrt(pairs) < rho < 1.0:
            corr_px = -float(step_px) / math.log(rho)
    return max(alpha / 2.0, 0.5 * p), float(dispersion), corr_px


def _from_differences(scan: Scan, nominal: NoiseModel) -> NoiseModel | None:
    """The range terms fitted to the second differences of the ranges along rows and
    columns, per range bin: ``1.4826 MAD / sqrt(6)`` is the std of white noise (the MAD
    ignores the few triplets that straddle an edge). Correlated noise partly cancels in a
    difference, so this reads low on a sensor whose noise is correlated; it serves scans
    whose tiles cannot pass as flat, where the noise dwarfs that error."""
    r = scan.range.astype(np.float64)
    d2 = [r[:, :-2] - 2.0 * r[:, 1:-1] + r[:, 2:], r[:-2] - 2.0 * r[1:-1] + r[2:]]
    mid = [r[:, 1:-1], r[1:-1]]
    dd = np.concatenate([d.ravel() for d in d2])
    rr = np.concatenate([m.ravel() for m in mid])
    ok = np.isfinite(dd) & np.isfinite(rr)
    dd, rr = dd[ok], rr[ok]
    if dd.size < MIN_FLAT_TILES * PATCH_PX**2:
        return None
    b = np.floor(rr / BIN_WIDTH).astype(np.int64)
    rows = []
    for k in np.unique(b):
        q = b == k
        if q.sum() < PATCH_PX**2:
            continue
        med = np.median(dd[q])
        std = 1.4826 * float(np.median(np.abs(dd[q] - med))) / math.sqrt(6.0)
        if std > 0:
            rows.append({"range": float(np.median(rr[q])), "std": std, "count": int(q.sum())})
    if not rows:
        return None
    try:
        fitted, _ = fit_bins(rows, NOISE_TERMS, nominal)
    except InputError:
        return None
    return dataclasses.replace(nominal, sigma0=fitted.sigma0, k1=fitted.k1, k2=fitted.k2,
                               row_corr=0.0, incidence_exponent=1.0)


def _tile_stats(tiles: TileResiduals, model: NoiseModel
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per flat tile: median range (m), robust residual std at normal incidence (m), the
    number of inliers, and the tile's id (ascending)."""
    inl = tiles.inlier
    tid = tiles.tile[inl]
    if tid.size == 0:
        z = np.zeros(0)
        return z, z, z, np.zeros(0, np.int64)
    # along the ray, back to normal incidence as the model's 1/max(cos, min_cos) factor
    e = np.abs(tiles.residual[inl]) * np.maximum(
        tiles.cos_incidence[inl], model.min_cos) ** model.incidence_exponent
    r = tiles.range[inl]
    ids, inv, counts = unique_runs(tid)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    # each tile's points together (they already are, in tile order: then nothing moves)
    if np.any(inv[1:] < inv[:-1]):
        by_tile = stable_order(inv)
        e, r = e[by_tile], r[by_tile]
    mad = _lower_medians(e, starts, counts)  # lower median of |e| per tile
    r_med = _lower_medians(r, starts, counts)
    return r_med, 1.4826 * mad, counts.astype(np.float64), ids


def scale_margin(alpha: float) -> float:
    """How far (in ln) the model's scale may be off before a 1-dof test at ``alpha`` fires
    at twice its rate: ln sqrt(chi2_{1,1-alpha} / chi2_{1,1-2 alpha}) (0.102 at 0.01)."""
    return 0.5 * math.log(chi2_isf(alpha, 1) / chi2_isf(2.0 * alpha, 1))


def _fit_tests(tiles: TileResiduals, model: NoiseModel, alpha: float, grid_width: int
               ) -> tuple[tuple[np.ndarray, ...], np.ndarray, np.ndarray, TestTable]:
    """Range bins and the NOISE_FIT test of the residuals against ``model``.

    Per range bin with :data:`MIN_TEST_TILES` flat tiles, ``d`` is the mean over its
    tiles of ln(tile std / model std), winsorized at 3 robust sigmas (a few tiles of ribbed
    or mixed surface that passed the flatness checks barely move it), with its standard
    error from the tiles' own spread (so correlated noise and heterogeneous surfaces are in
    it). A scale can never be known exactly (a tile's std carries biases of a percent or
    so), and only a relevant error matters: the test asks whether some bin's scale is off
    by more than :func:`scale_margin`, ``t_b = (|d_b| - margin) / se_b``, one-sided, with
    Bonferroni over the bins.

    Two things make ``se_b`` uncertain, and the test keeps its level only with both (bare
    active-stereo floors fired on 6 of 40 development scans without them, 0 with them):

    * the tiles' scales are correlated over the image (a stereo camera's matching quality
      varies slowly; :func:`tile_correlation`), so a bin's tiles are fewer independent
      ones than their number: its variance takes their :func:`design_effect`;
    * ``se_b`` is estimated from a few tiles (10 to 30), so ``t_b`` is Student's t with
      n / design effect - 1 degrees of freedom, not normal.

    Each bin's ``z`` is the normal quantile of its t tail probability. The same test of
    all tiles together joins the bins' (a scale off at every range shows surely in all
    tiles, barely in one bin's t of a few degrees of freedom) by a weighted Bonferroni:
    half the level to all tiles, half shared by the B bins. The test's p is min(1, 2 p_all,
    2 B min p_b), and its statistic the normal quantile of that p, against ``z_{1 -
    alpha}``.

    Returns the bins (range, tiles, std, model std, z, design effect, dof, p), the tiles'
    correlation, all tiles' (z, tiles, design effect, dof), and the test.
    """
    r, s, n, ids = _tile_stats(tiles, model)
    ok = s > 0
    r, s, n, ids = r[ok], s[ok], n[ok], ids[ok]
    empty = tuple(np.zeros(0) for _ in range(8))
    if r.size == 0:
        return empty, np.zeros(4), np.full(4, np.nan), TestTable.empty(alpha)
    # ln of a MAD-based std of n normal samples is biased low by about 1.36 / (2 n)
    b = np.floor(r / BIN_WIDTH).astype(np.int64)
    # a tile of quantized depth that spans less than one step reads below the steps'
    # own spread, as the fit's bins do (calibrate.noise.quantization_floor)
    inl = tiles.inlier
    rp, zp = tiles.range[inl], tiles.depth[inl]
    bp = np.floor(rp / BIN_WIDTH).astype(np.int64)
    floored = np.zeros(s.shape, bool)
    ks = np.unique(b)
    # each bin's points: the points' bins sorted once, not a mask per bin
    by_bin = stable_order(bp)
    bp_sorted = bp[by_bin]
    floors = _group_floors(rp, zp, by_bin, np.searchsorted(bp_sorted, ks, "left"),
                           np.searchsorted(bp_sorted, ks, "right"))
    for k, floor in zip(ks, floors):  # quantization_floor of the bin's points
        t = b == k
        floored[t] = s[t] <= floor
        s[t] = np.maximum(s[t], floor)
    d = np.log(s / model.sigma_range(r)) + 1.36 / (2.0 * n)
    margin = scale_margin(alpha)
    gy, gx = np.divmod(ids, grid_width)
    # the tiles' scales vary together over the image (a stereo camera's matching quality):
    # measured around a quadratic in range, which takes out a smooth misfit of the range
    # law (what the test is for: on a tilted floor it would read as a correlation along
    # the columns) but not a patch (each bin's median would take out a patch that fills
    # the bin). Tiles floored at their quantization step have no scale of their own
    corr = tile_correlation(gy[~floored], gx[~floored], (d - _range_trend(r, d))[~floored])
    rows = []
    for k in np.unique(b):
        q = b == k
        if q.sum() < MIN_TEST_TILES:
            continue
        rk = median(r[q])
        rows.append((rk, float(q.sum()), float(np.exp(median(np.log(s[q])))),
                     float(model.sigma_range(rk)), *_scale_off(d[q], gy[q], gx[q], corr,
                                                                margin)))
    if not rows:
        return empty, corr, np.full(4, np.nan), TestTable.empty(alpha)
    bins = tuple(np.array(c, dtype=np.float64) for c in zip(*rows))
    # every tile together: a model off by one factor at every range shows far more
    # surely in all of them than in any one bin's few
    z_all, deff_all, dof_all, p_all = _scale_off(d, gy, gx, corr, margin)
    pooled = np.array([z_all, float(d.size), deff_all, dof_all])
    # weighted Bonferroni: half the level to all tiles, half shared by the bins
    nb = len(rows)
    p = min(1.0, 2.0 * p_all, 2.0 * nb * float(bins[7].min()))
    z = float(norm_isf(max(p, 1e-300)))
    crit = float(norm_isf(alpha))
    return bins, corr, pooled, TestTable.decision(TestKind.NOISE_FIT, -1, nb + 1, z, crit,
                                                  p > alpha, alpha, p_value=p)


def _winsorized(x: np.ndarray, centre: float) -> np.ndarray:
    """``x`` clipped at 3 robust sigmas (1.4826 x the median |x - centre|) around
    ``centre``; as it is where that is 0."""
    scale = 1.4826 * median(np.abs(x - centre))
    return np.clip(x, centre - 3.0 * scale, centre + 3.0 * scale) if scale > 0 else x


def _range_trend(r: np.ndarray, d: np.ndarray) -> np.ndarray:
    """A least-squares quadratic in range through the tiles' ``d`` (winsorized at 3 robust
    sigmas), at each tile; a line or a constant where the ranges span too few bins."""
    med = median(d)
    e = _winsorized(d, med)
    deg = min(2, np.unique(np.floor(r / BIN_WIDTH)).size - 1)
    if deg < 1:
        return np.full(d.shape, med)
    x = r - float(np.mean(r))
    return np.asarray(np.polyval(np.polyfit(x, e, deg), x), dtype=np.float64)


def _scale_off(d: np.ndarray, gy: np.ndarray, gx: np.ndarray, corr: np.ndarray,
               margin: float) -> tuple[float, float, float, float]:
    """Whether tiles' ln(std / model std) ``d`` are off by more than ``margin``: (z, design
    effect, dof, p) of their winsorized mean, one-sided (see :func:`_fit_tests`)."""
    e = _winsorized(d, median(d))
    # the mean's standard error from the winsorized standard deviation, times the square
    # root of the design effect of the tiles' correlation; Student's t with as many degrees
    # of freedom as the tiles are independent ones (less one), given as the normal z of the
    # same tail probability
    deff = design_effect(gy, gx, corr)
    dof = max(1.0, d.size / deff - 1.0)
    sd = float(np.std(e, ddof=1)) if d.size > 1 else 0.0
    se = max(sd / math.sqrt(d.size) * math.sqrt(deff), 1e-12)
    p = float(t_sf((abs(float(np.mean(e))) - margin) / se, dof))
    return float(norm_isf(max(p, 1e-300))), deff, dof, p


#: Tile pairs the tiles' correlation needs at a lag.
MIN_TILE_PAIRS = 20
#: Largest decay per grid step the tiles' correlation is given (a fit to noisy correlations
#: can find no decay at all).
MAX_TILE_RATIO = 0.95
#: Tile-grid steps the tiles' correlation is measured at, along rows and along columns.
TILE_LAGS = (1, 2, 3, 4)


def tile_correlation(gy: np.ndarray, gx: np.ndarray, dev: np.ndarray) -> np.ndarray:
    """How the flat tiles' log scale deviations correlate over the tile grid, along its rows
    and along its columns: (c_r, a_r, c_c, a_c), the correlation ``c_r * a_r ** k`` between
    tiles k grid steps apart in one row, ``c_c * a_c ** k`` in one column.

    Per direction, ``c`` and ``a`` are the least-squares fit of ``c * a ** k`` to the
    correlations at :data:`TILE_LAGS` steps (the deviations winsorized at 3 robust
    sigmas; ``a`` on a grid of 0.01 up to :data:`MAX_TILE_RATIO`, ``c`` in [0, 1]): an
    exponential decay with a nugget, since each tile's scale also carries its own sampling
    error, which correlates with no other tile. The directions differ: a structured-light
    camera's noise offset common to an image row is common to every tile of that row of
    tiles, at any distance along it, and to none above or below. A direction with fewer
    than :data:`MIN_TILE_PAIRS` pairs at one step: (0, 0).

    Parameters
    ----------
    gy, gx : (T,) int
        The tiles' row and column in the examined tile grid.
    dev : (T,) float64
        Each tile's ln(std / model std) less its smooth trend in range.
    """
    out = np.zeros(4)
    if dev.size < 2:
        return out
    G = _on_grid(gy, gx, _winsorized(dev, 0.0))
    grid = np.arange(0.0, MAX_TILE_RATIO + 0.005, 0.01)
    for axis in (0, 1):  # along rows (x steps), along columns (y steps)
        lags, rho = [], []
        for lag in TILE_LAGS:
            r, pairs = _lag_correlation(G, lag, (axis,))
            if pairs < MIN_TILE_PAIRS or not np.isfinite(r):
                break
            lags.append(lag)
            rho.append(r)
        if not lags or not rho[0] > 0:
            continue
        k = np.asarray(lags, np.float64)
        y = np.asarray(rho)
        P = grid[:, None] ** k[None, :]  # (grid, lags): a ** k
        with np.errstate(invalid="ignore", divide="ignore"):
            c = np.clip((P @ y) / np.sum(P * P, 1), 0.0, 1.0)
        c[0] = 0.0  # a = 0: no correlation at any lag
        sse = np.sum((y[None, :] - c[:, None] * P) ** 2, 1)
        best = int(np.argmin(sse))
        out[2 * axis:2 * axis + 2] = (float(c[best]), float(grid[best]))
    return out


def _on_grid(gy: np.ndarray, gx: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The tiles' values at their grid positions, NaN where no tile."""
    G = np.full((int(gy.max()) + 1, int(gx.max()) + 1), np.nan)
    G[gy, gx] = values
    return G


def _lag_correlation(G: np.ndarray, lag: int, axes: tuple[int, ...]) -> tuple[float, int]:
    """The correlation (uncentred: the values are deviations already) of a grid's values
    ``lag`` steps apart along rows (axis 0) and/or columns (axis 1), pooled over ``axes``,
    and the number of pairs; NaN without a pair or a spread."""
    a = np.concatenate([(G[:, :-lag] if ax == 0 else G[:-lag]).ravel() for ax in axes])
    b = np.concatenate([(G[:, lag:] if ax == 0 else G[lag:]).ravel() for ax in axes])
    both = np.isfinite(a) & np.isfinite(b)
    den = math.sqrt(float(np.sum(a[both] ** 2)) * float(np.sum(b[both] ** 2)))
    rho = float(np.sum(a[both] * b[both])) / den if den > 0 else math.nan
    return rho, int(both.sum())


def design_effect(gy: np.ndarray, gx: np.ndarray, corr: np.ndarray) -> float:
    """Variance of the mean of tiles at grid positions (gy, gx) whose values correlate as
    ``corr`` (:func:`tile_correlation`), over that of independent tiles: 1 + (1/n) times
    the sum over pairs i != j of their correlation, ``c_r a_r^|dx|`` in one row,
    ``c_c a_c^|dy|`` in one column, ``sqrt(c_r c_c) a_r^|dx| a_c^|dy|`` otherwise."""
    c_r, a_r, c_c, a_c = (float(v) for v in corr)
    n = gy.size
    if n < 2 or not (c_r * a_r > 0 or c_c * a_c > 0):
        return 1.0
    if gy.dtype.kind == "i" and gx.dtype.kind == "i":
        # the same (n, n) correlations from one kernel, without the distance, factor and
        # power arrays: the powers from a table of np.power's own (element by element the
        # same ufunc); summed by NumPy as before
        gy, gx = gy.astype(np.int64), gx.astype(np.int64)
        p_r = np.power(a_r, np.arange(int(gx.max() - gx.min()) + 1, dtype=np.int64))
        p_c = np.power(a_c, np.arange(int(gy.max() - gy.min()) + 1, dtype=np.int64))
        rho = _correlations(gy, gx, c_r, c_c, math.sqrt(c_r * c_c), p_r, p_c)
    else:
        dx = np.abs(gx[:, None] - gx[None, :])
        dy = np.abs(gy[:, None] - gy[None, :])
        c = np.where(dy == 0, c_r, np.where(dx == 0, c_c, math.sqrt(c_r * c_c)))
        rho = c * np.power(a_r, dx) * np.power(a_c, dy)
    return 1.0 + float(rho.sum() - np.trace(rho)) / n


@kernel
def _correlations(gy: np.ndarray, gx: np.ndarray, c_r: float, c_c: float, c_x: float,
                  p_r: np.ndarray, p_c: np.ndarray) -> np.ndarray:
    """:func:`design_effect`'s (n, n) correlations, bit for bit: ``c * p_r[|dx|] *
    p_c[|dy|]`` with ``c`` = ``c_r`` in one row, else ``c_c`` in one column, else ``c_x``
    (its NumPy expression builds five (n, n) arrays and calls ``pow`` n**2 times)."""
    n = gy.shape[0]
    rho = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            dx = abs(gx[i] - gx[j])
            dy = abs(gy[i] - gy[j])
            c = c_r if dy == 0 else (c_c if dx == 0 else c_x)
            rho[i, j] = c * p_r[dx] * p_c[dy]
    return rho


def _z(tiles: TileResiduals, model: NoiseModel) -> np.ndarray:
    """|residual| / model sigma of every point of the flat tiles (their outliers too)."""
    e = tiles.residual
    fin = np.isfinite(e)
    return np.abs(e[fin]) / model.sigma_range(tiles.range[fin], tiles.cos_incidence[fin])


def _tail_rates(z: np.ndarray) -> np.ndarray:
    if z.size == 0:
        return np.full(len(TAIL_SIGMAS), np.nan)
    return np.array([np.mean(z > k) for k in TAIL_SIGMAS])


#: Lag-1 correlation below which the noise counts as white (a plane fit's own residuals
#: correlate a little).
WHITE_CORRELATION = 0.1


def correlation_length(corr: np.ndarray) -> float:
    """Correlation length (pixels) of exp(-k / L) fitted through the origin to ln of the
    measured correlation at :data:`boxloc.calibrate.noise.CORRELATION_LAGS`, over the lags where
    it is above 0.05 (further it is the plane fit's and the estimate's noise); 0 where the lag-1
    correlation is below :data:`WHITE_CORRELATION`."""
    lags = np.asarray(CORRELATION_LAGS, dtype=np.float64)
    c = np.asarray(corr, dtype=np.float64)
    if not (np.isfinite(c[0]) and c[0] >= WHITE_CORRELATION):
        return 0.0
    ok = np.isfinite(c) & (c > 0.05)
    x, y = lags[ok], np.log(c[ok])
    slope = float(x @ y / (x @ x))
    return round(-1.0 / slope, 3) if slope < 0 else float(lags[-1])


def _correlation(tiles: TileResiduals) -> np.ndarray:
    L = tiles.lag_sums
    with np.errstate(invalid="ignore", divide="ignore"):
        c = L[..., 0] / np.sqrt(L[..., 1] * L[..., 2])
    assert c.shape == (2, len(CORRELATION_LAGS))
    return np.where(np.isfinite(c), c, np.nan)

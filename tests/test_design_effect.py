"""Design effects of exceedance counts under correlated noise, and the exposure test that
uses them (boxloc.stages.design_effect, boxloc.stages.verify._test_exposed)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.signal import lfilter

from boxloc.scan import NoiseModel
from boxloc.stages.design_effect import (
    EXCEED_TILE_PX,
    exceedance_correlation,
    exceedance_design_effects,
    patch_factor,
)
from boxloc.stages.verify import _test_exposed

K = 2.5758293035489004  # sqrt(chi2(1)) at alpha 0.01


def _field(rng: np.random.Generator, h: int, w: int, r: float, Lr: float, Lc: float
           ) -> np.ndarray:
    """Standard normal noise with an offset common to each row (share r of the variance)
    and exp(-d / L) correlation along rows (Lr) and columns (Lc): an independent sampler,
    not the design effect's sums."""
    burn = 40
    x = rng.standard_normal((h + burn, w + burn))
    for L, axis in ((Lr, 1), (Lc, 0)):
        if L > 0:
            a = np.exp(-1.0 / L)
            x = lfilter([np.sqrt(1 - a * a)], [1, -a], x, axis=axis)
    x = x[burn:, burn:]
    return np.sqrt(r) * rng.standard_normal((h, 1)) + np.sqrt(1 - r) * x


def test_exceedance_correlation_is_the_bivariate_normals():
    from scipy.stats import multivariate_normal, norm

    p = multivariate_normal(mean=[0, 0]).cdf([-K, -K])  # independent: p^2
    assert p == pytest.approx(0.005**2, rel=0.01)
    for rho in (0.1, 0.3, 0.6, 0.9):
        cov = [[1, rho], [rho, 1]]
        both = multivariate_normal(mean=[0, 0], cov=cov).cdf([-K, -K])  # = P(>K, >K)
        opposite = multivariate_normal(mean=[0, 0], cov=[[1, -rho], [-rho, 1]]).cdf([-K, -K])
        q = norm.sf(K)
        front, sign = exceedance_correlation(K, rho)
        assert front == pytest.approx((both - q * q) / (q * (1 - q)), rel=1e-3)
        assert sign == pytest.approx((both - opposite) / q, rel=1e-3)
        assert 0 < front < rho and 0 < sign < rho  # far below rho itself
    f, s = exceedance_correlation(K, [0.0, 1.0])
    assert np.allclose(f, [0, 1]) and np.allclose(s, [0, 1])


def test_white_noise_has_no_design_effect():
    rows = np.repeat(np.arange(50), 70)
    D_f, D_s = exceedance_design_effects(rows, np.zeros(len(rows), int), 1, K, NoiseModel())
    assert D_f.tolist() == [1.0] and D_s.tolist() == [1.0]


@pytest.mark.parametrize("r, Lr, Lc", [(0.27, 4.0, 0.0), (0.35, 4.0, 3.0), (0.0, 3.0, 3.0),
                                       (0.3, 0.0, 0.0)])
def test_design_effect_is_the_counts_measured_variance(r, Lr, Lc):
    # the variance of exceedance counts over a 40 x 60 face, over 1500 draws of an
    # independent sampler, against the binomial's times D
    rng = np.random.default_rng(7)
    h, w = 40, 60
    F, S = [], []
    for _ in range(1500):
        z = _field(rng, h, w, r, Lr, Lc)
        F.append((z > K).sum())
        S.append((z > K).sum() - (z < -K).sum())
    p = 0.005
    n = h * w
    rows = np.repeat(np.arange(h), w)
    D_f, D_s = exceedance_design_effects(rows, np.zeros(n, int), 1, K,
                                         NoiseModel(row_corr=r, corr_px_rows=Lr,
                                                    corr_px_cols=Lc))
    assert D_f[0] > 2 and D_s[0] > 2
    assert np.var(F) / (n * p * (1 - p)) == pytest.approx(D_f[0], rel=0.2)
    assert np.var(S) / (n * 2 * p) == pytest.approx(D_s[0], rel=0.2)


def test_groups_pair_only_within_themselves():
    rows = np.repeat(np.arange(20), 30)
    cols = np.tile(np.arange(30), 20)
    noise = NoiseModel(row_corr=0.3, corr_px_rows=3.0, corr_px_cols=2.0)
    whole = exceedance_design_effects(rows, np.zeros(len(rows), int), 1, K, noise)[0][0]
    halves = exceedance_design_effects(rows, (cols >= 15).astype(int), 2, K, noise)[0]
    top = exceedance_design_effects(rows, (rows >= 10).astype(int), 2, K, noise)[0]
    # half as many points to each row: less inflation; a group of rows below another
    # does not pair with it (the key of row + dr never reaches the next group)
    assert np.all(halves < whole) and halves[0] == pytest.approx(halves[1])
    assert np.all(top < whole) and top[0] == pytest.approx(top[1])


def _fit(z: np.ndarray, spacing: float = 0.004) -> SimpleNamespace:
    """What _test_exposed reads of a face's fit: an h x w face, every point in the core."""
    h, w = z.shape
    rows, cols = np.indices((h, w))
    zz = z.ravel()
    return SimpleNamespace(rows=rows.ravel(), cols=cols.ravel(), du=cols.ravel() * spacing,
                           dv=rows.ravel() * spacing, core=np.ones(zz.size, bool),
                           front=zz > K, behind=zz < -K)


_HYP = SimpleNamespace(alpha=0.01, k=K, margin=0.01, attempt_id=0)


def test_exposure_holds_its_level_on_row_correlated_noise():
    # a bare 60 x 90 face whose noise has a row offset and short correlation along rows
    # (as the development structured-light scans): taking the points as independent calls
    # it covered many times more often than alpha; weighed by the design effect, at alpha
    rng = np.random.default_rng(11)
    noise = NoiseModel(row_corr=0.3, corr_px_rows=4.0)
    n, covered, covered_white = 400, 0, 0
    for _ in range(n):
        fit = _fit(_field(rng, 60, 90, 0.3, 4.0, 0.0))
        covered += not _test_exposed(fit, _HYP, noise)[0]
        covered_white += not _test_exposed(fit, _HYP, NoiseModel())[0]
    assert covered <= 3 * 0.01 * n  # 12: at most ~3 alpha over 400 draws
    assert covered_white >= 5 * covered + 10


def test_exposure_still_sees_an_occluder_on_correlated_noise():
    rng = np.random.default_rng(12)
    noise = NoiseModel(row_corr=0.3, corr_px_rows=4.0)
    z = _field(rng, 60, 90, 0.3, 4.0, 0.0)
    z[20:28, 40:48] += 25.0  # a box corner 8 x 8 px, far in front
    exposed, row = _test_exposed(_fit(z), _HYP, noise)
    assert not exposed and not row.accepted[0] and not row.accepted[2]
    # white noise: the rows' counts are the raw ones
    _, raw = _test_exposed(_fit(z), _HYP, NoiseModel())
    assert raw.statistic[0] >= 64 and row.statistic[0] < raw.statistic[0]


def _exact(rows: np.ndarray, cols: np.ndarray, noise: NoiseModel) -> tuple[float, float]:
    """D by brute force over every pair of actual pixel positions (the reference)."""
    r, Lr, Lc = noise.row_corr, noise.corr_px_rows, noise.corr_px_cols
    dr = np.abs(rows[:, None] - rows[None, :]).astype(float)
    dc = np.abs(cols[:, None] - cols[None, :]).astype(float)
    er = np.exp(-dc / Lr) if Lr > 0 else (dc == 0).astype(float)
    ec = np.exp(-dr / Lc) if Lc > 0 else (dr == 0).astype(float)
    rho = np.where(dr == 0, r + (1 - r) * er, (1 - r) * ec * er)
    np.fill_diagonal(rho, 0.0)
    f, s = exceedance_correlation(K, rho)
    np.fill_diagonal(f, 0.0)
    np.fill_diagonal(s, 0.0)
    n = len(rows)
    return 1 + f.sum() / n, 1 + s.sum() / n


def test_design_effect_sums_are_the_pairs_and_holes_only_raise_them():
    # contiguous rows: the closed-form sums equal the brute-force pair sums (to the
    # truncation of correlations below MIN_RHO); rows with holes
    # (every third pixel missing): the sums, which take each row as contiguous, are larger
    # than the exact ones (the test errs toward exposed)
    noise = NoiseModel(row_corr=0.3, corr_px_rows=4.0, corr_px_cols=2.5)
    rows, cols = (a.ravel() for a in np.indices((12, 25)))
    D = exceedance_design_effects(rows, np.zeros(len(rows), int), 1, K, noise)
    ex = _exact(rows, cols, noise)
    assert D[0][0] == pytest.approx(ex[0], rel=1e-3) and D[1][0] == pytest.approx(ex[1], rel=1e-3)
    keep = cols % 3 != 2
    Dh = exceedance_design_effects(rows[keep], np.zeros(keep.sum(), int), 1, K, noise)
    exh = _exact(rows[keep], cols[keep], noise)
    assert Dh[0][0] > exh[0] and Dh[1][0] > exh[1]
    assert Dh[0][0] < 1.5 * exh[0]  # an overestimate, not a different quantity


def test_patch_factor_sums_the_tiles_correlation() -> None:
    rows, cols = (a.ravel() for a in np.indices((32, 48)))  # 2 x 3 whole tiles of 16 px
    assert patch_factor(rows, cols, NoiseModel()) == 1.0  # tiles independent
    one = (rows < 16) & (cols < 16)  # a single tile
    assert patch_factor(rows[one], cols[one], NoiseModel(exceed_corr_px=50.0)) == 1.0
    L = 20.0
    got = patch_factor(rows, cols, NoiseModel(exceed_corr_px=L))
    # six equal tiles: 1 + (1/6) sum over ordered pairs of exp(-d / L)
    ty, tx = np.divmod(np.arange(6), 3)
    d = EXCEED_TILE_PX * np.hypot(ty[:, None] - ty[None], tx[:, None] - tx[None])
    want = 1.0 + (np.exp(-d / L).sum() - 6.0) / 6.0
    assert got == pytest.approx(want, rel=1e-12)
    # the longer the reach, the more a count over the same pixels varies, up to all six
    # tiles as one (factor 6)
    f = [patch_factor(rows, cols, NoiseModel(exceed_corr_px=x)) for x in (5.0, 20.0, 1e9)]
    assert 1.0 < f[0] < f[1] < f[2] == pytest.approx(6.0)


def test_design_effects_count_the_rows_as_numpys_unique_does() -> None:
    # the per-(group, row) counts by bincount: np.unique's keys and counts, in its order
    from boxloc.stages import design_effect as de

    noise = NoiseModel(row_corr=0.3, corr_px_rows=4.0, corr_px_cols=3.0)
    rng = np.random.default_rng(5)
    rows = rng.integers(0, 200, 3000)
    groups = rng.integers(0, 7, 3000)
    span = int(rows.max()) + 2 + de._reach(3.0, 0.7)
    key = groups * span + rows
    uk, n = np.unique(key, return_counts=True)
    counts = np.bincount(key, minlength=7 * span)
    assert uk.tolist() == np.flatnonzero(counts).tolist()
    assert n.tolist() == counts[uk].tolist()
    f, s = de.exceedance_design_effects(rows, groups, 7, 2.5, noise)
    assert f.shape == s.shape == (7,) and (f >= 1.0).all() and (s >= 1.0).all()

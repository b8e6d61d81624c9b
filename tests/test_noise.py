"""Noise estimation: known models from synthetic planes, robustness to edges and folds, and a
real Kinect frame (mOSD)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from real_data import MOSD

from boxloc.calibrate.noise import (
    estimate_noise,
    nnls_few,
    noise_toml,
    plane_residuals,
    quantization_floor,
)
from boxloc.cli import cli
from boxloc.config import Config
from boxloc.errors import InputError
from boxloc.io import write_npz
from boxloc.scan import NoiseModel, PinholeModel, Scan

SENSOR = PinholeModel(150.0, 150.0, 79.5, 59.5, width=160, height=120)


def _unit(v: list[float]) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    return a / np.linalg.norm(a)


def plane_range(distance: float, normal: np.ndarray, sensor: PinholeModel = SENSOR) -> np.ndarray:
    """Range image of the plane {x : normal . x = normal . (0, 0, distance)}."""
    rays = sensor.rays()
    return (normal @ np.array([0.0, 0.0, distance])) / (rays @ normal)


def noisy_scan(r_true: np.ndarray, normal: np.ndarray, model: NoiseModel, seed: int) -> Scan:
    """Add the model's range noise (Gaussian, along the ray) to a true range image."""
    rng = np.random.default_rng(seed)
    cos = np.abs(SENSOR.rays() @ normal)
    r = r_true + rng.normal(size=r_true.shape) * model.sigma_range(r_true, cos)
    return Scan(range=r.astype(np.float32), sensor=SENSOR)


TRUE = NoiseModel(sigma0=0.0008, k1=0.0, k2=0.0015)


def synthetic_planes(model: NoiseModel = TRUE) -> list[Scan]:
    """Tilted planes from 0.6 m to 3 m."""
    normals = [_unit([0, -0.4, -1]), _unit([0.3, -0.2, -1]), _unit([0, 0, -1])]
    return [noisy_scan(plane_range(d, normals[i % 3]), normals[i % 3], model, seed=i)
            for i, d in enumerate([0.6, 0.9, 1.3, 1.8, 2.4, 3.0])]


def test_plane_residuals_noise_free_plane_is_zero() -> None:
    n = _unit([0.2, -0.5, -1])
    scan = Scan(range=plane_range(1.5, n).astype(np.float32), sensor=SENSOR)
    r, cos, res = plane_residuals(scan)
    assert r.size == 112 * 160  # every whole 16 x 16 tile
    assert np.abs(res).max() < 5e-6  # float32 rounding of the range only
    want_cos = np.abs(SENSOR.rays() @ n)[:112]
    np.testing.assert_allclose(np.sort(cos), np.sort(want_cos.ravel()), atol=1e-6)
    np.testing.assert_allclose(np.sort(r), np.sort(scan.range[:112].ravel()), rtol=1e-6)


def test_estimate_recovers_known_model() -> None:
    scans = synthetic_planes()
    model, report = estimate_noise(scans, terms=("sigma0", "k2"))
    assert model.sigma0 == pytest.approx(TRUE.sigma0, rel=0.2)
    assert model.k2 == pytest.approx(TRUE.k2, rel=0.2)
    assert model.k1 == 0.0
    assert report["fit_rel_rms"] < 0.1
    # With all three terms the individual terms trade off; the curve itself must match.
    full, _ = estimate_noise(scans)
    for r in (0.7, 1.5, 2.5):
        assert full.sigma_range(r) == pytest.approx(TRUE.sigma_range(r), rel=0.2)
    # sigma_angle and min_cos come from the base model, untouched.
    assert full.sigma_angle == NoiseModel().sigma_angle and full.min_cos == NoiseModel().min_cos


def row_noisy_scan(r_true: np.ndarray, normal: np.ndarray, model: NoiseModel, rho: float,
                   seed: int) -> Scan:
    """As noisy_scan, with the share ``rho`` of the variance an offset common to each row."""
    rng = np.random.default_rng(seed)
    cos = np.abs(SENSOR.rays() @ normal)
    z = (np.sqrt(1.0 - rho) * rng.normal(size=r_true.shape)
         + np.sqrt(rho) * rng.normal(size=(r_true.shape[0], 1)))
    r = r_true + z * model.sigma_range(r_true, cos)
    return Scan(range=r.astype(np.float32), sensor=SENSOR)


@pytest.mark.parametrize("rho", [0.0, 0.25])
def test_estimate_measures_the_row_correlation(rho: float) -> None:
    normals = [_unit([0, -0.4, -1]), _unit([0.3, -0.2, -1]), _unit([0, 0, -1])]
    scans = [row_noisy_scan(plane_range(d, normals[i % 3]), normals[i % 3], TRUE, rho, i)
             for i, d in enumerate([0.6, 0.9, 1.3, 1.8, 2.4, 3.0])]
    model, report = estimate_noise(scans, terms=("sigma0", "k2"))
    assert model.row_corr == pytest.approx(rho, abs=0.03)
    assert report["row_corr"]["value"] == model.row_corr
    assert report["row_corr"]["tiles"] == report["n_tiles_used"]
    # the row offsets are part of each point's noise: the model's sigma is the total
    assert model.sigma_range(1.5) == pytest.approx(TRUE.sigma_range(1.5), rel=0.2)
    # a whole-row offset: along the row, residuals stay correlated at every lag (a little
    # under rho, whose linear trend across a tile's rows goes into its plane's tilt) ...
    corr = report["correlation"]
    assert corr["lags_px"] == [1, 2, 4, 8]
    for v in corr["along_rows"]:
        assert v == pytest.approx(0.85 * rho, abs=0.04)
    # ... and along a column the rows' offsets are independent
    assert max(abs(v) for v in corr["along_columns"]) < 0.05
    # normal noise has normal tails (the model fitted to the same data, so roughly)
    tails = report["tails"]
    assert tails["sigmas"] == [3.0, 4.0, 5.0] and tails["n_points"] > report["n_points"] * 0.99
    assert tails["observed"][0] == pytest.approx(tails["normal"][0], rel=0.3)
    assert tails["observed"][1] < 3 * tails["normal"][1]
    # columns carry no shared offset: transposed, the same estimator sees none
    if rho:
        cols = [Scan(range=np.ascontiguousarray(sc.range.T), sensor=PinholeModel(
            150.0, 150.0, 59.5, 79.5, width=120, height=160)) for sc in scans]
        assert estimate_noise(cols, terms=("sigma0", "k2"))[0].row_corr < 0.03


def test_tails_show_a_contaminated_noise() -> None:
    # 2 % of the points with 2.5 times the noise (a sensor's occasional misses): the
    # model's sigma barely moves, but beyond 4 sigma there are far more than normal
    normals = [_unit([0, -0.4, -1]), _unit([0.3, -0.2, -1]), _unit([0, 0, -1])]
    scans = []
    for i, d in enumerate([0.6, 0.9, 1.3, 1.8, 2.4, 3.0]):
        n = normals[i % 3]
        r_true = plane_range(d, n)
        rng = np.random.default_rng(100 + i)
        z = rng.normal(size=r_true.shape) * np.where(rng.random(r_true.shape) < 0.02, 2.5, 1.0)
        r = r_true + z * TRUE.sigma_range(r_true, np.abs(SENSOR.rays() @ n))
        scans.append(Scan(range=r.astype(np.float32), sensor=SENSOR))
    model, report = estimate_noise(scans, terms=("sigma0", "k2"))
    assert model.sigma_range(1.5) == pytest.approx(TRUE.sigma_range(1.5), rel=0.2)
    obs, normal = report["tails"]["observed"], report["tails"]["normal"]
    assert obs[0] > 1.5 * normal[0]
    assert obs[1] > 5 * normal[1]
    assert obs[2] > 20 * normal[2]


def test_row_corr_is_checked_and_recorded_at_zero() -> None:
    with pytest.raises(InputError, match="row_corr"):
        NoiseModel(row_corr=1.0)
    with pytest.raises(InputError, match="row_corr"):
        NoiseModel(row_corr=-0.1)
    assert NoiseModel().to_dict()["row_corr"] == 0.0
    pinned = Config(noise_auto=False)
    assert pinned.hash == pinned.with_overrides(["noise.row_corr=0"]).hash
    # giving an estimated term pins the model
    assert Config().with_overrides(["noise.row_corr=0"]) == pinned
    cfg = pinned.with_overrides(["noise.row_corr=0.25"])
    assert cfg.noise.to_dict()["row_corr"] == 0.25 and cfg.hash != pinned.hash
    assert Config.from_toml(cfg.to_toml()).noise.row_corr == 0.25


def test_estimate_recovers_linear_term_and_ignore_mode() -> None:
    true = NoiseModel(sigma0=0.0, k1=0.002, k2=0.0)
    scans = synthetic_planes(true)
    model, report = estimate_noise(scans, terms=("k1",))
    assert model.k1 == pytest.approx(0.002, rel=0.2)
    # Ignoring the incidence bins the raw along-ray scatter, which is larger (1 / cos).
    raw, rep_raw = estimate_noise(scans, terms=("k1",), incidence="ignore")
    assert raw.k1 > model.k1
    assert rep_raw["incidence"] == "ignore"


def test_report_layout() -> None:
    model, rep = estimate_noise(synthetic_planes()[:3], bin_width=0.2)
    assert rep["n_scans"] == 3 and rep["n_points"] > 0 and rep["n_tiles_used"] > 0
    assert rep["bins"] == sorted(rep["bins"])
    assert np.allclose(np.diff(rep["bins"]), 0.2)
    for row in rep["rows"]:
        assert row["lo"] <= row["range"] <= row["hi"]
        assert row["count"] > 0 and row["std_mad"] > 0 and row["std_clipped"] > 0
        assert row["model_std"] == pytest.approx(float(model.sigma_range(row["range"])))
    assert any(row["used"] for row in rep["rows"])
    assert rep["model"] == model.to_dict()


def step_scene(sigma: float, seed: int = 0) -> Scan:
    """A wall at 1.0 m left of column 72, at 1.3 m right of it, and a 40 deg fold (a roof
    at 0.8 m, creased along column 40) in the lower-left quarter."""
    rng = np.random.default_rng(seed)
    n0 = _unit([0, 0, -1])
    r = plane_range(1.0, n0)
    r[:, 72:] = plane_range(1.3, n0)[:, 72:]
    # Rows 60..: a roof, folded along column 40 (crease tiles must be rejected).
    rays = SENSOR.rays()
    a = np.deg2rad(20)
    left, right = _unit([np.sin(a), 0, -np.cos(a)]), _unit([-np.sin(a), 0, -np.cos(a)])
    apex = np.array([(40 - 79.5) / 150 * 0.8, 0, 0.8])
    rl = (left @ apex) / (rays @ left)
    rr = (right @ apex) / (rays @ right)
    roof = np.minimum(rl, rr)
    r[64:, :72] = roof[64:, :72]
    r = r + rng.normal(0, sigma, r.shape)
    return Scan(range=r.astype(np.float32), sensor=SENSOR)


def test_edges_and_folds_do_not_inflate_the_estimate() -> None:
    sigma = 0.001  # along the ray, the same everywhere
    scan = step_scene(sigma)
    r, cos, res = plane_residuals(scan)
    assert 1.4826 * np.median(np.abs(res - np.median(res))) == pytest.approx(sigma, rel=0.05)
    assert np.std(res) == pytest.approx(sigma, rel=0.05)  # no outliers left either
    # Without the tile tests the step and the fold leak in and inflate the spread.
    r2, cos2, res2 = plane_residuals(scan, max_outliers=1.0, max_curvature_ratio=1e12,
                                     min_cos=0.0)
    assert r2.size > r.size
    assert np.std(res2) > 3 * sigma


def test_mask_and_labels_restrict_tiles() -> None:
    scan = step_scene(0.001)
    mask = np.zeros(scan.shape, dtype=bool)
    mask[:48, :64] = True
    r, _, _ = plane_residuals(scan, mask)
    assert 0.99 * 12 * 256 <= r.size <= 12 * 256  # 3 x 4 tiles of 16 x 16, few outliers
    assert r.max() < 1.2  # only the near wall
    labels = np.zeros(scan.shape, dtype=np.int64)
    labels[:, 100:] = 1  # a boundary through the flat far wall, in tiles of columns 96..111
    r_lab, _, _ = plane_residuals(scan, labels=labels)
    r_all, _, _ = plane_residuals(scan)
    assert r_all.size - 7 * 256 <= r_lab.size < r_all.size - 6 * 256
    with pytest.raises(InputError, match="mask must have the scan's shape"):
        plane_residuals(scan, np.ones((3, 3), bool))


def test_bad_arguments_and_no_flat_surface() -> None:
    scans = synthetic_planes()[:1]
    with pytest.raises(InputError, match="at least one scan"):
        estimate_noise([])
    with pytest.raises(InputError, match="terms"):
        estimate_noise(scans, terms=("k3",))
    with pytest.raises(InputError, match="estimator"):
        estimate_noise(scans, estimator="mean")
    with pytest.raises(InputError, match="incidence"):
        estimate_noise(scans, incidence="sometimes")
    with pytest.raises(InputError, match="bin_width"):
        estimate_noise(scans, bin_width=0.0)
    with pytest.raises(InputError, match="2 masks"):
        estimate_noise(scans, masks=[None, None])
    with pytest.raises(InputError, match="patch"):
        plane_residuals(scans[0], patch=2)
    empty = Scan(range=np.full(SENSOR.shape, np.nan, np.float32), sensor=SENSOR)
    with pytest.raises(InputError, match="no flat surface"):
        estimate_noise([empty])
    with pytest.raises(InputError, match="not enough flat surface"):
        estimate_noise(scans, min_points=10**9)


def test_noise_toml_loads_as_config() -> None:
    model = NoiseModel(sigma0=0.0004, k1=0.0, k2=0.0017)
    text = noise_toml(model)
    assert tomllib.loads(text)["noise"]["k2"] == 0.0017
    assert Config.from_toml(text).noise == model


def test_cli_calibrate_noise(tmp_path: Path) -> None:
    for i, scan in enumerate(synthetic_planes()):
        write_npz(scan, tmp_path / f"s{i}.npz")
    out = tmp_path / "noise.toml"
    res = CliRunner().invoke(cli, ["calibrate-noise", str(tmp_path), "--terms", "sigma0,k2",
                                   "-o", str(out)])
    assert res.exit_code == 0, res.output
    cfg = Config.from_toml(res.stdout)
    assert cfg.noise.k2 == pytest.approx(TRUE.k2, rel=0.2)
    assert Config.load(out).noise == cfg.noise
    assert "range noise: 6 scan(s)" in res.stderr and "fit: relative RMS" in res.stderr
    assert "residual correlation at 1, 2, 4, 8 px: along rows" in res.stderr
    assert "beyond 3 sigma" in res.stderr and "(normal 2.70e-03)" in res.stderr
    bad = CliRunner().invoke(cli, ["calibrate-noise", str(tmp_path / "missing.npz")])
    assert bad.exit_code == 2
    assert bad.stderr.strip().splitlines() == [
        f"boxloc: error: scan file not found: {tmp_path / 'missing.npz'}"]


@pytest.mark.real_data("learn0.pcd")
def test_mosd_frame_noise() -> None:
    from boxloc.io import read_labels, read_scan

    scan = read_scan(MOSD / "learn0.pcd")
    labels = read_labels(MOSD / "learn0.pcd")
    model, rep = estimate_noise([scan], labels=[labels])
    # A Kinect at about 1 m: a millimetre or two, growing with range (measured on the 25
    # learn frames: k1 ~ 1.0e-3 with the model's 1/cos law; along the ray k2 ~ 1.7e-3).
    s1 = float(model.sigma_range(1.0))
    assert 0.5e-3 < s1 < 2.5e-3
    assert model.sigma_range(1.4) > model.sigma_range(0.7)
    assert rep["fit_rel_rms"] < 0.15
    assert sum(row["used"] for row in rep["rows"]) >= 5
    assert rep["n_tiles_used"] > 200
    # the Kinect's noise has a part common to each image row (measured on the 25 frames:
    # 0.28 of the variance); a frame alone measures it to a few hundredths
    assert 0.15 < model.row_corr < 0.4
    # ... but not to the whole row: along a row the residuals' correlation falls from 0.67
    # at 1 pixel to 0.03 at 8 (25 frames: 0.66 to 0.02); and they are correlated across
    # rows too (0.5 at 1 pixel): the sensor smooths over a window, wider than tall
    along_rows, along_cols = (rep["correlation"][k] for k in ("along_rows", "along_columns"))
    assert along_rows[0] > 0.5 and along_rows[3] < 0.1
    assert along_cols[0] > 0.3 and along_rows[0] > along_cols[0]
    # and its tails are heavier than normal: 5 times as many residuals beyond 4 sigma
    obs, normal = rep["tails"]["observed"], rep["tails"]["normal"]
    assert obs[1] > 3 * normal[1] and obs[2] > 30 * normal[2]


def test_quantized_depth_has_the_noise_of_its_steps() -> None:
    # Depth reported in 18 mm steps with 1 mm of noise under them: a flat tile spanning
    # less than a step reads nearly one value. The bins' std, floored at step / sqrt(12)
    # along the ray, is what a test must expect between neighbours; a continuous sensor's
    # floor is negligible.
    rng = np.random.default_rng(3)
    z = 4.0 + np.linspace(-0.05, 0.05, 5000) + rng.normal(0.0, 0.001, 5000)
    step = 0.018
    zq = (np.round(z / step) * step).astype(np.float32).astype(np.float64)
    ray = 1.1
    assert quantization_floor(ray * zq, zq) == pytest.approx(ray * step / np.sqrt(12), rel=1e-3)
    zc = 4.0 + rng.uniform(-0.05, 0.05, 1000)
    assert quantization_floor(zc, zc) < 1e-4



# --- the exact-median kernels: each equals the NumPy expression it replaces, bit for bit ---


def _same(a: object, b: object) -> bool:
    """Equal bytes as float64 (so -0.0 != 0.0 and NaN == NaN)."""
    return bool(np.asarray(a, np.float64).tobytes() == np.asarray(b, np.float64).tobytes())


def _samples(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    """Continuous values, heavy ties, quantized depths, signed zeros, extreme scales."""
    return [rng.normal(size=n), rng.integers(-3, 4, n).astype(np.float64),
            np.round(rng.normal(4.0, 0.05, n) / 0.018) * 0.018,
            rng.choice([-0.0, 0.0, 1.0, -1.0], n),
            rng.normal(size=n) * 10.0 ** rng.integers(-300, 300)]


def _floor_numpy(r: np.ndarray, z: np.ndarray) -> float:
    """quantization_floor as NumPy expressions (its definition)."""
    u = np.unique(z)
    gaps = np.diff(u)
    gaps = gaps[gaps > 1e-6 * float(np.median(np.abs(u)))] if u.size > 1 else gaps
    if gaps.size == 0:
        return 0.0
    with np.errstate(invalid="ignore", divide="ignore"):
        ray = float(np.median(r / z))
    return float(np.median(gaps)) / np.sqrt(12.0) * (ray if np.isfinite(ray) else 1.0)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 7, 8, 255, 256, 1001, 4096])
def test_median_kernels_are_numpys_bit_for_bit(n: int) -> None:
    import warnings

    from boxloc.calibrate.noise import _mad, _median

    rng = np.random.default_rng(n)
    for x in _samples(rng, n):
        for a in (x, np.where(np.arange(n) == n // 2, np.nan, x)):  # and with a NaN
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                ref, ref_mad = np.median(a), np.median(np.abs(a - np.median(a)))
            before = a.copy()
            assert _same(_median(a), ref) and _same(_mad(a), ref_mad)
            assert _same(a, before)  # the input is not reordered
            z = np.abs(a) + 1.0
            r = z * rng.uniform(1.0, 1.2, n)
            assert _same(quantization_floor(r, z), _floor_numpy(r, z))
    assert np.isnan(_median(np.zeros(0)))
    assert quantization_floor(np.zeros(0), np.zeros(0)) == 0.0


def test_grouped_median_kernels_are_numpys_bit_for_bit() -> None:
    from boxloc.calibrate.noise import (
        _abs_medians,
        _group_distinct,
        _group_floors,
        _group_medians,
        _lower_medians,
    )

    rng = np.random.default_rng(7)
    n, G = 5000, 40
    which = rng.integers(0, G, n)
    which[which == 5] = 6  # an empty group
    order = np.argsort(which, kind="stable")
    cuts = np.searchsorted(which[order], np.arange(G + 1))
    t = rng.integers(0, 60, n)
    for x in _samples(rng, n):
        z = np.abs(x) + 1.0
        r = z * rng.uniform(1.0, 1.2, n)
        med = _group_medians(x, order, cuts[:-1], cuts[1:], False)
        mad = _group_medians(x, order, cuts[:-1], cuts[1:], True)
        floors = _group_floors(r, z, order, cuts[:-1], cuts[1:])
        distinct = _group_distinct(t, order, cuts[:-1], cuts[1:])
        for g in range(G):
            sel = order[cuts[g]:cuts[g + 1]]
            if sel.size == 0:
                assert np.isnan(med[g]) and distinct[g] == 0 and floors[g] == 0.0
                continue
            xs = x[sel]
            assert _same(med[g], np.median(xs))
            assert _same(mad[g], np.median(np.abs(xs - np.median(xs))))
            assert _same(floors[g], _floor_numpy(r[sel], z[sel]))
            assert distinct[g] == np.unique(t[sel]).size
        # per row: nanmedian_last of the masked |h|, and the lower median of groups
        from boxloc.stats import nanmedian_last

        h = x[:4000].reshape(16, 250).copy()
        h[3, 7] = np.nan
        w = rng.random(h.shape) < 0.8
        w[2] = False  # a row without inliers
        w[4, 1:] = False  # a row of one
        with np.errstate(invalid="ignore"):
            ref = nanmedian_last(np.where(w, np.abs(h), np.nan))
        assert _same(_abs_medians(h, w), ref)
        assert _same(_abs_medians(h, w.astype(np.float64)), ref)
        counts = np.array([1, 2, 3, 250, 251, 500, 993])
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        y = np.abs(x[:counts.sum()])
        want = [np.sort(y[s:s + c])[(c - 1) // 2] for s, c in zip(starts, counts)]
        assert _same(_lower_medians(y, starts, counts), want)


def test_norms_and_lag_sums_are_numpys_bit_for_bit() -> None:
    from boxloc.calibrate.noise import CORRELATION_LAGS, _lag_sums, _norms

    rng = np.random.default_rng(12)
    for T, n in ((0, 256), (1, 1), (3, 7), (300, 256), (41, 1296)):
        P = rng.normal(size=(T, n, 3)) * 10.0 ** rng.uniform(-3, 3, (T, n, 3))
        if T:
            P[0, 0] = (np.nan, 1.0, 2.0)
            P[-1, -1] = (np.inf, 0.0, -0.0)
        assert _same(_norms(P), np.linalg.norm(P, axis=2))
    for patch in (4, 8, 16):
        T = 50
        h = rng.normal(size=(T, patch * patch))
        w = rng.random(h.shape) < 0.9
        w[0] = False
        want = np.zeros((2, len(CORRELATION_LAGS), 3))  # the sums as NumPy expressions
        H = np.where(w, h, 0.0).reshape(T, patch, patch)
        M = w.reshape(T, patch, patch)
        for j, lag in enumerate(CORRELATION_LAGS):
            if lag >= patch:
                continue
            for i, (a, b, ma, mb) in enumerate((
                    (H[:, :, :-lag], H[:, :, lag:], M[:, :, :-lag], M[:, :, lag:]),
                    (H[:, :-lag], H[:, lag:], M[:, :-lag], M[:, lag:]))):
                both = ma & mb
                want[i, j] = ((a * b)[both].sum(), (a * a)[both].sum(), (b * b)[both].sum())
        assert _same(_lag_sums(h, w, patch), want)


def test_unique_runs_and_stable_order_are_numpys() -> None:
    from boxloc.calibrate.noise import _group_distinct, stable_order, unique_runs

    rng = np.random.default_rng(13)
    cases = [np.zeros(0, np.int64), np.array([5]), np.sort(rng.integers(0, 40, 3000)),
             rng.integers(0, 40, 3000), np.repeat(np.arange(7) << 32, 5),
             np.sort(rng.integers(0, 9, 100)).astype(np.uint16),
             rng.integers(-(2**62), 2**62, 500), np.array([3, 3, -1, 7, 7, 7, 2])]
    for t in cases:
        for got, want in zip(unique_runs(t), np.unique(t, return_inverse=True,
                                                       return_counts=True)):
            assert got.dtype == want.dtype and np.array_equal(got, want)
        assert np.array_equal(stable_order(t), np.argsort(t, kind="stable"))
        if t.size:  # the distinct values of groups in order and out of it
            order = np.arange(t.size)
            starts, stops = np.array([0, t.size // 2]), np.array([t.size // 2, t.size])
            got = _group_distinct(t.astype(np.int64), order, starts, stops)
            assert list(got) == [np.unique(t[a:b]).size for a, b in zip(starts, stops)]


def test_window_points_are_numpys_gather() -> None:
    from boxloc.calibrate.noise import _window_points

    rng = np.random.default_rng(14)
    H, W, side, stride = 60, 80, 48, 3
    points = rng.normal(1.0, 1.0, (H, W, 3)).astype(np.float32)
    points[rng.random((H, W)) < 0.1] = np.nan
    valid = np.isfinite(points[..., 2]) & (rng.random((H, W)) < 0.95)
    r0, c0 = rng.integers(0, H - side + 1, 9), rng.integers(0, W - side + 1, 9)
    off = np.arange(0, side, stride)
    rr = r0[:, None, None] + off[None, :, None]
    cc = c0[:, None, None] + off[None, None, :]
    P = points[rr, cc].reshape(9, -1, 3).astype(np.float64)
    V = valid[rr, cc].reshape(9, -1) & (P[..., 2] > 0)
    P = np.where(V[..., None], P, 0.0)
    got_P, got_V = _window_points(points, valid, r0, c0, side, stride)
    assert _same(got_P, P) and np.array_equal(got_V, V)


def test_design_matrices_are_numpys_stack() -> None:
    from boxloc.calibrate.noise import _design

    rng = np.random.default_rng(15)
    u, v = rng.normal(size=(5, 256)), rng.normal(size=(5, 256))
    one = np.ones_like(u)
    assert _same(_design(u, v, False), np.stack([u, v, one], -1))
    assert _same(_design(u, v, True), np.stack([u, v, one, u * u, u * v, v * v], -1))
    assert _design(u, v, True).flags.c_contiguous


@pytest.mark.parametrize("seed", range(40))
def test_nnls_few_is_scipys_nnls(seed: int) -> None:
    """The exact small solver finds scipy.optimize.nnls's minimum: random problems of 1-4
    unknowns, most of them (32 of 40) with the optimum on the boundary (some x_j = 0)."""
    from scipy.optimize import nnls

    rng = np.random.default_rng(seed)
    n = 1 + seed % 4
    A = rng.normal(size=(12, n)) * rng.uniform(0.1, 10.0, n)
    b = A @ rng.normal(size=n) + 0.1 * rng.normal(size=12)
    x, ref = nnls_few(A, b), nnls(A, b)[0]
    assert np.all(x >= 0)
    np.testing.assert_allclose(x, ref, rtol=1e-9, atol=1e-12)
    assert np.linalg.norm(A @ x - b) <= np.linalg.norm(A @ ref - b) * (1 + 1e-12)
    # the fallback, where no optimality check passes: the best feasible support, the same x
    np.testing.assert_array_equal(nnls_few(A, b, rtol=-np.inf), x)


def test_nnls_few_edges() -> None:
    """All-zero optimum (b opposite every column), and too many unknowns refused."""
    A = np.ones((5, 2))
    np.testing.assert_array_equal(nnls_few(A, -np.ones(5)), [0.0, 0.0])
    with pytest.raises(ValueError, match="at most 6"):
        nnls_few(np.ones((9, 7)), np.ones(9))

"""The scan's own noise model (boxloc.stages.scan_noise) and its NOISE_FIT test."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from boxloc.calibrate.noise import tile_residuals
from boxloc.config import Config
from boxloc.pipeline import find_graspable_surfaces
from boxloc.products import NoiseSource, products_equal
from boxloc.scan import NoiseModel
from boxloc.simulate import simulate
from boxloc.stages.scan_noise import (
    MIN_FLAT_TILES,
    design_effect,
    estimate_scan_noise,
    tile_correlation,
)
from boxloc.stats import TestKind

SCENE = "pallet:width=320,height=240,f=262.5,distance=1.5"


def _median_range(sim) -> float:  # type: ignore[no-untyped-def]
    return float(np.nanmedian(sim.scan.range))


@pytest.fixture(scope="module")
def noisy():  # type: ignore[no-untyped-def]
    """A scan whose range noise is 2.5x the default model's."""
    nm = NoiseModel()
    return simulate(f"{SCENE},noise.sigma0={2.5 * nm.sigma0},noise.k2={2.5 * nm.k2}", 3)


def test_auto_estimates_the_scans_own_noise(noisy) -> None:  # type: ignore[no-untyped-def]
    est = estimate_scan_noise(noisy.scan, Config(noise_auto=True))
    assert est.source == NoiseSource.SCAN and "flat tiles" in est.reason
    assert est.n_tiles_used >= MIN_FLAT_TILES
    r = _median_range(noisy)
    truth = noisy.spec.noise.sigma_range(r)
    got = NoiseModel(**est.noise_model()).sigma_range(r)
    assert got == pytest.approx(truth, rel=0.15)
    # the terms a scan cannot measure come from the config
    assert est.noise_model()["sigma_angle"] == Config().noise.sigma_angle
    assert est.fits and est.tests.kind.tolist() == [TestKind.NOISE_FIT]


def test_a_pinned_model_that_is_wrong_for_the_scan_fails_its_test(noisy) -> None:  # type: ignore[no-untyped-def]
    est = estimate_scan_noise(noisy.scan, Config(noise_auto=False))
    assert est.source == NoiseSource.CONFIG
    np.testing.assert_array_equal(est.model, est.nominal)
    fit = est.tests.of_kind(TestKind.NOISE_FIT)
    assert len(fit) == 1 and not fit.accepted[0] and fit.p_value[0] < 1e-6
    # per bin, the scan's scatter is about 2.5x the model's
    assert np.median(est.bin_std / est.bin_model_std) == pytest.approx(2.5, rel=0.15)


def test_the_right_pinned_model_passes_its_test() -> None:
    sim = simulate(SCENE, 3)  # noise drawn from the default model
    fit = estimate_scan_noise(sim.scan, Config(noise_auto=False)).tests.of_kind(TestKind.NOISE_FIT)
    assert len(fit) == 1 and fit.accepted[0]


def test_too_few_flat_tiles_fits_second_differences() -> None:
    sim = simulate(SCENE, 3)
    rng = np.random.default_rng(0)
    holes = rng.random(sim.scan.shape) < 0.3  # no 16x16 tile is 90 % full
    scan = dataclasses.replace(sim.scan, range=np.where(holes, np.nan, sim.scan.range))
    est = estimate_scan_noise(scan, Config(noise_auto=True))
    assert est.source == NoiseSource.DIFFERENCES and "fewer than" in est.reason
    r = _median_range(sim)
    got = NoiseModel(**est.noise_model()).sigma_range(r)
    assert got == pytest.approx(sim.spec.noise.sigma_range(r), rel=0.2)


def test_nothing_to_fit_falls_back_to_the_config() -> None:
    sim = simulate(SCENE, 3)
    checker = (np.indices(sim.scan.shape).sum(0) % 2) == 1  # no two neighbours both valid
    scan = dataclasses.replace(sim.scan, range=np.where(checker, np.nan, sim.scan.range))
    est = estimate_scan_noise(scan, Config(noise_auto=True))
    assert est.source == NoiseSource.FALLBACK and "config's model" in est.reason
    np.testing.assert_array_equal(est.model, est.nominal)


def test_the_estimate_is_deterministic(noisy) -> None:  # type: ignore[no-untyped-def]
    a = estimate_scan_noise(noisy.scan, Config(noise_auto=True))
    b = estimate_scan_noise(dataclasses.replace(noisy.scan), Config(noise_auto=True))
    assert products_equal(a, b) == []


def test_the_pipeline_tests_against_the_scans_model(noisy) -> None:  # type: ignore[no-untyped-def]
    pinned = find_graspable_surfaces(noisy.scan, Config(noise_auto=False))
    auto = find_graspable_surfaces(noisy.scan, Config(noise_auto=True))
    assert auto.noise is not None and auto.noise.source == NoiseSource.SCAN
    # the default model, 2.5x too tight, makes noise into edges; the scan's own does not
    assert len(auto.edges) < 0.7 * len(pinned.edges)
    assert auto.config_hash == Config(noise_auto=True).hash


def test_a_given_noise_model_pins_it() -> None:
    auto = Config(noise_auto=True)
    assert Config.from_dict({"noise": {"k2": 0.001}}).noise_auto is False
    assert Config.from_dict({"noise_auto": True, "noise": {"k2": 0.001}}).noise_auto is True
    assert auto.with_overrides(["noise.k2=0.001"]).noise_auto is False
    assert auto.with_overrides(["noise.k2=0.001", "noise_auto=true"]).noise_auto is True
    # terms a scan cannot measure do not pin the model
    assert auto.with_overrides(["noise.edge_px=0.5"]).noise_auto is True
    assert Config.from_dict({"noise": {"edge_px": 0.5}, "noise_auto": True}).noise_auto
    assert Config.from_toml(auto.to_toml()) == auto


def test_locate_warns_when_the_model_does_not_fit(noisy, tmp_path) -> None:  # type: ignore[no-untyped-def]
    from click.testing import CliRunner

    from boxloc.cli import cli
    from boxloc.simulate import save_npz

    path = tmp_path / "noisy.npz"
    save_npz(noisy, path)
    # the default model pinned: 2.5x too tight for this scan
    res = CliRunner().invoke(cli, ["locate", str(path), "--set", "noise_auto=false"])
    assert res.exit_code == 0, res.output
    assert "warning: the noise model does not fit this scan" in res.stderr
    assert "noise_auto = true" in res.stderr
    res = CliRunner().invoke(cli, ["locate", str(path)])  # the default: the scan's own
    assert res.exit_code == 0 and "warning" not in res.stderr


def test_the_estimate_is_recorded_and_explained(noisy, tmp_path) -> None:  # type: ignore[no-untyped-def]
    from recorder.mcap.log import open_log
    from recorder.mcap.sink import McapRecorder
    from replay.explain import explain, format_explanation

    cfg = Config(noise_auto=True)
    with McapRecorder(tmp_path / "n.mcap", config=cfg, fsync=False) as rec:
        result = find_graspable_surfaces(noisy.scan, cfg, observer=rec)
    back = next(open_log(tmp_path / "n.mcap").scans())
    assert result.noise is not None
    assert products_equal(back.products["noise"], result.noise) == []
    assert "NOISE_FIT" in {r["kind"] for r in back.tests["noise"].rows()}
    d = explain(tmp_path / "n.mcap", 0)
    assert d["noise"]["source"] == "SCAN" and d["noise"]["fit"]["accepted"]
    r = d["noise"]["range_m"]
    assert d["noise"]["sigma_mm"] == pytest.approx(1e3 * noisy.spec.noise.sigma_range(r),
                                                   rel=0.15)
    assert "noise model: scan, sigma" in format_explanation(d)
    # the worst range bin, with what its standard error was widened by
    wb = d["noise"]["worst_bin"]
    assert wb["tiles"] >= 10 and wb["design_effect"] >= 1.0 and 0 < wb["dof"] < wb["tiles"]
    assert "worst range bin: " in format_explanation(d)
    # the exposure test's null, as the scan's flat tiles measured it
    assert d["noise"]["model"]["exceed_rate"] >= 0.005
    assert "exposure null: " in format_explanation(d)
    # how far its patches reach, where the scan measured a reach
    reach = d["noise"]["model"]["exceed_corr_px"]
    assert ("in patches reaching" in format_explanation(d)) == (reach > 0)


@pytest.mark.parametrize(("spec", "lo", "hi"), [
    # a laser's range noise does not grow with incidence; the default sensor's, as 1/cos.
    # A floor's incidences (cos 0.6-1) do not tell g = 1 from 1.5 (each wins on some
    # draws), so the second asks only that the noise grows with incidence
    ("floor:sensor=laser,width=320,height=240,f=262.5,distance=2.56,tilt=0.45", 0.0, 0.0),
    ("floor:width=320,height=240,f=262.5,distance=1.5,tilt=0.45", 1.0, 1.5),
])
@pytest.mark.parametrize("seed", [100, 101, 102])
def test_the_incidence_law_is_the_scans(spec: str, lo: float, hi: float, seed: int) -> None:
    est = estimate_scan_noise(simulate(spec, seed).scan, Config(noise_auto=True))
    assert lo <= est.noise_model()["incidence_exponent"] <= hi
    assert est.fits


def test_a_noisy_far_floor_is_not_seen_grazing() -> None:
    # Active stereo at 5 m: ~110 mm of correlated noise over a 16 px tile of ~180 mm. The
    # tiles' own normals scatter by tens of degrees; the incidence comes from the surface
    # around each tile, so the floor (seen at cos 0.8-1) is not called grazing and its
    # noise is not explained away by a 1 / cos**g law.
    spec = ("floor:f=440.0,distance=4.5,tilt=0.05,sensor=active-stereo,noise_scale=0.9,"
            "sensor_class=oak-d-pro")
    scan = simulate(spec, 1).scan
    t = tile_residuals(scan, None, patch=16, labels=None, min_valid=0.9, max_outliers=0.05,
                       max_curvature_ratio=1.5, min_cos=0.3)
    assert t.rejected["grazing incidence"] <= 0.01 * t.n_tiles  # was 15 %
    assert np.median(t.cos_incidence) > 0.8  # was 0.61


def _floor_tiles(spec: str, seed: int):  # type: ignore[no-untyped-def]
    """The noise stage's flat tiles of a simulated bare floor (its parameters)."""
    return tile_residuals(simulate(f"floor:{spec}", seed).scan, None, patch=16, labels=None,
                          min_valid=0.9, max_outliers=0.05, max_curvature_ratio=1.5,
                          min_cos=0.3)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_stereo_cameras_noisy_tiles_are_not_dropped_as_curved(seed: int) -> None:
    # Correlated stereo noise makes every tile's quadratic fit absorb some of it: with a
    # fixed curvature bound, a fifth to a third of a bare floor's tiles were dropped as
    # curved, the noisier ones, and the noise came out low
    t = _floor_tiles("sensor=active-stereo,width=320,height=240,f=220,distance=2.5,tilt=0.3",
                     seed)
    assert t.rejected["curved or folded"] <= 0.06 * t.n_tiles


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_far_noisy_floor_facing_the_camera_is_not_grazing(seed: int) -> None:
    # A structured-light camera's floor 3.5 m away, facing it: its range noise (centimetres)
    # is comparable to a tile's width, and a total-least-squares plane turned its normal
    # across the rays, so every tile of two of these scans was rejected as grazing
    t = _floor_tiles("sensor=structured-light,width=640,height=480,f=580,distance=3.5,"
                     "tilt=0.0", seed)
    assert t.rejected["grazing incidence"] == 0
    assert t.n_accepted >= 0.9 * t.n_tiles


@pytest.mark.parametrize("seed", [1, 2])
def test_the_exposure_null_is_measured_on_the_scans_flat_tiles(seed: int) -> None:
    # Active-stereo depth has heavy tails whose amplitude varies smoothly over the image: on
    # its bare floor several times alpha / 2 of the points lie beyond 2.58 sigma on a side,
    # in patches (seeds 1-3: 1.6-2.3 times the rate, counts 110-127 times as variable as
    # binomial ones). A laser's noise is normal and white: its rate is the normal's and
    # its counts vary about as binomial ones (tiles holding a neighbour's pixels aside)
    cfg = Config(noise_auto=True)
    stereo = estimate_scan_noise(simulate(
        "floor:sensor=active-stereo,width=320,height=240,f=220,distance=2.0,tilt=0.3",
        seed).scan, cfg).noise_model()
    assert stereo["exceed_rate"] > 1.4 * cfg.alpha / 2
    assert stereo["exceed_dispersion"] > 30.0
    # the patches reach beyond a tile: neighbouring tiles' counts correlate
    assert stereo["exceed_corr_px"] > 16.0
    laser = estimate_scan_noise(simulate(
        "floor:sensor=laser,width=320,height=240,f=262.5,distance=2.0,tilt=0.3",
        seed).scan, cfg).noise_model()
    assert cfg.alpha / 2 <= laser["exceed_rate"] < 2.0 * cfg.alpha / 2
    assert laser["exceed_dispersion"] < 4.0


def test_a_pinned_model_keeps_the_normal_exposure_null(noisy) -> None:  # type: ignore[no-untyped-def]
    est = estimate_scan_noise(noisy.scan, Config(noise_auto=False))
    assert est.noise_model()["exceed_rate"] == 0.0
    assert est.noise_model()["exceed_dispersion"] == 1.0
    assert est.noise_model()["exceed_corr_px"] == 0.0


def test_tile_correlation_recovers_a_smooth_field_and_none_in_white_noise() -> None:
    gy, gx = (a.ravel() for a in np.indices((30, 40)))
    dy, dx = np.abs(gy[:, None] - gy[None]), np.abs(gx[:, None] - gx[None])
    # a field correlating as 0.6^|dx| 0.3^|dy| (separable, each axis an AR(1))
    L = np.linalg.cholesky(0.6**dx * 0.3**dy + 1e-9 * np.eye(gy.size))
    for seed in range(3):
        rng = np.random.default_rng(seed)
        white = rng.standard_normal(gy.size)
        c_r, a_r, c_c, a_c = tile_correlation(gy, gx, white)
        assert c_r * a_r < 0.05 and c_c * a_c < 0.05  # the correlations at one step
        # half the variance that field, half each tile's own
        x = np.sqrt(0.5) * (L @ rng.standard_normal(gy.size)) + np.sqrt(0.5) * white
        c_r, a_r, c_c, a_c = tile_correlation(gy, gx, x - np.median(x))
        # the correlations at one step, 0.3 and 0.15, and the rows' slower decay
        assert c_r * a_r == pytest.approx(0.3, abs=0.06) and 0.4 < a_r < 0.8
        assert c_c * a_c == pytest.approx(0.15, abs=0.06)


def test_design_effect() -> None:
    gy, gx = np.zeros(10, np.int64), np.arange(10)
    assert design_effect(gy, gx, np.zeros(4)) == 1.0
    # fully correlated tiles: the mean of n is worth one
    assert design_effect(gy, gx, np.array([1.0, 0.999999, 0.0, 0.0])) == pytest.approx(
        10.0, rel=1e-4)
    # a row of 10 with c = 1, a = 0.5: 1 + (2 / n) sum_k (n - k) 0.5^k; a column the same
    want = 1.0 + 2.0 / 10 * sum((10 - k) * 0.5**k for k in range(1, 10))
    assert design_effect(gy, gx, np.array([1.0, 0.5, 0.0, 0.0])) == pytest.approx(want)
    assert design_effect(gx, gy, np.array([0.0, 0.0, 1.0, 0.5])) == pytest.approx(want)
    # correlated along rows only: a column of tiles is independent
    assert design_effect(gx, gy, np.array([1.0, 0.5, 0.0, 0.0])) == 1.0


def test_design_effect_kernel_is_the_numpy_expression_bit_for_bit() -> None:
    import math

    def numpy_design_effect(gy: np.ndarray, gx: np.ndarray, corr: np.ndarray) -> float:
        c_r, a_r, c_c, a_c = (float(v) for v in corr)
        dx = np.abs(gx[:, None] - gx[None, :])
        dy = np.abs(gy[:, None] - gy[None, :])
        c = np.where(dy == 0, c_r, np.where(dx == 0, c_c, math.sqrt(c_r * c_c)))
        rho = c * np.power(a_r, dx) * np.power(a_c, dy)
        return 1.0 + float(rho.sum() - np.trace(rho)) / gy.size

    rng = np.random.default_rng(11)
    for n in (2, 3, 9, 130, 400):
        gy, gx = rng.integers(0, 25, n), rng.integers(0, 30, n)
        for corr in (rng.uniform(0.0, 1.0, 4), np.array([0.7, 0.9, 0.0, 0.0]),
                     np.array([0.0, 0.0, 0.4, 0.6]), np.array([0.3, 0.0, 0.5, 0.95])):
            want = numpy_design_effect(gy, gx, corr)
            assert design_effect(gy, gx, corr) == want
            # integer tile indices of any width, and the float fallback
            assert design_effect(gy.astype(np.int32), gx.astype(np.int32), corr) == want
            assert design_effect(gy.astype(np.float64), gx.astype(np.float64), corr) == want


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_noise_fit_keeps_its_level_on_a_stereo_cameras_patchy_noise(seed: int) -> None:
    # Active-stereo depth noise varies in scale over the image (its matching quality): a
    # range bin's tiles in one patch scatter 1.5-2x the model's sigma on a bare floor. Its
    # own model must still fit (the test's level), and a model pinned 1.5x off must not
    cfg = Config(noise_auto=True)
    scan = simulate("floor:sensor=active-stereo,width=320,height=240,f=220,distance=1.8,"
                    "tilt=0.35", seed).scan
    est = estimate_scan_noise(scan, cfg)
    assert est.source == NoiseSource.SCAN and est.fits
    assert est.tile_correlation[0] > 0 and np.all(est.bin_design >= 1.0)
    assert np.all(est.bin_dof < est.bin_tiles) and est.fit_all[1] == est.n_tiles_used
    m = NoiseModel(**est.noise_model())
    for f in (0.5, 2.0):  # a model pinned off by a factor of 2 either way
        off = dataclasses.replace(m, sigma0=f * m.sigma0, k1=f * m.k1, k2=f * m.k2)
        assert not estimate_scan_noise(scan, Config(noise=off, noise_auto=False)).fits

"""Edge blur: the edge_px estimate, its effect on edge covariances, and what it feeds."""

from __future__ import annotations

import dataclasses
import tomllib

import numpy as np
import pytest
from cli_run import invoke
from scenes import box, scene, wall

from boxloc.calibrate.edgeblur import edge_offsets, estimate_edge_px
from boxloc.config import Config
from boxloc.errors import InputError
from boxloc.scan import Scan
from boxloc.simulate import save_npz
from boxloc.stages.edges import detect_edges
from boxloc.stages.hypotheses import _soft_votes
from boxloc.stages.verify import VerifyContext


@pytest.fixture(scope="module")
def boxes() -> list[Scan]:
    """Two scenes of separate boxes at 1.2 m: long straight edges."""
    out = []
    for seed, yaw in ((1, 0.2), (2, 0.7)):
        b = [box(-0.35, -0.2, 0.30, 0.40, 0.3, yaw), box(0.3, 0.25, 0.25, 0.35, 0.3, -yaw),
             box(0.3, -0.3, 0.2, 0.3, 0.25, yaw / 2)]
        out.append(scene(b, distance=1.2, seed=seed).scan)
    return out


def _blurred(scan: Scan, px: float, seed: int = 0) -> Scan:
    """Every row's and column's ranges shifted along it by a random whole number of pixels
    (normal, std ``px``), each on its own ray: edges wander as a correlation window makes
    them, faces stay where they were."""
    rng = np.random.default_rng(seed)
    P = scan.points.astype(np.float64)
    r = np.linalg.norm(P, axis=2)
    d = P / r[..., None]
    H, W = r.shape
    rows = np.clip(np.arange(H)[:, None] + np.rint(rng.normal(0, px, (1, W))), 0, H - 1)
    cols = np.clip(np.arange(W)[None, :] + np.rint(rng.normal(0, px, (H, 1))), 0, W - 1)
    r2 = r[rows.astype(int), cols.astype(int)]
    return Scan.from_points((d * r2[..., None]).astype(np.float32))


def test_the_simulator_needs_little_blur(boxes):
    edge_px, rep = estimate_edge_px(boxes, Config())
    assert rep["n_points"] > 500
    assert 0.0 <= edge_px < 0.5, rep
    assert rep["modelled_px"] > 0


def test_a_blurring_sensor_raises_the_estimate(boxes):
    base, _ = estimate_edge_px(boxes, Config())
    blur, rep = estimate_edge_px([_blurred(s, 1.0) for s in boxes], Config())
    assert blur > base + 0.3, rep
    assert blur < 2.0, rep


def test_offsets_are_within_the_corridor_in_pixels(boxes):
    off, mod = edge_offsets(boxes[0], Config())
    assert len(off) == len(mod) > 100
    assert np.all((off >= 0) & (off < 4.0))
    assert np.all(mod > 0)


def test_the_estimate_ignores_the_configs_own_edge_px(boxes):
    cfg = Config().with_overrides(["noise.edge_px=2.0"])
    a, _ = estimate_edge_px(boxes[:1], cfg)
    b, _ = estimate_edge_px(boxes[:1], Config())
    assert a == b


def test_a_scan_without_edges_is_an_input_error():
    with pytest.raises(InputError, match="too few edge points"):
        estimate_edge_px([Scan.from_points(wall())], Config())


def test_edge_px_widens_covariances_along_the_scan_line_only(boxes):
    cfg0 = Config()
    cfg1 = dataclasses.replace(cfg0, noise=dataclasses.replace(cfg0.noise, edge_px=1.0))
    e0 = detect_edges(boxes[0], config=cfg0)
    e1 = detect_edges(boxes[0], config=cfg1)
    assert np.array_equal(e0.pixels, e1.pixels)
    # single detections in both (fused points mix two scan lines; a wider covariance lets
    # more row and column estimates agree and fuse)
    single = (e0.scan_dir != 3) & (e1.scan_dir != 3)
    np.testing.assert_array_equal(e0.points[single], e1.points[single])
    dS = e1.covariances[single] - e0.covariances[single]
    w = np.linalg.eigvalsh(dS)
    # a rank-one addition: one positive eigenvalue, at least a pixel's footprint squared;
    # the others zero but for the covariances' rounding to float32 (7 digits)
    scale = np.abs(e1.covariances[single]).max(axis=(1, 2))[:, None]
    assert np.all(np.abs(w[:, :2]) <= 1e-6 * scale)
    assert np.all(1e-6 * scale < 1e-3 * w[:, 2:])
    r = np.linalg.norm(e0.points[single], axis=1)
    assert np.all(w[:, 2] >= 0.98 * (r * boxes[0].sensor.pixel_angle) ** 2)


def test_samples_along_a_receding_side_are_foreshortened():
    # a plane seen at 70 degrees incidence: a side receding from the sensor covers fewer
    # pixels than one across the view
    v, u = np.mgrid[0:120, 0:160].astype(np.float64)
    z = np.full_like(u, 1.0)
    P = np.stack([(u - 79.5) / 150 * z, (v - 59.5) / 150 * z, z], -1)
    scan = Scan.from_points(P.astype(np.float32))
    ctx = VerifyContext.build(scan, detect_edges(scan, config=Config()), Config(),
                              np.array([0.0, -1.0, 0.0]))
    c = np.array([0.0, 0.0, 1.0])
    t = np.radians(70.0)
    across = ctx.samples_along(c, c + np.array([0.05, 0.0, 0.0]))
    recede = ctx.samples_along(c, c + 0.05 * np.array([0.0, -np.cos(t), np.sin(t)]))
    flat = 0.05 / ctx.spacing_at(c)
    assert across == pytest.approx(flat, rel=0.02)
    assert recede < 0.5 * across


def test_soft_votes_keep_the_count_and_sharp_points_vote_in_their_bin():
    rng = np.random.default_rng(3)
    x = rng.uniform(0, 0.2, 300)
    h, nbins = 0.002, 110
    sharp = _soft_votes(x, np.zeros(300), h, nbins)
    hist = np.bincount((x / h).astype(int), minlength=nbins)
    # only a point within a few thousandths of a bin of a bin edge shares its vote
    assert np.abs(sharp - hist).max() < 0.5
    assert sharp.sum() == pytest.approx(300.0)
    blur = _soft_votes(x, np.full(300, 0.004), h, nbins)
    assert blur.sum() == pytest.approx(300.0)
    # one point spread over its error: the bins around it, centred on it
    one = _soft_votes(np.array([0.1001]), np.array([0.003]), h, nbins)
    assert one.max() < 0.5
    assert abs((one * (np.arange(nbins) + 0.5) * h).sum() - 0.1001) < 1e-4


def test_cli_prints_a_usable_line(tmp_path, boxes):
    p = tmp_path / "boxes.npz"
    save_npz(scene([box(0.0, 0.0, 0.45, 0.30, 0.25, 0.2)], distance=1.2, seed=4), p)
    r = invoke("calibrate-edges", str(p))
    assert r.returncode == 0, r.stderr
    px = tomllib.loads(r.stdout)["edge_px"]
    assert 0.0 <= px < 1.0
    Config().with_overrides([f"noise.edge_px={px}"])  # usable as given
    bad = invoke("calibrate-edges", str(tmp_path / "missing.npz"))
    assert bad.returncode == 2
    assert "missing.npz" in bad.stderr and "Traceback" not in bad.stderr


def test_pixel_footprint_grows_toward_grazing_and_is_floored():
    nm = Config().noise
    P = np.array([[0.0, 0.0, 2.0]] * 3)
    d = np.array([[1.0, 0.0, 0.0], [0.0, np.sin(1.2), np.cos(1.2)], [0.0, 0.0, 1.0]])
    f = nm.pixel_footprint(P, d, 0.002)
    assert f[0] == pytest.approx(2.0 * 0.002)
    assert f[1] == pytest.approx(2.0 * 0.002 / np.sin(1.2))
    assert f[2] == pytest.approx(2.0 * 0.002 / nm.min_cos)  # along the ray: the floor


def test_edge_px_is_printed_and_recorded_at_zero():
    cfg = Config()
    assert tomllib.loads(cfg.to_toml())["noise"]["edge_px"] == 0.0
    assert cfg.to_dict()["noise"]["edge_px"] == 0.0
    assert Config.from_toml(cfg.to_toml()).hash == cfg.hash
    assert cfg.with_overrides(["noise.edge_px=0.5"]).hash != cfg.hash

"""Tests of boxloc.evaluate.baseline, the open3d peer, on scenes ray-cast right here."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from boxloc.evaluate.baseline import baseline_surfaces, empty_surface_set, surface_set_from_rects
from boxloc.evaluate.metrics import match_surfaces
from boxloc.products import products_equal
from boxloc.scan import PinholeModel, Scan

# Boxes standing on a floor (base frame: z up, floor z = 0): (x0, x1, y0, y1, height).
BOXES = [(-0.20, 0.20, -0.15, 0.15, 0.40), (0.30, 0.60, -0.30, 0.10, 0.30)]


def _pose(tilt_deg: float, height: float = 2.0) -> np.ndarray:
    """Sensor looking straight down from ``height``, then tilted about the base x axis."""
    a = np.radians(tilt_deg)
    down = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # sensor z -> base -z
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    T = np.eye(4)
    T[:3, :3] = Rx @ down
    T[:3, 3] = [0.0, -height * np.tan(a), height]
    return T


def _cast(T: np.ndarray, shape: tuple[int, int] = (300, 400), f: float = 328.0,
          sigma: float = 0.0015, seed: int = 0, boxes: list = BOXES) -> Scan:
    """Ray-cast axis-aligned boxes and the floor; Gaussian range noise of ``sigma`` metres."""
    H, W = shape
    cam = PinholeModel(f, f, (W - 1) / 2, (H - 1) / 2, W, H)
    d = cam.rays() @ T[:3, :3].T  # rays in the base frame
    o = T[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d[..., 2] < 0, -o[2] / d[..., 2], np.inf)  # the floor
        for x0, x1, y0, y1, h in boxes:
            lo, hi = np.array([x0, y0, 0.0]), np.array([x1, y1, h])
            t1, t2 = (lo - o) / d, (hi - o) / d  # slab test
            tn = np.nanmax(np.minimum(t1, t2), axis=-1)
            tf = np.nanmin(np.maximum(t1, t2), axis=-1)
            hit = (tf >= tn) & (tn > 0)
            t = np.where(hit & (tn < t), tn, t)
    r = t + np.random.default_rng(seed).normal(0.0, sigma, t.shape)
    r[~np.isfinite(t)] = np.nan
    return Scan(range=r.astype(np.float32), sensor=cam, sensor_to_base=T)


@dataclass
class _Truth:
    centers: np.ndarray
    normals: np.ndarray
    x_axis: np.ndarray
    y_axis: np.ndarray
    width: np.ndarray
    length: np.ndarray
    fully_exposed: np.ndarray


def _truth(T: np.ndarray, boxes: list = BOXES) -> _Truth:
    """Box tops in the sensor frame (both tops fully exposed)."""
    R, o = T[:3, :3], T[:3, 3]
    C, X, Wd, L = [], [], [], []
    for x0, x1, y0, y1, h in boxes:
        C.append(R.T @ (np.array([(x0 + x1) / 2, (y0 + y1) / 2, h]) - o))
        sx, sy = x1 - x0, y1 - y0
        ax = np.array([1.0, 0, 0]) if sx <= sy else np.array([0, 1.0, 0])
        X.append(R.T @ ax)
        Wd.append(min(sx, sy))
        L.append(max(sx, sy))
    n = np.tile(R.T @ np.array([0, 0, 1.0]), (len(boxes), 1))
    X = np.array(X)
    return _Truth(np.array(C), n, X, np.cross(n, X), np.array(Wd), np.array(L),
                  np.ones(len(boxes), bool))


@functools.cache
def _found(tilt: float) -> tuple[Scan, Any]:
    """The scan of BOXES at ``tilt`` degrees and the baseline's surfaces (computed once:
    RANSAC takes seconds; the tests only read them)."""
    scan = _cast(_pose(tilt))
    return scan, baseline_surfaces(scan)


@pytest.mark.parametrize("tilt", [0.0, 20.0])
def test_baseline_finds_box_tops(tilt: float) -> None:
    T = _pose(tilt)
    scan, s = _found(tilt)
    truth = _truth(T)
    assert len(s) == 2
    m = match_surfaces(s, truth)
    assert (m.tp, m.fp, m.fn) == (2, 0, 0)
    np.testing.assert_array_less(m.width_err, 0.01)
    np.testing.assert_array_less(m.length_err, 0.01)
    np.testing.assert_array_less(m.center_err, 0.01)
    np.testing.assert_array_less(m.normal_err_deg, 2.0)
    # normals toward the sensor, width <= length, pick order top-most first
    assert (np.einsum("ij,ij->i", s.normals, s.centers) < 0).all()
    assert (s.width <= s.length).all()
    heights = s.centers @ scan.up
    assert heights[0] > heights[1]
    assert s.pick_order.tolist() == [0, 1]
    np.testing.assert_allclose(s.grasp_points, s.centers)
    assert s.scores.max() == pytest.approx(1.0) and (s.scores > 0).all()
    assert np.isfinite(s.covariances).all()
    assert (np.linalg.eigvalsh(s.covariances) > 0).all()


def test_baseline_is_deterministic() -> None:
    scan = _cast(_pose(10.0), seed=3)
    a = baseline_surfaces(scan)
    b = baseline_surfaces(scan)
    assert len(a) == 2
    assert products_equal(a, b) == []


def test_baseline_respects_size_priors() -> None:
    from boxloc.config import Config

    scan, found = _found(0.0)
    assert len(found) == 2  # found with the default prior ...
    # ... but the 0.4 x 0.3 and 0.3 x 0.4 tops are both too small for min_edge = 0.35.
    s = baseline_surfaces(scan, config=Config(min_edge=0.35))
    assert len(s) == 0


def test_baseline_floor_only_finds_nothing() -> None:
    # the same view with the boxes gives two tops: the empty answer is the floor's
    assert len(_found(0.0)[1]) == 2
    scan = _cast(_pose(0.0), boxes=[])
    assert len(baseline_surfaces(scan)) == 0


def test_baseline_empty_scan() -> None:
    cam = PinholeModel(50.0, 50.0, 15.5, 11.5, 32, 24)
    scan = Scan(range=np.full((24, 32), np.nan, np.float32), sensor=cam)
    timing: dict[str, float] = {}
    s = baseline_surfaces(scan, timing=timing)
    assert len(s) == 0 and s.centers.shape == (0, 3) and s.covariances.shape == (0, 6, 6)
    assert "total" in timing


def test_baseline_timing_is_filled() -> None:
    timing: dict[str, float] = {}
    baseline_surfaces(_cast(_pose(0.0)), timing=timing)
    assert set(timing) >= {"downsample", "planes", "clusters", "total"}
    assert all(v >= 0 for v in timing.values())


def test_surface_set_from_rects_normalizes() -> None:
    # normal given away from the sensor, width > length: both get fixed
    s = surface_set_from_rects(
        centers=[[0.0, 0.0, 2.0], [0.5, 0.0, 1.5]],
        normals=[[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]],
        x_axis=[[1.0, 0.0, 0.0], [1.0, 0.0, 0.01]],
        width=[0.5, 0.2],
        length=[0.3, 0.4],
    )
    # pick order: the nearer (higher, up = -z) surface first
    np.testing.assert_allclose(s.centers[0], [0.5, 0.0, 1.5])
    np.testing.assert_allclose(s.normals, [[0, 0, -1.0], [0, 0, -1.0]])
    np.testing.assert_allclose(s.width, [0.2, 0.3])
    np.testing.assert_allclose(s.length, [0.4, 0.5])
    # right-handed x, y, normal; x along the (new) width
    np.testing.assert_allclose(np.cross(s.x_axis, s.y_axis), s.normals, atol=1e-12)
    np.testing.assert_allclose(np.abs(s.x_axis[1]), [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(s.corners[1, 1] - s.corners[1, 0]), 0.3)
    np.testing.assert_allclose(np.linalg.norm(s.corners[1, 3] - s.corners[1, 0]), 0.5)
    np.testing.assert_allclose(s.corners.mean(axis=1), s.centers, atol=1e-12)
    assert s.hypothesis.tolist() == [-1, -1] and s.pick_order.tolist() == [0, 1]
    assert len(empty_surface_set()) == 0

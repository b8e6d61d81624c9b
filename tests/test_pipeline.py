"""End to end: find_graspable_surfaces on constructed and simulated scenes."""

from __future__ import annotations

import numpy as np
import pytest

from boxloc.config import Config
from boxloc.errors import InputError
from boxloc.evaluate.metrics import match_surfaces
from boxloc.observer import NullObserver
from boxloc.pipeline import find_graspable_surfaces
from boxloc.products import STAGES, products_equal
from boxloc.scan import PinholeModel, Scan
from boxloc.simulate import simulate
from tests.scenes import box, scene


@pytest.fixture(scope="module")
def single():
    sim = scene([box(0.02, -0.03, 0.40, 0.30, 0.25, 0.3)], seed=3)
    return sim, find_graspable_surfaces(sim.scan, Config())


def test_single_box_gives_one_surface_with_its_dimensions(single):
    sim, r = single
    assert len(r.surfaces) == 1
    s = r.surfaces
    # width <= length; within noise (+ the 4 mm bevel the edges see on each side)
    assert s.width[0] == pytest.approx(0.30, abs=0.008)
    assert s.length[0] == pytest.approx(0.40, abs=0.008)
    gt = sim.truth
    assert np.linalg.norm(s.grasp_points[0] - gt.centers[0]) < 0.005
    assert np.degrees(np.arccos(abs(s.normals[0] @ gt.normals[0]))) < 1.0
    m = match_surfaces(s, gt)
    assert (m.tp, m.fp, m.fn) == (1, 0, 0)


def test_surface_frame_conventions(single):
    _, r = single
    s = r.surfaces
    n, x, y = s.normals[0], s.x_axis[0], s.y_axis[0]
    assert n @ s.centers[0] < 0  # normal toward the sensor (at the origin)
    assert np.allclose(np.cross(x, y), n, atol=1e-9)
    assert np.allclose([np.linalg.norm(v) for v in (n, x, y)], 1.0)
    c = s.corners[0]
    assert np.linalg.norm(c[1] - c[0]) == pytest.approx(s.width[0])
    assert np.linalg.norm(c[3] - c[0]) == pytest.approx(s.length[0])
    assert np.allclose(s.covariances[0], s.covariances[0].T)
    assert (np.linalg.eigvalsh(s.covariances[0]) >= -1e-15).all()


def test_two_touching_boxes_of_equal_height_give_two_surfaces():
    # equal heights, a 2 mm seam, seen from 1 m: the seam is the only boundary between them
    sim = scene([box(0.0, -0.151, 0.40, 0.30, 0.30), box(0.0, 0.151, 0.40, 0.30, 0.30)],
                distance=1.0, tilt=0.05, seed=2)
    r = find_graspable_surfaces(sim.scan, Config())
    m = match_surfaces(r.surfaces, sim.truth)
    assert (m.tp, m.fp) == (2, 0)
    assert np.allclose(sorted(r.surfaces.length), [0.40, 0.40], atol=0.008)


def test_pick_order_is_top_most_first():
    sim = scene([box(-0.3, 0.0, 0.30, 0.25, 0.20), box(0.25, 0.0, 0.30, 0.25, 0.40)], seed=4)
    r = find_graspable_surfaces(sim.scan, Config())
    assert len(r.surfaces) == 2
    up = sim.scan.up
    h = r.surfaces.centers @ up
    assert list(r.surfaces.pick_order) == [0, 1]
    assert h[0] > h[1]


def test_empty_scene_is_not_an_error():
    sim = simulate("empty", seed=1)
    r = find_graspable_surfaces(sim.scan, Config())
    assert len(r.surfaces) == 0
    assert r.to_json()["surfaces"] == []


def test_all_nan_scan_is_refused():
    pin = PinholeModel(50.0, 50.0, 15.5, 11.5, 32, 24)
    scan = Scan(range=np.full((24, 32), np.nan, np.float32), sensor=pin)
    with pytest.raises(InputError, match="no valid range"):
        find_graspable_surfaces(scan, Config())


def test_scan_larger_than_max_pixels_is_refused(single):
    sim, _ = single
    with pytest.raises(InputError, match="exceeds max_pixels"):
        find_graspable_surfaces(sim.scan, Config(max_pixels=1000))


def test_same_scan_gives_the_same_products_bit_for_bit(single):
    sim, r1 = single
    r2 = find_graspable_surfaces(sim.scan, Config())
    assert products_equal(r1, r2) == []
    assert r1.seed == sim.scan.seed


def test_trial_seed_draws_another_stream_of_trials(single):
    sim, r0 = single
    # 0 is the scan's own stream: the default result
    assert Config().to_dict()["trial_seed"] == 0
    c1 = Config(trial_seed=1)
    assert c1.hash != Config().hash and c1.to_dict()["trial_seed"] == 1
    assert Config.from_toml(c1.to_toml()) == c1
    r1 = find_graspable_surfaces(sim.scan, c1)
    assert r1.seed == c1.seed_for(sim.scan.seed) != sim.scan.seed
    assert r1.lines.seed == r1.seed
    # another draw of the distinguished points: the Hough trials differ ...
    d = products_equal(r0, r1)
    assert any(x.startswith("lines") for x in d), d
    # ... the same draw reproduces bit for bit, and each (scan, k) has its own stream
    assert products_equal(r1, find_graspable_surfaces(sim.scan, c1)) == []
    assert Config(trial_seed=2).seed_for(sim.scan.seed) != r1.seed
    assert c1.seed_for(sim.scan.seed + 1) != r1.seed
    # a box this clear is found on any draw
    assert len(r1.surfaces) == 1
    for bad in (-1, 1.5, True):
        with pytest.raises(InputError, match="trial_seed"):
            Config(trial_seed=bad)


def test_workers_give_results_identical_to_serial():
    sim = simulate("pallet", seed=2)
    r1 = find_graspable_surfaces(sim.scan, Config())
    r2 = find_graspable_surfaces(sim.scan, Config(workers=2))
    assert products_equal(r1, r2) == []
    assert len(r1.surfaces) > 0


class _Recorder(NullObserver):
    def __init__(self) -> None:
        self.calls: list[str] = []

    def __getattribute__(self, name: str):  # type: ignore[no-untyped-def]
        if name.startswith("on_"):
            calls = object.__getattribute__(self, "calls")
            return lambda *a: calls.append(name[3:])
        return object.__getattribute__(self, name)


def test_observer_receives_every_product_in_order(single):
    sim, _ = single
    obs = _Recorder()
    r = find_graspable_surfaces(sim.scan, Config(), observer=obs)
    assert obs.calls == ["scan", "noise", "edges", "lines", "vertices", "hypotheses",
                         "verification", "selection", "surfaces", "result"]
    assert set(STAGES) <= {f for f in r.__dataclass_fields__}


def test_result_json_is_the_public_interface(single):
    _, r = single
    j = r.to_json()
    # issue #21 added "ambiguous" and the per-surface height and size keys; none renamed
    assert set(j) == {"surfaces", "ambiguous", "timing_ms", "version"}
    s = j["surfaces"][0]
    assert set(s) == {"id", "center", "normal", "x_axis", "y_axis", "width", "length",
                      "grasp_point", "score", "covariance", "pick_order", "bulge",
                      "height", "height_sigma", "height_source", "sku", "size_flagged"}
    assert j["ambiguous"] == []
    assert np.array(s["covariance"]).shape == (6, 6)
    assert set(j["timing_ms"]) >= {"edges", "lines", "vertices", "hypotheses", "total"}


@pytest.mark.parametrize("kind,seed", [("pallet", 1), ("mixed", 2), ("partial", 0)])
def test_simulated_scenes_end_to_end(kind, seed):
    # seeded regression: pins that real scenes give mostly right and no wrong surfaces
    sim = simulate(kind, seed=seed)
    r = find_graspable_surfaces(sim.scan, Config())
    m = match_surfaces(r.surfaces, sim.truth)
    assert m.fp == 0
    # mostly right: three in four exposed faces at least (all of them today)
    assert m.tp >= max(1, 0.75 * int(sim.truth.fully_exposed.sum()))


# --- holes the sensor leaves on a lid are no box ends ----------------------------------------


def _lid_hole(sim, shape_m: tuple[float, float], share: float, seed: int) -> Scan:
    """``sim``'s scan with a strip of ``shape_m`` (across, along the lid's first side,
    metres) at the lid's centre in which a ``share`` of the pixels has no return."""
    import cv2

    s = sim.scan
    q = s.sensor.project(np.asarray(sim.truth.corners[0]))
    px = float(np.nanmedian(s.range)) * s.sensor.pixel_angle  # metres per pixel, about
    t = (q[1] - q[0]) / np.linalg.norm(q[1] - q[0])
    n = (q[3] - q[0]) / np.linalg.norm(q[3] - q[0])
    c, a, b = q.mean(0), 0.5 * shape_m[1] / px, 0.5 * shape_m[0] / px
    signs = ((-1, -1), (1, -1), (1, 1), (-1, 1))
    poly = np.array([c + sa * a * t + sb * b * n for sa, sb in signs])
    mask = np.zeros(s.range.shape, np.uint8)
    cv2.fillPoly(mask, [np.rint(poly).astype(np.int32)], 1)
    r = s.range.copy()
    r[(mask > 0) & (np.random.default_rng(seed).random(r.shape) < share)] = np.nan
    return Scan(range=r, sensor=s.sensor)


@pytest.mark.parametrize("distance,width", [(1.5, 320), (2.5, 640)])
def test_a_box_is_found_whole_with_a_dark_label_or_lossy_tape_the_sensor_loses(distance, width):
    # a time-of-flight camera loses a dark label; shiny tape loses a share of its pixels in
    # runs as long as a seam's dashed holes: neither ends the box (a try at reading holes as
    # seams, e76b47c, lost this box to the tape at 30 and 50 %, its first version to the
    # label too)
    sim = scene([box(0.0, 0.0, 0.40, 0.30, 0.25)], distance=distance, seed=1, width=width,
                height=width * 3 // 4, f=width * 0.69)
    cfg = Config(min_edge=0.15, max_edge=0.6)
    for shape_m, share in (((0.07, 0.12), 1.0), ((0.05, 0.40), 0.3), ((0.05, 0.40), 0.5)):
        r = find_graspable_surfaces(_lid_hole(sim, shape_m, share, 1), cfg)
        m = match_surfaces(r.surfaces, sim.truth)
        assert m.tp == 1 and m.fp == 0, (shape_m, share)

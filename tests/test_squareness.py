"""The angle_tolerance estimate: near zero for a square-seeing sensor, up for a shearing one."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest
from cli_run import invoke
from real_data import MOSD
from scenes import box, scene, wall

from boxloc.calibrate.squareness import corner_departures, estimate_angle_tolerance
from boxloc.config import Config
from boxloc.errors import InputError
from boxloc.scan import Scan
from boxloc.simulate import save_npz, simulate


@pytest.fixture(scope="module")
def boxes() -> list[Scan]:
    """Three scenes of separate boxes at 1.2 m: plenty of square corners."""
    out = []
    for seed, yaw in ((1, 0.2), (2, 0.7), (3, 1.1)):
        b = [box(-0.35, -0.2, 0.30, 0.40, 0.3, yaw), box(0.3, 0.25, 0.25, 0.35, 0.3, -yaw),
             box(0.3, -0.3, 0.2, 0.3, 0.25, yaw / 2)]
        out.append(scene(b, distance=1.2, seed=seed).scan)
    return out


def _sheared(scan: Scan, s: float) -> Scan:
    """The scan's cloud with x += s * y (sensor frame): the sensor no longer sees squares."""
    P = scan.points.astype(np.float64).copy()
    P[..., 0] += s * P[..., 1]
    return Scan.from_points(P)


def test_a_square_seeing_sensor_needs_no_more_than_the_default(boxes):
    tol, rep = estimate_angle_tolerance(boxes, Config())
    assert rep["n_corners"] >= 10
    assert tol < Config().angle_tolerance
    assert rep["sigma_deg"] < 1.0


def test_a_shearing_sensor_raises_the_estimate(boxes):
    base, _ = estimate_angle_tolerance(boxes, Config())
    # a shear of 0.12 turns a square corner by up to ~7 degrees, depending on its yaw
    tol, rep = estimate_angle_tolerance([_sheared(s, 0.12) for s in boxes], Config())
    assert math.radians(1.5) < tol < math.radians(10.0), rep
    assert tol > 5 * base


def test_departures_are_within_the_bound_and_propagated_variances_positive(boxes):
    d, v = corner_departures(boxes[0], Config())
    assert len(d) == len(v) > 0
    assert np.all((d >= 0) & (d <= math.radians(45.0)))
    assert np.all(v > 0)


def test_departures_follow_the_configs_draw_of_the_trials(boxes):
    # the line stage draws its trials as the pipeline does: another trial_seed is another
    # draw (other lines, so other corners), and each draw is reproduced bit for bit
    d0, _ = corner_departures(boxes[0], Config())
    d2, _ = corner_departures(boxes[0], Config(trial_seed=2))
    assert not np.array_equal(d0, d2)
    assert np.array_equal(d2, corner_departures(boxes[0], Config(trial_seed=2))[0])


def test_a_scan_without_corners_is_an_input_error():
    # a wall 1.5 m ahead, seen by a 64 x 48 pinhole: no edges, no corners
    with pytest.raises(InputError, match="too few line pairs"):
        estimate_angle_tolerance([Scan.from_points(wall())], Config())


def test_cli_prints_a_toml_line(tmp_path, boxes):
    p = tmp_path / "pallet.npz"
    save_npz(simulate("pallet", seed=1), p)
    r = invoke("calibrate-angles", str(p))
    assert r.returncode == 0, r.stderr
    tol = tomllib.loads(r.stdout)["angle_tolerance"]
    assert 0.0 <= tol < Config().angle_tolerance
    Config().with_overrides([f"angle_tolerance={tol}"])  # usable as given
    bad = invoke("calibrate-angles", str(tmp_path / "missing.npz"))
    assert bad.returncode == 2
    assert "missing.npz" in bad.stderr and "Traceback" not in bad.stderr


@pytest.mark.real_data("learn0.pcd", "learn1.pcd", "learn2.pcd", "learn3.pcd")
def test_the_kinect_shears_box_tops_by_degrees():
    from boxloc.io import read_scan

    cfg = Config().with_overrides(["min_edge=0.035", "noise.sigma0=0.000176",
                                   "noise.k1=0.000998", "noise.k2=0.0"])
    scans = [read_scan(MOSD / f"learn{k}.pcd") for k in range(4)]
    tol, rep = estimate_angle_tolerance(scans, cfg)
    assert math.radians(2.0) < tol < math.radians(10.0), rep

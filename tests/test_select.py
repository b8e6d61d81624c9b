"""Stage 7: MDL selection."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from boxloc.config import Config
from boxloc.products import SelectReason, Verification
from boxloc.stages.select import face_units, select
from boxloc.stats import TestTable

#: Pixels per square metre of the synthetic faces below: a 0.15 m face has 1000 points.
DENSITY = 1000 / 0.15**2


def _verification(pixel_sets: list[np.ndarray], accepted: list[bool]) -> Verification:
    k = len(pixel_sets)
    offs = np.zeros(k + 1, np.int64)
    offs[1:] = np.cumsum([len(p) for p in pixel_sets])
    n = np.array([len(p) for p in pixel_sets], np.int32)
    z = np.zeros(k)
    return Verification(
        attempt=np.arange(k, dtype=np.int32), hypothesis=np.arange(k, dtype=np.int32),
        n_inside=n, n_valid=n, n_inliers=n, n_front=n * 0, n_behind=n * 0,
        inlier_fraction=z + 1, mean_distance=z, sigma_mean=z + 1e-3,
        n_interior_edges=n * 0, plane_centers=np.zeros((k, 3)), plane_normals=np.zeros((k, 3)),
        plane_covariances=np.zeros((k, 6, 6)), rms=z, error=n * 0.9,
        accepted=np.array(accepted), reason=np.zeros(k, np.uint8), inlier_offsets=offs,
        inlier_pixels=np.concatenate(pixel_sets).astype(np.int32),
        tests=TestTable.empty(0.01),
    )


def _dims(ver: Verification, density: float = DENSITY) -> Any:
    """Square attempts whose area holds their pixels at ``density`` (a HypothesisSet's
    ``att_width``/``att_length``, all ``select`` reads of it)."""
    side = np.sqrt(ver.n_inside / density)
    return SimpleNamespace(att_width=side, att_length=side)


def _select(ver: Verification, config: Config | None = None, density: float = DENSITY) -> Any:
    return select(ver, _dims(ver, density), config=config or Config(min_edge=0.15))


def test_duplicates_of_one_face_give_one_surface():
    a = np.arange(0, 5000)
    b = np.arange(40, 5040)  # the same face, a pixel row off
    s = _select(_verification([a, b], [True, True]))
    assert s.chosen.sum() == 1
    assert s.chosen[0]  # equal gains: the first candidate is taken (deterministic order)
    loser = int(np.flatnonzero(~s.chosen)[0])
    assert s.reason[loser] == SelectReason.OVERLAPS_CHOSEN
    assert s.beaten_by[loser] == int(np.flatnonzero(s.chosen)[0])
    assert s.objective > 0


def test_disjoint_faces_are_all_kept_and_tiny_ones_dropped():
    sets = [np.arange(0, 3000), np.arange(3000, 7000), np.arange(8000, 8050)]
    s = _select(_verification(sets, [True, True, True]))
    assert s.chosen.tolist() == [True, True, False]
    assert s.reason[2] == SelectReason.NO_GAIN
    assert list(s.order) == [1, 0]  # the larger gain first


def test_only_verified_attempts_compete():
    sets = [np.arange(0, 3000), np.arange(3000, 7000)]
    s = _select(_verification(sets, [False, True]))
    assert s.candidates.tolist() == [1]
    assert s.Q.shape == (1, 1)
    empty = _select(_verification(sets, [False, False]))
    assert len(empty) == 0 and empty.objective == 0.0


def _scene(points_per_face: int) -> Verification:
    """Two copies of one face a pixel row apart, a face beside them and a sliver, each
    sampled so that a smallest (0.15 m) face would show ``points_per_face`` points."""
    u = points_per_face
    sizes = [u, u, 2 * u, max(u // 20, 1)]
    starts = [0, u // 10, 2 * u, 5 * u]
    return _verification([np.arange(s, s + n) for s, n in zip(starts, sizes)], [True] * 4)


@pytest.mark.parametrize("u", [130, 1550, 24000])
def test_face_units_are_the_points_of_a_smallest_face(u: int) -> None:
    ver = _scene(u)
    density = u / 0.15**2
    units = face_units(ver, _dims(ver, density), np.arange(4), 0.15)
    np.testing.assert_allclose(units, u, rtol=1e-12)


def test_the_selection_does_not_depend_on_the_sampling_density() -> None:
    # a 320x240 camera 3.5 m away shows a 0.15 m face as ~130 points, a 1280x960 one at
    # 1 m as ~24000: the same scene must give the same choice
    chosen = []
    for u in (130, 1550, 24000):
        s = _select(_scene(u), density=u / 0.15**2)
        chosen.append(s.chosen.tolist())
        np.testing.assert_allclose(s.unit, u, rtol=1e-12)
        assert s.face_points == Config().mdl_face_points
    assert chosen == [[True, False, True, False]] * 3


def test_raw_points_lose_the_far_face() -> None:
    # what the density-free units fix: counted in raw points (Leonardis, logs before
    # mdl_face_points), a model's cost K3 N = 80 points outweighs what a 130-point face
    # gains (K1 n - K2 xi = 0.55 n), though the face twice its size still pays
    raw = Config(min_edge=0.15, mdl_face_points=0.0)
    far = _select(_scene(130), raw, density=130 / 0.15**2)
    near = _select(_scene(1550), raw, density=1550 / 0.15**2)
    assert far.chosen.tolist() == [False, False, True, False]
    assert far.reason[0] == SelectReason.NO_GAIN
    assert near.chosen.tolist() == [True, False, True, False]
    assert np.isnan(far.unit).all()


def test_raw_points_reproduce_the_selection_before_the_face_units() -> None:
    # mdl_face_points = 0 is the recorded value of every older log: Q as it was, bit for bit
    ver = _scene(900)
    s = select(ver, _dims(ver), config=Config(min_edge=0.15, mdl_face_points=0.0))
    n = ver.n_inliers.astype(np.int64)
    expect = np.diag(1.0 * n - 0.5 * ver.error - 10.0 * 8)
    assert np.array_equal(np.diag(s.Q), np.diag(expect))

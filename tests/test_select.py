"""Stage 7: MDL selection."""

from __future__ import annotations

import numpy as np

from boxloc.config import Config
from boxloc.products import SelectReason, Verification
from boxloc.stages.select import select
from boxloc.stats import TestTable


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


def test_duplicates_of_one_face_give_one_surface():
    a = np.arange(0, 5000)
    b = np.arange(40, 5040)  # the same face, a pixel row off
    s = select(_verification([a, b], [True, True]), config=Config())
    assert s.chosen.sum() == 1
    assert s.chosen[0]  # equal gains: the first candidate is taken (deterministic order)
    loser = int(np.flatnonzero(~s.chosen)[0])
    assert s.reason[loser] == SelectReason.OVERLAPS_CHOSEN
    assert s.beaten_by[loser] == int(np.flatnonzero(s.chosen)[0])
    assert s.objective > 0


def test_disjoint_faces_are_all_kept_and_tiny_ones_dropped():
    sets = [np.arange(0, 3000), np.arange(3000, 7000), np.arange(8000, 8050)]
    s = select(_verification(sets, [True, True, True]), config=Config())
    assert s.chosen.tolist() == [True, True, False]
    assert s.reason[2] == SelectReason.NO_GAIN
    assert list(s.order) == [1, 0]  # the larger gain first


def test_only_verified_attempts_compete():
    sets = [np.arange(0, 3000), np.arange(3000, 7000)]
    s = select(_verification(sets, [False, True]), config=Config())
    assert s.candidates.tolist() == [1]
    assert s.Q.shape == (1, 1)
    empty = select(_verification(sets, [False, False]), config=Config())
    assert len(empty) == 0 and empty.objective == 0.0

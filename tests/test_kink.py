"""Tests for boxloc.stages.kink: the slope jump where two bulged lids meet."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage

from boxloc.stages.kink import kink_critical, kink_z

SPACING = 0.003  # m between points
ALPHA = 0.01


def _grid(width: float, length: float) -> tuple[np.ndarray, np.ndarray]:
    u, v = np.meshgrid(np.arange(0.0, width, SPACING), np.arange(0.0, length, SPACING))
    return u.ravel(), v.ravel()


def _lid(u: np.ndarray, v: np.ndarray, u0: float, u1: float, length: float,
         bulge: float) -> np.ndarray:
    """A carton's bulged lid over u0..u1 (0 outside): bulge (1 - s^2)(1 - t^2)."""
    s = (u - 0.5 * (u0 + u1)) / (0.5 * (u1 - u0))
    t = (v - 0.5 * length) / (0.5 * length)
    inside = (u >= u0) & (u <= u1)
    return np.where(inside, bulge * (1 - s * s) * (1 - t * t), 0.0)


def _noise(rng: np.random.Generator, shape: tuple[int, int], sigma: float,
           corr_px: float, heavy: bool) -> np.ndarray:
    """Spatially correlated noise (a white field smoothed by a Gaussian of ``corr_px``
    points, rescaled to ``sigma``), heavy-tailed on request (Student's t, 3 dof)."""
    e = rng.standard_t(3, size=shape) if heavy else rng.standard_normal(shape)
    if corr_px > 0:
        e = ndimage.gaussian_filter(e, corr_px)
    return (sigma * e / e.std()).ravel()


def test_two_bulged_lids_show_their_seam() -> None:
    # two 0.26 x 0.52 m cartons side by side, bulged 8.8 mm, 5 mm noise correlated over a
    # few points: the face a wrong rectangle spanned on a development weave
    W, L = 0.52, 0.52
    u, v = _grid(W, L)
    rng = np.random.default_rng(3)
    w = (_lid(u, v, 0.0, 0.26, L, 0.0088) + _lid(u, v, 0.26, W, L, 0.0088)
         + _noise(rng, (len(np.unique(v)), len(np.unique(u))), 0.005, 2.0, False))
    z, dof = kink_z(u, v, w, 0, [0.26], W, L, SPACING)
    assert dof > 8
    assert z > kink_critical(ALPHA, dof)
    # ... and nothing along the other axis, where no seam runs
    z1, dof1 = kink_z(u, v, w, 1, [0.26], W, L, SPACING)
    assert z1 <= kink_critical(ALPHA, dof1)


def test_three_in_a_row_show_their_seams_together() -> None:
    W, L = 0.6, 0.4
    u, v = _grid(W, L)
    rng = np.random.default_rng(5)
    w = sum(_lid(u, v, a, a + 0.2, L, 0.006) for a in (0.0, 0.2, 0.4))
    w = w + _noise(rng, (len(np.unique(v)), len(np.unique(u))), 0.003, 1.0, False)
    z, dof = kink_z(u, v, w, 0, [0.2, 0.4], W, L, SPACING)
    assert z > kink_critical(ALPHA, dof)


@pytest.mark.parametrize("heavy", [False, True])
def test_one_bulged_lid_keeps_the_level(heavy: bool) -> None:
    # one carton, bulged, under correlated (and heavy-tailed) noise: the test at its
    # middle fires at about alpha, not more (the sandwich variance widens with the
    # correlation and the tails)
    W, L = 0.36, 0.30
    u, v = _grid(W, L)
    shape = (len(np.unique(v)), len(np.unique(u)))
    lid = _lid(u, v, 0.0, W, L, 0.008)
    rng = np.random.default_rng(11 if heavy else 7)
    fired, n = 0, 200
    for _ in range(n):
        w = lid + _noise(rng, shape, 0.004, 2.5, heavy)
        z, dof = kink_z(u, v, w, 0, [0.5 * W], W, L, SPACING)
        fired += bool(z > kink_critical(ALPHA, dof))
    # 2 expected; 9 or more has a probability of about 2e-4 at the level
    assert fired <= 8


def test_a_ridge_is_no_seam() -> None:
    # tape along the lid's middle, 2 mm thick and 5 cm wide: a ridge, not a V
    W, L = 0.4, 0.3
    u, v = _grid(W, L)
    rng = np.random.default_rng(2)
    w = (np.where(np.abs(u - 0.2) < 0.025, 0.002, 0.0)
         + _noise(rng, (len(np.unique(v)), len(np.unique(u))), 0.001, 0.0, False))
    z, dof = kink_z(u, v, w, 0, [0.2], W, L, SPACING)
    assert z < 0 < dof


def test_too_few_points_or_blocks_give_no_statistic() -> None:
    u, v = _grid(0.03, 0.03)
    z, dof = kink_z(u, v, np.zeros_like(u), 0, [0.015], 0.03, 0.03, SPACING)
    assert math.isnan(z) and dof == 0
    assert kink_critical(ALPHA, 0) == math.inf


def _two_lids_across(rng: np.random.Generator, wall: bool) -> tuple[np.ndarray, ...]:
    """Points of a 0.25 x 0.4 m face and 3 cm beyond its side u = 0.25: a neighbour's
    bulged lid (a V at the side), or a wall rising there (only its foot near the plane)."""
    u, v = _grid(0.28, 0.4)
    w = _lid(u, v, 0.0, 0.25, 0.4, 0.008) + rng.normal(0.0, 0.0008, u.shape)
    if wall:  # the wall's points beyond its first 2 mm of rise are off the plane
        beyond = u > 0.25
        w = np.where(beyond, 2.0 * (u - 0.25), w)
        keep = ~beyond | (w < 0.002)
        return u[keep], v[keep], w[keep]
    return u, v, w + _lid(u, v, 0.25, 0.5, 0.4, 0.008)


def test_a_side_between_two_bulged_lids_is_a_kink() -> None:
    from boxloc.stages.kink import side_kink_z
    u, v, w = _two_lids_across(np.random.default_rng(4), wall=False)
    z, dof = side_kink_z(u, v, w, 0, 0.25, -1.0, 0.0, 0.4, 0.03, SPACING)
    assert z > kink_critical(ALPHA / 20, dof)  # at a seam level of alpha over 10 vertices


def test_a_wall_rising_from_a_side_is_no_kink() -> None:
    # the foot of a wall bends the plane as sharply, but nothing lies beyond it on the
    # plane: no lid meets this one there
    from boxloc.stages.kink import side_kink_z
    u, v, w = _two_lids_across(np.random.default_rng(4), wall=True)
    z, dof = side_kink_z(u, v, w, 0, 0.25, -1.0, 0.0, 0.4, 0.03, SPACING)
    assert math.isnan(z) and dof == 0

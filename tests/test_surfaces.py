"""The result stage: a bulged lid's centre on the box's top (its rim), not above it."""

from __future__ import annotations

import numpy as np
import pytest

from boxloc.config import Config
from boxloc.evaluate.metrics import match_surfaces
from boxloc.pipeline import find_graspable_surfaces
from boxloc.stages.surfaces import fit_bulge
from boxloc.stats import TestKind
from tests.scenes import box, scene

X, Y, N = np.eye(3)


def _lid(k: float, seed: int = 0, sigma: float = 0.001) -> tuple[np.ndarray, np.ndarray]:
    """Points of a 0.3 x 0.4 m lid at z = 1.5 with bulge k toward the sensor (-z), noisy."""
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(-1, 1, (2, 3000))
    h = 0.002 + 0.001 * u + k * (1 - u * u) * (1 - v * v)  # rim 2 mm up, tilted a little
    P = np.stack([0.15 * u, 0.2 * v, 1.5 - h - rng.normal(0, sigma, u.size)], axis=1)
    return P, np.full(u.size, sigma)


@pytest.mark.parametrize("k", [0.0, 0.004, 0.012])
def test_fit_bulge_finds_the_rim_and_the_bulge(k: float) -> None:
    P, s = _lid(k)
    fit = fit_bulge(P, np.array([0.0, 0.0, 1.5]), X, Y, -N, 0.3, 0.4, s)
    assert fit is not None
    coef, cov = fit
    sd = np.sqrt(np.diag(cov))
    assert abs(coef[0] - 0.002) < 4 * sd[0] and sd[0] < 2e-4  # the rim, not the mean
    assert abs(coef[1] - 0.001) < 4 * sd[1]
    assert abs(coef[3] - k) < 4 * sd[3]


def _fit(seed: int) -> tuple[np.ndarray, np.ndarray]:
    P, s = _lid(0.006, seed)
    fit = fit_bulge(P, np.array([0.0, 0.0, 1.5]), X, Y, -N, 0.3, 0.4, s)
    assert fit is not None
    return fit


def test_fit_bulge_covariance_matches_the_scatter() -> None:
    ks = np.array([_fit(seed)[0] for seed in range(40)])
    cov = _fit(0)[1]
    assert ks.std(axis=0)[[0, 3]] == pytest.approx(np.sqrt(np.diag(cov))[[0, 3]], rel=0.35)


def test_fit_bulge_refuses_points_on_one_line() -> None:
    u = np.linspace(-0.1, 0.1, 40)
    P = np.stack([u, np.full_like(u, 0.05), np.full_like(u, 1.5)], axis=1)
    assert fit_bulge(P, np.array([0.0, 0.0, 1.5]), X, Y, -N, 0.3, 0.1,
                     np.full(40, 0.001)) is None


@pytest.mark.parametrize("bulge", [0.0, 0.01])
def test_a_bulged_lid_has_its_centre_on_the_box_top(bulge: float) -> None:
    sim = scene([box(0.02, -0.03, 0.40, 0.30, 0.25, 0.3)], seed=3, bulge=bulge)
    r = find_graspable_surfaces(sim.scan, Config())
    s, gt = r.surfaces, sim.truth
    assert match_surfaces(s, gt).tp == 1
    t = s.tests.of_kind(TestKind.SURFACE_BULGE)
    assert len(t) == 1 and t.a[0] == s.attempt[0] and t.dof[0] == 1
    # the plane of the points lies 4/9 of the bulge above the top (4.4 mm for 1 cm)
    assert abs((s.centers[0] - gt.centers[0]) @ gt.normals[0]) < 0.001
    assert s.grasp_points[0] == pytest.approx(s.centers[0])
    if bulge:
        assert not t.accepted[0]
        assert s.bulge[0] == pytest.approx(bulge, abs=0.002)
    else:
        assert t.accepted[0]
        assert abs(s.bulge[0]) < 0.001

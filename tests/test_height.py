"""A box's height (issue #21, point 3): from its visible side face, from the step down
beyond its sides, from the matched carton size, or none."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scenes import box, scene

from boxloc.config import Config
from boxloc.pipeline import find_graspable_surfaces
from boxloc.products import HeightSource
from boxloc.stages.height import box_heights, height_context
from boxloc.stats import TestKind

CFG = Config(min_edge=0.15, max_edge=0.6)


def _one_surface(tilt: float, height: float) -> tuple[object, object]:
    sim = scene([box(0.0, 0.0, 0.3, 0.4, height)], distance=1.5, tilt=tilt, bevel=0.0)
    r = find_graspable_surfaces(sim.scan, CFG)
    assert len(r.surfaces) == 1
    return sim, r


@pytest.mark.parametrize("height", [0.2, 0.35])
def test_height_from_the_side_face_seen_at_a_slant(height: float) -> None:
    # tilted 0.35 rad: two side faces face the sensor, down to the pallet
    _, r = _one_surface(0.35, height)
    s = r.surfaces
    assert s.height_source[0] == HeightSource.SIDE
    # the estimate's sigma is the flatness prior (5 mm) and the foot's spread; the error
    # must be within 3 sigma of it, and within the 10 mm
    err = abs(s.height[0] - height)
    assert err <= 3 * s.height_sigma[0] and err <= 0.010
    rows = s.tests.of_kind(TestKind.BOX_HEIGHT)
    assert len(rows) == 1 and rows.b[0] == HeightSource.SIDE and rows.accepted[0]
    j = r.to_json()["surfaces"][0]
    assert j["height_source"] == "side" and j["height"] == pytest.approx(s.height[0])


@pytest.mark.parametrize("height", [0.2, 0.35])
def test_height_from_the_step_down_to_the_pallet_seen_from_above(height: float) -> None:
    # straight down: no side face is seen; beyond every side lies the pallet's top
    _, r = _one_surface(0.0, height)
    s = r.surfaces
    assert s.height_source[0] == HeightSource.STEP
    err = abs(s.height[0] - height)
    assert err <= 3 * s.height_sigma[0] and err <= 0.010
    assert r.to_json()["surfaces"][0]["height_source"] == "step"


def test_without_a_measurement_the_listed_height_else_none() -> None:
    sim, r = _one_surface(0.0, 0.2)
    # the surface moved far from every point: nothing beyond its sides is seen
    s = dataclasses.replace(r.surfaces, corners=r.surfaces.corners + np.array([5.0, 0, 0]),
                            centers=r.surfaces.centers + np.array([5.0, 0, 0]))
    ctx = height_context(sim.scan, CFG, r.hypotheses.up)
    h, sig, src, tests = box_heights(ctx, s, CFG)
    assert src[0] == HeightSource.NONE and math.isnan(h[0]) and len(tests) == 0
    h, sig, src, tests = box_heights(ctx, s, CFG, sku_height=np.array([0.25]))
    assert src[0] == HeightSource.SKU and h[0] == 0.25 and sig[0] == CFG.size_tolerance


def test_a_flush_stack_measures_its_whole_height_unless_the_listed_height_says_otherwise(
        ) -> None:
    from scenes import TOP

    lower, upper = box(0.0, 0.0, 0.3, 0.4, 0.2), [0.0, 0.0, TOP + 0.3, 0.3, 0.4, 0.2, 0.0]
    sim = scene([lower, upper], distance=1.5, tilt=0.35, bevel=0.0)
    r = find_graspable_surfaces(sim.scan, CFG)
    s = r.surfaces
    assert len(s) == 1 and s.height_source[0] == HeightSource.SIDE
    # from the top alone, two flush sharp-edged cartons are one tall one (a limit)
    assert abs(s.height[0] - 0.4) <= 0.010
    r = find_graspable_surfaces(sim.scan, dataclasses.replace(CFG, box_sizes=((0.3, 0.4, 0.2),)))
    s = r.surfaces
    assert s.sku[0] == 0 and s.height_source[0] == HeightSource.SKU and s.height[0] == 0.2

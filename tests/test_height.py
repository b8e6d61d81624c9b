"""A box's height (issue #21, point 3): from its visible side face, from the step down
beyond its sides, from the matched carton size, or none."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from scenes import box, scene

from boxloc.config import Config
from boxloc.pipeline import find_graspable_surfaces
from boxloc.products import HeightSource
from boxloc.stages.height import box_heights, flush_layers, height_context
from boxloc.stats import TestKind, TestTable

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


def test_a_measurement_that_agrees_with_the_listed_height_is_combined_with_it() -> None:
    sim, r = _one_surface(0.35, 0.2)
    ctx = height_context(sim.scan, CFG, r.hypotheses.up)
    h0, s0, src0, _ = box_heights(ctx, r.surfaces, CFG)
    assert src0[0] == HeightSource.SIDE
    tol = CFG.size_tolerance
    # a listed 0.21 m agrees: the two weighed by their variances, the source the side's
    h, sig, src, tests = box_heights(ctx, r.surfaces, CFG, sku_height=np.array([0.21]))
    w_m, w_s = 1 / s0[0] ** 2, 1 / tol**2
    assert src[0] == HeightSource.SIDE
    assert h[0] == pytest.approx((w_m * h0[0] + w_s * 0.21) / (w_m + w_s))
    assert min(h0[0], 0.21) < h[0] < max(h0[0], 0.21)
    assert sig[0] == pytest.approx((w_m + w_s) ** -0.5) and sig[0] < min(s0[0], tol)
    row = tests.of_kind(TestKind.BOX_HEIGHT)
    assert row.statistic[0] == h[0] and row.critical[0] == sig[0]
    agree = tests.of_kind(TestKind.HEIGHT_SKU_AGREEMENT)
    assert len(agree) == 1 and agree.accepted[0] and agree.b[0] == HeightSource.SIDE
    assert agree.statistic[0] == pytest.approx((h0[0] - 0.21) ** 2 / (s0[0] ** 2 + tol**2))
    # a listed 0.3 m does not: the listed height, as the carton's
    h, sig, src, tests = box_heights(ctx, r.surfaces, CFG, sku_height=np.array([0.3]))
    assert src[0] == HeightSource.SKU and h[0] == 0.3 and sig[0] == tol
    agree = tests.of_kind(TestKind.HEIGHT_SKU_AGREEMENT)
    assert len(agree) == 1 and not agree.accepted[0] and agree.statistic[0] > agree.critical[0]


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


@pytest.mark.parametrize("tilt, kind", [(0.35, "side"), (0.0, "step")])
def test_a_measurement_deeper_than_any_carton_is_no_height(tilt: float, kind: str) -> None:
    # three flush 0.3 x 0.4 x 0.15 m cartons: the side face runs 0.45 m down the stack (at
    # a slant), or the step beyond every side drops 0.45 m to the pallet (from above)
    from scenes import TOP

    lower = box(0.0, 0.0, 0.3, 0.4, 0.15)
    stack = [lower] + [[0.0, 0.0, TOP + 0.15 * j + 0.075, 0.3, 0.4, 0.15, 0.0]
                       for j in (1, 2)]
    sim = scene(stack, distance=1.5, tilt=tilt, bevel=0.0)
    # a site whose largest carton edge is 0.6 m: the 0.45 m is reported (one tall carton)
    r = find_graspable_surfaces(sim.scan, CFG)
    s = r.surfaces
    assert len(s) == 1 and abs(s.height[0] - 0.45) <= 0.010
    assert s.height_source[0] == (HeightSource.SIDE if kind == "side" else HeightSource.STEP)
    assert len(s.tests.of_kind(TestKind.HEIGHT_WITHIN_BOX)) == 0
    # where no carton has an edge over 0.4 m, the 0.45 m is a stack's: no height, and the
    # rows say which measurements reached past the tallest carton
    r = find_graspable_surfaces(sim.scan, dataclasses.replace(CFG, max_edge=0.4))
    s = r.surfaces
    assert len(s) == 1 and s.height_source[0] == HeightSource.NONE and math.isnan(s.height[0])
    rows = s.tests.of_kind(TestKind.HEIGHT_WITHIN_BOX)
    assert len(rows) >= 1 and not rows.accepted.any() and (rows.a == s.attempt[0]).all()
    assert (rows.statistic > rows.critical).all() and (rows.critical > 0.4).all()
    assert np.all(np.abs(rows.statistic - 0.45) <= 0.015)
    assert ((rows.b < 4) if kind == "side" else (rows.b >= 4)).any()
    assert r.to_json()["surfaces"][0]["height_source"] == "none"


def _layer_on_a_stack(ledge: float) -> tuple[object, object]:
    """Two 0.3 x 0.4 x 0.2 m cartons A and B 4 mm apart on two others, seen at a slant: A
    is flush with the carton under it, B's stands out by ``ledge`` on every side but the
    one facing A."""
    from scenes import TOP

    h, g = 0.2, 0.004
    a = [-0.15 - g / 2, 0.0, TOP + h + h / 2, 0.3, 0.4, h, 0.0]
    b = [0.15 + g / 2, 0.0, TOP + h + h / 2, 0.3, 0.4, h, 0.0]
    under_a = box(-0.15 - g / 2, 0.0, 0.3, 0.4, h)
    under_b = box(0.15 + g / 2 + ledge / 2, 0.0, 0.3 + ledge, 0.4 + 2 * ledge, h)
    sim = scene([under_a, under_b, a, b], distance=1.5, tilt=0.35, bevel=0.0)
    return sim, find_graspable_surfaces(sim.scan, CFG)


def test_a_side_face_hidden_below_by_a_neighbour_across_a_gap_is_no_height() -> None:
    # 15 mm between 0.25 m cartons, seen at a slant: the face across the gap shows its top
    # 79 mm, then the neighbour's edge hides it. That run is no height (it had been every
    # top's, the flush layer's smallest); what else is seen gives 0.25 m
    boxes = [box(-0.1675, 0.0, 0.32, 0.4, 0.25), box(0.1675, 0.0, 0.32, 0.4, 0.25),
             box(0.0, 0.415, 0.3, 0.4, 0.25)]
    r = find_graspable_surfaces(scene(boxes, distance=1.5, tilt=0.2, bevel=0.0).scan, CFG)
    s = r.surfaces
    assert len(s) == 3
    assert np.all(np.abs(s.height - 0.25) <= 0.010), s.height


def test_a_flush_layer_takes_its_smallest_height_measurement() -> None:
    # A's side runs down the stack (0.4 m); B's ends on the ledge at its foot (0.2 m): one
    # layer, one support, so A takes B's height, and a LAYER_HEIGHT row says so
    _, r = _layer_on_a_stack(0.05)
    s = r.surfaces
    assert len(s) == 2
    assert np.all(np.abs(s.height - 0.2) <= 0.010), s.height
    rows = s.tests.of_kind(TestKind.LAYER_HEIGHT)
    assert len(rows) == 1 and rows.accepted[0] and rows.statistic[0] > rows.critical[0]
    taker = int(np.flatnonzero(s.attempt == rows.a[0])[0])
    giver = int(np.flatnonzero(s.attempt == rows.b[0])[0])
    assert taker != giver and s.height[taker] == s.height[giver]


def test_tops_that_do_not_touch_keep_their_own_heights() -> None:
    # the same measurements, the two tops moved apart in the surface set: not one layer
    sim, r = _layer_on_a_stack(0.05)
    s = r.surfaces
    far = dataclasses.replace(s, corners=s.corners.copy(), centers=s.centers.copy())
    far.corners[1] += 0.2 * s.x_axis[1]
    far.centers[1] += 0.2 * s.x_axis[1]
    assert len(set(flush_layers(height_context(sim.scan, CFG, r.hypotheses.up), far, CFG))) == 2
    same = flush_layers(height_context(sim.scan, CFG, r.hypotheses.up), s, CFG)
    assert same[0] == same[1]


def test_explain_says_a_height_came_from_the_flush_layer(tmp_path: Path) -> None:
    from recorder.mcap.sink import McapRecorder
    from replay.explain import explain, format_explanation

    sim, _ = _layer_on_a_stack(0.05)
    path = tmp_path / "layer.mcap"
    with McapRecorder(path) as rec:
        r = find_graspable_surfaces(sim.scan, CFG, observer=rec)
    taker = int(np.flatnonzero(r.surfaces.tests.of_kind(TestKind.LAYER_HEIGHT).accepted)[0])
    a = int(r.surfaces.tests.of_kind(TestKind.LAYER_HEIGHT).a[taker])
    k = int(np.flatnonzero(r.surfaces.attempt == a)[0])
    d = explain(path, 0, surface=k)["surfaces"][0]["height"]
    assert [t["kind"] for t in d["tests"]] == ["LAYER_HEIGHT", "BOX_HEIGHT"]
    text = format_explanation(explain(path, 0, surface=k))
    assert "of its flush layer" in text and "LAYER_HEIGHT" in text and "ACCEPTED" in text


def test_a_layer_height_decision_that_flips_between_versions_is_a_flipped_test() -> None:
    from replay.diff import ItemMatch, flipped_tests

    def rows(take: bool, giver: int) -> TestTable:
        return TestTable.decision(TestKind.LAYER_HEIGHT, [7], [giver], [3.0 if take else 1.0],
                                  [2.326], [take], 0.01)

    # attempt 7 of the base is attempt 9 of the candidate; the layer mate renumbers too
    maps = {"attempts": ItemMatch(10, 10, pairs=[(7, 9)])}
    base, cand = rows(True, 4), TestTable.decision(TestKind.LAYER_HEIGHT, [9], [5], [1.0],
                                                   [2.326], [False], 0.01)
    (f,) = flipped_tests("surfaces", base, cand, maps)
    assert f.kind == "LAYER_HEIGHT" and f.base["accepted"] and not f.candidate["accepted"]
    assert flipped_tests("surfaces", base, rows(True, 4), {"attempts": ItemMatch(
        10, 10, pairs=[(7, 7)])}) == []


def test_a_layer_pools_side_faces_only_and_a_step_keeps_its_own() -> None:
    from boxloc.stages.height import pool_layers

    S, T, N = int(HeightSource.SIDE), int(HeightSource.STEP), int(HeightSource.NONE)
    # one layer: a step to a shorter neighbour (0.15), a stack's side (0.60), a foot seen
    # on a side (0.30), a top with nothing; another layer of one top
    h = np.array([0.15, 0.60, 0.30, np.nan, 0.90])
    s = np.array([0.005, 0.005, 0.005, np.nan, 0.005])
    src = np.array([T, S, S, N, T], np.int8)
    rows = pool_layers(h, s, src, np.array([0, 0, 0, 0, 4]), np.arange(5, dtype=np.int32),
                       2.326, 0.01)
    assert list(h) == [0.15, 0.30, 0.30, 0.30, 0.90]
    assert list(src) == [T, S, S, S, T]
    # a row per layer mate of the giver (attempt 2); taken by the deeper side and the
    # top without a measurement, not by the shallower step
    assert sorted(zip(rows.a.tolist(), rows.b.tolist(), rows.accepted.tolist())) == [
        (0, 2, False), (1, 2, True), (3, 2, True)]


def test_a_top_whose_centre_uncertainty_is_unknown_joins_no_layer() -> None:
    sim, r = _layer_on_a_stack(0.05)
    s = r.surfaces
    cov = s.covariances.copy()
    cov[1] = np.nan
    ctx = height_context(sim.scan, CFG, r.hypotheses.up)
    assert len(set(flush_layers(ctx, dataclasses.replace(s, covariances=cov), CFG))) == 2

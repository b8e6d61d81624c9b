"""Verification (stage 6): the continuation test, on a single box with known geometry."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from boxloc.config import Config
from boxloc.pipeline import find_graspable_surfaces
from boxloc.products import EdgeKind, VerifyReason
from boxloc.stats import TestKind
from boxloc.verify import VerifyContext, continuation, verify
from tests.scenes import box, scene


@pytest.fixture(scope="module")
def single_box():
    sim = scene([box(0.0, 0.0, 0.40, 0.30, 0.25)], distance=1.2, tilt=0.05, seed=4)
    cfg = Config()
    r = find_graspable_surfaces(sim.scan, cfg)
    assert len(r.surfaces) == 1
    a = int(r.surfaces.attempt[0])
    H = r.hypotheses
    h = int(H.att_hypothesis[a])
    frame = (H.origins[h], H.x_axis[h], H.y_axis[h], H.normals[h],
             float(H.att_width[a]), float(H.att_length[a]))
    ctx = VerifyContext.build(sim.scan, r.edges, cfg, H.up)
    return sim, cfg, ctx, frame


def _verify(sim, cfg, ctx, frame, width=None, length=None):
    o, x, y, n, w, l_ = frame
    return verify(sim.scan, ctx, o, x, y, n, w if width is None else width,
                  l_ if length is None else length, np.eye(6) * 1e-10, cfg, attempt_id=0)


def test_the_whole_top_ends_at_all_four_sides(single_box):
    sim, cfg, ctx, frame = single_box
    out = _verify(sim, cfg, ctx, frame)
    assert out.reason == VerifyReason.ACCEPTED
    rows = out.tests.of_kind(TestKind.VERIFY_CONTINUATION)
    assert list(rows.b) == [0, 1, 2, 3]
    assert rows.accepted.all()
    # beyond a box's top lie its side walls and the pallet: almost nothing on its plane
    assert np.nanmax(rows.statistic) < 0.2
    assert np.all(rows.critical == cfg.min_inlier_fraction)


def test_a_rectangle_cut_short_by_spurious_edges_is_rejected(single_box):
    # a line of edge points across the top at 60 % of its length (sensor artefacts) makes
    # a boundary-supported far side; the top's plane continues beyond it
    sim, cfg, ctx, frame = single_box
    o, x, y, n, w, l_ = frame
    cut = 0.6 * l_
    spacing = ctx.spacing_at(o + 0.5 * w * x + 0.5 * l_ * y)
    s = np.arange(0.0, w, spacing)
    fake = o + s[:, None] * x + cut * y
    ctx2 = dataclasses.replace(
        ctx, edge_points=np.vstack([ctx.edge_points, fake]),
        edge_kinds=np.r_[ctx.edge_kinds, np.full(len(s), EdgeKind.JUMP, ctx.edge_kinds.dtype)])
    short = _verify(sim, cfg, ctx2, frame, length=cut)
    assert short.reason == VerifyReason.CONTINUES
    rows = short.tests.of_kind(TestKind.VERIFY_CONTINUATION)
    assert not rows.accepted[1] and rows.statistic[1] >= cfg.min_inlier_fraction
    assert rows.accepted[[0, 2, 3]].all()
    # the cut side was also tested as a seam (no groove, no gap there) and failed
    seam = short.tests.of_kind(TestKind.VERIFY_SEAM_SIDE)
    assert 1 in seam.b and not seam.accepted[list(seam.b).index(1)]


def test_continuation_fractions(single_box):
    sim, cfg, ctx, frame = single_box
    o, x, y, n, w, l_ = frame
    k = 2.576
    spacing = ctx.spacing_at(o)
    inner = continuation(ctx, o + 0.1 * x + 0.1 * y, x, y, w - 0.2, l_ - 0.2, o, n,
                         2 * spacing, 4 * spacing, k)
    assert np.all(inner[0] > 0.9)  # strips inside the top: the same plane on every side
    assert np.all(inner[1] > 0)

"""Work budgets: a stage that would run for minutes stops at its budget, and the log and
``explain`` say so."""

from __future__ import annotations

import numpy as np
import pytest

import boxloc.stages.hypotheses as hyp_stage
from boxloc.config import Config
from boxloc.errors import InputError
from boxloc.pipeline import find_graspable_surfaces
from boxloc.products import products_equal
from boxloc.simulate import simulate
from boxloc.stages.edges import detect_edges
from boxloc.stats import BUDGET_EDGES, BUDGET_HYPOTHESIS_WORK, TestKind

SCENE = "pallet:width=320,height=240,f=262.5,distance=1.5"


@pytest.fixture(scope="module")
def pallet():  # type: ignore[no-untyped-def]
    return simulate(SCENE, 3)


def _budget_rows(result, stage: int) -> list[dict[str, object]]:  # type: ignore[no-untyped-def]
    rows = result.hypotheses.tests.of_kind(TestKind.BUDGET).rows()
    return [r for r in rows if r["a"] == stage]


def test_an_exhausted_budget_is_recorded_and_explained(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from recorder.mcap.sink import McapRecorder
    from replay.explain import explain, format_explanation

    sim = simulate(SCENE, 3)
    cfg = Config(max_line_work=100, max_vertices=1)
    with McapRecorder(tmp_path / "b.mcap", config=cfg, fsync=False) as rec:
        find_graspable_surfaces(sim.scan, cfg, observer=rec)
    d = explain(tmp_path / "b.mcap", 0)
    assert "lines" in {b["stage"] for b in d["budgets"]}
    text = format_explanation(d)
    assert "budget exhausted: the lines stage stopped at 100 neighbour points" in text


def test_a_scan_under_the_pixel_budget_is_unchanged(pallet) -> None:  # type: ignore[no-untyped-def]
    # the default budget is far above what this scan reads: every product as without one
    # (the config hash names the budget, so it differs)
    r0 = find_graspable_surfaces(pallet.scan, Config(max_hypothesis_work=0))
    r1 = find_graspable_surfaces(pallet.scan, Config())
    assert products_equal(r0, r1, ignore=("timing_ms", "config_hash")) == []
    assert _budget_rows(r1, BUDGET_HYPOTHESIS_WORK) == []
    assert len(r1.surfaces) > 0


def test_a_scan_over_a_tiny_pixel_budget_records_it_and_keeps_valid_products(
        tmp_path, pallet) -> None:  # type: ignore[no-untyped-def]
    from recorder.mcap.sink import McapRecorder
    from replay.explain import explain, format_explanation

    cfg = Config(max_hypothesis_work=1)
    with McapRecorder(tmp_path / "h.mcap", config=cfg, fsync=False) as rec:
        r = find_graspable_surfaces(pallet.scan, cfg, observer=rec)
    (row,) = _budget_rows(r, BUDGET_HYPOTHESIS_WORK)
    assert not row["accepted"] and row["critical"] == 1 and float(row["statistic"]) > 1  # type: ignore[arg-type]
    # one vertex was worked on, whole: the highest, as tops are on top of the pile
    V, H = r.vertices, r.hypotheses
    worked = np.unique(H.att_hypothesis)
    assert len(worked) == 1 and len(V) > 1
    # (the stage orders by the up it estimates, within a fraction of a degree of the true)
    height = V.points @ pallet.scan.up
    assert height[worked[0]] >= height.max() - 0.01
    # the products are whole and consistent: a hypothesis per vertex, every reported
    # surface a verified attempt
    assert len(H) == len(V) and H.n_attempts == len(r.verification)
    assert r.verification.accepted[r.surfaces.attempt].all()
    assert isinstance(r.to_json()["surfaces"], list)
    d = explain(tmp_path / "h.mcap", 0)
    assert "hypotheses" in {b["stage"] for b in d["budgets"]}
    assert "budget exhausted: the hypotheses stage stopped at 1 " in format_explanation(d)


def test_a_budget_stops_at_the_same_place_in_serial_and_parallel(pallet) -> None:  # type: ignore[no-untyped-def]
    # room for more than one vertex, not for all of them
    one = _budget_rows(find_graspable_surfaces(pallet.scan, Config(max_hypothesis_work=1)),
                       BUDGET_HYPOTHESIS_WORK)[0]["statistic"]
    cfg = Config(max_hypothesis_work=int(one) + 1)  # type: ignore[call-overload]
    r1 = find_graspable_surfaces(pallet.scan, cfg)
    assert len(_budget_rows(r1, BUDGET_HYPOTHESIS_WORK)) == 1
    assert len(np.unique(r1.hypotheses.att_hypothesis)) >= 2
    r2 = find_graspable_surfaces(pallet.scan, Config(max_hypothesis_work=cfg.max_hypothesis_work,
                                                     workers=2))
    assert products_equal(r1, r2) == []


def test_flat_regions_wait_until_every_vertex_was_searched_for_a_top(
        pallet, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    calls: list[str] = []
    search, region = hyp_stage._search_vertex, hyp_stage._search_region

    def search_spy(i, ctx):  # type: ignore[no-untyped-def]
        calls.append("top")
        return search(i, ctx)

    def region_spy(item, ctx):  # type: ignore[no-untyped-def]
        calls.append("region")
        return region(item, ctx)

    monkeypatch.setattr(hyp_stage, "_search_vertex", search_spy)
    monkeypatch.setattr(hyp_stage, "_search_region", region_spy)
    r = find_graspable_surfaces(pallet.scan, Config(max_hypothesis_work=10**12))
    assert "region" in calls and "top" in calls
    # under a budget the regions (never surfaces) come after every search for a top
    assert calls == sorted(calls, key=lambda c: c == "region")
    assert _budget_rows(r, BUDGET_HYPOTHESIS_WORK) == []


@pytest.mark.parametrize("bad", [-1, 1.5, True, "many"])
def test_the_pixel_budget_must_be_a_count(bad) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(InputError, match="max_hypothesis_work"):
        Config(max_hypothesis_work=bad)


# --- the edge stage (issue #22 part 2) -------------------------------------------------------


def _edge_budget(edges) -> list[dict[str, object]]:  # type: ignore[no-untyped-def]
    return [r for r in edges.tests.of_kind(TestKind.BUDGET).rows() if r["a"] == BUDGET_EDGES]


def test_a_scan_under_the_edge_budget_is_unchanged(pallet) -> None:  # type: ignore[no-untyped-def]
    r0 = find_graspable_surfaces(pallet.scan, Config(max_edge_work=0))
    r1 = find_graspable_surfaces(pallet.scan, Config())
    assert products_equal(r0, r1, ignore=("timing_ms", "config_hash")) == []
    assert _edge_budget(r1.edges) == []


def test_the_edge_budget_stops_scan_lines_and_is_recorded_and_explained(
        tmp_path, pallet) -> None:  # type: ignore[no-untyped-def]
    from recorder.mcap.log import open_log
    from recorder.mcap.sink import McapRecorder
    from replay.explain import explain, format_explanation

    full = detect_edges(pallet.scan, config=Config())
    # small enough that the rows' half ends before the middle row on this scan
    cfg = Config(max_edge_work=150_000)
    with McapRecorder(tmp_path / "e.mcap", config=cfg, fsync=False) as rec:
        r = find_graspable_surfaces(pallet.scan, cfg, observer=rec)
    (row,) = _edge_budget(r.edges)
    assert not row["accepted"] and row["critical"] == 150_000
    assert 150_000 <= float(row["statistic"]) < 170_000  # type: ignore[arg-type]
    # what it has: the first rows and the first columns, each a subset of the full map's
    assert 0 < len(r.edges) < len(full)
    rows, cols = r.edges.pixels[:, 0], r.edges.pixels[:, 1]
    H, W = pallet.scan.shape
    assert ((rows < H // 2) | (cols < W // 2)).all()
    on = full.labels[rows, cols] != 0
    assert on.mean() > 0.9
    # the recorded row reads back, and explain names the stage
    back = next(iter(open_log(tmp_path / "e.mcap").scans())).products["edges"]
    assert products_equal(back, r.edges) == []
    assert [x["statistic"] for x in _edge_budget(back)] == [row["statistic"]]
    d = explain(tmp_path / "e.mcap", 0)
    assert "edges" in {b["stage"] for b in d["budgets"]}
    assert ("budget exhausted: the edges stage stopped at 150000 samples visited"
            in format_explanation(d).replace(",", ""))


def test_the_edge_budget_must_be_a_count() -> None:
    with pytest.raises(InputError, match="max_edge_work"):
        Config(max_edge_work=-5)

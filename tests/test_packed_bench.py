"""Tests of boxloc.evaluate.packed_bench (issue 21 point 4): tiny packed scenes, no timings.

The localizers here answer from the ground truth with known faults, so every figure of the
report has a value worked out by hand; one test runs the real pipeline on two tiny scenes.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

import boxloc.evaluate.packed_bench as pb
import boxloc.simulate as sim
from boxloc.config import Config
from boxloc.evaluate.baseline import surface_set_from_rects
from boxloc.products import AmbiguityReason, AmbiguousSet, HeightSource

#: The report's top-level keys.
TOP_KEYS = {
    "schema", "version", "mode", "n", "seed", "jobs", "scan_timeout_s", "warmup", "threads",
    "default_configuration", "config", "config_hash", "site", "sizes", "suite", "held_out",
    "sensors", "variants", "lids", "seeds", "groups", "targets", "timeouts", "errors",
    "timing", "memory", "scenes",
}
#: The figures of a group.
GROUP_KEYS = {
    "n_scenes", "n_scans", "tp", "fp", "fn", "n_pred", "n_exposed", "precision", "recall",
    "errors", "timeouts", "time", "wrong_rectangles", "wrong_no_match", "wrong_spans",
    "off_top", "wrong_rate", "ambiguous_regions", "ambiguous_per_scan",
    "ambiguous_area_median_m2", "ambiguous_reasons", "ambiguous_without_top",
    "tops_in_ambiguous", "missed_in_ambiguous", "missed_silently", "silent_scans",
    "height_sources",
    "height_n", "height_err_median_mm", "height_err_p95_mm", "height_by_source",
    "height_stack_like", "sku_matched", "sku_flagged", "sku_flagged_tp",
}
#: Every variant reports a height 3 mm too high.
HEIGHT_BIAS = 0.003


def _tiny(n: int = 4, interlocked: int = 0) -> list[Any]:
    """Packed scenes at 160 x 120 (same field of view), so a test takes seconds."""
    return [dataclasses.replace(s, width=160, height=120, f=s.f * 160 / s.width)
            for s in pb.packed_suite(n, 0, interlocked)]


def _truths(specs: list[Any]) -> dict[int, tuple[Any, Any]]:
    out = {}
    for spec in specs:
        s = sim.simulate(spec)
        out[s.scan.seed] = (s.truth, spec)
    return out


def _layer_outline(t: Any, faces: np.ndarray) -> tuple[np.ndarray, float]:
    """The rectangle around ``faces`` (tops of one layer, one orientation) and its area."""
    x, y = t.x_axis[faces[0]], t.y_axis[faces[0]]
    pts = t.corners[faces].reshape(-1, 3)
    c0 = pts.mean(axis=0)
    u, v = (pts - c0) @ x, (pts - c0) @ y
    rect = np.array([c0 + a * x + b * y for a, b in ((u.min(), v.min()), (u.max(), v.min()),
                                                     (u.max(), v.max()), (u.min(), v.max()))])
    return rect, float((u.max() - u.min()) * (v.max() - v.min()))


def _oracle(specs: list[Any], slow: frozenset[str] = frozenset()) -> Any:
    """A localizer answering from the ground truth, with known faults.

    Without sizes: on laser scenes one rectangle over the first two exposed tops and a tenth
    beyond (a wrong rectangle), elsewhere nothing; on every scene one ambiguous region around
    the exposed tops. With sizes (which must be the scene's): every exposed top, with its
    height 3 mm too high from a side (even rows) or a step (odd rows); tof finds nothing;
    structured light flags its first top as matching no size. Sensors in ``slow`` sleep a
    minute with sizes.
    """
    truth = _truths(specs)

    def localize(scan: Any, config: Config) -> Any:
        t, spec = truth[scan.seed]
        ex = np.flatnonzero(np.asarray(t.fully_exposed, bool))
        outline, area = _layer_outline(t, ex)
        amb = AmbiguousSet(hypothesis=np.array([-1]), corners=outline[None],
                           area=np.array([area]),
                           reason=np.array([AmbiguityReason.LARGER_THAN_MAX_BOX], np.int8))
        if not config.box_sizes:
            if spec.sensor == "laser":
                a, b = ex[0], ex[1]
                c = 0.5 * (t.centers[a] + t.centers[b])
                d = t.centers[b] - t.centers[a]
                along_x = abs(d @ t.x_axis[a]) > abs(d @ t.y_axis[a])
                # a tenth beyond the pair: its IoU with either top is 1 / 2.2, no match (over
                # exactly the two it is 1/2, the match's bound, which rounding then decides)
                w = t.width[a] * (2.2 if along_x else 1)
                ln = t.length[a] * (1 if along_x else 2.2)
                s = surface_set_from_rects(c[None], t.normals[a][None], t.x_axis[a][None],
                                           [w], [ln], up=scan.up)
            else:
                s = surface_set_from_rects(np.zeros((0, 3)), np.zeros((0, 3)),
                                           np.zeros((0, 3)), [], [])
            return SimpleNamespace(surfaces=s, ambiguous=amb, timing_ms={"total": 1.0})
        want = {tuple(round(v, 3) for v in r) for r in config.box_sizes}
        assert want == {tuple(round(v, 3) for v in sorted(b[3:5]) + [b[5]]) for b in t.boxes}
        if spec.sensor in slow:
            time.sleep(60)
        if spec.sensor == "tof":
            ex = ex[:0]
        s = surface_set_from_rects(t.centers[ex], t.normals[ex], t.x_axis[ex], t.width[ex],
                                   t.length[ex], up=scan.up)
        # rows are in pick order: find each row's face by its centre
        face = [int(np.argmin(np.linalg.norm(t.centers[ex] - c, axis=1))) for c in s.centers]
        true_h = t.boxes[t.box_index[ex][face], 5] if len(ex) else np.zeros(0)
        n = len(s)
        src = np.where(np.arange(n) % 2 == 0, HeightSource.SIDE, HeightSource.STEP)
        flagged = np.zeros(n, bool)
        if spec.sensor == "structured-light" and n:
            flagged[0] = True
        s = dataclasses.replace(s, height=true_h + HEIGHT_BIAS, height_sigma=np.full(n, 0.002),
                                height_source=src.astype(np.int8),
                                sku=np.where(flagged, -1, 0).astype(np.int32),
                                sku_flagged=flagged)
        return SimpleNamespace(surfaces=s, ambiguous=AmbiguousSet(), timing_ms={"total": 1.0})

    return localize


def _sum(rows: list[dict[str, Any]], variant: str, key: str) -> int:
    return sum(r["runs"][variant]["match"][key] for r in rows)


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    specs = _tiny()
    out = tmp_path_factory.mktemp("packed")
    r = pb.run_packed_bench(specs=specs, localizer=_oracle(specs), warmup=False,
                            progress=False, out=out)
    r["_out"] = str(out)
    return r


def test_packed_suite_is_the_matrix_layered_cells() -> None:
    specs = pb.packed_suite(9, 3)
    assert [s.sensor for s in specs] == [sim.SENSORS[i % 4] for i in range(9)]
    assert all(s.kind == "layered" and s.bevel == 0.0 for s in specs)
    matrix = [s for s in sim.matrix_suite(96, 3) if s.kind == "layered"]
    assert specs == matrix[:9]
    assert pb.packed_suite(4, 3) == specs[:4]  # a longer suite starts with the shorter one
    assert pb.packed_suite(0) == []
    with pytest.raises(pb.InputError, match="integer >= 0"):
        pb.packed_suite(-1)


def test_interlocked_scenes_follow_the_grids() -> None:
    specs = pb.packed_suite(5, 3, 3)
    assert specs[:5] == pb.packed_suite(5, 3)
    matrix = [s for s in sim.matrix_suite(96, 3) if s.kind == "layered"]
    assert specs[5:] == [dataclasses.replace(s, pattern="weave") for s in matrix[5:8]]
    assert [s.pattern for s in specs] == ["grid"] * 5 + ["weave"] * 3
    assert [pb.default_interlocked(n) for n in (96, 12, 11, 4)] == [32, 4, 0, 0]
    with pytest.raises(pb.InputError, match="interlocked count must be an integer >= 0"):
        pb.packed_suite(4, 0, -1)


def test_interlocked_layers_are_reported_apart(report: dict[str, Any]) -> None:
    specs = _tiny(4, 4)
    r = pb.run_packed_bench(specs=specs, localizer=_oracle(specs), warmup=False,
                            progress=False)
    assert r["n"] == 4 and r["suite"]["patterns"] == {"grid": 4, "weave": 4}
    rows = r["scenes"]
    assert [row["pattern"] for row in rows] == ["grid"] * 4 + ["weave"] * 4
    def timeless(g: Any) -> Any:  # a group's figures but its wall times
        if isinstance(g, dict):
            return {k: timeless(x) for k, x in g.items() if k != "time"}
        return g

    # the grid groups are the grid scenes' alone: those of the same four without weaves
    for v in pb.VARIANTS:
        g = r["groups"][v]
        assert timeless(g["overall"]) == timeless(report["groups"][v]["overall"])
        assert timeless(g["sensors"]) == timeless(report["groups"][v]["sensors"])
        woven = g["interlocked"]
        assert woven["overall"]["all"]["n_exposed"] == sum(row["n_exposed"] for row in rows[4:])
        assert woven["overall"]["all"]["tp"] == _sum(rows[4:], v, "tp")
        laser = next(row for row in rows[4:] if row["sensor"] == "laser")
        assert woven["sensors"]["laser"]["wrong_rectangles"] == \
            laser["runs"][v]["wrong"]["n_wrong"]
    assert "interlocked" not in report["groups"]["with_sizes"]
    targets = {t["name"]: t for t in r["targets"]}
    # the oracle's one rectangle over two tops on laser without sizes: a wrong rectangle
    t = targets["wrong-rectangle rate on interlocked layers without sizes, every sensor"]
    assert t["layers"] == "interlocked"
    assert t["all"]["value"] == 1.0 and t["all"]["where"] == "laser"
    assert t["all"]["pass"] is False
    t = targets["wrong-rectangle rate on interlocked layers with sizes, every sensor"]
    assert t["all"]["value"] == 0.0 and t["all"]["pass"] is True
    # a suite of grids alone has no such figure
    gone = {t["name"]: t for t in report["targets"]}
    assert gone[t["name"]]["all"] == {"value": None, "where": None, "pass": None}


def test_the_carton_list_is_the_scenes_sizes_as_a_user_writes_them() -> None:
    s = sim.simulate(_tiny(1)[0])
    text = pb.box_sizes_csv(s.truth)
    lines = text.splitlines()
    assert lines[0] == "width,length,height" and len(lines) == 2  # one carton per pallet
    (row,) = pb.read_sizes_as_a_user(text)
    b = s.truth.boxes[0]
    np.testing.assert_allclose(row, [*sorted(b[3:5]), b[5]], atol=0.0005 + 1e-12)
    assert all(len(v.split(".")[1]) == 3 for v in lines[1].split(","))  # millimetres


def test_report_on_disk_and_documented(report: dict[str, Any]) -> None:
    out = Path(report["_out"])
    on_disk = json.loads((out / pb.REPORT_NAME).read_text())
    assert on_disk == {k: v for k, v in report.items() if k != "_out"}
    assert set(on_disk) == TOP_KEYS
    table = (out / pb.TABLE_NAME).read_text()
    assert "wrong-rectangle rate without sizes" in table and "FAIL" in table
    assert "with_sizes: per sensor" in table
    doc = pb.__doc__ or ""
    for key in (*TOP_KEYS, *GROUP_KEYS):  # every key is documented in the module docstring
        assert f"``{key}``" in doc, key
    for v in pb.VARIANTS:
        g = report["groups"][v]
        assert GROUP_KEYS <= set(g["overall"]["all"])
        assert set(g["sensors"]) == set(sim.SENSORS)
    assert report["schema"] == "boxloc.bench_packed/1" and report["mode"] == "packed"
    assert report["default_configuration"] is True
    lo, hi = report["site"]["min_edge"], report["site"]["max_edge"]
    assert Config.from_dict(report["config"]) == Config(min_edge=lo, max_edge=hi)
    assert report["sizes"]["size_tolerance_m"] == Config().size_tolerance
    assert report["errors"]["total"] == 0 and report["timeouts"] == []
    assert [r["index"] for r in report["scenes"]] == [0, 1, 2, 3]
    assert all(set(r["runs"]) == set(pb.VARIANTS) for r in report["scenes"])


def test_figures_without_sizes(report: dict[str, Any]) -> None:
    rows, g = report["scenes"], report["groups"]["without_sizes"]
    laser = g["sensors"]["laser"]
    # the one rectangle over two tops: wrong (it spans them), not a match
    assert (laser["n_pred"], laser["tp"], laser["wrong_rectangles"]) == (1, 0, 1)
    assert laser["wrong_rate"] == 1.0 and laser["recall"] == 0.0
    assert laser["wrong_spans"] + laser["wrong_no_match"] == 1
    for s in ("tof", "structured-light", "active-stereo"):
        assert g["sensors"][s]["n_pred"] == 0 and g["sensors"][s]["wrong_rate"] == 0.0
    ov = g["overall"]["all"]
    assert ov["ambiguous_regions"] == 4 and ov["ambiguous_per_scan"] == 1.0
    assert ov["ambiguous_reasons"] == {"LARGER_THAN_MAX_BOX": 4}
    assert ov["ambiguous_without_top"] == 0
    n_exposed = sum(r["n_exposed"] for r in rows)
    assert ov["n_exposed"] == n_exposed and ov["fn"] == _sum(rows, "without_sizes", "fn")
    # every exposed top lies in its scene's region, so no miss is silent
    assert ov["tops_in_ambiguous"] == n_exposed == ov["missed_in_ambiguous"]
    assert ov["missed_silently"] == 0 and ov["silent_scans"] == 0
    assert ov["height_n"] == 0 and ov["height_err_median_mm"] is None
    for r in rows:
        amb = r["runs"]["without_sizes"]["ambiguous"]
        assert amb["n"] == 1 and amb["tops"] == [r["n_exposed"]]
    wr = {t["name"]: t for t in report["targets"]}["wrong-rectangle rate without sizes, "
                                                    "every sensor"]
    assert wr["all"] == {"value": 1.0, "where": "laser", "pass": False}


def test_figures_with_sizes(report: dict[str, Any]) -> None:
    rows, g = report["scenes"], report["groups"]["with_sizes"]
    for s in ("laser", "structured-light", "active-stereo"):
        f = g["sensors"][s]
        assert f["recall"] == 1.0 and f["precision"] == 1.0 and f["wrong_rectangles"] == 0
    assert g["sensors"]["tof"]["recall"] == 0.0 and g["sensors"]["tof"]["n_pred"] == 0
    dev, allf = g["overall"]["development"], g["overall"]["all"]
    assert dev["recall"] == 1.0 and allf["recall"] < 1.0
    tof_tops = next(r["n_exposed"] for r in rows if r["sensor"] == "tof")
    assert allf["fn"] == tof_tops == allf["missed_silently"]
    assert allf["silent_scans"] == 1 == g["sensors"]["tof"]["silent_scans"]  # tof: nothing
    # every true top has a side or step height, 3 mm high
    assert allf["height_n"] == allf["tp"] == _sum(rows, "with_sizes", "tp")
    assert allf["height_err_median_mm"] == pytest.approx(HEIGHT_BIAS * 1e3, abs=1e-6)
    assert allf["height_err_p95_mm"] == pytest.approx(HEIGHT_BIAS * 1e3, abs=1e-6)
    hs = allf["height_sources"]
    assert hs["side"] + hs["step"] == allf["n_pred"] and hs["sku"] == hs["none"] == 0
    assert hs["side"] == sum(math.ceil(r["runs"]["with_sizes"]["match"]["n_pred"] / 2)
                             for r in rows)
    assert allf["height_stack_like"] == 0
    by = allf["height_by_source"]
    assert by["side"]["n"] + by["step"]["n"] == allf["height_n"]
    assert allf["sku_flagged"] == allf["sku_flagged_tp"] == 1
    assert g["sensors"]["structured-light"]["sku_flagged"] == 1
    assert allf["sku_matched"] == allf["n_pred"] - 1
    assert allf["ambiguous_regions"] == 0
    tg = {t["name"]: t for t in report["targets"]}
    assert tg["recall with sizes"]["development"]["pass"] is True
    assert tg["recall with sizes"]["all"]["pass"] is False  # tof finds nothing
    assert tg["precision with sizes"]["all"]["value"] == 1.0
    med = tg["median height error (side or step), with sizes"]["all"]
    assert med["pass"] is True and med["value"] == pytest.approx(3.0, abs=1e-6)
    assert tg["median height error (side or step), without sizes"]["all"]["pass"] is None


def test_a_broken_localizer_scores_nothing() -> None:
    """Rectangles half a box off every top: recall 0, and every one of them wrong."""
    specs = _tiny(2)
    truth = _truths(specs)

    def shifted(scan: Any, config: Config) -> Any:
        t, _ = truth[scan.seed]
        ex = np.flatnonzero(np.asarray(t.fully_exposed, bool))
        c = t.centers[ex] + 0.5 * t.width[ex, None] * t.x_axis[ex]
        return SimpleNamespace(surfaces=surface_set_from_rects(
            c, t.normals[ex], t.x_axis[ex], t.width[ex], t.length[ex], up=scan.up))

    r = pb.run_packed_bench(specs=specs, localizer=shifted, warmup=False, progress=False)
    for v in pb.VARIANTS:
        ov = r["groups"][v]["overall"]["all"]
        assert ov["n_pred"] > 0 and ov["tp"] == 0 and ov["recall"] == 0.0
        # each straddles a seam (IoU 1/3 with both neighbours) or hangs over the layer's edge
        assert ov["wrong_no_match"] + ov["off_top"] == ov["n_pred"]
        assert ov["wrong_no_match"] > 0 and ov["wrong_spans"] == 0
        assert ov["ambiguous_regions"] == 0 and ov["missed_silently"] == ov["n_exposed"]
        assert ov["silent_scans"] == 0  # it reported something


def test_a_slow_run_is_stopped_and_the_other_variant_kept() -> None:
    specs = _tiny(2)  # laser, tof
    r = pb.run_packed_bench(specs=specs, localizer=_oracle(specs, slow=frozenset({"tof"})),
                            warmup=False, progress=False, scan_timeout=1.0)
    tof = r["scenes"][1]["runs"]
    assert tof["without_sizes"]["status"] == "ok"
    assert tof["with_sizes"]["status"] == "timeout"
    assert tof["with_sizes"]["match"]["fn"] == r["scenes"][1]["n_exposed"]
    (to,) = r["timeouts"]
    assert (to["scene"], to["sensor"], to["variant"], to["phase"]) == (1, "tof", "with_sizes",
                                                                      "localize")
    assert r["timing"]["per_scan_ms"]["with_sizes"][1] == 1000.0
    assert r["groups"]["with_sizes"]["sensors"]["tof"]["timeouts"] == 1
    assert r["scenes"][0]["runs"]["with_sizes"]["status"] == "ok"


def test_draws_pool_per_scan_rows(tmp_path: Path) -> None:
    specs = _tiny(2)
    r = pb.run_packed_bench(specs=specs, localizer=_oracle(specs), warmup=False,
                            progress=False, seeds=2, jobs=2, out=tmp_path)
    assert [(x["index"], x["trial_seed"]) for x in r["scenes"]] == [(0, 0), (0, 1), (1, 0),
                                                                    (1, 1)]
    assert r["seeds"]["trial_seeds"] == [0, 1]
    laser = r["groups"]["with_sizes"]["sensors"]["laser"]
    assert laser["n_scans"] == 2 and laser["n_scenes"] == 1
    per = r["seeds"]["per_seed"][1]["groups"]["laser"]["with_sizes"]
    assert per["recall"] == 1.0 and per["tp"] == laser["tp"] // 2
    assert "laser: with_sizes" in (tmp_path / pb.TABLE_NAME).read_text()


def test_one_variant_and_jobs() -> None:
    specs = _tiny(2)
    kw: dict[str, Any] = {"specs": specs, "localizer": _oracle(specs), "warmup": False,
                          "progress": False}
    one = pb.run_packed_bench(variants=["with_sizes"], **kw)
    assert one["variants"] == ["with_sizes"] and set(one["groups"]) == {"with_sizes"}
    two = pb.run_packed_bench(variants=["with_sizes"], jobs=2, **kw)
    assert one["scenes"] == two["scenes"]
    with pytest.raises(pb.InputError, match="variants"):
        pb.run_packed_bench(variants=["sizes"], **kw)


def test_the_real_localizer_on_packed_layers() -> None:
    specs = _tiny(2)  # laser and tof, 160 x 120
    r = pb.run_packed_bench(specs=specs, progress=False, warmup=False)
    for row in r["scenes"]:
        for v in pb.VARIANTS:
            x = row["runs"][v]
            assert x["status"] == "ok", x["error"]
            m, w = x["match"], x["wrong"]
            assert m["n_pred"] == m["tp"] + m["fp"] == w["n_pred"]
            assert m["tp"] + m["fn"] == row["n_exposed"]
            assert w["n_wrong"] == w["no_match"] + w["spans"]
            assert x["ambiguous"]["n"] == len(x["ambiguous"]["area_m2"])


def test_main_bad_input_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert pb.main(["--n", "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "n >= 1" in err and "Traceback" not in err
    assert pb.main(["--n", "1", "--variants", "with"]) == 2
    assert "variants" in capsys.readouterr().err

"""Issue #21 on the recording side: ambiguous regions, box heights and carton sizes in the
log (MCAP), the viewer (Rerun), ``explain``, ``diff`` and ``replay --box-sizes``.

The products are made by hand (:func:`with_issue21`) on top of the shaped-right products of
``tests/factories.py``, so these tests do not depend on the algorithm filling them in.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner
from factories import feed, make_result, make_scan
from mcap.reader import make_reader

from boxloc.cli import cli
from boxloc.config import Config
from boxloc.errors import LogError
from boxloc.products import (
    AmbiguityReason,
    AmbiguousSet,
    HeightSource,
    Result,
    SurfaceSet,
    products_equal,
)
from boxloc.stats import TestKind, TestTable
from recorder.mcap import channels as C
from recorder.mcap import encode as E
from recorder.mcap.log import open_log
from recorder.mcap.sink import McapRecorder, box_sizes_attachment
from replay.diff import diff_logs, load_tolerances
from replay.explain import explain, format_explanation

ALPHA = 0.01
LOGS = Path(__file__).resolve().parent.parent / "logs"
SIZES_CSV = "width,length,height\n0.30,0.40,0.25\n0.20,0.30,\n"


# --- hand-made products -------------------------------------------------------------------


def _region_around(P: np.ndarray, w: float, ln: float) -> np.ndarray:
    """A (4, 3) outline of a w x ln rectangle centred on P, in the plane z = P_z."""
    o = P - np.array([w / 2, ln / 2, 0.0])
    return np.stack([o, o + [w, 0, 0], o + [w, ln, 0], o + [0, ln, 0]])


def valid_pixel(scan: Any) -> tuple[int, int]:
    """(col, row) of a pixel with a return near the middle of the image."""
    H, W = scan.shape
    rows, cols = np.nonzero(scan.valid)
    k = int(np.argmin((rows - H / 2) ** 2 + (cols - W / 2) ** 2))
    return int(cols[k]), int(rows[k])


def make_ambiguous(scan: Any, attempt: int = 0) -> AmbiguousSet:
    """Two regions: #0 (NO_END_EVIDENCE) around the middle pixel's point, with its four
    END_EVIDENCE rows (side 1 without evidence); #1 (SEVERAL_SPLITS) 3 m away, with a
    SKU_SPLIT_SEAM row."""
    col, row = valid_pixel(scan)
    P = np.asarray(scan.points[row, col], np.float64)
    corners = np.stack([_region_around(P, 0.6, 0.8),
                        _region_around(P + [3.0, 0.0, 0.0], 0.4, 0.9)])
    a0, a1 = attempt, attempt + 1
    tests = TestTable.concat([
        TestTable.decision(TestKind.END_EVIDENCE, a0, [0, 1, 2, 3], [1.0, 0.0, 2.0, 1.0], 1.0,
                           [True, False, True, True], ALPHA),
        TestTable.decision(TestKind.SKU_SPLIT_SEAM, a1, 0, 0.7, 2.3, False, ALPHA),
    ], ALPHA)
    return AmbiguousSet(
        hypothesis=np.array([3, 4], np.int64), attempt=np.array([a0, a1], np.int64),
        corners=corners, area=np.array([0.48, 0.36]), width=np.array([0.6, 0.4]),
        length=np.array([0.8, 0.9]),
        reason=np.array([AmbiguityReason.NO_END_EVIDENCE, AmbiguityReason.SEVERAL_SPLITS],
                        np.int8),
        tests=tests)


def with_heights(s: SurfaceSet) -> SurfaceSet:
    """Surface 0: 250 +- 3 mm from its side, size 0; surface 1: from a step, flagged; the
    rest: not measured. Their BOX_HEIGHT and SKU_SIZE rows join the surfaces' tests."""
    n = len(s)
    h, sig = np.full(n, np.nan), np.full(n, np.nan)
    src = np.full(n, HeightSource.NONE, np.int8)
    sku, flag = np.full(n, -1, np.int32), np.zeros(n, bool)
    rows = [s.tests]
    if n >= 1:
        h[0], sig[0], src[0], sku[0] = 0.25, 0.003, HeightSource.SIDE, 0
        j = int(s.attempt[0])
        rows += [TestTable.decision(TestKind.BOX_HEIGHT, j, int(HeightSource.SIDE), 0.25,
                                    0.003, True, ALPHA),
                 TestTable.chi2(TestKind.SKU_SIZE, j, [0, 1], [0.8, 40.0], 2, ALPHA)]
    if n >= 2:
        h[1], sig[1], src[1], flag[1] = 0.31, 0.006, HeightSource.STEP, True
        rows.append(TestTable.chi2(TestKind.SKU_SIZE, int(s.attempt[1]), [0, 1], [30.0, 55.0],
                                   2, ALPHA))
    return dataclasses.replace(s, height=h, height_sigma=sig, height_source=src, sku=sku,
                               sku_flagged=flag, tests=TestTable.concat(rows, s.tests.alpha))


def with_issue21(scan: Any, seed: int = 0) -> Result:
    """A factories result with two ambiguous regions and heights on its surfaces."""
    r = make_result(scan, seed)
    return dataclasses.replace(r, surfaces=with_heights(r.surfaces),
                               ambiguous=make_ambiguous(scan, attempt=r.hypotheses.n_attempts))


def two_surfaces(scan: Any) -> Result:
    """with_issue21 on the first seed whose result has at least two surfaces."""
    for seed in range(50):
        r = with_issue21(scan, seed)
        if len(r.surfaces) >= 2:
            return r
    raise AssertionError("no factories result with two surfaces")


def record(path: Path, pairs: list[tuple[Any, Result]], config: Config | None = None,
           **kw: Any) -> Path:
    with McapRecorder(path, **kw) as rec:
        for scan, result in pairs:
            feed(rec, scan, result, config)
    return path


# --- the record -----------------------------------------------------------------------------


def test_ambiguous_regions_and_heights_round_trip_through_a_log_bit_for_bit(
        tmp_path: Path) -> None:
    scans = [make_scan(0), make_scan(1, raytable=True)]
    results = [two_surfaces(scans[0]), make_result(scans[1], 1)]  # the second: no regions
    path = record(tmp_path / "amb.mcap", list(zip(scans, results)))
    recs = list(open_log(path))
    for r, rec in zip(results, recs):
        assert products_equal(r, rec.result) == []
        assert products_equal(r.ambiguous, rec.ambiguous) == []
    back = recs[0].result
    assert len(back.ambiguous) == 2 and back.ambiguous.tests_of(0).kind.tolist() == [
        TestKind.END_EVIDENCE] * 4
    assert back.surfaces.height[0] == 0.25 and back.surfaces.sku_flagged[1]
    # its tests are rows of stage "ambiguous" on /boxloc/tests, once
    (tests_msg,) = [m for m in open_log(path).messages({C.TESTS}) if m.sequence == 0]
    rows = E.decode_test_rows(tests_msg.data)
    assert sum(r["stage"] == E.AMBIGUOUS_STAGE for r in rows) == 5
    assert {r["kind"] for r in rows} >= {"END_EVIDENCE", "SKU_SPLIT_SEAM", "SKU_SIZE",
                                         "BOX_HEIGHT"}
    _, arrays = E.decode_arrays(next(open_log(path).messages({C.AMBIGUOUS})).data,
                                E.AMBIGUOUS_RECORD)
    assert "tests/statistic" not in arrays and arrays["corners"].shape == (2, 4, 3)


def test_the_locate_view_has_the_new_surface_keys_and_the_ambiguous_list(
        tmp_path: Path) -> None:
    scan = make_scan(0)
    r = two_surfaces(scan)
    path = record(tmp_path / "loc.mcap", [(scan, r)])
    (msg,) = list(open_log(path).messages({C.LOCATE}))
    doc = E.decode_locate_json(msg.data)
    assert doc["schema"] == f"boxloc.Locate/{E.SCHEMA_VERSION}" and E.SCHEMA_VERSION == "1.7"
    s0, s1 = doc["surfaces"][0], doc["surfaces"][1]
    assert (s0["height"], s0["height_sigma"], s0["height_source"], s0["sku"],
            s0["size_flagged"]) == (0.25, 0.003, "side", 0, False)
    assert s1["height_source"] == "step" and s1["sku"] is None and s1["size_flagged"]
    # the same records as `boxloc locate` prints, plus hypothesis and attempt
    locate = r.to_json()
    assert [a["reason"] for a in doc["ambiguous"]] == ["no_end_evidence", "several_splits"]
    for mine, theirs in zip(doc["ambiguous"], locate["ambiguous"]):
        assert {k: v for k, v in mine.items() if k not in ("hypothesis", "attempt")} == theirs
    assert doc["ambiguous"][0]["tests"][1] == {
        "kind": "END_EVIDENCE", "b": 1, "statistic": 0.0, "dof": 0.0, "critical": 1.0,
        "decision": "rejected"}
    # every key the rows have is in the channel's JSON Schema
    props = E.LOCATE_JSON_SCHEMA["properties"]
    assert set(s0) <= set(props["surfaces"]["items"]["properties"])
    assert set(doc["ambiguous"][0]) <= set(props["ambiguous"]["items"]["properties"])


def test_the_scene_outlines_ambiguous_regions_and_labels_heights() -> None:
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    scan = make_scan(0)
    r = two_surfaces(scan)
    upd = SceneUpdate()
    upd.ParseFromString(E.encode_scene({"surfaces": r.surfaces, "ambiguous": r.ambiguous},
                                       0, 1))
    ents = {e.id: e for e in upd.entities}
    amb = ents["ambiguous"]
    assert len(amb.lines[0].points) == 2 * 8  # two closed outlines as a LINE_LIST
    assert [t.text for t in amb.texts] == [
        "ambiguous #0: no end evidence, 600x800 mm, 0.480 m2",
        "ambiguous #1: several splits, 400x900 mm, 0.360 m2"]
    assert "height 250 mm (side)" in ents["surfaces"].texts[0].text
    assert "height" not in ents["surfaces"].texts[2].text if len(r.surfaces) > 2 else True


def test_an_old_sample_log_reads_with_no_ambiguous_regions_and_nan_heights() -> None:
    log = open_log(LOGS / "pallet-320x240.mcap")
    assert log.run["schema_version"] == "1.2"
    for rec in log:
        assert len(rec.ambiguous) == 0 and "ambiguous" not in rec.products
        res = rec.result
        assert res is not None and len(res.ambiguous) == 0
        S = res.surfaces
        assert len(S) and np.isnan(S.height).all() and np.isnan(S.height_sigma).all()
        assert (S.height_source == HeightSource.NONE).all() and (S.sku == -1).all()
        assert not S.sku_flagged.any()
        assert res.to_json()["ambiguous"] == []


def test_a_malformed_ambiguous_record_is_refused() -> None:
    scan = make_scan(0)
    amb = make_ambiguous(scan)
    good = E.encode_ambiguous(amb, 0, 0)
    cols = E.decode_test_columns(E.encode_test_rows(0, {E.AMBIGUOUS_STAGE: amb.tests}))
    assert products_equal(E.decode_ambiguous(good, cols[E.AMBIGUOUS_STAGE]), amb) == []
    _, arrays = E.decode_arrays(good, E.AMBIGUOUS_RECORD)
    short = {**arrays, "area": arrays["area"][:1]}
    with pytest.raises(LogError, match="inconsistent shapes"):
        E.decode_ambiguous(E.encode_arrays(E.AMBIGUOUS_RECORD, short, 0, 0),
                           cols[E.AMBIGUOUS_STAGE])
    lacking = {k: v for k, v in arrays.items() if k != "reason"}
    with pytest.raises(LogError, match="lacks field.*reason"):
        E.decode_ambiguous(E.encode_arrays(E.AMBIGUOUS_RECORD, lacking, 0, 0))
    with pytest.raises(TypeError, match="AmbiguousSet"):
        E.encode_ambiguous(scan, 0, 0)  # type: ignore[arg-type]


# --- the carton file as an attachment -------------------------------------------------------


def _attachment_names(path: Path) -> list[str]:
    with open(path, "rb") as f:
        return [a.name for a in make_reader(f).iter_attachments()]


def test_the_box_sizes_file_is_attached_once_per_file_and_read_back(tmp_path: Path) -> None:
    csv = tmp_path / "sizes.csv"
    csv.write_bytes(SIZES_CSV.encode())
    att = box_sizes_attachment(csv)
    scans = [make_scan(i, index=i) for i in range(3)]
    path = record(tmp_path / "att.mcap", [(s, make_result(s, i)) for i, s in enumerate(scans)],
                  attachments=att)
    assert _attachment_names(path).count(C.BOX_SIZES_ATTACHMENT) == 1
    log = open_log(path)
    assert log.attachment(C.BOX_SIZES_ATTACHMENT) == SIZES_CSV.encode()
    (info,) = [a for a in log.attachments() if a.name == C.BOX_SIZES_ATTACHMENT]
    assert info.media_type == "text/csv" and info.size == len(SIZES_CSV)
    # a rotated session: one copy in every file, each a log of its own
    rot = tmp_path / "rot"
    with McapRecorder(rot, rotate_bytes=1, attachments=att, session="s") as rec:
        for i, s in enumerate(scans):
            feed(rec, s, make_result(s, i))
    assert len(rec.paths) == 3
    assert all(_attachment_names(p).count(C.BOX_SIZES_ATTACHMENT) == 1 for p in rec.paths)
    out = CliRunner().invoke(cli, ["info", str(path)])
    assert out.exit_code == 0 and "box_sizes.csv" in out.output


def test_the_recorder_refuses_to_replace_its_own_attachments(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="config.toml"):
        McapRecorder(tmp_path / "x.mcap", attachments={C.CONFIG_ATTACHMENT: ("t", b"")})


# --- replay --box-sizes ---------------------------------------------------------------------


def _sim_log(tmp_path: Path, config: Config) -> Path:
    """One small simulated pile, recorded by the real pipeline."""
    import replay_helpers as helpers

    return helpers.record(tmp_path / "in.mcap", config, scenes=[2])


def test_replay_with_box_sizes_changes_the_config_attaches_the_file_and_diff_shows_it(
        tmp_path: Path) -> None:
    src = _sim_log(tmp_path, Config())
    csv = tmp_path / "sizes.csv"
    csv.write_bytes(SIZES_CSV.encode())
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["replay", str(src), "--out", str(out), "--box-sizes",
                                   str(csv), "-j", "1", "-q"])
    assert res.exit_code in (0, 1), res.output
    new = open_log(out / "in.mcap")
    cfg = new.config
    assert cfg is not None and cfg.box_sizes[0] == (0.3, 0.4, 0.25)
    assert cfg.box_sizes[1][:2] == (0.2, 0.3) and math.isnan(cfg.box_sizes[1][2])
    assert new.attachment(C.BOX_SIZES_ATTACHMENT) == SIZES_CSV.encode()
    assert re.search(r"box_sizes \[\] -> \[\[0\.3, 0\.4, 0\.25\], \[0\.2, 0\.3\]\]",
                     res.output), res.output
    ld = diff_logs(src, out / "in.mcap")
    assert ld.config_changes["box_sizes"] == [[], [[0.3, 0.4, 0.25], [0.2, 0.3]]]
    # the override is exact: the same list through --set gives the same config hash
    from boxloc.io.box_sizes import read_box_sizes
    from replay.replay import box_sizes_override

    assert Config().with_overrides([box_sizes_override(read_box_sizes(csv))]).hash == cfg.hash
    # replaying the new log as recorded carries the file over
    again = tmp_path / "again"
    res = CliRunner().invoke(cli, ["replay", str(out / "in.mcap"), "--out", str(again),
                                   "-j", "1", "-q", "--no-diff"])
    assert res.exit_code == 0, res.output
    assert open_log(again / "in.mcap").attachment(C.BOX_SIZES_ATTACHMENT) == SIZES_CSV.encode()
    # ... but not when the sizes are replaced by --set
    other = tmp_path / "other"
    res = CliRunner().invoke(cli, ["replay", str(out / "in.mcap"), "--out", str(other),
                                   "-j", "1", "-q", "--no-diff", "--set",
                                   "box_sizes=[[0.5, 0.6]]"])
    assert res.exit_code == 0, res.output
    assert C.BOX_SIZES_ATTACHMENT not in {a.name for a in open_log(other / "in.mcap")
                                          .attachments()}


def test_replay_refuses_a_bad_box_sizes_file_in_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("w,l,h\n0.3,0.4,0.2\n")
    res = CliRunner().invoke(cli, ["replay", str(LOGS / "pallet-320x240.mcap"), "--out",
                                   str(tmp_path / "o"), "--box-sizes", str(bad)])
    assert res.exit_code == 2
    assert "header must be width,length,height" in res.output
    assert "Traceback" not in res.output and not (tmp_path / "o").exists()


# --- explain ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def amb_log(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Result]:
    scan = make_scan(0)
    r = two_surfaces(scan)
    path = tmp_path_factory.mktemp("amb") / "amb.mcap"
    record(path, [(scan, r)], Config(box_sizes=((0.3, 0.4, 0.25), (0.2, 0.3, math.nan))))
    return path, r


def test_explain_at_an_ambiguous_region_says_why_it_could_not_be_split(
        amb_log: tuple[Path, Result]) -> None:
    path, r = amb_log
    col, row = valid_pixel(make_scan(0))
    d = explain(path, 0, at=f"{col},{row}")
    a = d["at"]
    assert d["n_ambiguous"] == 2 and a["stopped_at"] == "ambiguous"
    amb = a["ambiguous"]
    assert (amb["region"], amb["reason"], amb["width_mm"], amb["length_mm"]) == (
        0, "NO_END_EVIDENCE", 600.0, 800.0)
    assert [t["accepted"] for t in amb["tests"]] == [True, False, True, True]
    assert "side v = length" in a["why"] and "no evidence of a box's end" in a["why"]
    text = format_explanation(d)
    assert "the chain stopped at: AMBIGUOUS" in text
    assert "END_EVIDENCE" in text and "REJECTED" in text
    # statistic, relation, critical value and decision of the failed side
    assert re.search(r"END_EVIDENCE \d+,1 \[side v = length\] \(no evidence\): 0 < 1: "
                     r"REJECTED", text), text
    # the same through the CLI, and as JSON
    res = CliRunner().invoke(cli, ["explain", str(path), "--scan", "0", "--at",
                                   f"{col},{row}"])
    assert res.exit_code == 0 and "ambiguous region #0: no_end_evidence" in res.output
    res = CliRunner().invoke(cli, ["explain", str(path), "--scan", "0", "--at",
                                   f"{col},{row}", "--json"])
    assert json.loads(res.output)["at"]["ambiguous"]["reason"] == "NO_END_EVIDENCE"


def test_explain_surface_shows_height_source_sigma_and_the_size_match_or_flag(
        amb_log: tuple[Path, Result]) -> None:
    path, r = amb_log
    d0 = explain(path, 0, surface=0)["surfaces"][0]
    assert d0["height"] == {"height_mm": 250.0, "sigma_mm": 3.0, "source": "SIDE",
                            "tests": d0["height"]["tests"]}
    assert d0["height"]["tests"][0]["kind"] == "BOX_HEIGHT"
    assert d0["size"]["sku"] == 0 and d0["size"]["listed_mm"] == [300.0, 400.0, 250.0]
    text0 = format_explanation(explain(path, 0, surface=0))
    assert "box height 250 mm +- 3 mm, from its visible side face" in text0
    assert "carton size: listed size 0 (300 x 400 x 250 mm)" in text0
    assert "SKU_SIZE" in text0 and "BOX_HEIGHT" in text0
    text1 = format_explanation(explain(path, 0, surface=1))
    assert "box height 310 mm +- 6 mm, from the step down" in text1
    assert "carton size: FLAGGED, it matches none of the 2 listed sizes" in text1
    if len(r.surfaces) > 2:
        assert "box height not measured" in format_explanation(explain(path, 0, surface=2))


# --- diff ------------------------------------------------------------------------------------


def test_diff_reports_ambiguous_regions_and_heights(tmp_path: Path) -> None:
    scan = make_scan(0)
    base = two_surfaces(scan)
    a = record(tmp_path / "a.mcap", [(scan, base)])
    # the same log again: identical, nothing reported
    same = diff_logs(a, record(tmp_path / "same.mcap", [(scan, base)]))
    assert same.identical and same.all_differences == []
    # one region fewer, the other moved 20 mm; surface 0 10 mm taller; surface 1 unflagged
    amb = base.ambiguous
    keep = np.array([False, True])
    corners = amb.corners[keep] + [0.02, 0.0, 0.0]
    fewer = AmbiguousSet(hypothesis=amb.hypothesis[keep], attempt=amb.attempt[keep],
                         corners=corners, area=amb.area[keep], width=amb.width[keep],
                         length=amb.length[keep], reason=amb.reason[keep],
                         tests=amb.tests.select(amb.tests.a == amb.attempt[1]))
    S = base.surfaces
    h = S.height.copy()
    h[0] += 0.010
    flag = S.sku_flagged.copy()
    flag[1] = False
    cand = dataclasses.replace(base, ambiguous=fewer,
                               surfaces=dataclasses.replace(S, height=h, sku_flagged=flag))
    ld = diff_logs(a, record(tmp_path / "b.mcap", [(scan, cand)]))
    (sd,) = ld.scans
    kinds = {d.kind: d for d in sd.differences}
    assert {"ambiguous_removed", "ambiguous_changed", "height_changed", "sku_changed",
            "count"} <= set(kinds)
    assert sd.counts["ambiguous"] == (2, 1)
    assert kinds["ambiguous_removed"].values == {"base": 0} and kinds[
        "ambiguous_removed"].regression
    assert abs(kinds["ambiguous_changed"].values["dcenter_mm"] - 20.0) < 1e-6
    assert "height 250 mm (side) -> 260 mm (side)" in kinds["height_changed"].message
    assert ld.regression
    # tolerances in the one table: 20 mm is within a wider gate, 10 mm within height_mm 15
    loose = tmp_path / "loose.toml"
    loose.write_text("[surfaces]\nheight_mm = 15.0\nambiguous_center_mm = 25.0\n"
                     "[regression]\nambiguous_removed = false\nsku_changed = false\n")
    ld = diff_logs(a, tmp_path / "b.mcap", load_tolerances(loose))
    assert not ld.regression
    assert {d.kind for d in ld.scans[0].differences} == {"ambiguous_removed", "sku_changed",
                                                         "count"}


def test_an_old_log_and_a_new_one_without_regions_do_not_differ_on_them(
        tmp_path: Path) -> None:
    """A 1.2 log has no /boxloc/ambiguous; its replay has an empty set: not a difference."""
    import replay_helpers as helpers

    src = helpers.record(tmp_path / "new.mcap", Config(), scenes=[0])
    old = tmp_path / "old.mcap"
    with McapRecorder(old) as rec:
        for r in open_log(src):
            res = r.result
            assert res is not None and len(res.ambiguous) == 0
            # the same products, recorded without their (empty) ambiguous set
            feed(_WithoutAmbiguous(rec), r.scan, res)
    assert "ambiguous" not in next(iter(open_log(old))).products
    ld = diff_logs(old, src)
    assert ld.error is None and all(s.identical for s in ld.scans), [
        s.changed_fields for s in ld.scans]


class _WithoutAmbiguous:
    """An observer that passes everything to ``inner`` but a result without ambiguous
    regions (what a recorder before schema 1.5 wrote)."""

    def __init__(self, inner: McapRecorder) -> None:
        self.inner = inner

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def on_result(self, scan: Any, result: Result) -> None:
        class _R:
            def __getattr__(self, k: str) -> Any:
                if k == "ambiguous":
                    raise AttributeError(k)
                return getattr(result, k)

        self.inner.on_result(scan, _R())  # type: ignore[arg-type]


# --- Rerun -----------------------------------------------------------------------------------


def test_rerun_logs_ambiguous_outlines_and_heights(tmp_path: Path) -> None:
    import rerun as rr
    from test_rerun_sink import _rerun, rrd_entities

    from recorder.rerun.sink import AMBIGUOUS, log_recording, recording_id_for

    scan = make_scan(0)
    r = two_surfaces(scan)
    path = tmp_path / "amb.rrd"
    rec = rr.RecordingStream("boxloc", recording_id=recording_id_for("amb", "x"))
    rec.save(str(path))
    log_recording(rec, [(scan, r)])
    rec.disconnect()
    ents = rrd_entities(path)
    assert {"LineStrips3D:strips", "LineStrips3D:labels", "reason", "area"} <= ents[
        f"/{AMBIGUOUS}"]
    assert {"height", "height_source", "sku_flagged"} <= ents["/world/surfaces"]
    out = _rerun("rrd", "print", "-vvv", "--entity", f"/{AMBIGUOUS}", str(path)).stdout
    assert "ambiguous #0: no end evidence, 600x800 mm, 0.480 m2" in out
    out = _rerun("rrd", "print", "-vvv", "--entity", "/world/surfaces", str(path)).stdout
    assert "h 250 mm side" in out and "NO SKU" in out


# --- run --box-sizes -------------------------------------------------------------------------


def test_run_with_box_sizes_records_the_list_and_attaches_the_file(tmp_path: Path) -> None:
    csv = tmp_path / "sizes.csv"
    csv.write_bytes(SIZES_CSV.encode())
    log = tmp_path / "run.mcap"
    res = CliRunner().invoke(cli, ["run", "sim:single:width=160,height=120,f=131.25",
                                   "--record", str(log), "--box-sizes", str(csv), "-q"])
    assert res.exit_code == 0, res.output
    lg = open_log(log)
    assert lg.config is not None and lg.config.box_sizes[0] == (0.3, 0.4, 0.25)
    assert _attachment_names(log).count(C.BOX_SIZES_ATTACHMENT) == 1
    assert lg.attachment(C.BOX_SIZES_ATTACHMENT) == SIZES_CSV.encode()
    (rec,) = list(lg)
    assert rec.result is not None and rec.result.config_hash == lg.config.hash
    # with a list, every surface is tested against it: matched or flagged
    S = rec.surfaces
    sku_rows = S.tests.of_kind(TestKind.SKU_SIZE)
    assert len(S) == 0 or len(sku_rows) >= len(S)
    assert all(int(k) >= 0 or bool(f) for k, f in zip(S.sku, S.sku_flagged))


def test_run_refuses_a_bad_box_sizes_file_before_any_work(tmp_path: Path) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("width,length,height\n0.3,-1,0.2\n")
    log = tmp_path / "run.mcap"
    res = CliRunner().invoke(cli, ["run", "sim:single:width=160,height=120,f=131.25",
                                   "--record", str(log), "--box-sizes", str(bad)])
    assert res.exit_code == 2 and "row 2: length must be a positive" in res.output
    assert "Traceback" not in res.output and not log.exists()


def test_heights_and_regions_added_over_an_old_baseline_are_reported_not_judged(
        tmp_path: Path) -> None:
    """A log older than schema 1.5 could not record heights, sizes or ambiguous regions:
    its replay gaining them is no regression (the same change between two 1.5 logs is)."""
    scan = make_scan(0)
    cand = two_surfaces(scan)
    S = cand.surfaces
    n = len(S)
    plain = dataclasses.replace(
        S, height=np.full(n, np.nan), height_sigma=np.full(n, np.nan),
        height_source=np.zeros(n, np.int8), sku=np.full(n, -1, np.int32),
        sku_flagged=np.zeros(n, bool),
        tests=S.tests.select(~np.isin(S.tests.kind, [TestKind.BOX_HEIGHT, TestKind.SKU_SIZE])))
    base = dataclasses.replace(cand, surfaces=plain, ambiguous=AmbiguousSet())
    old = tmp_path / "old.mcap"
    with McapRecorder(old) as rec:
        feed(_WithoutAmbiguous(rec), scan, base)
    new = record(tmp_path / "new.mcap", [(scan, cand)])
    ld = diff_logs(old, new)
    kinds = [d.kind for d in ld.all_differences]
    assert kinds.count("height_changed") == 2 and "ambiguous_added" in kinds
    assert not ld.regression, [d.message for d in ld.all_differences if d.regression]
    assert any("predates box heights" in d.message for d in ld.all_differences)
    # between two 1.5 logs the same change is judged
    ld = diff_logs(record(tmp_path / "base15.mcap", [(scan, base)]), new)
    assert ld.regression and {"height_changed", "ambiguous_added"} <= {
        d.kind for d in ld.all_differences if d.regression}

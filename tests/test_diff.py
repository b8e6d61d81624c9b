"""``replay.diff`` / ``replay.report`` / ``boxloc diff``: matching, regressions, outputs, bless.

Logs are recorded here from small simulated scans (tests/replay_helpers.py); the candidate
runs differ from the baseline by one config value, so what must change is known.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import shutil
from pathlib import Path
from xml.etree import ElementTree

import numpy as np
import pytest
import replay_helpers as helpers
import tomli_w
from click.testing import CliRunner

from boxloc.cli import cli
from boxloc.config import Config
from boxloc.errors import InputError
from recorder.annotate import append_outcome, sidecar_path
from recorder.mcap.log import open_log
from replay.diff import (
    DEFAULT_TOLERANCES,
    compare_surfaces,
    diff_logs,
    diff_paths,
    diff_scans,
    differs,
    load_tolerances,
    match_lines,
    match_vertices,
    regression,
)
from replay.replay import replay_log
from replay.report import bless, exit_code, print_table, write_outputs


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory, recorded_log: Path) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("logs")
    return {
        "base": recorded_log,  # tests/conftest.py
        # the same scans and config again: another file, the same products bit for bit
        "same": helpers.record(d / "same.mcap"),
        # MDL's cost per model so high that no hypothesis pays: every surface is dropped
        # while all the stages before the selection stay bit for bit the same
        "k3": helpers.record(d / "k3.mcap", Config(mdl_k3=1e7)),
        # another significance level: everything from the edges on changes
        "alpha": helpers.record(d / "alpha.mcap", Config(alpha=0.001)),
        # scan 0 is another scene under the same index, the other scans are missing
        "other": helpers.record(d / "other.mcap", scenes=(1,), index_of={1: 0}),
    }


@pytest.fixture(scope="module")
def found(logs: dict[str, Path]) -> dict[int, int]:
    """Surfaces per scan of the baseline (what the tests below need of it: a few)."""
    from boxloc.evaluate.metrics import match_surfaces

    n, tp = {}, 0
    for r in open_log(logs["base"]).scans():
        n[r.index] = len(r.surfaces)
        tp += match_surfaces(r.surfaces, helpers.sim(r.index).truth).tp
    assert sum(n.values()) >= 2 and tp >= 1 and any(v == 0 for v in n.values()), (
        f"the test scenes no longer give found (true) and missed boxes: {n}, tp {tp}")
    return n


def _tol_file(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "tol.toml"
    p.write_text(text)
    return p


# --- tolerances ------------------------------------------------------------------------------


def test_every_default_tolerance_is_commented() -> None:
    """Each key of tolerances.toml sits in a block (or a line) that says why."""
    blocks: list[list[str]] = [[]]
    for line in DEFAULT_TOLERANCES.read_text().splitlines():
        if not line.strip():
            blocks.append([])
        else:
            blocks[-1].append(line.strip())
    n_keys = 0
    for b in blocks:
        keys = [ln for ln in b if re.match(r"^[a-z_]+\s*=", ln)]
        n_keys += len(keys)
        if keys:
            assert any(ln.startswith("#") for ln in b), f"uncommented tolerances: {keys}"
    tol = load_tolerances()
    n_fields = sum(len(dataclasses.fields(getattr(tol, s)))
                   for s in ("ignore", "match", "surfaces", "scores", "regression"))
    assert n_keys == n_fields  # the file states every default, and nothing else


def test_tolerances_override_subset(tmp_path: Path) -> None:
    tol = load_tolerances(_tol_file(tmp_path, "[surfaces]\ncenter_mm = 7\n"
                                              "[regression]\nsurface_added = false\n"))
    assert tol.surfaces.center_mm == 7.0
    assert tol.regression.surface_added is False
    assert tol.surfaces.dim_mm == load_tolerances().surfaces.dim_mm  # untouched default
    assert tol.ignore.fields == ("timing_ms",)


@pytest.mark.parametrize("text, match", [
    ("[surfaces]\ncentre_mm = 1\n", "unknown tolerance.*centre_mm"),
    ("[nope]\nx = 1\n", "unknown tolerance section"),
    ("[regression]\ntp_lost = 1\n", "true or false"),
    ("[match]\nline_angle_deg = -1\n", ">= 0"),
    ("[scores]\ntruth = ['oracle']\n", "unknown source"),
    ("[match\n", "not valid TOML"),
])
def test_bad_tolerances_are_refused(tmp_path: Path, text: str, match: str) -> None:
    with pytest.raises(InputError, match=match):
        load_tolerances(_tol_file(tmp_path, text))


def test_missing_tolerances_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not found"):
        load_tolerances(tmp_path / "missing.toml")


def test_differs_uses_atol_and_rtol() -> None:
    assert not differs(100.0, 100.9, atol=1.0)
    assert differs(100.0, 101.1, atol=1.0)
    assert not differs(100.0, 101.1, atol=1.0, rtol=0.02)  # 2 % of 101.1 > 1.1
    assert differs(1.0, 1.1, atol=0.0, rtol=0.05)
    assert not differs(math.nan, math.nan, atol=0.0)
    assert differs(math.nan, 1.0, atol=10.0)


# --- matching --------------------------------------------------------------------------------


def test_items_match_themselves_and_not_a_shifted_copy(logs: dict[str, Path]) -> None:
    rec = next(iter(open_log(logs["base"]).scans()))
    tol = load_tolerances()
    L, V = rec.products["lines"], rec.products["vertices"]
    m = match_lines(L, L, tol.match)
    assert m.pairs == [(i, i) for i in range(len(L))] and m.same
    shift = np.array([0.0, 0.0, 0.05])  # 5 cm: far beyond any gate
    L2 = dataclasses.replace(L, starts=L.starts + shift, ends=L.ends + shift,
                             points=L.points + shift)
    m2 = match_lines(L, L2, tol.match, pixel_angle=rec.scan.sensor.pixel_angle)
    assert m2.pairs == [] and m2.only_base == list(range(len(L)))
    mv = match_vertices(V, V, tol.match)
    assert len(mv.pairs) == len(V) > 0
    V2 = dataclasses.replace(V, points=V.points + shift)
    assert match_vertices(V, V2, tol.match).pairs == []


def _two_surfaces(S: object) -> object:
    """Surface 0 of ``S`` and a copy of it 0.5 m along x: two surfaces, picks 0 and 1."""
    def two(a: np.ndarray, shift: bool = False) -> np.ndarray:
        b = a[:1].copy()
        if shift:
            b = b + np.array([0.5, 0.0, 0.0])
        return np.concatenate([a[:1], b])

    kw = {f.name: two(getattr(S, f.name)) for f in dataclasses.fields(S) if f.name != "tests"}
    for name in ("centers", "grasp_points"):
        kw[name] = two(getattr(S, name), shift=True)
    kw["corners"] = np.concatenate([S.corners[:1], S.corners[:1] + [0.5, 0.0, 0.0]])
    kw["pick_order"] = np.array([0, 1], np.int32)
    return dataclasses.replace(S, **kw)


def test_surfaces_moved_removed_and_pick_order(logs: dict[str, Path],
                                               found: dict[int, int]) -> None:
    k = next(i for i, n in found.items() if n)
    S = _two_surfaces([r for r in open_log(logs["base"]).scans() if r.index == k][0].surfaces)
    tol = load_tolerances().surfaces
    # surface 0 moves 10 mm along x; surface 1 stays
    moved = dataclasses.replace(S, centers=S.centers + [[0.01, 0, 0], [0, 0, 0]])
    sd = compare_surfaces(S, moved, tol)
    assert [p.base for p in sd.moved] == [0]
    assert sd.moved[0].dcenter_mm == pytest.approx(10.0, abs=1e-6)
    # within tolerance: not moved
    nudged = dataclasses.replace(S, centers=S.centers + [[0.001, 0, 0], [0, 0, 0]])
    assert compare_surfaces(S, nudged, tol).moved == []
    # surface 1 dropped: removed, the order of the rest is unchanged
    one = dataclasses.replace(S, **{f.name: getattr(S, f.name)[:1]
                                    for f in dataclasses.fields(S) if f.name != "tests"})
    sd = compare_surfaces(S, one, tol)
    assert sd.removed == [1] and sd.added == [] and not sd.pick_order_changed
    sd = compare_surfaces(one, S, tol)
    assert sd.added == [1] and sd.removed == []
    swapped = dataclasses.replace(S, pick_order=S.pick_order[::-1].copy())
    sd = compare_surfaces(S, swapped, tol)
    assert sd.pick_order_changed and sd.moved == []
    assert sd.pick_order_base == [0, 1] and sd.pick_order_candidate == [1, 0]


# --- whole logs ------------------------------------------------------------------------------


def test_a_log_against_itself_is_identical(logs: dict[str, Path]) -> None:
    ld = diff_logs(logs["base"], logs["base"])
    assert ld.error is None and len(ld.scans) == len(helpers.SCENES)
    assert all(s.identical and s.status == "identical" for s in ld.scans)
    assert ld.all_differences == [] and not ld.regression
    assert exit_code([ld]) == 0


def test_a_rerun_of_the_same_config_is_identical(logs: dict[str, Path]) -> None:
    assert logs["base"].read_bytes() != logs["same"].read_bytes()  # provenance differs
    ld = diff_logs(logs["base"], logs["same"])
    assert ld.identical and exit_code([ld]) == 0
    # ground truth comes back from the recorded simulator spec: scores for both runs
    assert all(s.scores is not None for s in ld.scans)
    assert ld.pooled["base"] == ld.pooled["candidate"]


def test_timing_never_counts(logs: dict[str, Path]) -> None:
    a = next(iter(open_log(logs["base"]).scans()))
    slow = dataclasses.replace(a, timing_ms={k: v * 1000 + 5000 for k, v in a.timing_ms.items()})
    sd = diff_scans(a, slow)
    assert sd.identical and sd.differences == [] and not sd.regression
    assert sd.timing["candidate"]["total"] > sd.timing["base"]["total"]  # still reported


def test_a_failed_scan_is_a_result(logs: dict[str, Path]) -> None:
    a = next(iter(open_log(logs["base"]).scans()))
    err = {"scan_index": a.index, "stage": "vertices", "error_type": "MemoryError",
           "message": "out of memory"}
    failed = dataclasses.replace(
        a, error=err, result_info=None,
        products={k: v for k, v in a.products.items() if k in ("edges", "lines")})
    sd = diff_scans(a, failed)
    assert sd.status == "changed" and not sd.identical
    assert sd.counts["vertices"] == (len(a.products["vertices"]), None)
    d = [d for d in sd.differences if d.kind == "scan_failed"]
    assert len(d) == 1 and d[0].regression and "MemoryError in vertices" in d[0].message
    back = diff_scans(failed, a)  # the candidate runs where the baseline failed: good news
    assert [d.kind for d in back.differences if d.stage == "scan"] == ["scan_recovered"]
    assert not any(d.regression for d in back.differences if d.stage == "scan")


def test_dropped_surfaces_are_a_regression(logs: dict[str, Path],
                                           found: dict[int, int]) -> None:
    ld = diff_logs(logs["base"], logs["k3"])
    for s in ld.scans:
        # nothing before the selection changed: lines, vertices, hypotheses all match
        assert not any(c.startswith(("edges/", "lines/", "vertices/", "hypotheses/"))
                       for c in s.changed_fields)
        assert s.flipped == [] and all(m.same for m in s.items.values())
        assert s.surfaces.removed == list(range(found[s.scan]))
        if not found[s.scan]:  # nothing to lose: only selection/k3 differs
            assert s.status == "equivalent" and s.differences == []
            continue
        kinds = {d.kind for d in s.differences}
        assert {"surface_removed", "count"} <= kinds
        # with truth, truth judges: only lost true positives are regressions
        tp = s.scores["base"]["tp"]
        regs = [d.rule for d in s.differences if d.regression]
        assert regs == (["tp_lost"] if tp else [])
    assert ld.regression and exit_code([ld]) == 1
    pooled = [d for d in ld.differences if d.rule == "recall_drop"]
    assert pooled and pooled[0].regression


def test_without_truth_any_removed_surface_is_a_regression(
        logs: dict[str, Path], found: dict[int, int], tmp_path: Path) -> None:
    tol = load_tolerances(_tol_file(tmp_path, "[scores]\ntruth = []\n"))
    ld = diff_logs(logs["base"], logs["k3"], tol)
    assert all(s.scores is None for s in ld.scans) and ld.pooled is None
    regs = [d for d in ld.all_differences if d.regression]
    assert {d.kind for d in regs} == {"surface_removed"}
    assert len(regs) == sum(found.values())
    assert exit_code([ld]) == 1
    # the same diff, re-judged under rules that accept removals: no regression
    lenient = dataclasses.replace(tol, regression=dataclasses.replace(
        tol.regression, surface_removed=False))
    assert not regression([ld], lenient) and exit_code([ld], lenient) == 0


def test_another_alpha_changes_the_stages_but_they_are_not_regressions(
        logs: dict[str, Path], tmp_path: Path) -> None:
    ld = diff_logs(logs["base"], logs["alpha"])
    assert ld.config_changes == {"alpha": [0.01, 0.001]}
    changed = [s for s in ld.scans if s.status == "changed"]
    assert changed
    # the edge stage's tests use alpha: its product changes
    assert all(any(c.startswith("edges/") for c in s.changed_fields) for s in ld.scans)
    stage = [d for s in ld.scans for d in s.differences
             if d.kind in ("count", "only_base", "only_candidate", "flipped", "edge_map")]
    assert stage and not any(d.regression for d in stage)
    # every flipped test really flipped, on matched entities
    for s in ld.scans:
        for f in s.flipped:
            assert f.base["accepted"] != f.candidate["accepted"]
    # with ground truth, surfaces added/removed/moved are judged by it, not by themselves
    assert all(s.scores is not None for s in ld.scans)
    assert not any(d.regression for s in ld.scans for d in s.differences
                   if d.kind in ("surface_added", "surface_removed", "surface_moved"))
    strict = load_tolerances(_tol_file(tmp_path, "[regression]\nstage_counts = true\n"
                                                 "flipped_tests = true\n"))
    assert regression(changed[0], strict) and regression([ld], strict)


def test_annotated_picks(logs: dict[str, Path], found: dict[int, int],
                         tmp_path: Path) -> None:
    base = tmp_path / "base.mcap"
    shutil.copyfile(logs["base"], base)
    surfaces = [(i, k) for i, n in sorted(found.items()) for k in range(n)]
    (fs, fk), (os_, ok_) = surfaces[0], surfaces[1]
    append_outcome(base, fs, fk, False, "slipped")
    append_outcome(base, os_, ok_, True)
    ld = diff_logs(base, logs["k3"])
    by = {s.scan: s for s in ld.scans}
    pick = [p for p in by[fs].picks if p["surface"] == fk][0]
    assert pick["fate"] == "removed" and not pick["ok"]
    failed = [d for d in by[fs].differences if d.kind == "failed_pick"]
    assert len(failed) == 1 and not failed[0].regression and "slipped" in failed[0].message
    # the surface whose pick failed is exempt from the "surface removed" rule
    assert not any(d.regression for d in by[fs].differences
                   if d.kind == "surface_removed" and d.values.get("base") == fk)
    ok = [d for d in by[os_].differences if d.kind == "ok_pick"]
    assert len(ok) == 1 and ok[0].regression
    # a candidate that keeps the failed surface unchanged: reported, not a regression
    ld = diff_logs(base, logs["same"])
    picks = [p for s in ld.scans for p in s.picks]
    assert [p["fate"] for p in picks] == ["unchanged", "unchanged"]
    kept = [d for s in ld.scans for d in s.differences if d.kind == "failed_pick"]
    assert len(kept) == 1 and "still chosen unchanged" in kept[0].message
    assert not kept[0].regression and exit_code([ld]) == 0


def test_other_input_and_missing_scans(logs: dict[str, Path]) -> None:
    ld = diff_logs(logs["base"], logs["other"])
    st = {s.scan: s.status for s in ld.scans}
    assert st == {0: "error", **{k: "missing" for k in helpers.ALL[1:]}}
    assert "not the same input" in ld.scans[0].error
    assert exit_code([ld]) == 2
    missing = [d for s in ld.scans for d in s.differences if d.kind == "scan_missing"]
    assert len(missing) == len(helpers.ALL) - 1 and all(d.regression for d in missing)


def test_directories_are_matched_by_file_name(logs: dict[str, Path], tmp_path: Path) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    shutil.copyfile(logs["base"], a / "run.mcap")
    shutil.copyfile(logs["same"], b / "run.mcap")
    diffs = diff_paths(a, b)
    assert [d.name for d in diffs] == ["run.mcap"] and exit_code(diffs) == 0
    shutil.copyfile(logs["base"], a / "extra.mcap")
    diffs = diff_paths(a, b)
    assert {d.name: d.error is not None for d in diffs} == {"extra.mcap": True,
                                                            "run.mcap": False}
    assert exit_code(diffs) == 2
    with pytest.raises(InputError, match="cannot compare a directory"):
        diff_paths(a, logs["base"])
    with pytest.raises(InputError, match="not found"):
        diff_paths(a, tmp_path / "nope")


def test_unreadable_log_is_an_error_not_a_crash(logs: dict[str, Path], tmp_path: Path) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not an mcap file at all")
    ld = diff_logs(logs["base"], bad)
    assert ld.error and exit_code([ld]) == 2


# --- outputs ---------------------------------------------------------------------------------


def test_outputs_are_written_and_valid(logs: dict[str, Path], tmp_path: Path) -> None:
    diffs = diff_paths(logs["base"], logs["alpha"])
    out = tmp_path / "out"
    summ = write_outputs(diffs, out)
    lines = (out / "diff.jsonl").read_text().splitlines()
    assert len(lines) == len(helpers.SCENES)
    rows = [json.loads(ln) for ln in lines]
    assert [r["scan"] for r in rows] == list(helpers.ALL)
    assert all("timing_ms" in r and "differences" in r for r in rows)
    # timing is its own channel: no difference ever names it
    assert not any("timing" in json.dumps(d) for r in rows for d in r["differences"])
    on_disk = json.loads((out / "summary.json").read_text())
    assert on_disk == summ
    assert on_disk["exit_code"] == exit_code(diffs)
    assert on_disk["n_scans"] == len(helpers.SCENES)
    assert sum(on_disk["scans"].values()) == len(helpers.SCENES)
    assert set(on_disk["scores"]) == {"n_logs", "base", "candidate"}
    html = (out / "report.html").read_text()
    assert html.startswith("<!DOCTYPE html>") and html.rstrip().endswith("</html>")
    assert html.count("<svg") >= 3 and "http://" not in html.replace(
        "http://www.w3.org/2000/svg", "")  # self-contained
    assert (out / "report.html").stat().st_size < 1_000_000
    for svg in re.findall(r"<svg.*?</svg>", html, flags=re.S):  # every plot is well-formed
        ElementTree.fromstring(svg)


def test_terminal_table(logs: dict[str, Path], found: dict[int, int]) -> None:
    from rich.console import Console

    diffs = diff_paths(logs["base"], logs["k3"])
    con = Console(record=True, width=200)
    print_table(diffs, con, bless_command="boxloc diff a b --update-refs a")
    text = con.export_text()
    assert "REGRESSION" in text and "tp_lost" in text
    assert "timing [ms]" in text and "--update-refs" in text


# --- bless -----------------------------------------------------------------------------------


def test_bless_keeps_the_replaced_reference(logs: dict[str, Path], found: dict[int, int],
                                            tmp_path: Path) -> None:
    refs = tmp_path / "refs"
    refs.mkdir()
    ref = refs / "k3.mcap"
    shutil.copyfile(logs["base"], ref)
    append_outcome(ref, next(i for i, n in found.items() if n), 0, False, "slipped")
    old = ref.read_bytes()
    written = bless(logs["k3"], refs)
    assert written == [ref] and ref.read_bytes() == logs["k3"].read_bytes()
    bak = refs / ".boxloc-bak" / "k3-001.mcap"
    assert bak.read_bytes() == old
    assert sidecar_path(bak).exists() and not sidecar_path(ref).exists()
    bless(logs["alpha"], ref)  # into the file itself
    assert (refs / ".boxloc-bak" / "k3-002.mcap").read_bytes() == logs["k3"].read_bytes()
    assert diff_logs(ref, logs["alpha"]).identical
    assert [p.name for p in refs.iterdir() if p.is_file()] == ["k3.mcap"]  # no .tmp left


def test_bless_a_directory(logs: dict[str, Path], tmp_path: Path) -> None:
    cand = tmp_path / "cand"
    cand.mkdir()
    shutil.copyfile(logs["k3"], cand / "a.mcap")
    shutil.copyfile(logs["alpha"], cand / "b.mcap")
    written = bless(cand, tmp_path / "new-refs")
    assert sorted(p.name for p in written) == ["a.mcap", "b.mcap"]
    with pytest.raises(InputError, match="into the file"):
        bless(cand, tmp_path / "x.mcap")
    with pytest.raises(InputError, match="not found"):
        bless(tmp_path / "nope", tmp_path / "r")


# --- the command line ------------------------------------------------------------------------


def test_cli_exit_codes_and_outputs(logs: dict[str, Path], found: dict[int, int],
                                    tmp_path: Path) -> None:
    run = CliRunner().invoke
    r = run(cli, ["diff", str(logs["base"]), str(logs["same"])])
    assert r.exit_code == 0, r.output
    out = tmp_path / "o"
    r = run(cli, ["diff", str(logs["base"]), str(logs["k3"]), "--out", str(out)])
    assert r.exit_code == 1, r.output
    assert "--update-refs" in r.output
    assert {p.name for p in out.iterdir()} == {"diff.jsonl", "summary.json", "report.html"}
    r = run(cli, ["diff", str(logs["base"]), str(logs["k3"]), "--json"])
    assert r.exit_code == 1 and json.loads(r.stdout)["exit_code"] == 1
    r = run(cli, ["diff", str(logs["base"]), str(logs["other"])])
    assert r.exit_code == 2


def test_cli_update_refs(logs: dict[str, Path], tmp_path: Path) -> None:
    ref = tmp_path / "ref.mcap"
    shutil.copyfile(logs["base"], ref)
    r = CliRunner().invoke(cli, ["diff", str(ref), str(logs["k3"]), "--update-refs", str(ref)])
    assert r.exit_code == 0, r.output
    assert ref.read_bytes() == logs["k3"].read_bytes()
    r = CliRunner().invoke(cli, ["diff", str(ref), str(logs["k3"])])
    assert r.exit_code == 0


@pytest.mark.parametrize("args, match", [
    (["nope.mcap", "nope2.mcap"], "not found"),
    (["{base}", "{dir}"], "cannot compare a file"),
    (["{base}", "{base}", "--tolerances", "{bad}"], "unknown tolerance"),
    (["{base}", "{base}", "--rerun", "save:x.txt"], "must end in .rrd"),
])
def test_cli_bad_input_is_one_line_and_exit_2(
        logs: dict[str, Path], tmp_path: Path, args: list[str], match: str) -> None:
    bad = _tol_file(tmp_path, "[match]\nfoo = 1\n")
    fill = {"base": str(logs["base"]), "dir": str(tmp_path), "bad": str(bad)}
    r = CliRunner().invoke(cli, ["diff", *(a.format(**fill) for a in args)])
    assert r.exit_code == 2, r.output
    err = r.stderr.strip().splitlines()
    assert len(err) == 1 and re.search(match, err[0]) and "Traceback" not in r.output


def test_tolerances_round_trip_through_the_summary(logs: dict[str, Path],
                                                   tmp_path: Path) -> None:
    """The tolerances a diff's summary records, written back as a tolerances file, give the
    same tolerances: a report says enough to run its diff again."""
    tol_file = _tol_file(tmp_path, "[surfaces]\ncenter_mm = 7.5\n[scores]\ntruth = [\"npz\"]\n"
                                   "[regression]\nsurface_removed = false\n")
    tol = load_tolerances(tol_file)
    assert tol != load_tolerances()  # the file changed something
    summ = write_outputs(diff_paths(logs["base"], logs["same"], tolerances=tol),
                         tmp_path / "out")
    recorded = json.loads((tmp_path / "out" / "summary.json").read_text())["tolerances"]
    assert recorded == summ["tolerances"] and recorded["source"] == str(tol_file)
    again = tmp_path / "again.toml"
    again.write_text(tomli_w.dumps({k: v for k, v in recorded.items() if k != "source"}))
    back = load_tolerances(again)
    assert dataclasses.replace(back, source=tol.source) == tol


def test_a_replayed_log_diffs_to_nothing_and_a_perturbed_replay_does_not(
        logs: dict[str, Path], tmp_path: Path) -> None:
    """Record, replay the log with this code, diff: zero differences; replay it again with
    one value changed, diff: the change shows, and dropping every surface is a regression."""
    same = replay_log(logs["base"], out_dir=tmp_path / "same")
    assert same.status == "ok", same.error
    ld = diff_logs(logs["base"], Path(same.output))
    assert ld.error is None and len(ld.scans) == len(helpers.SCENES)
    assert ld.identical and ld.all_differences == [] and exit_code([ld]) == 0
    worse = replay_log(logs["base"], out_dir=tmp_path / "k3", overrides=["mdl_k3=1e7"])
    assert worse.status == "ok", worse.error
    ld = diff_logs(logs["base"], Path(worse.output))
    assert not ld.identical and ld.all_differences
    assert ld.regression and exit_code([ld]) == 1
    had = {r.index for r in open_log(logs["base"]).scans() if len(r.surfaces)}
    assert had and had <= {s.scan for s in ld.scans if not s.identical}

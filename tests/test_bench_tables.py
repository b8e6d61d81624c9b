"""scripts/bench_tables.py: the docs' benchmark tables come from the bench's JSON reports.

Small fixture reports, shaped like the benches' (bench_matrix.json, bench_real.json,
bench.json, bench_packed.json, bench_bare.json), go through the script into a scratch
checkout; the tables must show their figures, a second run must change nothing, and a
report of the wrong schema must stop the script with one line and exit status 2 before it
writes anything.
"""

from __future__ import annotations

import copy
import importlib.util
import json
import subprocess
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "scripts" / "bench_tables.py"


def _load() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_tables", SCRIPT)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["bench_tables"] = mod
    spec.loader.exec_module(mod)
    return mod


bt = _load()

README = """# boxloc

Prose before the tables stays as it is.

<!-- bench:matrix:summary -->
stale text
<!-- /bench -->

Prose between them too.

<!-- bench:real:summary -->
<!-- /bench -->
"""

BENCHMARKS = """# Benchmarks

<!-- bench:matrix:targets -->
<!-- /bench -->

<!-- bench:matrix:kinds -->
<!-- /bench -->

<!-- bench:matrix:cells -->
<!-- /bench -->

<!-- bench:matrix:stages -->
<!-- /bench -->

<!-- bench:real:targets -->
<!-- /bench -->

<!-- bench:real:draws -->
<!-- /bench -->

<!-- bench:real:inputs -->
<!-- /bench -->

<!-- bench:real:stages -->
<!-- /bench -->

<!-- bench:sim:summary -->
<!-- /bench -->

<!-- bench:sim:kinds -->
<!-- /bench -->

<!-- bench:sim:draws -->
<!-- /bench -->

<!-- bench:sim:stages -->
<!-- /bench -->
"""


# --- fixture reports (the fields the benches write, few scans) -----------------------------


def _fig(tp: int, fp: int, fn: int, **extra: Any) -> dict[str, Any]:
    n_pred, n_exp = tp + fp, tp + fn
    p = tp / n_pred if n_pred else 1.0
    r = tp / n_exp if n_exp else 1.0
    return {"n_scans": 2, "tp": tp, "fp": fp, "fn": fn, "n_pred": n_pred, "n_exposed": n_exp,
            "precision": p, "recall": r, "f1": 2 * p * r / (p + r) if p + r else 0.0,
            "grasp_err_median_mm": 2.25, "grasp_err_p95_mm": 7.75,
            "center_err_median_mm": 2.0, "dim_err_median_mm": 3.0, "dim_err_p95_mm": 9.0,
            "normal_err_median_deg": 0.5, "normal_err_p95_deg": 1.5, "iou_median": 0.9,
            **extra}


def _group(tp: int, fp: int, fn: int, no_box: dict[str, Any] | None = None) -> dict[str, Any]:
    return {"n_scenes": 2, **_fig(tp, fp, fn), "errors": 0, "timeouts": 1,
            "time": {"median_ms": 1500.0, "p99_ms": 9000.0, "max_ms": 9100.0,
                     "max_over_median": 6.07}, "no_box": no_box}


NO_BOX = {"n_scans": 2, "false_surfaces": 0, "false_surfaces_per_scan": 0.0,
          "zero_surface_scans": 2, "zero_surface_share": 1.0, "edge_scans": 2,
          "pixels": 1000, "edge_points": 12, "false_edge_points": 7,
          "edge_points_per_pixel": 0.012, "false_edge_points_per_pixel": 0.007}


def matrix_report() -> dict[str, Any]:
    laser, tof = _group(17, 12, 46, NO_BOX), _group(21, 2, 48, NO_BOX)
    cells = {f"{s}/{k}": {"sensor": s, "kind": k, "held_out": s == "tof",
                          **_group(3, 1, 2, NO_BOX if k == "empty" else None)}
             for s in ("laser", "tof") for k in ("single", "empty")}
    return {
        "schema": "boxloc.bench_matrix/1", "version": "0.1.0", "mode": "matrix", "n": 8,
        "seed": 0, "jobs": 2, "scan_timeout_s": 120.0, "warmup": True, "threads": {},
        "default_configuration": True, "config": {"alpha": 0.01}, "config_hash": "feedc0de",
        "site": {"min_edge": 0.15, "max_edge": 0.6},
        "held_out": {"sensor": "tof", "cells": ["tof/single", "tof/empty"]},
        "sensors": ["laser", "tof"], "kinds": ["single", "empty"], "no_box_kinds": ["empty"],
        "seeds": {"n": 1, "trial_seeds": [0], "per_seed": [], "spread": {}},
        "groups": {"overall": {"development": laser, "all": _group(38, 14, 94, NO_BOX)},
                   "sensors": {"laser": laser, "tof": tof},
                   "kinds": {k: {"development": _group(5, 1, 9), "all": _group(6, 1, 9)}
                             for k in ("single", "empty")},
                   "cells": cells},
        "targets": [{"name": "recall overall", "key": "recall", "over": "overall", "op": ">=",
                     "bound": 0.9, "target": ">= 0.9", "unit": "",
                     "development": {"value": 0.2698, "where": "overall", "pass": False},
                     "all": {"value": 0.2879, "where": "overall", "pass": False}}],
        "timeouts": [{"scene": 3, "trial_seed": 0, "sensor": "tof", "kind": "empty",
                      "spec_text": "empty:seed=1", "phase": "localize", "limit_s": 120.0}],
        "errors": {"total": 0, "list": []},
        "timing": {"stages_ms": {"edges": {"median": 257.8, "p95": 1660.2}},
                   "total_ms": {"median": 1500.0, "p95": 9000.0},
                   "per_scan_ms": [1500.0] * 8, "run_s": 61.0},
        "memory": {"worker_peak_rss_mb_median": 438.2, "worker_peak_rss_mb_max": 642.8},
        "scenes": [{"index": i, "status": "ok"} for i in range(8)],
    }


def real_report() -> dict[str, Any]:
    boxes = {"n_frames": 4, "boxloc": {**_fig(35, 1, 3), "errors": 0},
             "baseline": {**_fig(37, 57, 1), "errors": 0}}
    spread = {m: {k: {"min": 0.89, "max": 0.95, "mean": 0.92} for k in ("precision", "recall")}
              for m in ("boxloc", "baseline")}
    config = {"alpha": 0.01, "min_edge": 0.035, "noise_auto": True, "noise": {"sigma0": 0.001}}
    return {
        "version": "0.1.0", "data_dir": "../shared/data/mosd", "n_frames": 2,
        "seeds": {"n": 2, "trial_seeds": [0, 1],
                  "per_seed": [{"trial_seed": s, "groups": {"boxes": {
                      "boxloc": _fig(17 + s, 1, 2), "baseline": _fig(18, 28, 1)}}}
                      for s in (0, 1)],
                  "spread": {"boxes": spread}},
        "config": config, "config_hash": "abad1dea",
        "noise": {"source": "auto: the config as given (noise_auto: each scan's own model)",
                  "model": {"sigma0": 0.001, "k2": 0.0006}},
        "squareness": {"source": "config", "angle_tolerance_deg": 1.0},
        "pose": "plane: sensor_to_base from each frame's dominant plane (no labels)",
        "summary": {"boxloc": _fig(35, 1, 3), "baseline": _fig(37, 57, 1)},
        "groups": {"boxes": boxes},
        "targets": [{"name": "recall (box frames)", "key": "boxes.recall", "target": ">= 0.9",
                     "value": 35 / 38, "baseline": 37 / 38, "unit": "", "pass": True}],
        "timing": {m: {"stages_ms": {"lines": {"median": 454.0, "p95": 900.0}},
                       "total_ms": {"median": 894.0, "p95": 2000.0},
                       "per_frame_ms": [894.0, 895.0]} for m in ("boxloc", "baseline")},
        "memory": {}, "errors": {"count": {"boxloc": 0, "baseline": 0}, "total": 0, "list": []},
        "skipped": [], "frames": [{"frame": "learn0"}, {"frame": "learn1"}],
    }


def sim_report() -> dict[str, Any]:
    targets = [{"name": "precision", "key": "precision", "target": ">= 0.99", "value": 0.984,
                "baseline": 0.747, "unit": "", "pass": False},
               {"name": "median grasp error", "key": "grasp_err_median_mm",
                "target": "<= 5 mm", "value": 2.4, "baseline": 3.5, "unit": "mm", "pass": True}]
    return {
        "version": "0.1.0", "n": 2, "seed": 0,
        "seeds": {"n": 1, "trial_seeds": [0], "per_seed": [
            {"trial_seed": 0, "figures": {"boxloc": _fig(343, 4, 20),
                                          "baseline": _fig(118, 39, 245)}}]},
        "config": {"alpha": 0.01}, "config_hash": "0ddba11",
        "summary": {"boxloc": _fig(343, 4, 20), "baseline": _fig(118, 39, 245)},
        "edges": {"any": {"precision": 0.83, "recall": 0.85}},
        "per_kind": {"pallet": {"n_scenes": 1, "boxloc": _fig(10, 0, 1),
                                "baseline": _fig(0, 0, 11)}},
        "targets": targets,
        "timing": {"boxloc": {"stages_ms": {}, "total_ms": {"median": 480.0, "p95": 900.0},
                              "per_scene_total_ms": [480.0, 481.0]}},
        "memory": {"boxloc_peak_rss_mb": 645.0},
        "errors": {"count": {}, "total": 0, "list": []},
        "scenes": [{"index": 0}, {"index": 1}],
    }


# --- helpers -----------------------------------------------------------------------------------


@pytest.fixture()
def checkout(tmp_path: Path) -> Path:
    """A scratch repository root with a README and docs/benchmarks.md to regenerate."""
    root = tmp_path / "repo"
    (root / "docs").mkdir(parents=True)
    (root / "README.md").write_text(README)
    (root / "docs" / "benchmarks.md").write_text(BENCHMARKS)
    return root


def _write(path: Path, report: dict[str, Any]) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report))
    return path


def _run(root: Path, *args: str) -> int:
    return int(bt.main(["--root", str(root), *args]))


def _ingest_all(root: Path, tmp: Path) -> int:
    return _run(root, "--matrix", str(_write(tmp / "m" / "bench_matrix.json", matrix_report())),
                "--real", str(_write(tmp / "r" / "bench_real.json", real_report())),
                "--sim", str(_write(tmp / "s" / "bench.json", sim_report())),
                "--date", "2026-11-25 10:45 UTC", "--commit", "abc1234")


def _snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file()}


# --- tests -------------------------------------------------------------------------------------


def test_tables_are_generated_from_the_reports(checkout: Path, tmp_path: Path) -> None:
    assert _ingest_all(checkout, tmp_path) == 0
    readme = (checkout / "README.md").read_text()
    # the prose outside the regions is untouched, the stale text inside is gone
    assert readme.startswith("# boxloc\n\nProse before the tables stays as it is.\n")
    assert "Prose between them too." in readme and "stale text" not in readme
    # the simulated table: per sensor, the held-out one marked, the two overall rows
    rows = {line.split(" | ")[0].strip("| *"): line for line in readme.splitlines()
            if line.startswith("| ")}
    assert "17 / 12 / 46 | 0.586 | 0.270 | 2.2 / 7.8 | 1.50 / 9.10 | 1 / 0" in rows["laser"]
    assert "21 / 2 / 48 | 0.913 | 0.304" in rows["tof (held out)"]
    assert "38 / 14 / 94" in rows["all sensors"] and "all but tof" in rows
    # stamped with the date, the commit and the command, linked to the committed copy
    assert ("*2026-11-25 10:45 UTC, commit abc1234, boxloc 0.1.0, config feedc0de: `boxloc "
            "bench --matrix --n 8 --seed 0 --seeds 1 --jobs 2 --held-out tof --scan-timeout "
            "120 --out DIR` (reconstructed); [report](docs/results/bench_matrix.json).*"
            ) in readme
    # the real-data table: pooled figures with the worst and best draw, per group
    assert ("| box frames (learn0–16) | 19 | 35 / 1 / 3 | 0.921 (0.890–0.950) | "
            "0.972 (0.890–0.950) | 37 / 57 / 1 |") in readme
    assert ("`boxloc bench --real ../shared/data/mosd --set min_edge=0.035 --seeds 2 --noise "
            "auto --squareness config --pose plane --out DIR`") in readme

    bench = (checkout / "docs" / "benchmarks.md").read_text()
    assert "[report](results/bench_matrix.json)" in bench  # relative to docs/
    assert "| recall overall | >= 0.9 | 0.270 | miss | 0.288 | miss |" in bench
    assert "| tof/single (held out) | 2 | 5 | 3 / 1 / 2 |" in bench
    # nothing found and nothing to find: no precision and no recall, not 1.0
    assert "| laser/empty | 2 | 5 |" in bench
    assert "scene 3 (tof/empty, localize)" in bench and "The run took 61 s" in bench
    assert "| 0 | 17 / 1 / 2 | 18 / 28 / 1 |" in bench and "| 1 | 18 / 1 / 2 |" in bench
    assert "| precision | 0.984 | 0.747 | >= 0.99 | miss |" in bench
    assert "| median grasp error | 2.4 mm | 3.5 mm | <= 5 mm | pass |" in bench
    assert "| TP / FP / FN | 343 / 4 / 20 | 118 / 39 / 245 |" in bench
    assert "| pallet | 1 | 10 / 0 / 1 | 1.000 / 0.909 |" in bench
    assert "No report yet" not in bench


def test_the_vertex_normals_table_shows_each_sensor_against_chi2() -> None:
    rep = copy.deepcopy(matrix_report())
    rep["groups"]["sensors"]["laser"]["funnel"] = {
        "vertex_normals": {"n": 40, "median": 4.6, "beyond_p99": 0.275},
        "line_directions": {"jump": {"n": 12, "median_abs": 1.67, "beyond_p99": 0.39},
                            "crease": {"n": 30, "median_abs": 0.41, "beyond_p99": 0.0}}}
    out = bt.matrix_normals(rep)
    assert "| laser | 40 | 4.60 | 0.275 | 12 | 1.67 | 0.390 | 30 | 0.41 | 0.000 |" in out
    # a group without vertices (or a report from before the check) shows empty cells
    assert "| tof (held out) | – | – | – | – | – | – | – | – | – |" in out
    # the reference row: chi2(2)'s and N(0, 1)'s medians and 1 % tails
    assert "| calibrated |  | 1.39 | 0.010 |  | 0.67 | 0.010 |  | 0.67 | 0.010 |" in out
    assert "beyond 9.21" in out and "beyond 2.58" in out and "jump lines" in out


def test_committed_copies_are_trimmed_and_stamped(checkout: Path, tmp_path: Path) -> None:
    assert _ingest_all(checkout, tmp_path) == 0
    results = checkout / "docs" / "results"
    m = json.loads((results / "bench_matrix.json").read_text())
    assert "scenes" not in m and "per_scan_ms" not in m["timing"]
    assert m["groups"] == matrix_report()["groups"]  # the figures themselves are kept
    assert m["provenance"]["commit"] == "abc1234" and not m["provenance"]["commit_inferred"]
    assert m["provenance"]["trimmed"] == ["scenes", "timing.per_scan_ms"]
    r = json.loads((results / "bench_real.json").read_text())
    assert "frames" not in r and "per_frame_ms" not in r["timing"]["boxloc"]
    s = json.loads((results / "bench.json").read_text())
    assert "scenes" not in s and s["provenance"]["date"] == "2026-11-25 10:45 UTC"


def test_a_second_run_changes_nothing(checkout: Path, tmp_path: Path) -> None:
    assert _ingest_all(checkout, tmp_path) == 0
    first = _snapshot(checkout)
    assert _run(checkout) == 0
    assert _snapshot(checkout) == first
    assert _run(checkout, "--check") == 0
    # ingesting a committed copy again keeps its stamp: the same bytes
    copy_ = tmp_path / "again" / "bench_matrix.json"
    copy_.parent.mkdir()
    copy_.write_bytes((checkout / "docs" / "results" / "bench_matrix.json").read_bytes())
    assert _run(checkout, "--matrix", str(copy_)) == 0
    assert _snapshot(checkout) == first


def test_check_finds_a_table_older_than_its_report(checkout: Path, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    assert _ingest_all(checkout, tmp_path) == 0
    path = checkout / "docs" / "results" / "bench_matrix.json"
    rep = json.loads(path.read_text())
    rep["groups"]["sensors"]["laser"]["tp"] = 99
    path.write_text(json.dumps(rep))
    capsys.readouterr()
    assert _run(checkout, "--check") == 1
    assert "README.md" in capsys.readouterr().err
    assert "99 / 12 / 46" not in (checkout / "README.md").read_text()  # --check writes nothing
    assert _run(checkout) == 0
    assert "99 / 12 / 46" in (checkout / "README.md").read_text()


def test_an_absent_report_leaves_a_recipe(checkout: Path) -> None:
    assert _run(checkout) == 0
    readme = (checkout / "README.md").read_text()
    assert ("No report yet. Run `boxloc bench --real ../shared/data/mosd --set min_edge=0.035 "
            "--seeds 8 --out DIR`, then `python scripts/bench_tables.py --real "
            "DIR/bench_real.json`") in readme


def _bad_matrix_schema() -> dict[str, Any]:
    return {**matrix_report(), "schema": "boxloc.bench_matrix/2"}


def _real_without_groups() -> dict[str, Any]:
    r = real_report()
    del r["groups"]
    return r


@pytest.mark.parametrize("option, report, message", [
    ("--matrix", _bad_matrix_schema, "schema 'boxloc.bench_matrix/2', expected "
                                     "'boxloc.bench_matrix/1'"),
    ("--real", matrix_report, "a boxloc.bench_matrix/1 report, not a bench_real.json"),
    ("--sim", real_report, "not a bench.json report: no n, seed, per_kind"),
    ("--real", _real_without_groups, "not a bench_real.json report: no groups"),
    ("--matrix", lambda: [1, 2], "not a bench report (a JSON object), got list"),
])
def test_a_report_of_the_wrong_schema_is_refused(
        checkout: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str,
        report: Any, message: str) -> None:
    before = _snapshot(checkout)
    path = _write(tmp_path / "in" / "report.json", report())
    assert _run(checkout, option, str(path)) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("bench_tables: ") and message in err, err
    assert _snapshot(checkout) == before  # nothing written


def test_a_committed_report_of_the_wrong_schema_stops_the_rewrite(
        checkout: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _write(checkout / "docs" / "results" / "bench_matrix.json", _bad_matrix_schema())
    before = _snapshot(checkout)
    assert _run(checkout) == 2
    assert "docs/results/bench_matrix.json: schema" in capsys.readouterr().err
    assert _snapshot(checkout) == before


@pytest.mark.parametrize("text, message", [
    ("<!-- bench:matrix:nonsense -->\n<!-- /bench -->\n", "unknown region bench:matrix:nonsense"),
    ("<!-- bench:matrix:summary -->\nno end\n", "bench:matrix:summary is not closed"),
])
def test_a_bad_region_is_refused(checkout: Path, capsys: pytest.CaptureFixture[str],
                                 text: str, message: str) -> None:
    (checkout / "docs" / "other.md").write_text(text)
    assert _run(checkout) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err, err


def test_bad_options_are_one_line_and_exit_2(checkout: Path, tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    m = _write(tmp_path / "m.json", matrix_report())
    r = _write(tmp_path / "r.json", real_report())
    assert _run(checkout, "--matrix", str(m), "--real", str(r), "--command", "x") == 2
    assert "--command names one report's command" in capsys.readouterr().err
    assert _run(checkout, "--check", "--matrix", str(m)) == 2
    assert _run(checkout, "--matrix", str(tmp_path / "absent.json")) == 2
    assert "absent.json: no such file" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        _run(checkout, "--no-such-option")
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1 and "--no-such-option" in err


def test_wrong_schema_from_the_command_line_is_one_line_and_exit_2(tmp_path: Path) -> None:
    """The script as run: exit status 2, one line on stderr, no traceback."""
    root = tmp_path / "repo"
    root.mkdir()
    bad = _write(tmp_path / "bench_matrix.json", _bad_matrix_schema())
    p = subprocess.run([sys.executable, str(SCRIPT), "--root", str(root), "--matrix", str(bad)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2, p.stderr
    assert p.stderr.count("\n") == 1 and "Traceback" not in p.stderr
    assert p.stderr.startswith("bench_tables: ")


def test_the_repository_docs_are_what_the_reports_say() -> None:
    """README.md and docs/*.md hold the tables of docs/results/ and recorder/mcap/channels.py:
    after a new report or a channel change, run `python scripts/bench_tables.py`."""
    assert _run(ROOT, "--check") == 0


def test_the_matrix_command_is_rebuilt_from_the_report() -> None:
    rep = copy.deepcopy(matrix_report())
    rep.update(n=320, jobs=1, scan_timeout_s=60.0, held_out={"sensor": "laser"})
    rep["seeds"]["n"] = 3
    assert bt.reconstruct_command(rep, bt.KINDS["matrix"]) == (
        "boxloc bench --matrix --n 320 --seed 0 --seeds 3 --jobs 1 --held-out laser "
        "--scan-timeout 60 --out DIR")


# --- packed layers and bare planes -------------------------------------------------------------

PACKED_DOC = """# Benchmarks

<!-- bench:packed:summary -->
<!-- /bench -->

<!-- bench:packed:targets -->
<!-- /bench -->

<!-- bench:bare:summary -->
<!-- /bench -->

<!-- bench:bare:targets -->
<!-- /bench -->

<!-- bench:bare:tests -->
<!-- /bench -->
"""


def _packed_group(tp: int, fp: int, fn: int, wrong: int, height_n: int) -> dict[str, Any]:
    n_pred = tp + fp
    return {**_group(tp, fp, fn), "wrong_rectangles": wrong,
            "wrong_rate": wrong / n_pred if n_pred else 0.0, "ambiguous_regions": 3,
            "ambiguous_per_scan": 1.5, "silent_scans": 1,
            "height_sources": {"none": 0, "side": 2, "step": 1, "sku": 4},
            "height_n": height_n,
            "height_err_median_mm": 6.25 if height_n else None,
            "height_err_p95_mm": 31.5 if height_n else None}


def packed_report() -> dict[str, Any]:
    def variant(tp: int, wrong: int) -> dict[str, Any]:
        laser = _packed_group(tp, 1, 10, wrong, 3)
        return {"overall": {"development": laser, "all": _packed_group(2 * tp, 1, 20, wrong, 5)},
                "sensors": {"laser": laser, "tof": _packed_group(0, 0, 9, 0, 0)}}

    def target(name: str, variant: str, key: str, bound: float, dev: float, all_: float,
               where: str = "overall", unit: str = "") -> dict[str, Any]:
        return {"name": name, "variant": variant, "key": key, "op": "<=", "bound": bound,
                "target": f"<= {bound:g}" + (f" {unit}" if unit else ""), "unit": unit,
                "development": {"value": dev, "where": where, "pass": dev <= bound},
                "all": {"value": all_, "where": where, "pass": all_ <= bound}}

    return {
        "schema": "boxloc.bench_packed/1", "version": "0.1.0", "mode": "packed", "n": 4,
        "seed": 0, "jobs": 1, "scan_timeout_s": 120.0, "config": {"alpha": 0.01},
        "config_hash": "facade01", "held_out": {"sensor": "tof"}, "sensors": ["laser", "tof"],
        "variants": ["without_sizes", "with_sizes"], "lids": ["flat"],
        "seeds": {"n": 1, "trial_seeds": [0], "per_seed": [], "spread": {}},
        "groups": {"without_sizes": variant(1, 1), "with_sizes": variant(9, 0)},
        "targets": [target("wrong-rectangle rate without sizes, every sensor", "without_sizes",
                           "wrong_rate", 0.01, 0.5, 0.5, where="laser"),
                    target("median height error, with sizes", "with_sizes",
                           "height_err_median_mm", 10.0, 6.25, 6.25, unit="mm")],
        "timeouts": [], "errors": {"total": 0, "list": []},
        "timing": {"without_sizes": {}, "with_sizes": {}, "per_scan_ms": [900.0] * 8,
                   "run_s": 20.0},
        "memory": {}, "scenes": [{"index": i} for i in range(4)],
    }


def _bare_group(n: int, zero: int, edge: float, tests: dict[str, Any]) -> dict[str, Any]:
    return {"n_scans": n, "ok": n, "timeouts": 0, "errors": 0, "surfaces": n - zero,
            "zero_surface_scans": zero, "zero_surface_share": zero / n, "pixels": 1000 * n,
            "edge_points": int(edge * 1000 * n), "false_edge_points": 0,
            "edge_points_per_pixel": edge, "false_edge_points_per_pixel": edge / 2,
            "tests": tests, "noise_fit": {"scans": n, "rejected": 1, "rate": 1 / n},
            "time": {"median_ms": 1250.0, "max_ms": 4000.0}}


def bare_report() -> dict[str, Any]:
    laser_tests = {"NOISE_FIT": {"tested": 50, "rejected": 1, "rate": 0.02,
                                 "level_alpha_null": True},
                   "JUMP": {"tested": 30, "rejected": 30, "rate": 1.0,
                            "level_alpha_null": False, "per_sample": 0.00021},
                   "FACE_EXTENT": {"tested": 8, "rejected": 2, "rate": 0.25,
                                   "level_alpha_null": False}}
    stereo_tests = {"NOISE_FIT": {"tested": 40, "rejected": 4, "rate": 0.1,
                                  "level_alpha_null": True}}
    laser = _bare_group(50, 50, 0.0017, laser_tests)
    stereo = _bare_group(40, 38, 0.0351, stereo_tests)
    targets = [{"sensor": s, "name": "edge points per pixel", "key": "edge_points_per_pixel",
                "op": "<=", "bound": 0.02, "value": g["edge_points_per_pixel"],
                "pass": g["edge_points_per_pixel"] <= 0.02}
               for s, g in (("laser", laser), ("active-stereo", stereo))]
    return {
        "schema": "boxloc.bench_bare/1", "version": "0.1.0", "n": 50, "n_scans": 90, "seed": 0,
        "jobs": 2, "scan_timeout_s": 120.0, "alpha": 0.01, "config": {"alpha": 0.01},
        "config_hash": "b0a7d0c5", "site": {}, "sensors": ["laser", "active-stereo"],
        "kinds": ["floor", "empty"], "null_kinds": ["NOISE_FIT"],
        "groups": {"sensors": {"laser": laser, "active-stereo": stereo},
                   "all": _bare_group(90, 88, 0.0165, {})},
        "targets": targets, "timeouts": [], "errors": [], "run_s": 30.0,
        "scenes": [{"index": i} for i in range(90)],
    }


@pytest.fixture()
def packed_checkout(tmp_path: Path) -> Path:
    root = tmp_path / "repo"
    (root / "docs").mkdir(parents=True)
    (root / "docs" / "benchmarks.md").write_text(PACKED_DOC)
    return root


def test_packed_and_bare_tables_are_generated_from_their_reports(
        packed_checkout: Path, tmp_path: Path) -> None:
    root = packed_checkout
    assert _run(root, "--packed", str(_write(tmp_path / "p" / "bench_packed.json",
                                             packed_report())),
                "--date", "2026-11-25 14:00 UTC", "--commit", "abc1234") == 0
    assert _run(root, "--bare", str(_write(tmp_path / "b" / "bench_bare.json", bare_report())),
                "--date", "2026-11-25 14:10 UTC", "--commit", "def5678") == 0
    doc = (root / "docs" / "benchmarks.md").read_text()
    assert "No report yet" not in doc
    # packed: one row per variant and sensor, with the wrong-rectangle rate and its count,
    # ambiguous regions per scan, silent scans, height error and its sources
    assert ("| without sizes | laser | 2 | 1 / 1 / 10 | 0.500 | 0.091 | 0.500 (1) | 1.50 | 1 "
            "| 6.2 / 31.5 (3) | 2 / 1 / 4 / 0 |") in doc
    assert ("| with sizes | tof (held out) | 2 | 0 / 0 / 9 | – | 0.000 | – | 1.50 | 1 | – (0) "
            "|") in doc
    assert "| with sizes | **all sensors** | 2 | 18 / 1 / 20 |" in doc
    assert ("| wrong-rectangle rate without sizes, every sensor | <= 0.01 | 0.500 (laser) | "
            "miss | 0.500 (laser) | miss |") in doc
    assert "| median height error, with sizes | <= 10 mm | 6.2 mm | pass |" in doc
    assert "| with sizes | laser | 2 | 9 / 1 / 10 | 0.900 | 0.474 | 0.000 (0) |" in doc
    assert ("*2026-11-25 14:00 UTC, commit abc1234, boxloc 0.1.0, config facade01: `boxloc "
            "bench --packed --n 4 --seed 0 --seeds 1 --jobs 1 --held-out tof --scan-timeout "
            "120 --out DIR` (reconstructed); [report](results/bench_packed.json).*") in doc
    # bare: per sensor against 99 % and 2 alpha; the rates per test kind, NOISE_FIT vs alpha
    assert "| laser | 50 | 0 / 0 | 50 / 50 (1.00) | pass | 0 | 0.0017 | pass |" in doc
    assert "| 1 / 50 (0.020) | 1.25 / 4.00 |" in doc
    assert "| active-stereo | 40 | 0 / 0 | 38 / 40 (0.95) | miss | 2 | 0.0351 | miss |" in doc
    assert "<= 2 alpha = 0.02" in doc
    assert "| active-stereo | edge points per pixel | <= 0.02 | 0.0351 | miss |" in doc
    assert ("| `NOISE_FIT` * | 1 / 50 (0.020) = 2.0 alpha | 4 / 40 (0.100) = 10.0 alpha |"
            in doc)
    assert "| `JUMP` | 30 / 30 (1.000), 0.00021 per sample | – |" in doc
    assert "| `FACE_EXTENT` | 2 / 8 (0.250) | – |" in doc
    assert "commit def5678" in doc and "[report](results/bench_bare.json)" in doc
    # the committed copies lose their per-scan rows and keep their figures
    p = json.loads((root / "docs" / "results" / "bench_packed.json").read_text())
    assert "scenes" not in p and "per_scan_ms" not in p["timing"]
    assert p["groups"] == packed_report()["groups"]
    b = json.loads((root / "docs" / "results" / "bench_bare.json").read_text())
    assert "scenes" not in b and b["provenance"]["trimmed"] == ["scenes"]
    assert b["groups"] == bare_report()["groups"]
    # idempotent
    first = _snapshot(root)
    assert _run(root) == 0 and _run(root, "--check") == 0
    assert _snapshot(root) == first


def _packed_without_variants() -> dict[str, Any]:
    r = packed_report()
    del r["variants"]
    return r


@pytest.mark.parametrize("option, report, message", [
    ("--packed", matrix_report, "schema 'boxloc.bench_matrix/1', expected "
                                "'boxloc.bench_packed/1'"),
    ("--packed", _packed_without_variants, "not a bench_packed.json report: no variants"),
    ("--bare", packed_report, "schema 'boxloc.bench_packed/1', expected "
                              "'boxloc.bench_bare/1'"),
    ("--bare", lambda: {**bare_report(), "schema": "boxloc.bench_bare/2"},
     "schema 'boxloc.bench_bare/2'"),
    ("--matrix", bare_report, "schema 'boxloc.bench_bare/1', expected"),
    ("--sim", packed_report, "a boxloc.bench_packed/1 report, not a bench.json"),
])
def test_a_packed_or_bare_report_of_the_wrong_kind_is_refused(
        packed_checkout: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str,
        report: Any, message: str) -> None:
    before = _snapshot(packed_checkout)
    path = _write(tmp_path / "in" / "report.json", report())
    assert _run(packed_checkout, option, str(path)) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("bench_tables: ") and message in err, err
    assert _snapshot(packed_checkout) == before


def test_a_bare_report_missing_a_figure_is_one_line(
        packed_checkout: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A committed report that passes the schema check but lacks a table's figure: one line
    naming the region, exit 2, not a traceback."""
    rep = bare_report()
    del rep["groups"]["all"]
    _write(packed_checkout / "docs" / "results" / "bench_bare.json", rep)
    assert _run(packed_checkout) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot make bench:bare:summary" in err, err


def test_the_packed_and_bare_commands_are_rebuilt_from_the_reports() -> None:
    assert bt.reconstruct_command(bare_report(), bt.KINDS["bare"]) == (
        "python -m boxloc.evaluate.bare_bench --n 50 --seed 0 --jobs 2 --scan-timeout 120 "
        "--out DIR")
    rep = packed_report()
    rep.update(n=96, jobs=2)
    assert bt.reconstruct_command(rep, bt.KINDS["packed"]) == (
        "boxloc bench --packed --n 96 --seed 0 --seeds 1 --jobs 2 --held-out tof "
        "--scan-timeout 120 --out DIR")


# --- speed and footprint (issue 22 part 6) -----------------------------------------------------

PROFILE = ROOT / "scripts" / "profile_stages.py"

SPEED_DOC = """# boxloc

<!-- bench:speed:summary -->
<!-- /bench -->

<!-- bench:footprint:summary -->
<!-- /bench -->

<!-- bench:footprint:channels -->
<!-- /bench -->
"""


def _stage(median: float, p99: float, mx: float, share: float | None) -> dict[str, Any]:
    return {"median": median, "p99": p99, "max": mx, "share": share}


def speed_report() -> dict[str, Any]:
    """Shaped like scripts/profile_stages.py --out (two stages and the total)."""
    return {
        "schema": "boxloc.bench_speed/1", "version": "0.1.0", "suite": "matrix", "n": 32,
        "seed": 0, "size": "640x480", "scans": 32, "pixels": 307200,
        "config_hash": "feedc0de", "threads": {"numba_threads": 1}, "warmup": True,
        "stages_ms": {"edges": _stage(104.0, 248.1, 253.7, 0.198),
                      "hypotheses": _stage(280.7, 1193.9, 1271.0, 0.5338),
                      "total": _stage(525.8, 1821.6, 2085.1, None)},
        "wall_ms": {"median": 527.0, "p99": 1823.0, "max": 2086.0},
        "baseline": {"wall_ms": {"median": 250.4, "p99": 455.4, "max": 470.0}, "errors": [],
                     "ratio": {"median": 2.1, "p99": 4.0}},
        "targets": [{"name": "median time per scan", "key": "median", "bound_ms": 100.0,
                     "value_ms": 525.8, "pass": False},
                    {"name": "p99 time per scan", "key": "p99", "bound_ms": 500.0,
                     "value_ms": 1821.6, "pass": False}],
        "memory": {"process_max_rss_mb_before": 400.0, "process_max_rss_mb": 612.4,
                   "process_max_rss_mb_with_baseline": 700.0},
        "machine": {"cpu_count": 2, "load_average_1min_before": 1.62,
                    "load_average_1min_after": 2.5},
        "run_s": 18.9, "per_scan_ms": [525.8] * 32,
        "provenance": {"date": "2026-11-25 15:30 UTC", "commit": "4b381f9",
                       "commit_inferred": False, "dirty": "false",
                       "command": "python scripts/profile_stages.py --suite matrix --n 32 "
                                  "--out /tmp/s.json",
                       "command_reconstructed": False},
    }


def footprint_report() -> dict[str, Any]:
    """Shaped like `boxloc bench --section recording --out DIR`'s bench.json."""
    return {
        "version": "0.1.0", "n": 100, "seed": 0, "config": {}, "config_hash": "feedc0de",
        "threads": {"numba_threads": 1},
        "sections": {"recording": {
            "scans": 10, "mcap_fraction": 0.0449, "mcap_end_to_end_fraction": 0.229,
            "mcap_bytes_per_scan": 1005461.8, "mcap_max_scan_bytes": 1184446,
            "rerun_fraction": 0.0294, "rerun_end_to_end_fraction": 0.079,
            "mcap_kb_per_scan_by_channel": {"/scan/range": 689.4, "/boxloc/edges": 142.8,
                                            "/boxloc/result": 0.2},
            "rrd_bytes_per_scan": 1816564.9,
            "throughput": {"scans": 32, "runs": [
                {"workers": 1, "wall_s": 33.8, "scans_per_s": 0.947, "cpu_s": 20.4,
                 "core_share": 0.604, "first_scans_wall_s": 2.7},
                {"workers": 2, "wall_s": 14.7, "scans_per_s": 2.18, "cpu_s": 19.0,
                 "core_share": 0.648, "first_scans_wall_s": 2.7}],
                "speedup": 2.302, "steady_speedup": 2.507, "cpu_bound_speedup": 2.147,
                "same_log": True, "load_average_1min": 3.53, "cpu_count": 2},
            "run_workers_speedup": 2.302,
            "targets": {"mcap_fraction <= 0.05": True, "rerun_fraction <= 0.05": True,
                        "mcap_bytes_per_scan <= 1 MB": False,
                        "run --workers 2 >= 1.8x scans/s of --workers 1": True,
                        "run --workers 2 >= 1.8x, steady state": True,
                        "run --workers 2 log == --workers 1 log": True},
        }},
        "errors": {"total": 0, "list": []},
    }


@pytest.fixture()
def speed_checkout(tmp_path: Path) -> Path:
    root = tmp_path / "repo"
    (root / "docs").mkdir(parents=True)
    (root / "README.md").write_text(SPEED_DOC)
    return root


def test_speed_and_footprint_tables_come_from_their_reports(speed_checkout: Path,
                                                            tmp_path: Path) -> None:
    root = speed_checkout
    # the footprint alone: its tables, and no peak-RSS row while the speed report is absent
    assert _run(root, "--footprint", str(_write(tmp_path / "f" / "bench.json",
                                                footprint_report())),
                "--date", "2026-11-25 15:09 UTC", "--commit", "bc27de9") == 0
    doc = (root / "README.md").read_text()
    assert "peak RSS" not in doc
    assert "*No report yet. Run `nice .venv/bin/python scripts/profile_stages.py" in doc
    assert ("| MCAP log per 640×480 scan, scene suite (file / scans) | 1.01 MB (largest scan "
            "1.18 MB) | ≤ 1 MB | miss |") in doc
    assert "sensor × scene matrix" not in doc  # a report from before the matrix row
    assert "| 4.5 % (end to end 22.9 %) | ≤ 5 % | pass |" in doc
    assert "| 2.9 % (end to end 7.9 %) | ≤ 5 % | pass |" in doc
    assert "| Rerun .rrd per scan | 1.82 MB |" in doc
    assert ("| `run --workers 2` / `--workers 1`, scans/s (32 scans) | 2.30× (steady 2.51×; "
            "core shares 0.60 / 0.65) | ≥ 1.8× scans/s of --workers 1 | pass |") in doc
    assert "| `--workers 2` log = `--workers 1` log | yes | equal | pass |" in doc
    assert "on 2 cores (load average 3.5); a core share below 1" in doc
    assert ("*2026-11-25 15:09 UTC, commit bc27de9, boxloc 0.1.0, config feedc0de: `boxloc "
            "bench --section recording --n 100 --seed 0 --out DIR` (reconstructed); "
            "[report](docs/results/bench_footprint.json).*") in doc
    # by channel, largest first, with its share
    assert "| `/scan/range` | 689.4 | 82.8 % |" in doc
    assert doc.index("`/scan/range`") < doc.index("`/boxloc/edges`") < doc.index(
        "`/boxloc/result`")
    # then the speed report: its own provenance stamps the table; the footprint gains the row
    assert _run(root, "--speed", str(_write(tmp_path / "s" / "bench_speed.json",
                                            speed_report()))) == 0
    doc = (root / "README.md").read_text()
    assert ("*2026-11-25 15:30 UTC, commit 4b381f9, boxloc 0.1.0, config feedc0de: `python "
            "scripts/profile_stages.py --suite matrix --n 32 --out /tmp/s.json`; "
            "[report](docs/results/bench_speed.json).*") in doc
    assert "| edges | 104.0 | 248.1 | 253.7 | 20 % |" in doc
    assert "| hypotheses | 280.7 | 1193.9 | 1271.0 | 53 % |" in doc
    assert "| **total** | 525.8 | 1821.6 | 2085.1 |  |" in doc
    assert "| open3d baseline, same scans | 250.4 | 455.4 | 470.0 |  |" in doc
    assert "| boxloc / baseline (time) | 2.10× | 4.00× |  |  |" in doc
    assert "| target (issue 22) | ≤ 100: miss | ≤ 500: miss |  |  |" in doc
    assert "Peak RSS 612 MB" in doc and "(load average 1.6 before, 2.5 after)" in doc
    assert "| peak RSS, one process at 640x480 | 612 MB (speed run, 4b381f9) |" in doc
    # the committed speed report loses its per-scan times, keeps its figures
    s = json.loads((root / "docs" / "results" / "bench_speed.json").read_text())
    assert "per_scan_ms" not in s and s["stages_ms"] == speed_report()["stages_ms"]
    assert s["provenance"]["command_reconstructed"] is False
    f = json.loads((root / "docs" / "results" / "bench_footprint.json").read_text())
    assert f["sections"] == footprint_report()["sections"]
    # idempotent, and --check sees a stale table
    first = _snapshot(root)
    assert _run(root) == 0 and _run(root, "--check") == 0 and _snapshot(root) == first
    rep = speed_report()
    rep["stages_ms"]["total"]["median"] = 99.0
    _write(root / "docs" / "results" / "bench_speed.json", rep)
    assert _run(root, "--check") == 1 and _snapshot(root)["README.md"] == first["README.md"]
    assert _run(root) == 0 and "| **total** | 99.0 |" in (root / "README.md").read_text()


def test_a_throughput_of_several_rounds_shows_its_medians_and_range(
        speed_checkout: Path, tmp_path: Path) -> None:
    rep = footprint_report()
    tp = rep["sections"]["recording"]["throughput"]
    tp.update({"rounds": [{"runs": tp["runs"]}] * 3, "speedup": 1.704,
               "speedup_range": [1.582, 2.007], "steady_speedup": 1.86,
               "steady_speedup_range": [1.741, 2.257]})
    assert _run(speed_checkout, "--footprint", str(_write(tmp_path / "bench.json", rep))) == 0
    doc = (speed_checkout / "README.md").read_text()
    assert ("| `run --workers 2` / `--workers 1`, scans/s (32 scans) | median of 3 rounds: "
            "1.70× (1.58×–2.01×), steady 1.86× (1.74×–2.26×); core shares 0.60 / 0.65 |") in doc


def test_the_footprint_of_the_matrix_is_the_target_row_and_gives_the_channels(
        speed_checkout: Path, tmp_path: Path) -> None:
    rep = footprint_report()
    sec = rep["sections"]["recording"]
    sec["matrix"] = {"scans": 32, "seed": 0, "bytes_per_scan": 979_412.0,
                     "median_scan_bytes": 879_000, "max_scan_bytes": 1_732_000,
                     "by_sensor": {"active-stereo": 1_500_000.0, "laser": 800_000.0},
                     "kb_per_scan_by_channel": {"/scan/range": 673.3, "/boxloc/tests": 111.1}}
    sec["targets"]["matrix_bytes_per_scan <= 1 MB"] = True
    assert _run(speed_checkout, "--footprint", str(_write(tmp_path / "bench.json", rep))) == 0
    doc = (speed_checkout / "README.md").read_text()
    assert ("| MCAP log per 640×480 scan, sensor × scene matrix (32 scans, file / scans) | "
            "0.979 MB (a scan: median 0.88, largest 1.73; by sensor active-stereo 1.50, "
            "laser 0.80) | ≤ 1 MB | pass |") in doc
    assert doc.index("sensor × scene matrix") < doc.index("scene suite (file / scans)")
    assert ("The matrix: its first 32 scenes (seed 0) at 640×480, its configuration, every "
            "product recorded; the rest: the first 10 scans") in doc
    # the channels are the matrix's
    assert "| `/boxloc/tests` | 111.1 | 14.2 % |" in doc and "`/boxloc/edges`" not in doc


def test_a_dirty_tree_and_a_missing_baseline_show_in_the_speed_table(
        speed_checkout: Path, tmp_path: Path) -> None:
    rep = speed_report()
    rep["provenance"]["dirty"] = "true"
    rep["baseline"] = None
    assert _run(speed_checkout, "--speed", str(_write(tmp_path / "s.json", rep))) == 0
    doc = (speed_checkout / "README.md").read_text()
    assert "commit 4b381f9 with uncommitted changes" in doc
    assert "baseline" not in doc.split("<!-- bench:footprint")[0].split("-->", 1)[1]
    assert bt.reconstruct_command(rep, bt.KINDS["speed"]) == (
        "python scripts/profile_stages.py --suite matrix --n 32 --seed 0 --size 640x480 "
        "--no-baseline --box-range defaults --out DIR/bench_speed.json")
    assert "at 640x480, the bare defaults; one process" in doc
    # a report that ran with the site's box range says so, and its command needs no option
    rep["box_range"] = [0.15, 0.6]
    assert _run(speed_checkout, "--speed", str(_write(tmp_path / "s.json", rep))) == 0
    assert ("at 640x480, defaults with the site's box range 0.15–0.6 m (as the matrix "
            "bench); one process") in (speed_checkout / "README.md").read_text()
    assert bt.reconstruct_command(rep, bt.KINDS["speed"]).endswith(
        "--no-baseline --out DIR/bench_speed.json")
    rep["compiled_while_timed"] = 3  # a kernel compiled inside a timed scan is said
    assert _run(speed_checkout, "--speed", str(_write(tmp_path / "s.json", rep))) == 0
    assert ("0.15–0.6 m (as the matrix bench), 3 numba compilation(s) timed; one process"
            ) in (speed_checkout / "README.md").read_text()


def _no_recording() -> dict[str, Any]:
    r = footprint_report()
    r["sections"] = {"replay": {}}
    return r


@pytest.mark.parametrize("option, report, message", [
    ("--speed", matrix_report, "schema 'boxloc.bench_matrix/1', expected "
                               "'boxloc.bench_speed/1'"),
    ("--speed", lambda: {k: v for k, v in speed_report().items() if k != "stages_ms"},
     "not a bench_speed.json report: no stages_ms"),
    ("--footprint", _no_recording, "no recording section (make it with `boxloc bench "
                                   "--section recording --out DIR`)"),
    ("--footprint", speed_report, "a boxloc.bench_speed/1 report, not a bench_footprint.json"),
    ("--sim", footprint_report, "not a bench.json report: no seeds"),
])
def test_a_speed_or_footprint_report_of_the_wrong_kind_is_refused(
        speed_checkout: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str,
        report: Any, message: str) -> None:
    before = _snapshot(speed_checkout)
    assert _run(speed_checkout, option, str(_write(tmp_path / "in.json", report()))) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("bench_tables: ") and message in err, err
    assert _snapshot(speed_checkout) == before


def test_profile_stages_writes_a_report_the_tables_read(speed_checkout: Path,
                                                         tmp_path: Path) -> None:
    """The profile, on two small scans, end to end into the speed table (no figure is
    checked but its consistency: the run's times vary)."""
    out = tmp_path / "speed.json"
    p = subprocess.run([sys.executable, str(PROFILE), "--suite", "scene", "--n", "2",
                        "--size", "96x72", "--out", str(out)], capture_output=True, text=True,
                       timeout=600, cwd=ROOT)
    assert p.returncode == 0, p.stderr
    rep = json.loads(out.read_text())
    assert rep["schema"] == "boxloc.bench_speed/1" and rep["scans"] == 2
    assert rep["size"] == "96x72" and rep["pixels"] == 96 * 72
    assert rep["threads"]["numba_threads"] == 1
    assert rep["box_range"] == [0.15, 0.6]  # the simulator's boxes: the site input
    assert rep["compiled_while_timed"] == 0  # set-up's warm-up ran first
    assert list(rep["stages_ms"])[-1] == "total" and "hypotheses" in rep["stages_ms"]
    for f in rep["stages_ms"].values():
        assert f["median"] <= f["p99"] <= f["max"]
    total, base = rep["stages_ms"]["total"], rep["baseline"]
    assert base["errors"] == [] and base["ratio"]["median"] == pytest.approx(
        total["median"] / base["wall_ms"]["median"], rel=1e-2)
    assert [t["pass"] for t in rep["targets"]] == [total["median"] <= 100.0,
                                                   total["p99"] <= 500.0]
    assert len(rep["per_scan_ms"]) == 2 and rep["memory"]["process_max_rss_mb"] > 0
    assert rep["provenance"]["command"] == (
        f"python scripts/profile_stages.py --suite scene --n 2 --size 96x72 --out {out}")
    assert _run(speed_checkout, "--speed", str(out)) == 0
    doc = (speed_checkout / "README.md").read_text()
    assert "2 scans of `scene_suite(2, 0)` at 96x72" in doc and "| **total** |" in doc


def test_profile_stages_refuses_bad_options_in_one_line() -> None:
    p = subprocess.run([sys.executable, str(PROFILE), "--size", "big"], capture_output=True,
                       text=True, timeout=120, cwd=ROOT)
    assert p.returncode == 2 and p.stderr.count("\n") == 1, p.stderr
    assert "--size must be WxH or 'native', got 'big'" in p.stderr


def test_the_readme_stays_short() -> None:
    """The README is for users: long prose goes to docs/ (issue 22 part 6 keeps it at most
    15,000 bytes with the speed and footprint tables in it)."""
    readme = (ROOT / "README.md").read_bytes()
    assert len(readme) <= 15_000, len(readme)
    text = readme.decode()
    for region in ("bench:speed:summary", "bench:footprint:summary"):
        assert f"<!-- {region} -->" in text
    # the two commands of the set-up stay as they are
    assert "bash scripts/demo.sh    # installs" in text
    assert "bash scripts/test.sh    # installs, then runs ruff, mypy and pytest" in text

"""Tests of boxloc.evaluate.matrix_bench and `boxloc bench --matrix` (tiny scenes, no timings)."""

from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

import boxloc.evaluate.matrix_bench as bm
import boxloc.simulate as sim
from boxloc.cli import cli
from boxloc.config import Config
from boxloc.evaluate.baseline import surface_set_from_rects

#: The report's top-level keys: a stable structure that docs tables are generated from.
TOP_KEYS = {
    "schema", "version", "mode", "n", "seed", "jobs", "scan_timeout_s", "warmup", "threads",
    "default_configuration", "config", "config_hash", "site", "held_out", "sensors", "kinds",
    "no_box_kinds", "seeds", "groups", "targets", "timeouts", "errors", "timing", "memory",
    "scenes",
}
GROUP_KEYS = {"n_scenes", "n_scans", "tp", "fp", "fn", "n_pred", "n_exposed", "precision",
              "recall", "grasp_err_median_mm", "grasp_err_p95_mm", "errors", "timeouts",
              "time", "no_box", "false_kinds"}

#: matrix_suite indices: single (0-3), pallet (4-7) and floor (28-31) of every sensor
PICK = (0, 1, 2, 3, 4, 5, 6, 7, 28, 29, 30, 31)


def _tiny(pick: tuple[int, ...] = PICK) -> list[Any]:
    """Matrix scenes at 160 x 120 (same field of view), so a test takes seconds."""
    base = sim.matrix_suite(32, 0)
    return [dataclasses.replace(base[i], width=160, height=120,
                                f=base[i].f * 160 / base[i].width) for i in pick]


Key = tuple[str, str]


def _flawed_oracle(specs: list[Any], slow: frozenset[Key] = frozenset(),
                   die: frozenset[Key] = frozenset(), lag: frozenset[Key] = frozenset()) -> Any:
    """A localizer answering from the ground truth, with known faults.

    tof misses every face; laser misses the first exposed face of each scene; on the
    structured-light floor it reports one false surface and 100 false edge pixels; scans of
    the (sensor, kind) in ``slow`` sleep a minute, in ``die`` end their process, in ``lag``
    take half a second (so that parallel scans finish out of order).
    """
    truth = {}
    for spec in specs:
        s = sim.simulate(spec)
        truth[s.scan.seed] = (s.truth, spec)

    def localize(scan: Any, config: Any) -> Any:
        t, spec = truth[scan.seed]
        key = (spec.sensor, spec.kind)
        if key in slow:
            time.sleep(60)
        if key in die:
            os._exit(3)
        if key in lag:
            time.sleep(0.5)
        ex = np.flatnonzero(np.asarray(t.fully_exposed, bool))
        if spec.sensor == "tof":
            ex = ex[:0]
        elif spec.sensor == "laser":
            ex = ex[1:]
        c, n, x = t.centers[ex], t.normals[ex], t.x_axis[ex]
        w, length = t.width[ex], t.length[ex]
        labels = np.asarray(t.edge_labels).copy()
        if key == ("structured-light", "floor"):
            mid = np.nanmedian(scan.points.reshape(-1, 3), axis=0)
            c = np.vstack([c, mid[None]])
            n = np.vstack([n, -scan.up[None]])
            a = np.cross(scan.up, [1.0, 0.0, 0.0])
            x = np.vstack([x, (a / np.linalg.norm(a))[None]])
            w, length = np.append(w, 0.3), np.append(length, 0.4)
            labels[10:20, 10:20] = 1
        surfaces = surface_set_from_rects(c, n, x, w, length, up=scan.up)
        return SimpleNamespace(surfaces=surfaces, edges=SimpleNamespace(labels=labels),
                               timing_ms={"edges": 1.0, "total": 2.0})

    return localize


def _sum(rows: list[dict[str, Any]], key: str) -> int:
    return sum(r["match"][key] for r in rows)


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    specs = _tiny()
    out = tmp_path_factory.mktemp("matrix")
    r = bm.run_matrix_bench(specs=specs, localizer=_flawed_oracle(specs), warmup=False,
                            progress=False, out=out)
    r["_out"] = str(out)
    return r


def test_every_cell_is_reported_and_adds_up_to_the_rows(report: dict[str, Any]) -> None:
    rows = report["scenes"]
    assert [r["index"] for r in rows] == list(range(len(PICK)))  # the suite's order
    cells = report["groups"]["cells"]
    want = {f"{s}/{k}" for s in sim.SENSORS for k in ("single", "pallet", "floor")}
    assert set(cells) == want
    for key, c in cells.items():
        mine = [r for r in rows if f"{r['sensor']}/{r['kind']}" == key]
        assert c["n_scenes"] == len(mine) == 1
        for k in ("tp", "fp", "fn"):
            assert c[k] == _sum(mine, k), (key, k)
        assert c["n_exposed"] == sum(r["n_exposed"] for r in mine)
    for s, g in report["groups"]["sensors"].items():
        mine = [r for r in rows if r["sensor"] == s]
        assert (g["tp"], g["fp"], g["fn"]) == tuple(_sum(mine, k) for k in ("tp", "fp", "fn"))
        assert sum(g["false_kinds"].values()) == g["fp"]  # every false surface has a kind
    # the faults are seen where they were put
    assert cells["tof/pallet"]["tp"] == 0 and cells["tof/pallet"]["fn"] > 0
    assert cells["laser/pallet"]["fn"] == 1 and cells["laser/single"]["recall"] == 0.0
    assert cells["active-stereo/pallet"]["recall"] == 1.0
    assert cells["active-stereo/pallet"]["precision"] == 1.0
    floor = cells["structured-light/floor"]["no_box"]
    assert floor["false_surfaces"] == 1 and floor["zero_surface_share"] == 0.0
    assert floor["false_edge_points"] == 100 and floor["pixels"] == 160 * 120
    assert floor["false_edge_points_per_pixel"] == pytest.approx(100 / (160 * 120))
    assert cells["laser/floor"]["no_box"]["zero_surface_share"] == 1.0
    assert cells["laser/pallet"]["no_box"] is None
    assert report["errors"]["total"] == 0 and report["timeouts"] == []


def test_held_out_sensor_is_apart(report: dict[str, Any]) -> None:
    rows = report["scenes"]
    assert report["held_out"] == {"sensor": "tof",
                                  "cells": ["tof/single", "tof/pallet", "tof/floor"]}
    assert all(r["held_out"] == (r["sensor"] == "tof") for r in rows)
    ov = report["groups"]["overall"]
    dev = [r for r in rows if r["sensor"] != "tof"]
    assert ov["development"]["tp"] == _sum(dev, "tp")
    assert ov["development"]["fn"] == _sum(dev, "fn")
    assert ov["all"]["fn"] == _sum(rows, "fn") > ov["development"]["fn"]
    assert ov["development"]["n_scenes"] == 9 and ov["all"]["n_scenes"] == 12
    assert ov["all"]["recall"] < ov["development"]["recall"]
    pallet = report["groups"]["kinds"]["pallet"]
    assert pallet["development"]["tp"] == _sum([r for r in dev if r["kind"] == "pallet"], "tp")


def test_targets_table(report: dict[str, Any]) -> None:
    rows = {t["name"]: t for t in report["targets"]}
    assert list(rows) == [t.name for t in bm.MATRIX_TARGETS]
    ov = report["groups"]["overall"]
    rec = rows["recall overall"]
    for scope in bm.SCOPES:
        assert rec[scope]["value"] == ov[scope]["recall"]
        assert rec[scope]["pass"] == (ov[scope]["recall"] >= 0.9)
    assert rec["development"]["value"] > rec["all"]["value"]  # tof finds nothing
    # the false surface on the structured-light floor: precision 0 there, in both scopes
    prec = rows["precision in every cell"]
    assert prec["development"] == {"value": 0.0, "where": "structured-light/floor",
                                   "pass": False}
    zero = rows["no-box scans with zero surfaces, every sensor"]
    assert zero["all"]["where"] == "structured-light" and zero["all"]["pass"] is False
    edge = rows["false edge points per pixel on no-box scans, every sensor"]
    assert edge["bound"] == pytest.approx(2 * Config().alpha)
    assert edge["all"]["value"] == pytest.approx(100 / (160 * 120))
    assert edge["all"]["pass"] is True  # 0.005 <= 0.02
    grasp = rows["median grasp error"]
    assert grasp["all"]["pass"] is True and grasp["all"]["value"] < 1e-3


def test_report_on_disk_and_default_configuration(report: dict[str, Any]) -> None:
    out = Path(report["_out"])
    on_disk = json.loads((out / bm.REPORT_NAME).read_text())
    assert on_disk == {k: v for k, v in report.items() if k != "_out"}
    table = (out / bm.TABLE_NAME).read_text()
    assert "held out: the tof cells" in table and "FAIL" in table
    assert set(on_disk) == TOP_KEYS
    assert GROUP_KEYS <= set(report["groups"]["overall"]["all"])
    doc = bm.__doc__ or ""
    for key in (*TOP_KEYS, *GROUP_KEYS):  # every key is documented in the module docstring
        assert f"``{key}``" in doc, key
    assert report["schema"] == bm.SCHEMA and report["default_configuration"] is True
    lo, hi = report["site"]["min_edge"], report["site"]["max_edge"]
    assert (lo, hi) == (sim.SceneSpec().min_edge, sim.SceneSpec().max_edge)
    assert Config.from_dict(report["config"]) == Config(min_edge=lo, max_edge=hi)
    obs = report["site"]["observed"]
    assert lo <= obs["min_edge"] <= obs["max_edge"] <= hi


def test_jobs_give_the_serial_results() -> None:
    specs = _tiny()
    loc = _flawed_oracle(specs, lag=frozenset({("laser", "single"), ("tof", "pallet")}))
    kw: dict[str, Any] = {"specs": specs, "localizer": loc, "warmup": False, "progress": False}
    one = bm.run_matrix_bench(jobs=1, **kw)
    two = bm.run_matrix_bench(jobs=2, **kw)
    assert two["jobs"] == 2
    assert one["scenes"] == two["scenes"]

    def no_time(g: Any) -> Any:
        if isinstance(g, dict):
            return {k: no_time(v) for k, v in g.items() if k != "time"}
        return g

    assert no_time(one["groups"]) == no_time(two["groups"])
    assert [t for t in one["targets"] if "time" not in t["key"]] == \
        [t for t in two["targets"] if "time" not in t["key"]]


def test_draws_pool_per_scan_rows() -> None:
    specs = _tiny((0, 1))
    r = bm.run_matrix_bench(specs=specs, localizer=_flawed_oracle(specs), warmup=False,
                            progress=False, seeds=2, jobs=2)
    assert [(x["index"], x["trial_seed"]) for x in r["scenes"]] == [(0, 0), (0, 1), (1, 0),
                                                                    (1, 1)]
    assert r["seeds"]["trial_seeds"] == [0, 1]
    assert r["groups"]["cells"]["laser/single"]["n_scans"] == 2
    assert r["groups"]["cells"]["laser/single"]["n_scenes"] == 1


def test_a_slow_scan_is_stopped_and_reported() -> None:
    specs = _tiny((0, 2, 3, 28))  # laser, structured light (slow), active stereo; floor
    loc = _flawed_oracle(specs, slow=frozenset({("structured-light", "single")}),
                         die=frozenset({("laser", "floor")}))
    r = bm.run_matrix_bench(specs=specs, localizer=loc, warmup=False, progress=False,
                            scan_timeout=1.0, jobs=2)
    status = [x["status"] for x in r["scenes"]]
    assert status == ["ok", "timeout", "ok", "error"]
    (to,) = r["timeouts"]
    assert (to["scene"], to["sensor"], to["kind"], to["phase"]) == (1, "structured-light",
                                                                    "single", "localize")
    assert to["spec_text"].startswith("single:")
    slow = r["scenes"][1]
    assert slow["n_exposed"] == 1 and slow["match"]["fn"] == 1 and slow["match"]["tp"] == 0
    assert r["timing"]["per_scan_ms"][1] == 1000.0  # the limit: a lower bound
    cell = r["groups"]["cells"]["structured-light/single"]
    assert cell["timeouts"] == 1 and cell["recall"] == 0.0
    (err,) = r["errors"]["list"]
    assert err["scene"] == 3 and "died" in err["error"]
    # a dead no-box scan is not a clean one
    assert r["groups"]["cells"]["laser/floor"]["no_box"]["zero_surface_share"] == 0.0
    # the scans after the stopped one still ran
    assert r["scenes"][2]["status"] == "ok" and r["scenes"][2]["match"]["fn"] == 0


def test_the_real_localizer_through_the_matrix() -> None:
    specs = _tiny((0, 28))  # laser: a single box, the bare floor
    r = bm.run_matrix_bench(specs=specs, progress=False, warmup=False)
    assert [x["status"] for x in r["scenes"]] == ["ok", "ok"], r["errors"]
    for x in r["scenes"]:
        assert x["edges"] is not None and x["pixels"] == 160 * 120
        m = x["match"]
        assert m["n_pred"] == m["tp"] + m["fp"] and m["tp"] + m["fn"] == x["n_exposed"]
    nb = r["groups"]["cells"]["laser/floor"]["no_box"]
    assert nb["edge_points"] == r["scenes"][1]["edges"]["any"]["n_pred"]


def test_cli_matrix_refuses_settings(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    runner = CliRunner()
    for extra in (["--set", "alpha=0.05"], ["--config", str(tmp_path / "c.toml")],
                  ["--scene-set", "dropout=0"], ["--noise", "config"]):
        r = runner.invoke(cli, ["bench", "--matrix", "--n", "1", *extra])
        assert r.exit_code == 2, (extra, r.output)
        assert "default configuration only" in r.output and "Traceback" not in r.output
    r = runner.invoke(cli, ["bench", "--n", "1", "--jobs", "2"])
    assert r.exit_code == 2 and "only apply with --matrix, --packed or --bare" in r.output
    r = runner.invoke(cli, ["bench", "--matrix", "--n", "1", "--held-out", "sonar"])
    assert r.exit_code == 2 and "--held-out" in r.output
    seen: dict[str, Any] = {}

    def fake(n: int, seed: int, **kw: Any) -> dict[str, Any]:
        seen.update(n=n, seed=seed, **kw)
        return {}

    monkeypatch.setattr(bm, "run_matrix_bench", fake)
    r = runner.invoke(cli, ["bench", "--matrix"])
    assert r.exit_code == 0, r.output
    assert (seen["n"], seen["seeds"], seen["jobs"], seen["held_out"],
            seen["scan_timeout"]) == (320, 3, 1, "tof", 120.0)  # three draws of the trials
    r = runner.invoke(cli, ["bench", "--matrix", "--n", "64", "--jobs", "2", "--seeds", "2",
                            "--held-out", "laser", "--scan-timeout", "5", "--out",
                            str(tmp_path / "o")])
    assert r.exit_code == 0, r.output
    assert (seen["n"], seen["seeds"], seen["jobs"], seen["held_out"], seen["scan_timeout"],
            seen["out"]) == (64, 2, 2, "laser", 5.0, tmp_path / "o")


def test_cli_packed_runs_the_packed_bench_with_defaults_only(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from boxloc.evaluate import packed_bench as pb

    runner = CliRunner()
    for extra in (["--set", "alpha=0.05"], ["--scene-set", "dropout=0"], ["--matrix"]):
        r = runner.invoke(cli, ["bench", "--packed", "--n", "1", *extra])
        assert r.exit_code == 2, (extra, r.output)
        assert "Traceback" not in r.output
    seen: dict[str, Any] = {}

    def fake(n: int, seed: int, **kw: Any) -> dict[str, Any]:
        seen.update(n=n, seed=seed, **kw)
        return {}

    monkeypatch.setattr(pb, "run_packed_bench", fake)
    r = runner.invoke(cli, ["bench", "--packed"])
    assert r.exit_code == 0, r.output
    assert (seen["n"], seen["seeds"], seen["jobs"], seen["held_out"]) == (
        pb.DEFAULT_N, 3, 1, pb.HELD_OUT)
    r = runner.invoke(cli, ["bench", "--packed", "--n", "8", "--jobs", "2", "--out",
                            str(tmp_path / "o")])
    assert r.exit_code == 0, r.output
    assert (seen["n"], seen["jobs"], seen["out"]) == (8, 2, tmp_path / "o")


def test_cli_bare_runs_the_bare_bench_with_defaults_only(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from boxloc.evaluate import bare_bench as bb

    runner = CliRunner()
    for extra in (["--set", "alpha=0.05"], ["--packed"], ["--held-out", "laser"],
                  ["--seeds", "2"]):
        r = runner.invoke(cli, ["bench", "--bare", "--n", "1", *extra])
        assert r.exit_code == 2, (extra, r.output)
        assert "Traceback" not in r.output
    seen: dict[str, Any] = {}

    def fake(n: int, seed: int, **kw: Any) -> dict[str, Any]:
        seen.update(n=n, seed=seed, **kw)
        return {}

    monkeypatch.setattr(bb, "run_bare_bench", fake)
    r = runner.invoke(cli, ["bench", "--bare", "--seed", "3", "--jobs", "2", "--out",
                            str(tmp_path / "o")])
    assert r.exit_code == 0, r.output
    assert (seen["n"], seen["seed"], seen["jobs"], seen["out"]) == (
        bb.DEFAULT_N, 3, 2, tmp_path / "o")


def test_matrix_config_refuses_scenes_of_another_box_range() -> None:
    specs = _tiny((0,))
    cfg, site = bm.matrix_config(specs)
    assert (cfg.min_edge, cfg.max_edge) == (site["min_edge"], site["max_edge"])
    with pytest.raises(bm.InputError, match="one site input"):
        bm.matrix_config([dataclasses.replace(specs[0], min_edge=0.2)])

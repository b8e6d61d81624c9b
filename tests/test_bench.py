"""Tests of boxloc.evaluate.scene_bench and the `boxloc bench` verb (no timing assertions)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

import boxloc.evaluate.scene_bench as bench
import boxloc.simulate as sim
from boxloc.cli import cli
from boxloc.evaluate.baseline import surface_set_from_rects
from boxloc.evaluate.scene_bench import PeakRSS, evaluate_targets, run_bench
from boxloc.simulate import scene_suite

TOP_KEYS = {
    "version", "n", "seed", "seeds", "config", "config_hash", "scene_noise", "threads",
    "warmup",
    "crash_policy", "summary", "edges", "per_kind", "common_grasp", "timing", "memory",
    "targets", "sections", "errors", "scenes",
}
SUMMARY_KEYS = {
    "precision", "recall", "f1", "tp", "fp", "fn", "grasp_err_median_mm", "grasp_err_p95_mm",
    "dim_err_median_mm", "normal_err_median_deg",
}


def _tiny_specs() -> list[Any]:
    """Two small scenes (160 x 120) of different kinds, so the test stays fast."""
    base = sim.scene_suite(2, seed=7)
    return [dataclasses.replace(s, width=160, height=120, f=131.25) for s in base]


def _oracle(specs: list[Any]) -> Any:
    """A localizer that answers with the ground truth (exposed faces, exact edges)."""
    by_seed = {}
    for spec in specs:
        s = sim.simulate(spec)
        by_seed[s.scan.seed] = s.truth

    def localize(scan: Any, config: Any) -> Any:
        t = by_seed[scan.seed]
        ex = np.asarray(t.fully_exposed, bool)
        surfaces = surface_set_from_rects(t.centers[ex], t.normals[ex], t.x_axis[ex],
                                          t.width[ex], t.length[ex], up=scan.up)
        edges = SimpleNamespace(labels=np.asarray(t.edge_labels))
        return SimpleNamespace(surfaces=surfaces, edges=edges,
                               timing_ms={"edges": 1.0, "total": 2.0})

    return localize


def test_run_bench_writes_report(tmp_path: Path) -> None:
    specs = _tiny_specs()
    calls: list[Any] = []

    def section(ctx: bench.BenchContext) -> dict[str, Any]:
        calls.append(ctx)
        return {"scenes_seen": ctx.n, "ratio": float("nan"), "nested": {"a": 1}}

    def broken(ctx: bench.BenchContext) -> dict[str, Any]:
        raise RuntimeError("section exploded")

    report = run_bench(
        specs=specs, out=tmp_path, progress=False, localizer=_oracle(specs),
        sections=[("extra", section), ("broken", broken)], warmup=False,
    )
    assert set(report) == TOP_KEYS
    text = (tmp_path / "bench.json").read_text()
    on_disk = json.loads(text)  # strict JSON: NaN would not parse back as null
    assert "NaN" not in text
    assert on_disk == report
    # the oracle is perfect, the baseline ran
    s = report["summary"]
    assert set(s) == {"boxloc", "baseline"}
    assert SUMMARY_KEYS <= set(s["boxloc"]) and SUMMARY_KEYS <= set(s["baseline"])
    assert s["boxloc"]["precision"] == 1.0 and s["boxloc"]["recall"] == 1.0
    assert s["boxloc"]["fn"] == 0 and s["boxloc"]["fp"] == 0
    assert s["boxloc"]["tp"] == sum(r["n_exposed"] for r in report["scenes"])
    assert s["boxloc"]["grasp_err_median_mm"] == pytest.approx(0.0, abs=1e-6)
    assert report["edges"]["any"]["precision"] == 1.0 and report["edges"]["any"]["recall"] == 1.0
    # per kind, per scene
    kinds = {spec.kind for spec in specs}
    assert set(report["per_kind"]) == kinds
    assert len(report["scenes"]) == 2
    for row, spec in zip(report["scenes"], specs):
        assert row["kind"] == spec.kind
        assert {"boxloc", "baseline", "spec", "n_faces", "n_exposed"} <= set(row)
        assert row["spec"]["width"] == 160
        assert not _keys_ending(row, "_ms")  # durations live in "timing", not in the rows
    # timing, memory, targets
    assert report["timing"]["boxloc"]["stages_ms"]["edges"]["median"] == pytest.approx(1.0)
    assert len(report["timing"]["baseline"]["per_scene_total_ms"]) == 2
    assert report["memory"]["boxloc_peak_rss_mb"] > 0
    assert report["memory"]["process_max_rss_mb"] > 0
    names = [t["name"] for t in report["targets"]]
    assert names == [t.name for t in bench.TARGETS]
    prec = next(t for t in report["targets"] if t["key"] == "precision")
    assert prec["pass"] is True and prec["value"] == 1.0
    # sections: the good one is stored (NaN -> null), the broken one is an error
    assert report["sections"] == {"extra": {"scenes_seen": 2, "ratio": None, "nested": {"a": 1}}}
    assert calls and calls[0].report["summary"]["boxloc"]["recall"] == 1.0
    assert report["errors"]["total"] == 1
    assert report["errors"]["list"][0]["method"] == "section:broken"
    assert "section exploded" in report["errors"]["list"][0]["error"]
    assert report["config_hash"] and report["version"]


def _keys_ending(d: Any, suffix: str) -> list[str]:
    if isinstance(d, dict):
        return [k for k in d if k.endswith(suffix)] + sum(
            (_keys_ending(v, suffix) for v in d.values()), [])
    if isinstance(d, list):
        return sum((_keys_ending(v, suffix) for v in d), [])
    return []


def _scene(kind: str, seed: int) -> Any:
    return dataclasses.replace(sim.parse_spec(f"{kind}:width=160,height=120,f=131.25"),
                               seed=seed)


def test_run_bench_scores_the_real_localizer() -> None:
    """The real pipeline through the bench, on scenes small enough for a second: the single
    boxes are found, nothing is invented on the empty floor, the piles are mostly found,
    and the summary and per-kind figures are the per-scene rows added up."""
    specs = [_scene("single", 0), _scene("single", 2), _scene("mixed", 2), _scene("pallet", 1),
             _scene("empty", 0)]
    report = run_bench(specs=specs, baseline=False, progress=False, sections=[], warmup=False)
    assert report["errors"]["total"] == 0, report["errors"]["list"]
    rows = [r["boxloc"] for r in report["scenes"]]
    assert [r["kind"] for r in report["scenes"]] == [s.kind for s in specs]
    assert all(r["error"] is None for r in rows)
    for row, scene in zip(rows, report["scenes"]):
        assert row["n_pred"] == row["tp"] + row["fp"]
        assert row["tp"] + row["fn"] == row["n_exposed"] == scene["n_exposed"]
    one, other, mixed, pallet, empty = rows
    # one box on the floor, in plain view: found, and nothing else
    assert (one["tp"], one["fp"], other["tp"], other["fp"]) == (1, 0, 1, 0)
    assert empty["n_pred"] == 0 and empty["n_exposed"] == 0
    assert mixed["n_exposed"] >= 3 and pallet["n_exposed"] >= 3
    assert mixed["tp"] >= mixed["n_exposed"] // 2 and pallet["tp"] >= pallet["n_exposed"] // 2
    # the summary is the rows pooled
    s = report["summary"]["boxloc"]
    tp, fp, fn = (sum(r[k] for r in rows) for k in ("tp", "fp", "fn"))
    assert (s["tp"], s["fp"], s["fn"], s["n_pred"]) == (tp, fp, fn, tp + fp)
    assert s["precision"] == pytest.approx(tp / (tp + fp))
    assert s["recall"] == pytest.approx(tp / (tp + fn))
    assert s["precision"] >= 0.9 and s["recall"] >= 0.6
    # a found face is where the box is: millimetres at 1-2 m, not centimetres
    assert 0 < s["grasp_err_median_mm"] < 10 and s["normal_err_median_deg"] < 2
    assert sum(k["boxloc"]["tp"] for k in report["per_kind"].values()) == tp
    assert report["per_kind"]["single"]["boxloc"]["recall"] == 1.0
    assert len(report["timing"]["boxloc"]["per_scene_total_ms"]) == len(specs)


def test_run_bench_pools_draws_of_the_random_trials() -> None:
    specs = _tiny_specs()
    oracle, seen = _oracle(specs), []

    def lucky(scan: Any, config: Any) -> Any:
        # perfect on even draws, nothing on odd ones
        seen.append(config.trial_seed)
        r = oracle(scan, config)
        if config.trial_seed % 2:
            r.surfaces = surface_set_from_rects(np.zeros((0, 3)), np.zeros((0, 3)),
                                                np.zeros((0, 3)), np.zeros(0), np.zeros(0))
        return r

    report = run_bench(specs=specs, baseline=False, progress=False, localizer=lucky,
                       sections=[], warmup=False, seeds=2)
    assert seen == [0, 1, 0, 1]
    d = report["seeds"]
    assert d["n"] == 2 and d["trial_seeds"] == [0, 1]
    per = {p["trial_seed"]: p["figures"]["boxloc"] for p in d["per_seed"]}
    n_exposed = sum(r["n_exposed"] for r in report["scenes"]) // 2
    assert (per[0]["tp"], per[0]["fn"], per[0]["recall"]) == (n_exposed, 0, 1.0)
    assert (per[1]["tp"], per[1]["fn"], per[1]["recall"]) == (0, n_exposed, 0.0)
    assert d["spread"]["boxloc"]["recall"] == {"min": 0.0, "max": 1.0, "mean": 0.5}
    # everything else pools the draws: the expected figure
    assert report["summary"]["boxloc"]["recall"] == 0.5
    assert [(r["index"], r["trial_seed"]) for r in report["scenes"]] == [(0, 0), (0, 1),
                                                                         (1, 0), (1, 1)]
    assert len(report["timing"]["boxloc"]["per_scene_total_ms"]) == 4
    with pytest.raises(bench.InputError, match="seeds"):
        run_bench(specs=specs, progress=False, seeds=0)


def test_run_bench_counts_crashes(tmp_path: Path) -> None:
    specs = _tiny_specs()[:1]

    def crash(scan: Any, config: Any) -> Any:
        raise ValueError("localizer exploded")

    report = run_bench(specs=specs, out=None, baseline=False, progress=False,
                       localizer=crash, sections=[], warmup=True)
    assert set(report["summary"]) == {"boxloc"}
    assert report["errors"]["count"]["boxloc"] == 1
    assert "localizer exploded" in report["errors"]["list"][0]["error"]
    row = report["scenes"][0]
    assert row["boxloc"]["error"].startswith("ValueError")
    # a crash scores as "found nothing"
    assert row["boxloc"]["n_pred"] == 0
    assert row["boxloc"]["fn"] == row["n_exposed"]
    beats = [t for t in report["targets"] if t["target"].endswith("baseline")]
    assert beats and all(t["pass"] is None for t in beats)
    assert not (tmp_path / "bench.json").exists()


def test_discovered_sections_run(monkeypatch: pytest.MonkeyPatch) -> None:
    class EP:
        def __init__(self, name: str, fn: Any = None) -> None:
            self.name, self.value, self._fn = name, f"fake:{name}", fn

        def load(self) -> Any:
            if self._fn is None:
                raise ImportError("no such module")
            return self._fn

    eps = [EP("zeta", lambda ctx: {"ok": True}), EP("alpha")]
    monkeypatch.setattr(bench, "entry_points", lambda group: eps if group == "boxloc.bench"
                        else [])
    found = bench.discover_sections()
    assert [n for n, _ in found] == ["alpha", "zeta"]
    assert found[1][1](None) == {"ok": True}
    with pytest.raises(ImportError, match="cannot load fake:alpha"):
        found[0][1](None)


def _report(boxloc: dict[str, Any], baseline: dict[str, Any] | None) -> dict[str, Any]:
    summary = {"boxloc": boxloc} | ({"baseline": baseline} if baseline is not None else {})
    timing = {m: {"total_ms": {"median": 100.0}} for m in summary}
    memory = {f"{m}_peak_rss_mb": 300.0 for m in summary}
    return {"summary": summary, "timing": timing, "memory": memory}


def test_evaluate_targets() -> None:
    good = {"precision": 0.995, "recall": 0.97, "f1": 0.98, "grasp_err_median_mm": 3.0,
            "grasp_err_p95_mm": 9.0, "dim_err_median_mm": 4.0}
    worse = {"precision": 0.8, "recall": 0.5, "f1": 0.6, "grasp_err_median_mm": 6.0,
             "grasp_err_p95_mm": 20.0, "dim_err_median_mm": 7.0}
    rows = {r["name"]: r for r in evaluate_targets(_report(good, worse))}
    assert all(r["pass"] is True for r in rows.values())
    rows = {r["name"]: r for r in evaluate_targets(_report(worse, good))}
    assert rows["median time per scan"]["pass"] is True
    assert rows["peak RSS"]["pass"] is True
    others = [r for n, r in rows.items() if n not in ("median time per scan", "peak RSS")]
    assert all(r["pass"] is False for r in others)
    assert rows["F1 better than baseline"]["baseline"] == 0.98
    # no true positive: the error figures are n/a, and losing to a baseline that has one
    none = dict(good, grasp_err_median_mm=None, grasp_err_p95_mm=None, dim_err_median_mm=None)
    rows = {r["name"]: r for r in evaluate_targets(_report(none, good))}
    assert rows["median grasp error"]["pass"] is None
    assert rows["grasp error better than baseline"]["pass"] is False
    rows = {r["name"]: r for r in evaluate_targets(_report(good, None))}
    assert rows["F1 better than baseline"]["pass"] is None


def test_peak_rss_sees_an_allocation() -> None:
    with PeakRSS() as before:
        pass
    with PeakRSS() as pk:
        a = np.ones(64 * 2**20 // 8)  # 64 MiB, touched
    assert a.sum() > 0  # still alive when the exit sample is taken
    assert pk.peak_mb >= before.peak_mb + 48


def test_jsonable() -> None:
    out = bench._jsonable({"a": np.float32(1.5), "b": [np.nan, np.inf, 2], "c": (np.int64(3),),
                           "d": np.arange(2), "e": Path("/x"), "f": None, "g": True})
    assert out == {"a": 1.5, "b": [None, None, 2], "c": [3], "d": [0, 1], "e": "PosixPath('/x')",
                   "f": None, "g": True}
    json.dumps(out, allow_nan=False)


def test_cli_bench_help_and_bad_n() -> None:
    runner = CliRunner()
    r = runner.invoke(cli, ["bench", "--help"])
    assert r.exit_code == 0
    for opt in ("--n", "--seed", "--out", "--no-baseline", "--config", "--set"):
        assert opt in r.output
    r = runner.invoke(cli, ["bench", "--n", "0"])
    assert r.exit_code == 2
    r = runner.invoke(cli, ["bench", "--n", "1", "--set", "nonsense=1"])
    assert r.exit_code == 2
    assert "unknown config key" in r.output
    assert "--scene-set" in runner.invoke(cli, ["bench", "--help"]).output
    r = runner.invoke(cli, ["bench", "--n", "1", "--scene-set", "noise.bogus=1"])
    assert r.exit_code == 2 and "bogus" in r.output and "Traceback" not in r.output


def test_cli_bench_scene_set_changes_every_scene(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: dict[str, object] = {}

    def fake_run_bench(n: int, seed: int, **kw: object) -> dict:
        seen.update(n=n, seed=seed, **kw)
        return {}

    monkeypatch.setattr(bench, "run_bench", fake_run_bench)
    r = CliRunner().invoke(cli, ["bench", "--n", "3", "--no-baseline", "--scene-set",
                                 "noise.row_corr=0.3", "--scene-set", "dropout=0"])
    assert r.exit_code == 0, r.output
    specs = seen["specs"]
    assert [s.seed for s in specs] == [s.seed for s in scene_suite(3, 0)]
    assert all(s.noise.row_corr == 0.3 and s.dropout == 0 for s in specs)
    assert seen["seeds"] == 3  # the default pools three draws of the random trials
    # without it the suite is the default one (run_bench builds it)
    CliRunner().invoke(cli, ["bench", "--n", "3", "--no-baseline", "--seeds", "4"])
    assert seen["specs"] is None and seen["seeds"] == 4
    r = CliRunner().invoke(cli, ["bench", "--n", "3", "--seeds", "0"])
    assert r.exit_code == 2 and "Traceback" not in r.output


def test_common_grasp_compares_on_the_faces_both_found() -> None:
    from boxloc.evaluate.metrics import match_surfaces
    from boxloc.simulate import simulate

    T = simulate("touching", seed=3).truth

    def found(faces, shift=0.0):
        f = np.asarray(faces)
        return surface_set_from_rects(T.centers[f], T.normals[f], T.x_axis[f], T.width[f],
                                      T.length[f], grasp_points=T.centers[f] + shift * T.x_axis[f])

    every = np.flatnonzero(T.fully_exposed)
    assert len(every) >= 2
    exact = match_surfaces(found(every), T)
    # the other method found only the first face, its grasp point 1 cm off
    other = match_surfaces(found(every[:1], 0.01), T)
    assert (exact.tp, other.tp) == (len(every), 1)
    cg = bench.common_grasp([(exact, other), (exact, None)])
    assert cg["n"] == 1
    assert cg["a_median_mm"] == pytest.approx(0.0, abs=1e-6)
    assert cg["b_median_mm"] == pytest.approx(10.0, abs=1e-3)


def test_the_thread_report_starts_no_numba_pool_so_a_later_compile_still_works(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The benches report the pools in force (_limit_threads), and the stream and replay
    pools set NUMBA_NUM_THREADS for their workers in this process's environment. A kernel
    compiled afterwards here must still compile: numba refuses a changed NUMBA_NUM_THREADS
    once its threading layer has started, which _limit_threads once did (it set numba to
    one thread), and a test's kernel then failed depending on the tests' order."""
    import os

    import numba
    from numba.core import config as numba_config

    info = bench._limit_threads()
    assert info["numba_threads"] == numba_config.NUMBA_NUM_THREADS
    other = "2" if int(numba_config.NUMBA_NUM_THREADS) == 1 else "1"
    monkeypatch.setenv("NUMBA_NUM_THREADS", other)  # as recorder.stream._pin_threads may
    add = numba.njit(lambda x, y: x + y)  # new to this process: compiled here
    assert add(2, 3) == 5
    assert os.environ["NUMBA_NUM_THREADS"] == other

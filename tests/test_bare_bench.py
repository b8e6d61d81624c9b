"""Tests of boxloc.evaluate.bare_bench (tiny scenes, no timings)."""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

import boxloc.evaluate.bare_bench as bb
import boxloc.simulate as sim
from boxloc.errors import InputError
from boxloc.evaluate.baseline import surface_set_from_rects
from boxloc.stats import TestKind, TestTable


def _tiny(n: int = 1, seed: int = 3) -> list[Any]:
    """Bare scenes at 160 x 120 (same field of view), so a test takes seconds."""
    return [dataclasses.replace(s, width=160, height=120, f=s.f * 160 / s.width)
            for s in bb.bare_suite(n, seed)]


def _table(n: int, rejected: int, kind: TestKind) -> TestTable:
    acc = np.ones(n, bool)
    acc[:rejected] = False
    return TestTable(kind=np.full(n, int(kind), np.uint8), a=np.full(n, -1, np.int32),
                     b=np.full(n, -1, np.int32), statistic=np.where(acc, 0.0, 2.0),
                     dof=np.ones(n, np.float32), critical=np.ones(n), p_value=np.full(n, 0.5),
                     accepted=acc, alpha=0.01)


def _fake(n_false: int = 1, edge_px: int = 7) -> Any:
    """A localizer that reports ``n_false`` surfaces, ``edge_px`` edge pixels in the image's
    top-left corner, 10 JUMP rows of which 3 rejected and a NOISE_FIT row that rejects."""

    def localize(scan: Any, config: Any) -> Any:
        h, w = scan.range.shape[:2]
        labels = np.zeros((h, w), np.uint8)
        labels.flat[:edge_px] = 1
        up = np.asarray(scan.up, float)
        a = np.cross(up, [1.0, 0.0, 0.0])
        c = np.tile([0.0, 0.0, 2.0], (n_false, 1))
        surfaces = surface_set_from_rects(
            c, np.tile(-up, (n_false, 1)), np.tile(a / np.linalg.norm(a), (n_false, 1)),
            np.full(n_false, 0.3), np.full(n_false, 0.4), up=up)
        return SimpleNamespace(
            surfaces=surfaces,
            edges=SimpleNamespace(labels=labels, tests=_table(10, 3, TestKind.JUMP)),
            noise=SimpleNamespace(tests=_table(1, 1, TestKind.NOISE_FIT), source=1))

    return localize


def test_bare_suite_draws_only_bare_scenes_of_every_sensor() -> None:
    specs = bb.bare_suite(3, 5)
    assert len(specs) == 3 * len(sim.SENSORS)
    assert [s.sensor for s in specs[:4]] == list(sim.SENSORS)
    assert {s.kind for s in specs} == set(bb.BARE_KINDS)
    assert [s.kind for s in specs[::4]] == ["floor", "empty", "floor"]
    assert bb.bare_suite(3, 5) == specs  # deterministic
    assert bb.bare_suite(3, 6) != specs
    for s in specs:
        assert 1.0 <= s.distance <= 3.5 and 0.0 <= s.tilt <= np.radians(30.0)
    with pytest.raises(InputError):
        bb.bare_suite(0)
    with pytest.raises(InputError):
        bb.bare_suite(2, sensors=["sonar"])


def test_figures_come_from_the_products(tmp_path: Path) -> None:
    specs = _tiny()
    r = bb.run_bare_bench(specs=specs, localizer=_fake(1, 7), jobs=2, out=tmp_path)
    assert r["schema"] == "boxloc.bench_bare/1"
    assert json.loads((tmp_path / bb.REPORT_NAME).read_text()) == r
    assert "edge/px" in (tmp_path / bb.TABLE_NAME).read_text()
    assert [row["index"] for row in r["scenes"]] == list(range(len(specs)))
    a = r["groups"]["all"]
    n = len(specs)
    # one fake surface per scan: no scan is clean, and every target on them fails
    assert a["zero_surface_scans"] == 0 and a["surfaces"] == n
    assert a["edge_points"] == 7 * n and a["pixels"] == 160 * 120 * n
    assert a["edge_points_per_pixel"] == pytest.approx(7 / (160 * 120))
    samples = sum(row["samples"] for row in r["scenes"])
    assert 0 < samples <= 2 * a["pixels"]
    assert a["tests"]["JUMP"] == {"tested": 10 * n, "rejected": 3 * n, "rate": 0.3,
                                  "level_alpha_null": False,
                                  "per_sample": pytest.approx(3 * n / samples)}
    assert a["noise_fit"] == {"scans": n, "rejected": n, "rate": 1.0}
    zs = [t for t in r["targets"] if t["key"] == "zero_surface_share"]
    assert len(zs) == len(sim.SENSORS) and not any(t["pass"] for t in zs)
    for s in sim.SENSORS:
        assert r["groups"]["sensors"][s]["n_scans"] == 1


def test_clean_localizer_passes_zero_surfaces() -> None:
    r = bb.run_bare_bench(specs=_tiny(), localizer=_fake(0, 0), jobs=1)
    a = r["groups"]["all"]
    assert a["zero_surface_scans"] == a["n_scans"] == len(sim.SENSORS)
    assert a["edge_points_per_pixel"] == 0.0
    assert all(t["pass"] for t in r["targets"])


def test_timeout_and_crash_are_not_clean() -> None:
    specs = _tiny()[:2]
    slow = _seed(specs[0])

    def loc(scan: Any, config: Any) -> Any:
        if scan.seed == slow:
            time.sleep(60)
        raise RuntimeError("boom")

    r = bb.run_bare_bench(specs=specs, localizer=loc, jobs=2, scan_timeout=3.0)
    st = [row["status"] for row in r["scenes"]]
    assert st == ["timeout", "error"]
    assert r["groups"]["all"]["zero_surface_scans"] == 0
    assert len(r["timeouts"]) == 1 and "boom" in r["errors"][0]["error"]


def _seed(spec: Any) -> int:
    return int(sim.simulate(spec).scan.seed)


def test_real_pipeline_products() -> None:
    """The real localizer on one tiny bare scan per sensor: the figures add up."""
    r = bb.run_bare_bench(specs=_tiny(), jobs=2)
    assert r["errors"] == [] and r["timeouts"] == []
    rows = r["scenes"]
    a = r["groups"]["all"]
    assert a["edge_points"] == sum(row["edge_points"] for row in rows)
    assert a["surfaces"] == sum(row["surfaces"] for row in rows)
    assert "NOISE_FIT" in {k for row in rows for k in row["tests"]} or all(
        row["noise_fit"] is None for row in rows)
    for row in rows:
        assert 0 <= row["false_edge_points"] <= row["edge_points"] <= row["pixels"]
        for t, rej in row["tests"].values():
            assert 0 <= rej <= t


def test_bad_input() -> None:
    with pytest.raises(InputError):
        bb.run_bare_bench(specs=_tiny(), jobs=0)
    with pytest.raises(InputError):
        bb.run_bare_bench(specs=_tiny(), scan_timeout=0)
    assert bb.main(["--n", "0"]) == 2

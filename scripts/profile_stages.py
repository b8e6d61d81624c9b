"""Per-stage time of the pipeline over simulated scenes, as a markdown table.

Each scene of the suite is simulated (not timed), rescaled to one resolution (the focal
length follows, so the field of view stays the sensor's), and localized once after a
warm-up scan; the table gives each stage's median, p99 and maximum of
``Result.timing_ms`` over the scenes, and its share of the median total. ``--cprofile K``
adds the K functions with the most own time under cProfile (a second pass, since the
profiler slows Python code several-fold: its times are for ranking, not for the table).

The open3d baseline (:func:`boxloc.evaluate.baseline.baseline_surfaces`, as ``boxloc bench``
runs it) is timed on the same scans after the pipeline, unless ``--no-baseline``; the
report gives the pipeline's median and p99 over the baseline's. The thread pools are pinned
to one thread as ``boxloc bench`` pins them (the targets of issue 22 are per core).

``--out FILE`` writes the figures as JSON (schema :data:`SCHEMA`), for
``scripts/bench_tables.py --speed FILE``:

- ``schema``, ``version``, ``suite``, ``n``, ``seed``, ``size`` (``"WxH"`` or ``"native"``),
  ``scans``, ``pixels`` (median per scan), ``config_hash``, ``box_range`` (``[min_edge,
  max_edge]``, m), ``threads``, ``warmup``, ``compiled_while_timed`` (numba compilations
  inside the timed scans: 0 after the warm-up, which runs set-up's ``scripts/warm_up.py``
  and one scan of the suite)
- ``stages_ms``: per stage in pipeline order, then ``total`` (``Result.timing_ms``):
  ``median``, ``p99``, ``max`` (ms) and ``share`` (of the median total)
- ``wall_ms``: ``median``, ``p99``, ``max`` of the whole call (ms, ``perf_counter``)
- ``baseline``: null with ``--no-baseline``, else ``wall_ms`` (the same figures for
  ``baseline_surfaces``), ``errors`` and ``ratio`` (boxloc's ``total`` over the baseline's
  wall time: ``median``, ``p99``)
- ``targets``: ``name``, ``key``, ``bound_ms``, ``value_ms``, ``pass``
- ``memory``: the process's peak resident set (``ru_maxrss``, MB) after simulating and the
  warm-up scan (``process_max_rss_mb_before``), after the timed pipeline runs
  (``process_max_rss_mb``: the pipeline's peak, simulation included) and, with the
  baseline, after it (``process_max_rss_mb_with_baseline``)
- ``machine``: ``cpu_count``, ``load_average_1min`` before and after the timed runs (the
  machine is shared: a load above its one busy core means other work competed)
- ``run_s``: the timed pipeline runs, seconds; ``per_scan_ms``: each scan's total
- ``provenance``: ``date`` (UTC, end of the run), ``commit`` and ``dirty`` of the boxloc
  source tree that ran (:func:`recorder.mcap.sink.git_info`), ``command``

Run it on one core, with nothing else busy, e.g.::

    nice .venv/bin/python scripts/profile_stages.py --suite matrix --n 32 --out speed.json
    nice .venv/bin/python scripts/profile_stages.py --suite scene --n 12 --cprofile 25

Usage: python scripts/profile_stages.py [--suite scene|matrix] [--n N] [--seed S]
[--size WxH|native] [--cprofile K] [--scans-cache DIR] [--no-baseline] [--out FILE]
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import dataclasses
import datetime as dt
import hashlib
import io
import json
import math
import os
import pickle
import pstats
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

# numpy is imported in the functions: the thread pools are pinned before it loads (main)

#: The stages in pipeline order (``boxloc.pipeline``), then the total.
STAGES = ("noise", "edges", "lines", "up", "vertices", "hypotheses", "select", "surfaces",
          "total")
#: The report's ``schema`` (``scripts/bench_tables.py --speed`` checks it).
SCHEMA = "boxloc.bench_speed/1"
#: Issue 22's targets for one 640x480 scan on one core: (name, key of ``stages_ms.total``,
#: bound in ms).
TARGETS = (("median time per scan", "median", 100.0), ("p99 time per scan", "p99", 500.0))


def _specs(suite: str, n: int, seed: int, size: tuple[int, int] | None) -> list[Any]:
    """The suite's scene specs, rescaled to ``size`` (W, H) unless None."""
    from boxloc.simulate import matrix_suite, scene_suite

    specs = (matrix_suite if suite == "matrix" else scene_suite)(n, seed)
    if size is None:
        return specs
    w, h = size
    # the same field of view at the new width: f scales with it
    return [dataclasses.replace(s, width=w, height=h, f=float(s.f) * w / s.width)
            for s in specs]


def site_config(box_range: str) -> Any:
    """The configuration a profile runs with: ``Config()`` with the smallest and largest box
    of the simulated scenes (``box_range="site"``: the one site input a user gives, as the
    matrix benchmark runs), or ``Config()`` alone (``"defaults"``: ``min_edge`` 0.1 m,
    ``max_edge`` 1 m, wider than the scenes' boxes: more search per vertex and region)."""
    from boxloc.config import Config
    from boxloc.evaluate.matrix_bench import matrix_config

    return Config() if box_range == "defaults" else matrix_config([])[0]


def _warm_up_module() -> Any:
    """scripts/warm_up.py, the set-up's kernel warm-up, as a module."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("boxloc_warm_up",
                                                  Path(__file__).with_name("warm_up.py"))
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _scans(specs: list[Any], cache: Path | None) -> list[Any]:
    """Simulated scans of the specs (read from / written to ``cache`` when given)."""
    from boxloc.simulate import simulate

    out = []
    for spec in specs:
        path = None
        if cache is not None:
            key = hashlib.sha1(repr(spec).encode()).hexdigest()[:16]
            path = cache / f"{key}.pkl"
            if path.exists():
                out.append(pickle.loads(path.read_bytes()))
                continue
        scan = simulate(spec).scan
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(pickle.dumps(scan))
        out.append(scan)
    return out


def figures(values: Sequence[float]) -> dict[str, float | None]:
    """Median, p99 and maximum of durations (ms); None each when there are none.

    The 99th percentile is numpy's linear interpolation: with fewer than 100 scans it lies
    between the two largest.
    """
    import numpy as np

    x = np.asarray([v for v in values if math.isfinite(v)], dtype=np.float64)
    if not x.size:
        return {"median": None, "p99": None, "max": None}
    return {"median": round(float(np.median(x)), 3),
            "p99": round(float(np.percentile(x, 99)), 3), "max": round(float(x.max()), 3)}


def stage_figures(times: dict[str, list[float]]) -> dict[str, dict[str, float | None]]:
    """:func:`figures` per stage in pipeline order (stages the runs did not time last),
    each with ``share``: its median over the median total."""
    names = [k for k in STAGES if k in times] + [k for k in times if k not in STAGES]
    out = {k: figures(times[k]) for k in names}
    total = out.get("total", {}).get("median")
    for k, f in out.items():
        med = f["median"]
        f["share"] = (round(med / total, 4) if k != "total" and total and med is not None
                      else None)
    return out


def stage_table(times: dict[str, list[float]]) -> str:
    """The markdown table of per-stage times (ms): median, p99, max, share of the total."""
    lines = ["| stage | median ms | p99 ms | max ms | share of median total |",
             "|---|---:|---:|---:|---:|"]
    for name, f in stage_figures(times).items():
        share = "" if f["share"] is None else f"{100 * f['share']:.0f} %"
        lines.append(f"| {name} | {f['median']:.1f} | {f['p99']:.1f} | {f['max']:.1f} | "
                     f"{share} |")
    return "\n".join(lines)


def _ratio(a: float | None, b: float | None) -> float | None:
    return round(a / b, 3) if a is not None and b else None


def _target(name: str, key: str, bound: float, value: float | None) -> dict[str, Any]:
    return {"name": name, "key": key, "bound_ms": bound, "value_ms": value,
            "pass": None if value is None else bool(value <= bound)}


def _load() -> float | None:
    return round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None


def time_baseline(scans: list[Any], config: Any) -> tuple[list[float], list[str]]:
    """Wall time (ms) of the open3d baseline on each scan, after one untimed warm-up call,
    and its errors (one line each: a crash is reported, not timed)."""
    from boxloc.evaluate.baseline import baseline_surfaces

    baseline_surfaces(scans[0], config=config)  # open3d's first call sets up its pools
    walls, errors = [], []
    for scan in scans:
        t0 = time.perf_counter()
        try:
            baseline_surfaces(scan, config=config)
        except Exception as e:  # noqa: BLE001 - a crash on one scan is a result
            errors.append(f"scan {scan.index}: {type(e).__name__}: {e}".splitlines()[0])
            continue
        walls.append((time.perf_counter() - t0) * 1e3)
    return walls, errors


def speed_report(times: dict[str, list[float]], walls: list[float],
                 baseline: tuple[list[float], list[str]] | None, *, suite: str, n: int,
                 seed: int, size: tuple[int, int] | None, pixels: list[int], config: Any,
                 threads: dict[str, Any], run_s: float, rss_mb: tuple[float, float],
                 load: tuple[float | None, float | None], argv: Sequence[str],
                 compiled: int = 0) -> dict[str, Any]:
    """The JSON report of a profile run (layout in the module's docstring).

    Parameters
    ----------
    times : dict of str to list of float
        ``Result.timing_ms`` per stage, one value per scan, ms.
    walls : list of float
        The whole ``find_graspable_surfaces`` call per scan, ms.
    baseline : (list of float, list of str) or None
        :func:`time_baseline`'s walls (ms) and errors; None when not run.
    rss_mb : (float, float)
        The process's peak RSS (MB) before and after the timed pipeline runs.
    """
    import boxloc
    from boxloc.evaluate.scene_bench import process_max_rss_mb
    from recorder.mcap.sink import git_info

    stages = stage_figures(times)
    total = stages.get("total", figures([]))
    base = None
    if baseline is not None:
        bw = figures(baseline[0])
        base = {"wall_ms": bw, "errors": baseline[1],
                "ratio": {q: _ratio(total[q], bw[q]) for q in ("median", "p99")}}
    commit, dirty = git_info()
    return {
        "schema": SCHEMA, "version": boxloc.__version__, "suite": suite, "n": n, "seed": seed,
        "size": "native" if size is None else f"{size[0]}x{size[1]}", "scans": len(walls),
        "pixels": int(sorted(pixels)[len(pixels) // 2]) if pixels else 0,
        "config_hash": config.hash, "box_range": [config.min_edge, config.max_edge],
        "threads": threads, "compiled_while_timed": compiled, "warmup": True,
        "stages_ms": stages, "wall_ms": figures(walls), "baseline": base,
        "targets": [_target(name, key, bound, total[key]) for name, key, bound in TARGETS],
        "memory": {"process_max_rss_mb_before": round(rss_mb[0], 1),
                   "process_max_rss_mb": round(rss_mb[1], 1),
                   "process_max_rss_mb_with_baseline": None if baseline is None else
                   round(process_max_rss_mb(), 1)},
        "machine": {"cpu_count": os.cpu_count(), "load_average_1min_before": load[0],
                    "load_average_1min_after": load[1]},
        "run_s": round(run_s, 3),
        "per_scan_ms": [round(v, 3) for v in times.get("total", [])],
        "provenance": {
            "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
            "commit": commit[:7] if commit != "unknown" else commit,
            "commit_inferred": False, "dirty": dirty,
            "command": " ".join(["python scripts/profile_stages.py",
                                 *map(shlex.quote, argv)]),
            "command_reconstructed": False,
        },
    }


def profile_table(stats: pstats.Stats, k: int) -> str:
    """The K functions with the most own time, as a markdown table."""
    rows = sorted(stats.stats.items(), key=lambda kv: -kv[1][2])[:k]  # type: ignore[attr-defined]
    total = sum(v[2] for v in stats.stats.values()) or 1.0  # type: ignore[attr-defined]
    lines = ["| function | calls | own s | share | cumulative s |", "|---|---:|---:|---:|---:|"]
    for (file, line, func), (_cc, nc, tt, ct, _callers) in rows:
        where = f"{Path(file).parent.name}/{Path(file).name}:{line}" if line else file
        lines.append(f"| `{func}` {where} | {nc} | {tt:.3f} | {100 * tt / total:.1f} % | "
                     f"{ct:.3f} |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--suite", choices=("scene", "matrix"), default="matrix")
    ap.add_argument("--n", type=int, default=32, help="scenes (default 32: each matrix cell once)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", default="640x480",
                    help="WxH every scene is rescaled to, or 'native' (default 640x480)")
    ap.add_argument("--cprofile", type=int, default=0, metavar="K",
                    help="also list the K functions with the most own time")
    ap.add_argument("--scans-cache", type=Path, default=None, metavar="DIR",
                    help="keep the simulated scans here (pickles) for repeated runs")
    ap.add_argument("--no-baseline", action="store_true",
                    help="do not time the open3d baseline on the same scans")
    ap.add_argument("--box-range", choices=("site", "defaults"), default="site",
                    help="site (default): Config() with the suite's box range, the one site "
                         "input, as its accuracy bench runs it; defaults: Config() alone")
    ap.add_argument("--out", type=Path, default=None, metavar="FILE",
                    help="write the figures as JSON (for scripts/bench_tables.py --speed)")
    a = ap.parse_args(argv)
    if a.n < 1:
        print(f"profile_stages: --n must be >= 1, got {a.n}", file=sys.stderr)
        return 2
    size = None
    if a.size != "native":
        try:
            w, h = (int(v) for v in a.size.lower().split("x"))
        except ValueError:
            print(f"profile_stages: --size must be WxH or 'native', got {a.size!r}",
                  file=sys.stderr)
            return 2
        size = (w, h)

    # one core, as `boxloc bench` measures: pin the pools before numpy and numba load
    for var in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    from boxloc.evaluate.scene_bench import _limit_threads, process_max_rss_mb
    from boxloc.pipeline import find_graspable_surfaces

    threads = _limit_threads()
    config = site_config(a.box_range)
    scans = _scans(_specs(a.suite, a.n, a.seed, size), a.scans_cache)
    # not timed: every numba kernel compiled or loaded (set-up's warm-up reaches them all; a
    # scan alone need not, and a kernel compiled inside a timed scan adds seconds to it),
    # then the lazy tables of a scan of the suite
    warm = _warm_up_module()
    with contextlib.redirect_stderr(io.StringIO()) as said:
        missed = warm.warm_up() != 0
    if missed:  # a kernel the warm-up does not reach may compile inside a timed scan
        print(said.getvalue().strip().splitlines()[-1], file=sys.stderr)
    find_graspable_surfaces(scans[0], config)
    compiled_before = warm.compilations()
    rss_before = process_max_rss_mb()
    load_before = _load()
    times: dict[str, list[float]] = {}
    walls: list[float] = []
    t0 = time.perf_counter()
    for scan in scans:
        t1 = time.perf_counter()
        res = find_graspable_surfaces(scan, config)
        walls.append((time.perf_counter() - t1) * 1e3)
        for k, v in res.timing_ms.items():
            times.setdefault(k, []).append(float(v))
    wall = time.perf_counter() - t0
    compiled = warm.compilations() - compiled_before
    if compiled:
        print(f"profile_stages: {compiled} numba compilation(s) inside the timed scans: "
              "their times include it", file=sys.stderr)
    load_after = _load()
    rss_after = process_max_rss_mb()
    baseline = None if a.no_baseline else time_baseline(scans, config)
    shape = "native sizes" if size is None else f"{size[0]}x{size[1]}"
    print(f"Per-stage time over {a.n} scenes of `{a.suite}_suite({a.n}, {a.seed})` at {shape} "
          f"(ms, `Result.timing_ms`; {wall:.1f} s in all):\n")
    print(stage_table(times))
    if a.out is not None:
        report = speed_report(times, walls, baseline, suite=a.suite, n=a.n, seed=a.seed,
                              size=size, pixels=[s.range.size for s in scans], config=config,
                              threads=threads, run_s=wall, rss_mb=(rss_before, rss_after),
                              load=(load_before, load_after), argv=argv, compiled=compiled)
        if report["baseline"] is not None:
            r = report["baseline"]["ratio"]
            print(f"\nboxloc's total over the open3d baseline's time on the same scans: "
                  f"median {r['median']}x, p99 {r['p99']}x")
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(report, indent=1) + "\n")
        print(f"\nwrote {a.out}")
    if a.cprofile > 0:
        prof = cProfile.Profile()
        prof.enable()
        for scan in scans:
            find_graspable_surfaces(scan, config)
        prof.disable()
        stats = pstats.Stats(prof, stream=io.StringIO())
        print(f"\nThe {a.cprofile} functions with the most own time (cProfile):\n")
        print(profile_table(stats, a.cprofile))
    return 0


if __name__ == "__main__":
    sys.exit(main())

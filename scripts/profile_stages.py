"""Per-stage time of the pipeline over simulated scenes, as a markdown table.

Each scene of the suite is simulated (not timed), rescaled to one resolution (the focal
length follows, so the field of view stays the sensor's), and localized once after a
warm-up scan; the table gives each stage's median, p99 and maximum of
``Result.timing_ms`` over the scenes, and its share of the median total. ``--cprofile K``
adds the K functions with the most own time under cProfile (a second pass, since the
profiler slows Python code several-fold: its times are for ranking, not for the table).

Run it on one core, with nothing else busy, e.g.::

    nice .venv/bin/python scripts/profile_stages.py --suite matrix --n 32
    nice .venv/bin/python scripts/profile_stages.py --suite scene --n 12 --cprofile 25

Usage: python scripts/profile_stages.py [--suite scene|matrix] [--n N] [--seed S]
[--size WxH|native] [--cprofile K] [--scans-cache DIR]
"""

from __future__ import annotations

import argparse
import cProfile
import dataclasses
import hashlib
import io
import math
import pickle
import pstats
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

#: The stages in pipeline order (``boxloc.pipeline``), then the total.
STAGES = ("noise", "edges", "lines", "up", "vertices", "hypotheses", "select", "surfaces",
          "total")


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


def _p99(x: np.ndarray) -> float:
    # the 99th percentile by linear interpolation (numpy's default); with fewer than 100
    # scenes it lies between the two largest
    return float(np.percentile(x, 99)) if x.size else math.nan


def stage_table(times: dict[str, list[float]]) -> str:
    """The markdown table of per-stage times (ms): median, p99, max, share of the total."""
    total = float(np.median(times["total"])) if times.get("total") else math.nan
    lines = ["| stage | median ms | p99 ms | max ms | share of median total |",
             "|---|---:|---:|---:|---:|"]
    for name in STAGES:
        if name not in times:
            continue
        x = np.asarray(times[name], dtype=np.float64)
        med = float(np.median(x))
        share = f"{100 * med / total:.0f} %" if name != "total" and total > 0 else ""
        lines.append(f"| {name} | {med:.1f} | {_p99(x):.1f} | {float(x.max()):.1f} | {share} |")
    return "\n".join(lines)


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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", choices=("scene", "matrix"), default="matrix")
    ap.add_argument("--n", type=int, default=32, help="scenes (default 32: each matrix cell once)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", default="640x480",
                    help="WxH every scene is rescaled to, or 'native' (default 640x480)")
    ap.add_argument("--cprofile", type=int, default=0, metavar="K",
                    help="also list the K functions with the most own time")
    ap.add_argument("--scans-cache", type=Path, default=None, metavar="DIR",
                    help="keep the simulated scans here (pickles) for repeated runs")
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

    from boxloc.config import Config
    from boxloc.pipeline import find_graspable_surfaces

    config = Config()
    scans = _scans(_specs(a.suite, a.n, a.seed, size), a.scans_cache)
    find_graspable_surfaces(scans[0], config)  # numba kernels and lazy tables, not timed
    times: dict[str, list[float]] = {}
    t0 = time.perf_counter()
    for scan in scans:
        res = find_graspable_surfaces(scan, config)
        for k, v in res.timing_ms.items():
            times.setdefault(k, []).append(float(v))
    wall = time.perf_counter() - t0
    shape = "native sizes" if size is None else f"{size[0]}x{size[1]}"
    print(f"Per-stage time over {a.n} scenes of `{a.suite}_suite({a.n}, {a.seed})` at {shape} "
          f"(ms, `Result.timing_ms`; {wall:.1f} s in all):\n")
    print(stage_table(times))
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

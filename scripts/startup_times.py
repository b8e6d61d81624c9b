"""Start-up of `boxloc locate` with the ahead-of-time kernels and with numba's JIT.

For each kind of kernels (``BOXLOC_KERNELS=aot``, then ``jit``, in turn, ``--runs`` times):

* ``boxloc locate SCAN -o OUT`` in a new process: its wall time, the pipeline's time
  (``timing_ms.total``, the first scan of a process) and the difference, what the process
  spends beyond the pipeline (interpreter, imports, reading, writing);
* in one new process: the pipeline on SCAN three times, read anew each time (a Scan caches
  its rays), the first call against the median of the other two (the first scan's extra:
  kernels loaded, tables built, lazy imports).

Prints a markdown table of the medians (and ranges). The scan defaults to a simulated
640x480 laser pallet (``pallet:seed=1``). Run it with nothing else busy.

Usage: python scripts/startup_times.py [--scan FILE] [--runs N]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
_IN_PROCESS = """
import json, sys, time
from boxloc import kernels
from boxloc.config import Config
from boxloc.io import read_scan
from boxloc.pipeline import find_graspable_surfaces
t = []
for _ in range(3):
    scan = read_scan(sys.argv[1])  # a new Scan each time: its rays are cached on the object
    a = time.perf_counter()
    find_graspable_surfaces(scan, Config())
    t.append(time.perf_counter() - a)
print(json.dumps({"mode": kernels.mode(), "times": t}))
"""


def _env(mode: str) -> dict[str, str]:
    return {**os.environ, "BOXLOC_KERNELS": mode, "OMP_NUM_THREADS": "1",
            "NUMBA_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}


def _locate(scan: Path, out: Path, mode: str) -> tuple[float, float]:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "boxloc.cli", "locate", str(scan), "-o", str(out)],
                   env=_env(mode), check=True, cwd=ROOT, timeout=600)
    wall = time.perf_counter() - t0
    return wall, json.loads(out.read_text())["timing_ms"]["total"] / 1e3


def _in_process(scan: Path, mode: str) -> tuple[float, float]:
    r = subprocess.run([sys.executable, "-c", _IN_PROCESS, str(scan)], env=_env(mode),
                       check=True, cwd=ROOT, capture_output=True, text=True, timeout=600)
    d = json.loads(r.stdout.strip().splitlines()[-1])
    if d["mode"] != mode:
        raise SystemExit(f"startup_times: asked for {mode}, ran {d['mode']}")
    return d["times"][0], statistics.median(d["times"][1:])


def _fmt(xs: list[float]) -> str:
    return f"{statistics.median(xs):.2f} ({min(xs):.2f}–{max(xs):.2f})"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scan", type=Path)
    ap.add_argument("--runs", type=int, default=5)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        scan = a.scan
        if scan is None:
            scan = Path(tmp) / "pallet.npz"
            subprocess.run([sys.executable, "-m", "boxloc.cli", "simulate", "pallet:seed=1",
                            "--sensor", "laser", "-o", str(scan)], check=True, cwd=ROOT,
                           capture_output=True, timeout=300)
        rows: dict[str, dict[str, list[float]]] = {
            m: {"wall": [], "pipe": [], "beyond": [], "first": [], "later": []}
            for m in ("aot", "jit")}
        for _ in range(a.runs):
            for m in ("aot", "jit"):
                wall, pipe = _locate(scan, Path(tmp) / "out.json", m)
                first, later = _in_process(scan, m)
                r = rows[m]
                r["wall"].append(wall)
                r["pipe"].append(pipe)
                r["beyond"].append(wall - pipe)
                r["first"].append(first)
                r["later"].append(later)
    print(f"`boxloc locate` of {scan.name if a.scan else 'a simulated 640x480 laser pallet'}, "
          f"{a.runs} runs each, in turn; seconds, median (range):\n")
    print("| kernels | locate: wall | its pipeline (first scan) | beyond the pipeline | "
          "in one process: first scan | the next two (median) |")
    print("|---|---|---|---|---|---|")
    for m, name in (("aot", "ahead of time"), ("jit", "numba JIT + cache")):
        r = rows[m]
        print(f"| {name} | {_fmt(r['wall'])} | {_fmt(r['pipe'])} | {_fmt(r['beyond'])} | "
              f"{_fmt(r['first'])} | {_fmt(r['later'])} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Helpers of the replay tests: small recorded logs, product comparison, a worker killer.

Logs are recorded by the real pipeline on small simulated scans (160 x 120 pixels, the
focal length scaled with the image, the sensor 1 m above the pile), so a scan takes tens
of milliseconds and still yields edges, lines, vertices and a surface.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import signal
from collections.abc import Callable
from pathlib import Path
from typing import Any

from boxloc.config import Config
from boxloc.products import STAGES, products_equal

SPEC = "single:width=160,height=120,f=131.25,distance=1.0"
PALLET = "pallet:width=160,height=120,f=131.25,distance=1.0"


def make_log(path: Path, seeds: list[int], *, spec: str = SPEC,
             config: Config | None = None) -> Path:
    """Record one log of ``len(seeds)`` simulated scans (indices 0, 1, ...) to ``path``."""
    from boxloc.pipeline import find_graspable_surfaces
    from boxloc.simulate import parse_spec, simulate
    from recorder.mcap.sink import McapRecorder

    cfg = config or Config()
    sp = parse_spec(spec)
    with McapRecorder(path, config=cfg, fsync=False) as rec:
        for i, seed in enumerate(seeds):
            scan = dataclasses.replace(simulate(sp, seed=seed).scan, index=i)
            find_graspable_surfaces(scan, cfg, observer=rec)
    return path


def make_logs(folder: Path, n_logs: int = 3, scans_per_log: int = 2) -> list[Path]:
    """``n_logs`` logs in ``folder`` (``log0.mcap`` ...), alternating single boxes and pallets."""
    folder.mkdir(parents=True, exist_ok=True)
    return [make_log(folder / f"log{k}.mcap",
                     [100 * k + j for j in range(scans_per_log)],
                     spec=SPEC if k % 2 == 0 else PALLET)
            for k in range(n_logs)]


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def snapshot(paths: list[Path]) -> dict[str, tuple[str, int]]:
    """Content hash and modification time (ns) of each file: to prove nothing touched them."""
    return {str(p): (sha256(p), os.stat(p).st_mtime_ns) for p in paths}


def product_differences(a: Path, b: Path) -> list[str]:
    """Everything that differs between the scans and products of two logs (empty: same).

    Scans are paired in order; compared: count, index, log time, range bytes, every stage's
    product bit for bit (``products_equal``), the Result's own fields and the error record.
    """
    from recorder.mcap.log import open_log

    ra, rb = list(open_log(a).scans()), list(open_log(b).scans())
    out: list[str] = []
    if len(ra) != len(rb):
        return [f"scan count {len(ra)} != {len(rb)}"]
    for x, y in zip(ra, rb):
        tag = f"scan {x.index}"
        if x.index != y.index or x.log_time_ns != y.log_time_ns:
            out.append(f"{tag}: index/log time {x.index}/{x.log_time_ns} != "
                       f"{y.index}/{y.log_time_ns}")
        if x.scan.range.tobytes() != y.scan.range.tobytes():
            out.append(f"{tag}: range")
        if set(x.products) != set(y.products):
            out.append(f"{tag}: stages {sorted(x.products)} != {sorted(y.products)}")
        for s in STAGES:
            if s in x.products and s in y.products:
                out += [f"{tag}: {s}/{f}" for f in products_equal(x.products[s], y.products[s])]
        if x.result_info != y.result_info:
            out.append(f"{tag}: result info {x.result_info} != {y.result_info}")
        ex = None if x.error is None else (x.error["stage"], x.error["error_type"])
        ey = None if y.error is None else (y.error["stage"], y.error["error_type"])
        if ex != ey:
            out.append(f"{tag}: error {ex} != {ey}")
    return out


@dataclasses.dataclass(frozen=True)
class KillOnce:
    """Wraps a replay function: the first call on log ``victim`` kills its own process
    (SIGKILL, as the OOM killer would), leaving a marker so the retry runs normally."""

    fn: Callable[[Path], Any]
    victim: str
    marker_dir: str

    def __call__(self, path: Path) -> Any:
        marker = Path(self.marker_dir) / f"{Path(path).name}.killed"
        if Path(path).name == self.victim and not marker.exists():
            marker.write_text(str(os.getpid()))
            os.kill(os.getpid(), signal.SIGKILL)
        return self.fn(path)


@dataclasses.dataclass(frozen=True)
class KillAlways:
    """Wraps a replay function: every call on log ``victim`` kills its own process."""

    fn: Callable[[Path], Any]
    victim: str

    def __call__(self, path: Path) -> Any:
        if Path(path).name == self.victim:
            os.kill(os.getpid(), signal.SIGKILL)
        return self.fn(path)

"""The ``replay`` section of ``boxloc bench``: replay throughput, 1 worker against 2.

Registered in the ``boxloc.bench`` entry-point group (``boxloc bench`` runs it after the
scenes; ``boxloc bench --replay`` runs only it). It records :data:`N_LOGS` small logs of
:data:`SCANS_PER_LOG` simulated scans each (the bench's scene suite at a reduced
resolution), replays them all with the current code on 1 and then on 2 local worker
processes, and reports logs/s and the speed-up (target >= :data:`TARGET_SPEEDUP`).

Both runs use worker processes (``run_local(..., pool=True)``), so both pay the same
start-up; the times are wall clock of the whole run, start-up included. On a machine
whose cores are busy with other work the speed-up is lower: ``cpu_count``, the load
average before the runs and ``core_share`` (CPU time of the replays / (wall time x
workers): the share of a core each worker actually got) are reported with it.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

#: Logs replayed (the issue asks for >= 50).
N_LOGS = 50
#: Scans per log.
SCANS_PER_LOG = 2
#: Reduced resolution of the scans (a quarter of VGA; the focal length scales with it).
WIDTH, HEIGHT = 320, 240
TARGET_SPEEDUP = 1.8


def make_logs(out_dir: Path, *, n_logs: int = N_LOGS, scans_per_log: int = SCANS_PER_LOG,
              seed: int = 0, config: Any = None) -> list[Path]:
    """Record ``n_logs`` logs of simulated scans into ``out_dir``; return their paths.

    The scenes are ``boxloc.simulate.scene_suite(n_logs * scans_per_log, seed)`` at
    :data:`WIDTH` x :data:`HEIGHT`.
    """
    from boxloc.config import Config
    from boxloc.pipeline import find_graspable_surfaces
    from boxloc.simulate import scene_suite, simulate
    from recorder.mcap.sink import McapRecorder

    cfg = config or Config()
    specs = scene_suite(n_logs * scans_per_log, seed)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for k in range(n_logs):
        path = out_dir / f"bench-{k:03d}.mcap"
        with McapRecorder(path, config=cfg, session=f"bench-{k:03d}", fsync=False) as rec:
            for j in range(scans_per_log):
                spec = specs[k * scans_per_log + j]
                spec = dataclasses.replace(spec, width=WIDTH, height=HEIGHT,
                                           f=spec.f * WIDTH / spec.width)
                scan = dataclasses.replace(simulate(spec).scan, index=j)
                try:
                    find_graspable_surfaces(scan, cfg, observer=rec)
                except Exception as e:  # noqa: BLE001 - recorded as the scan's result
                    rec.on_error(scan, e)
        paths.append(path)
    return paths


def measure(paths: list[Path], out_dir: Path, jobs: int) -> dict[str, Any]:
    """Replay ``paths`` into ``out_dir`` on ``jobs`` worker processes; time it."""
    from replay.executors import run_local
    from replay.replay import ReplayJob, plan_outputs

    names = plan_outputs(paths, out_dir)
    job = ReplayJob(out_dir=str(out_dir), names={str(p): n for p, n in zip(paths, names)})
    t0 = time.perf_counter()
    outcomes = run_local(paths, job, jobs, pool=True)
    wall = time.perf_counter() - t0
    return {
        "jobs": jobs,
        "wall_s": round(wall, 3),
        "logs_per_s": round(len(paths) / wall, 3),
        "scans_per_s": round(sum(o.n_scans for o in outcomes) / wall, 3),
        # the work itself, summed over logs: what a perfect pool would divide by its size
        "work_s": round(sum(o.seconds for o in outcomes), 3),
        "cpu_s": round(sum(o.cpu_seconds for o in outcomes), 3),
        # the share of a core each worker got while replaying (1.0: a core of its own; less
        # when other processes compete for the cores)
        "core_share": round(sum(o.cpu_seconds for o in outcomes) / (wall * jobs), 3),
        "errors": sum(o.error is not None for o in outcomes),
        "failed_scans": sum(o.n_failed for o in outcomes),
    }


def replay_section(ctx: Any) -> dict[str, Any]:
    """``boxloc.bench`` section: replay throughput on :data:`N_LOGS` logs, 1 vs 2 workers."""
    # Scratch space only (some 200 MB of logs): nothing of it is worth keeping.
    root = Path(tempfile.mkdtemp(prefix="boxloc-replay-bench-"))
    try:
        t0 = time.perf_counter()
        logs = make_logs(root / "logs", n_logs=N_LOGS, scans_per_log=SCANS_PER_LOG,
                         seed=ctx.seed, config=ctx.config)
        make_s = time.perf_counter() - t0
        load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
        one = measure(logs, root / "jobs1", 1)
        two = measure(logs, root / "jobs2", 2)
        speedup = one["wall_s"] / two["wall_s"] if two["wall_s"] > 0 else None
        return {
            "n_logs": len(logs),
            "scans_per_log": SCANS_PER_LOG,
            "resolution": f"{WIDTH}x{HEIGHT}",
            "make_logs_s": round(make_s, 3),
            "jobs_1": one,
            "jobs_2": two,
            "speedup_2_over_1": None if speedup is None else round(speedup, 3),
            "target_speedup": TARGET_SPEEDUP,
            "pass": None if speedup is None else speedup >= TARGET_SPEEDUP,
            "cpu_count": os.cpu_count(),
            # other work on the machine (load before the runs) lowers the speed-up
            "load_average_1min": None if load is None else round(load, 2),
        }
    finally:
        shutil.rmtree(root, ignore_errors=True)

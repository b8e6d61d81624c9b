"""The ``recording`` section of ``boxloc bench``: what recording costs, and the throughput of
``boxloc run --workers``.

Registered in the ``boxloc.bench`` entry-point group. On the first :data:`N_SCANS` scenes of
the benchmark (640x480 by default) it measures the time the MCAP recorder and the Rerun
sink add to the pipeline and the log bytes per scan, against the targets of issue 22: each
cost <= 5 % of the pipeline's own time, <= 1 MB per scan with all intermediates. The issue
measures the log's size on the sensor x scene matrix: :func:`matrix_footprint` records its
first :data:`N_MATRIX` scenes at 640x480 (and gives the bytes by channel, in kB). The time
figures are the work done inside the sink over the pipeline's time (robust on a busy
machine); the end-to-end differences of two runs are reported too.

Throughput (issue 22 part 4, >= :data:`TARGET_SPEEDUP` x scans per second on 2 cores): the
first :data:`N_STREAM` scenes are written as scan files and recorded by
``boxloc run DIR --record LOG --workers W`` for W = 1, then 2, each a process of its own as
a user starts it, so the figures include start-up (imports, the workers' forkserver). Wall
time gives scans/s and the speed-up; the CPU time of each run's whole process tree
(parent, forkserver, workers; read with psutil every :data:`POLL_S`) is reported beside
it, because on a loaded machine the wall time depends on what else runs. From the CPU
times, ``cpu_bound_speedup`` = 2 x CPU(1) / CPU(2) is the speed-up two idle cores would
allow at most (the parallel run's extra CPU is what keeps it below 2). Both logs must be
the same, but for the wall-clock ``/boxloc/timing``. A run of the first W scans alone
(start-up and one scan per worker) is timed too: taken off the full run, it leaves the
steady rate of a long stream (``steady_speedup``), which the start-up (about 2 s before
the workers' first scan, 1 s before a serial run's) does not weigh on. The runs are made
:data:`STREAM_ROUNDS` times, serial and parallel in turn, and the figures are the rounds'
medians, each round's kept beside them.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

#: Scans measured (enough to average over scene kinds, few enough to take under a minute).
N_SCANS = 10
#: Scenes of the sensor x scene matrix (seed 0, brought to 640x480) whose log size is the
#: issue's footprint figure: every sensor and scene kind, 8 of each sensor.
N_MATRIX = 32
TARGET_FRACTION = 0.05
TARGET_BYTES_PER_SCAN = 1_000_000
#: Scans of each throughput run: 16 per worker, so that the start-up (~1.5 s before the
#: workers' first scan, ~1 s of it in the serial run too) weighs little against a stream's
#: steady state (~14 s of scans per worker at 640x480).
N_STREAM = 32
#: Rounds of the throughput runs (each: serial, then parallel, with their first scans), the
#: figures the medians: one round's ratio moved 1.3-1.8 between runs of the same code here.
STREAM_ROUNDS = 3
#: The speed-up of ``--workers 2`` over ``--workers 1`` that issue 22 asks for.
TARGET_SPEEDUP = 1.8
#: Seconds between two reads of the process tree's CPU times (the last interval of each
#: process, at most this much CPU, is not seen).
POLL_S = 0.02


def run_measured(cmd: list[str]) -> dict[str, Any]:
    """Run ``cmd``; its wall time and the CPU time of every process it starts.

    Returns
    -------
    dict
        ``wall_s``; ``cpu_s`` (user + system of the command and every descendant, s: the
        command's own, with the children it waited for, from its exit status; the others
        as last read); ``processes`` (the command and the descendants counted apart);
        ``returncode``; ``stderr`` (its last line).

    Notes
    -----
    A direct child still running at the last read before the command exited is taken
    as one it did not wait for (it outlived the command or ended in the last
    :data:`POLL_S`), and counted apart.
    """
    import psutil

    errf = tempfile.TemporaryFile()  # not a pipe: a chatty command never blocks on it
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=errf)
    root = psutil.Process(proc.pid)
    seen: dict[int, float] = {}
    direct: set[int] = set()  # the command's own children
    last: set[int] = set()  # the processes of the last read
    rusage = None
    try:
        while True:
            pid, status, ru = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                rusage, proc.returncode = ru, os.waitstatus_to_exitcode(status)
                break
            try:
                kids = root.children(recursive=True)
                # an exited command's children were given to init before this listing
                exited = root.status() == psutil.STATUS_ZOMBIE
            except psutil.NoSuchProcess:
                kids, exited = [], True
            if exited:
                continue  # reaped at the next turn; the last read stays the last
            last = set()
            for q in kids:
                try:
                    c = q.cpu_times()
                    seen[q.pid] = c.user + c.system
                    last.add(q.pid)
                    if q.ppid() == proc.pid:
                        direct.add(q.pid)
                except psutil.NoSuchProcess:
                    pass
            time.sleep(POLL_S)
        wall = time.perf_counter() - t0
        errf.seek(0)
        err = errf.read().decode(errors="replace")
    finally:
        if proc.returncode is None:
            proc.kill()
            proc.wait()
        errf.close()
    # A child the command waited for (git, run by the recorder) is in its rusage already;
    # one that outlived it (the forkserver, which reaps the workers) is not.
    counted = {pid: t for pid, t in seen.items() if pid not in direct or pid in last}
    lines = err.strip().splitlines()
    return {
        "wall_s": wall,
        "cpu_s": rusage.ru_utime + rusage.ru_stime + sum(counted.values()),
        "processes": 1 + len(counted),
        "returncode": proc.returncode,
        "stderr": lines[-1] if lines else "",
    }


def _messages(path: Path) -> list[tuple[str, int, int, bytes]]:
    """A log's messages as stored, but the wall-clock timing."""
    from recorder.mcap import channels as C
    from recorder.mcap.log import open_log

    return [(m.topic, m.log_time, m.sequence, m.data) for m in open_log(path).messages()
            if m.topic != C.TIMING]


def measure_throughput(scans: list[Any], config: Any, *, workers: tuple[int, ...] = (1, 2),
                       rounds: int = 1) -> dict[str, Any]:
    """``boxloc run DIR --record LOG --workers W`` on the same scans, for each W in order,
    ``rounds`` times over.

    The runs of each W alternate within a round, so a neighbour's load that comes and goes
    falls on both; the figures are the rounds' medians (a machine whose CPU time for fixed
    work varies by tens of per cent within minutes makes one round a draw).

    Parameters
    ----------
    scans : list of Scan
        Written as ``.npz`` files (the run reads them as a user's files).
    config : Config
        Given to the runs as ``--config``.
    workers : tuple of int
        The ``--workers`` of each run; the first is the reference of ``speedup``.
    rounds : int
        Times every run is repeated (>= 1).

    Returns
    -------
    dict
        ``scans``; ``rounds``: per round, ``runs`` (per W: ``workers``, ``wall_s``,
        ``scans_per_s``, ``cpu_s``, ``cpu_per_scan_s``, ``core_share`` = CPU / (wall x W),
        ``processes``, ``first_scans_wall_s``: a run of the first W scans alone, i.e.
        start-up and one scan per worker, and ``steady_scans_per_s`` = (N - W) / (wall -
        that): the rate of a long stream, start-up left out), ``speedup`` (scans/s of the
        last run over the first's), ``steady_speedup`` (the same of the steady rates) and
        ``cpu_bound_speedup`` (W_last x CPU(first) / CPU(last), with W_last the last run's
        workers); ``speedup``, ``steady_speedup`` and ``cpu_bound_speedup``: the medians
        over the rounds (``speedup_range``, ``steady_speedup_range``: their smallest and
        largest); ``runs``: the runs of the round whose speedup is the median (the lower
        middle one of an even count); ``same_log`` (every log equal to the first's, but
        the timing); ``load_average_1min`` (before the runs) and ``cpu_count``.

    Raises
    ------
    RuntimeError
        If a run fails (its last line of stderr).
    ValueError
        If ``rounds`` < 1.
    """
    import statistics

    from boxloc.io import write_npz

    if rounds < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds}")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    logs: list[Any] = []
    done: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="boxloc-throughput-") as tmp:
        src = Path(tmp) / "scans"
        src.mkdir()
        for k, scan in enumerate(scans):
            write_npz(scan, src / f"scan-{k:04d}.npz")
        cfg = Path(tmp) / "config.toml"
        cfg.write_text(config.to_toml())
        files = sorted(src.iterdir())

        def run(w: int, sources: list[Path], name: str) -> dict[str, Any]:
            log = Path(tmp) / f"{name}.mcap"
            log.unlink(missing_ok=True)
            r = run_measured([sys.executable, "-m", "boxloc.cli", "run", *map(str, sources),
                              "--record", str(log), "--config", str(cfg), "-q", "--workers",
                              str(w)])
            if r["returncode"] != 0:
                raise RuntimeError(f"boxloc run --workers {w} failed ({r['returncode']}): "
                                   f"{r['stderr']}")
            r["log"] = log
            return r

        for _ in range(rounds):
            runs = []
            for w in workers:
                r = run(w, [src], f"workers{w}")
                # start-up and one scan per worker: what the stream's steady state is without
                first = run(w, files[:w], f"first{w}") if len(files) > w else None
                steady = None if first is None or r["wall_s"] <= first["wall_s"] else \
                    (len(files) - w) / (r["wall_s"] - first["wall_s"])
                runs.append({"workers": w, "wall_s": round(r["wall_s"], 3),
                             "scans_per_s": round(len(scans) / r["wall_s"], 3),
                             "cpu_s": round(r["cpu_s"], 3),
                             "cpu_per_scan_s": round(r["cpu_s"] / len(scans), 4),
                             # the share of its W cores the run got (about 1 on idle
                             # cores; less when other work competes for them)
                             "core_share": round(r["cpu_s"] / (r["wall_s"] * w), 3),
                             "processes": r["processes"],
                             "first_scans_wall_s": None if first is None else
                             round(first["wall_s"], 3),
                             "steady_scans_per_s": None if steady is None else
                             round(steady, 3)})
                logs.append(_messages(r["log"]))
            first_run, last = runs[0], runs[-1]
            done.append({
                "runs": runs,
                "speedup": round(last["scans_per_s"] / first_run["scans_per_s"], 3),
                "steady_speedup": (
                    None if not (first_run["steady_scans_per_s"]
                                 and last["steady_scans_per_s"]) else
                    round(last["steady_scans_per_s"] / first_run["steady_scans_per_s"], 3)),
                "cpu_bound_speedup": round(last["workers"] * first_run["cpu_s"]
                                           / last["cpu_s"], 3)})

    def median(key: str) -> float | None:
        vals = [d[key] for d in done if d[key] is not None]
        return None if not vals else round(float(statistics.median(vals)), 3)

    def span(key: str) -> list[float] | None:
        vals = [d[key] for d in done if d[key] is not None]
        return None if not vals else [min(vals), max(vals)]

    order = sorted(range(len(done)), key=lambda i: done[i]["speedup"])
    return {
        "scans": len(scans),
        "rounds": done,
        "runs": done[order[(len(done) - 1) // 2]]["runs"],
        "speedup": median("speedup"),
        "speedup_range": span("speedup"),
        "steady_speedup": median("steady_speedup"),
        "steady_speedup_range": span("steady_speedup"),
        "cpu_bound_speedup": median("cpu_bound_speedup"),
        "same_log": all(x == logs[0] for x in logs[1:]),
        "load_average_1min": None if load is None else round(load, 2),
        "cpu_count": os.cpu_count(),
    }


def matrix_footprint(n: int = N_MATRIX, seed: int = 0) -> dict[str, Any]:
    """Log bytes per scan of the first ``n`` scenes of the sensor x scene matrix (``seed``),
    each brought to 640x480 (:func:`recorder.mcap.footprint.suite`), recorded with every
    intermediate product, run as the matrix benchmark runs them (its configuration: the
    defaults and the site's box range, :func:`boxloc.evaluate.matrix_bench.matrix_config`).

    Returns
    -------
    dict
        ``scans``; ``bytes_per_scan`` (file / scans); ``median_scan_bytes``,
        ``max_scan_bytes`` (a scan's chunk with its index); ``by_sensor``: ``{sensor: mean
        chunk bytes}``; ``kb_per_scan_by_channel``; ``seed``.
    """
    import statistics

    from boxloc.evaluate.matrix_bench import matrix_config
    from recorder.mcap.footprint import record_footprint, suite

    specs = suite("matrix", n, seed)
    fp = record_footprint(specs, matrix_config(specs)[0])
    chunks = fp["scan_bytes"] or [0]
    by: dict[str, list[int]] = {}
    for scene, b in zip(fp["scenes"], fp["scan_bytes"]):
        by.setdefault(scene["sensor"], []).append(b)
    return {
        "scans": fp["scans"], "seed": seed,
        "bytes_per_scan": fp["bytes_per_scan"],
        "median_scan_bytes": statistics.median(chunks), "max_scan_bytes": max(chunks),
        "by_sensor": {k: sum(v) / len(v) for k, v in sorted(by.items())},
        "kb_per_scan_by_channel": {t: round(c["zstd"] / 1e3, 1)
                                   for t, c in fp["channels"].items()},
    }


def recording_section(ctx: Any) -> dict[str, Any]:
    """Recording overhead on the benchmark's scenes (a ``boxloc.evaluate.scene_bench`` section)."""
    from boxloc.simulate import simulate
    from recorder.overhead import measure_overhead
    from recorder.rerun.overhead import measure_rerun_overhead

    scans = [simulate(spec).scan for spec in ctx.specs[:N_SCANS]]
    mcap = measure_overhead(scans, ctx.config)
    rr = measure_rerun_overhead(scans, ctx.config)
    stream = [simulate(spec).scan for spec in ctx.specs[:N_STREAM]]
    tp = measure_throughput(stream, ctx.config, rounds=STREAM_ROUNDS)
    fp = matrix_footprint()
    return {
        "scans": len(scans),
        "mcap_fraction": mcap["recorder_fraction"],
        "mcap_end_to_end_fraction": mcap["overhead_fraction"],
        "mcap_bytes_per_scan": mcap["bytes_per_scan"],
        "mcap_max_scan_bytes": mcap["max_scan_bytes"],
        "rerun_fraction": rr["log_fraction"],
        "rerun_end_to_end_fraction": rr["overhead"],
        "mcap_kb_per_scan_by_channel": {t: round(c["zstd"] / 1e3, 1)
                                        for t, c in mcap["channels"].items()},
        "rrd_bytes_per_scan": rr["rrd_bytes"] / max(len(scans), 1),
        # the figure: the matrix benchmark's scans at 640x480
        "matrix": fp,
        # boxloc run DIR --workers 1, then 2, on the same scans (start-up included)
        "throughput": tp,
        "run_workers_speedup": tp["speedup"],
        "targets": {
            "mcap_fraction <= 0.05": bool(mcap["recorder_fraction"] <= TARGET_FRACTION),
            "rerun_fraction <= 0.05": bool(rr["log_fraction"] <= TARGET_FRACTION),
            "mcap_bytes_per_scan <= 1 MB": bool(
                mcap["bytes_per_scan"] <= TARGET_BYTES_PER_SCAN),
            "matrix_bytes_per_scan <= 1 MB": bool(
                fp["bytes_per_scan"] <= TARGET_BYTES_PER_SCAN),
            f"run --workers 2 >= {TARGET_SPEEDUP}x scans/s of --workers 1": bool(
                tp["speedup"] >= TARGET_SPEEDUP),
            f"run --workers 2 >= {TARGET_SPEEDUP}x, steady state": bool(
                tp["steady_speedup"] is not None and tp["steady_speedup"] >= TARGET_SPEEDUP),
            "run --workers 2 log == --workers 1 log": bool(tp["same_log"]),
        },
    }

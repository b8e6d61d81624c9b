"""What Rerun logging costs the pipeline: the pipeline alone vs. with a :class:`RerunSink`.

The sink saves to a temporary ``.rrd`` (the cheapest sink that still does all the work of
converting and serializing every product). The time with the sink includes closing it, i.e.
waiting for its background thread and the file's flush, so nothing is hidden in a queue.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from boxloc.config import Config
from boxloc.scan import Scan
from recorder.rerun.sink import log_products, open_rerun_sink, recording_id_for


def measure_rerun_overhead(
    scans: Sequence[Scan], config: Config | None = None, *, repeats: int = 1,
    threaded: bool = True,
) -> dict[str, Any]:
    """Time the pipeline over ``scans`` without and with Rerun logging.

    Parameters
    ----------
    scans : sequence of Scan
        At least one. The first is also run once beforehand, untimed (JIT warm-up).
    config : Config, optional
    repeats : int
        Each variant runs this many times, alternating; the fastest run of each counts
        (the machine is shared, the minimum is the least disturbed).
    threaded : bool
        Log on the sink's background thread (the default of :func:`open_rerun_sink`).

    Returns
    -------
    dict
        ``n_scans``, ``pipeline_s`` (alone), ``with_rerun_s``, ``overhead``
        (``with_rerun_s / pipeline_s - 1``; noisy on a shared machine), ``log_only_s``
        (logging the same results inline, without the pipeline: the work the sink does),
        ``log_fraction`` (``log_only_s / pipeline_s``), ``rrd_bytes``, ``threaded``.
    """
    from boxloc.pipeline import find_graspable_surfaces

    if not scans:
        raise ValueError("measure_rerun_overhead needs at least one scan")
    config = config or Config()
    find_graspable_surfaces(scans[0], config)  # warm-up: JIT compilation, caches

    best_base = best_rr = float("inf")
    rrd_bytes = 0
    results = []
    with tempfile.TemporaryDirectory(prefix="boxloc-rerun-") as tmp:
        for r in range(max(1, repeats)):
            t0 = time.perf_counter()
            results = [find_graspable_surfaces(s, config) for s in scans]
            best_base = min(best_base, time.perf_counter() - t0)

            path = Path(tmp) / f"overhead-{r}.rrd"
            t0 = time.perf_counter()
            sink = open_rerun_sink(f"save:{path}", recording_id=recording_id_for(
                f"overhead-{r}", "bench"), threaded=threaded)
            assert sink is not None
            try:
                for s in scans:
                    find_graspable_surfaces(s, config, observer=sink)
            finally:
                sink.close()
            best_rr = min(best_rr, time.perf_counter() - t0)
            rrd_bytes = path.stat().st_size

        # The logging work alone, inline, on the results of the last plain run.
        import rerun as rr

        rec = rr.RecordingStream("boxloc", recording_id=recording_id_for("log-only", "bench"))
        rec.set_log_time_enabled(False)
        rec.save(str(Path(tmp) / "log-only.rrd"))
        t0 = time.perf_counter()
        for s, res in zip(scans, results):
            log_products(rec, s, res)
        rec.flush()
        log_only = time.perf_counter() - t0
        rec.disconnect()

    return {
        "n_scans": len(scans),
        "pipeline_s": best_base,
        "with_rerun_s": best_rr,
        "overhead": best_rr / best_base - 1.0 if best_base > 0 else float("nan"),
        "log_only_s": log_only,
        # the robust estimate on a busy machine: the sink's work over the pipeline's
        "log_fraction": log_only / best_base if best_base > 0 else float("nan"),
        "rrd_bytes": rrd_bytes,
        "threaded": threaded,
    }

"""What recording costs: time added to the pipeline and log bytes per scan.

Used by ``boxloc bench``. Two measures of the time are reported, because a loaded machine
makes a difference of two run times noisy:

* ``recorder_fraction``: the time spent inside the recorder (encoding every product,
  compressing, writing, fsync, the summary at the end), measured around each recorder call,
  over the pipeline's own time. This is the cost recording adds.
* ``overhead_fraction``: (pipeline with the recorder - pipeline alone) / pipeline alone,
  from wall-clock runs of both; the same thing measured end to end, noisier.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Iterable
from functools import partial
from pathlib import Path
from typing import Any

from boxloc.config import Config
from boxloc.scan import Scan


def _timed(fn: Any) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def measure_overhead(scans: Iterable[Scan], config: Config | None = None, *,
                     fsync: bool = True, warmup: bool = True) -> dict[str, Any]:
    """Run each scan through the pipeline alone, then with an :class:`McapRecorder`.

    Parameters
    ----------
    scans : iterable of Scan
    config : Config, optional
    fsync : bool
        fsync after each scan, as in production.
    warmup : bool
        Record the first scan once, untimed, so JIT compilation, imports and the
        once-per-process provenance lookup are not charged to anyone.

    Returns
    -------
    dict
        ``scans``, ``pixels`` (mean per scan), ``pipeline_s``, ``with_recorder_s``,
        ``recorder_s``, ``recorder_fraction``, ``overhead_fraction``, ``log_bytes``,
        ``bytes_per_scan`` (file size / scans), ``max_scan_bytes`` (largest scan chunk with
        its index), ``channels`` (bytes per scan by topic, see
        :func:`recorder.mcap.footprint.log_footprint`) and ``per_scan`` (index, pixels,
        pipeline_s, recorder_s, chunk_bytes).
    """
    from boxloc.pipeline import find_graspable_surfaces
    from recorder.mcap.footprint import log_footprint
    from recorder.mcap.log import open_log
    from recorder.mcap.sink import McapRecorder

    cfg = config or Config()
    scans = list(scans)
    if not scans:
        raise ValueError("measure_overhead needs at least one scan")
    per_scan: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="boxloc-overhead-") as tmp:
        if warmup:  # JIT, imports and the once-per-process provenance (git) are not charged
            with McapRecorder(Path(tmp) / "warmup.mcap", fsync=fsync) as rec:
                find_graspable_surfaces(scans[0], cfg, observer=rec)
        path = Path(tmp) / "overhead.mcap"
        t_alone = t_with = 0.0
        with McapRecorder(path, config=cfg, fsync=fsync) as rec:
            for k, scan in enumerate(scans):
                before = rec.record_seconds
                run_alone = partial(find_graspable_surfaces, scan, cfg)
                run_with = partial(find_graspable_surfaces, scan, cfg, observer=rec)
                # Alternate which run goes first: the second one finds caches warm.
                if k % 2 == 0:
                    alone, with_ = _timed(run_alone), _timed(run_with)
                else:
                    with_, alone = _timed(run_with), _timed(run_alone)
                t_alone += alone
                t_with += with_
                per_scan.append({"index": scan.index, "pixels": scan.range.size,
                                 "pipeline_s": alone,
                                 "recorder_s": rec.record_seconds - before})
            t3 = time.perf_counter()
        finish_s = time.perf_counter() - t3
        recorder_s = rec.record_seconds + finish_s
        size = path.stat().st_size
        channels = log_footprint(path)["channels"]
        log = open_log(path)
        chunks = sorted(log.summary.chunk_indexes if log.summary else [],
                        key=lambda c: c.chunk_start_offset)
        for row, ci in zip(per_scan, chunks):
            row["chunk_bytes"] = ci.chunk_length + ci.message_index_length
    n = len(scans)
    return {
        "scans": n,
        "pixels": sum(r["pixels"] for r in per_scan) / n,
        "pipeline_s": t_alone,
        "with_recorder_s": t_with,
        "recorder_s": recorder_s,
        "recorder_fraction": recorder_s / t_alone if t_alone > 0 else float("nan"),
        "overhead_fraction": (t_with - t_alone) / t_alone if t_alone > 0 else float("nan"),
        "log_bytes": size,
        "bytes_per_scan": size / n,
        "max_scan_bytes": max((r.get("chunk_bytes", 0) for r in per_scan), default=0),
        "channels": channels,
        "per_scan": per_scan,
    }

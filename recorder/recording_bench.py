"""The ``recording`` section of ``boxloc bench``: what recording costs.

Registered in the ``boxloc.bench`` entry-point group. On the first :data:`N_SCANS` scenes of
the benchmark (640x480 by default) it measures the time the MCAP recorder and the Rerun
sink add to the pipeline and the log bytes per scan (and by channel, in kB), against the
targets of issue 22: each cost <= 5 % of the pipeline's own time, <= 1 MB per scan with all
intermediates. The time figures are the work done inside the sink over the pipeline's time
(robust on a busy machine); the end-to-end differences of two runs are reported too.
"""

from __future__ import annotations

from typing import Any

#: Scans measured (enough to average over scene kinds, few enough to take under a minute).
N_SCANS = 10
TARGET_FRACTION = 0.05
TARGET_BYTES_PER_SCAN = 1_000_000


def recording_section(ctx: Any) -> dict[str, Any]:
    """Recording overhead on the benchmark's scenes (a ``boxloc.evaluate.scene_bench`` section)."""
    from boxloc.simulate import simulate
    from recorder.overhead import measure_overhead
    from recorder.rerun.overhead import measure_rerun_overhead

    scans = [simulate(spec).scan for spec in ctx.specs[:N_SCANS]]
    mcap = measure_overhead(scans, ctx.config)
    rr = measure_rerun_overhead(scans, ctx.config)
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
        "targets": {
            "mcap_fraction <= 0.05": bool(mcap["recorder_fraction"] <= TARGET_FRACTION),
            "rerun_fraction <= 0.05": bool(rr["log_fraction"] <= TARGET_FRACTION),
            "mcap_bytes_per_scan <= 1 MB": bool(
                mcap["bytes_per_scan"] <= TARGET_BYTES_PER_SCAN),
        },
    }

"""Log bytes per scan, by channel: what each intermediate product costs in a log.

A log is chunked one scan per chunk (:mod:`recorder.mcap.sink`), so a scan's bytes are its
chunk's (compressed, with its message index). A channel's share is measured by compressing
its messages of each scan alone, at the recorder's zstd level: the chunk compresses them
together, so the channels' figures add up to about the chunk, not exactly. The range record
is compressed by its own filter (schema 1.6, :data:`recorder.mcap.encode._FILTER_IMAGE_SPLIT`),
so its raw and zstd figures are about equal.

This module gives the per-channel footprint of a log or a suite of scenes::

    python -m recorder.mcap.footprint --suite scene --n 8      # boxloc.simulate.scene_suite
    python -m recorder.mcap.footprint --suite matrix --n 32    # matrix_suite at 640x480, its config

The README's footprint table is not made by this command: it comes from ``boxloc bench
--section recording`` (which measures its logs with :func:`log_footprint`, through
:mod:`recorder.overhead`), written into the README and docs/benchmarks.md by
``scripts/bench_tables.py --footprint OUT/bench.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import zstandard

from boxloc.config import Config
from recorder.mcap import channels as C


def log_footprint(path: str | Path) -> dict[str, Any]:
    """Bytes per scan of a log, by channel.

    Parameters
    ----------
    path : str or Path
        A complete MCAP log written by :class:`recorder.mcap.sink.McapRecorder`.

    Returns
    -------
    dict
        ``file_bytes``; ``scans``; ``bytes_per_scan`` (file bytes / scans, bytes: the summary,
        schemas and attachments included); ``scan_bytes`` (each scan's chunk with its
        message index, bytes, in file order); ``channels``: ``{topic: {"raw", "zstd"}}``,
        the mean per scan of the messages' bytes, and of those bytes compressed alone at the
        recorder's level (bytes).
    """
    from recorder.mcap.log import open_log
    from recorder.mcap.sink import ZSTD_LEVEL

    log = open_log(path)
    chunks = sorted(log.summary.chunk_indexes if log.summary else [],
                    key=lambda c: c.chunk_start_offset)
    z = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
    raw: dict[str, int] = {}
    packed: dict[str, int] = {}
    scan: dict[str, list[bytes]] = {}
    n = 0

    def close() -> None:
        for topic, parts in scan.items():
            data = b"".join(parts)
            raw[topic] = raw.get(topic, 0) + len(data)
            packed[topic] = packed.get(topic, 0) + len(z.compress(data))
        scan.clear()

    for m in log.messages():
        if m.topic == C.START_TOPIC:
            close()  # a scan without its end record still counts what it has
        scan.setdefault(m.topic, []).append(m.data)
        if m.topic in C.END_TOPICS:
            n += 1
            close()
    close()
    size = Path(path).stat().st_size
    per = max(n, 1)
    return {
        "file_bytes": size,
        "scans": n,
        "bytes_per_scan": size / per,
        "scan_bytes": [c.chunk_length + c.message_index_length for c in chunks],
        "channels": {t: {"raw": raw[t] / per, "zstd": packed[t] / per}
                     for t in sorted(raw, key=lambda t: -packed[t])},
    }


def record_footprint(specs: Sequence[Any], config: Config | None = None) -> dict[str, Any]:
    """Simulate each scene, run the pipeline recording to a temporary log; its footprint.

    Parameters
    ----------
    specs : sequence of SceneSpec
    config : Config, optional

    Returns
    -------
    dict
        :func:`log_footprint` of the log, and ``scenes`` (kind, sensor, size of each).
    """
    from boxloc.pipeline import find_graspable_surfaces
    from boxloc.simulate import simulate
    from recorder.mcap.sink import McapRecorder

    cfg = config or Config()
    with tempfile.TemporaryDirectory(prefix="boxloc-footprint-") as tmp:
        path = Path(tmp) / "footprint.mcap"
        with McapRecorder(path, config=cfg, fsync=False) as rec:
            for i, spec in enumerate(specs):
                scan = dataclasses.replace(simulate(spec).scan, index=i)
                find_graspable_surfaces(scan, cfg, observer=rec)
        out = log_footprint(path)
    out["scenes"] = [{"kind": s.kind, "sensor": s.sensor, "size": f"{s.width}x{s.height}"}
                     for s in specs]
    return out


def suite(name: str, n: int, seed: int = 0) -> list[Any]:
    """``n`` scenes of ``scene_suite`` (640x480), or of ``matrix_suite`` with every scene
    brought to 640x480 (the focal length scaled with it, so each sensor keeps its field of
    view)."""
    from boxloc.simulate import matrix_suite, scene_suite

    if name == "scene":
        return scene_suite(n, seed)
    return [dataclasses.replace(s, width=640, height=480, f=round(s.f * 640 / s.width, 3))
            for s in matrix_suite(n, seed)]


def format_table(fp: dict[str, Any]) -> str:
    """The footprint as a text table: kB per scan by channel, and the totals."""
    total = sum(c["zstd"] for c in fp["channels"].values()) or 1.0
    lines = [f"{'channel':26s} {'raw kB':>9s} {'zstd kB':>9s} {'share':>6s}"]
    for topic, c in fp["channels"].items():
        lines.append(f"{topic:26s} {c['raw'] / 1e3:9.1f} {c['zstd'] / 1e3:9.1f} "
                     f"{100 * c['zstd'] / total:5.1f}%")
    sb = fp["scan_bytes"] or [0]
    lines.append(f"{fp['scans']} scans: {fp['bytes_per_scan'] / 1e6:.3f} MB per scan (file / "
                 f"scans); a scan's chunk: median {statistics.median(sb) / 1e6:.3f} MB, "
                 f"max {max(sb) / 1e6:.3f} MB")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m recorder.mcap.footprint``: print the footprint table of simulated scans."""
    ap = argparse.ArgumentParser(prog="python -m recorder.mcap.footprint", description=__doc__
                                 .split("\n\n")[0])
    ap.add_argument("--suite", choices=["scene", "matrix"], default="scene")
    ap.add_argument("--n", type=int, default=8, help="scenes [default: 8]")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--log", type=Path, default=None,
                    help="measure this log instead of simulating scenes")
    args = ap.parse_args(argv)
    if args.log is not None:
        from boxloc.errors import BoxlocError

        try:
            fp = log_footprint(args.log)
        except (BoxlocError, OSError) as e:
            msg = str(e).splitlines()[0] if str(e) else type(e).__name__
            print(f"footprint: error: {msg}", file=sys.stderr)
            return 2
    else:
        if args.n < 1:
            ap.error("--n must be at least 1")
        from boxloc.evaluate.matrix_bench import matrix_config

        specs = suite(args.suite, args.n, args.seed)
        # the matrix as its benchmark runs it: the defaults and the site's box range
        cfg = matrix_config(specs)[0] if args.suite == "matrix" else None
        fp = record_footprint(specs, cfg)
    print(format_table(fp))
    return 0


if __name__ == "__main__":
    sys.exit(main())

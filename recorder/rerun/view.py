"""``boxloc view LOG.mcap [--save FILE.rrd]``: one of our logs as a Rerun recording.

Every recorded scan and product goes into the entity tree of :mod:`recorder.rerun.sink`,
with the default blueprint; the recording then opens in a viewer or goes to a file. The
recording id derives from the log's content and the version that wrote it, so viewing the
same log again replaces its recording in a running viewer rather than adding a copy.
"""

from __future__ import annotations

import hashlib
import os
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import click
import rerun as rr

from boxloc.scan import Scan
from recorder.rerun.sink import (
    RerunSink,
    entity,
    log_recording,
    open_rerun_sink,
    parse_rerun_target,
    recording_id_for,
    set_scan_time,
)

#: scans whose pipeline failed: the error, as a text log
ERRORS = "errors"


def log_identity(path: str | os.PathLike[str]) -> str:
    """A content digest of a log file (reading it is cheap next to decoding it)."""
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return f"mcap-blake2b:{h.hexdigest()}"


def _pairs(log: Any, rec: rr.RecordingStream, prefix: str
           ) -> Iterator[tuple[Scan, Mapping[str, Any]]]:
    for r in log.scans():
        if r.error:
            set_scan_time(rec, r.scan)
            e = r.error
            rec.log(entity(prefix, ERRORS), rr.TextLog(
                f"scan {r.scan.index}: {e.get('stage') or 'pipeline'} failed: "
                f"{e.get('error_type', '')}: {e.get('message', '')}", level=rr.TextLogLevel.ERROR))
        yield r.scan, {**r.products, "timing": r.timing_ms}


def view_log(
    path: str | os.PathLike[str], target: str, *, allow_truncated: bool = False,
    prefix: str = "",
) -> tuple[RerunSink, int]:
    """Log every scan of the MCAP log ``path`` into a Rerun sink opened for ``target``.

    Returns the (still open) sink and the number of scans; the caller closes the sink,
    after watching a served viewer if it wants to.

    Raises
    ------
    InputError
        A bad target. :class:`boxloc.errors.LogError`: an unreadable log.
    """
    from recorder.mcap.log import open_log

    parse_rerun_target(target)  # refuse a bad target before reading anything
    log = open_log(path, allow_truncated=allow_truncated)
    rid = recording_id_for(log_identity(path), log.version)
    sink = open_rerun_sink(target, recording_id=rid, prefix=prefix, threaded=False)
    if sink is None:
        raise click.UsageError("nothing to do: the target is none")
    try:
        sink.rec.send_recording_name(Path(path).name)
        n = log_recording(sink.rec, _pairs(log, sink.rec, prefix), prefix=prefix,
                          max_points=sink.max_points)
        sink.flush()
    except BaseException:
        sink.close()
        raise
    return sink, n


@click.command("view")
@click.argument("log_path", metavar="LOG.mcap", type=click.Path(dir_okay=False))
@click.option("--save", "save_path", metavar="FILE.rrd", default=None,
              help="Write the recording to FILE.rrd (no viewer unless --rerun asks for one).")
@click.option("--rerun", "target", metavar="TARGET", default=None,
              help="Where else to send it: spawn, connect URL, serve (web viewer on "
                   "127.0.0.1), or several joined by commas. Default: spawn, unless --save.")
@click.option("--allow-truncated", is_flag=True,
              help="Show a log without summary up to its last good record.")
def view(log_path: str, save_path: str | None, target: str | None,
         allow_truncated: bool) -> None:
    """Turn LOG.mcap into a Rerun recording with the full entity tree and blueprint,
    then open it in a viewer or save it."""
    parts = [f"save:{save_path}"] if save_path else []
    if target:
        parts.append(target)
    if not parts:
        parts.append("spawn")
    sink, n = view_log(log_path, ",".join(parts), allow_truncated=allow_truncated)
    try:
        where = ", ".join(f"{k} {v}" for k, v in sink.urls.items() if k != "command")
        click.echo(f"boxloc view: {n} scan(s) of {log_path} -> {where or 'viewer'}", err=True)
        if "web" in sink.urls:
            click.echo(f"serving on 127.0.0.1; open {sink.urls['web']} (Ctrl-C stops)", err=True)
            while True:
                time.sleep(1.0)
    finally:
        sink.close()

"""Baseline and candidate in one Rerun recording, next to each other, with what differs marked.

Both runs go into one recording on the same ``scan`` timeline, each under its own prefix
(the entity tree of :mod:`recorder.rerun.sink`)::

    /baseline/...                   the baseline log, scan by scan
    /candidate/...                  the candidate log
    /baseline/world/diff            red: surfaces of the baseline the candidate lost
                                    orange: surfaces that moved (labelled with the change)
                                    magenta: surfaces whose pick failed
    /candidate/world/diff           red: surfaces new in the candidate; orange: moved
    /diff                           one text line per scan: what differs, regressions as ERROR

The markers hang under each run's ``world`` so they share its frame; they are cleared at
every scan, so a marker belongs to its scan only. The blueprint shows the two runs side by
side (image with edges and projected surfaces, 3D view, plots), the differences below.

Used by ``boxloc diff --rerun ...`` and by ``boxloc replay --rerun ...``.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from boxloc.errors import InputError
from boxloc.scan import Scan
from recorder.rerun.blueprint import counts_view, tests_view, timing_view, world_view
from recorder.rerun.sink import (
    EDGE_IMAGE,
    LINES,
    RANGE,
    SCAN,
    SURFACES,
    TIMELINE_CAPTURE,
    TIMELINE_SCAN,
    RerunSink,
    entity,
    log_recording,
    open_rerun_sink,
    parse_rerun_target,
    recording_id_for,
)
from replay.diff import LogDiff, ScanDiff, Tolerances, diff_logs

BASELINE = "baseline"
CANDIDATE = "candidate"
#: markers of what differs, under each run's world (sensor frame)
DIFF_MARKERS = "world/diff"
#: the per-scan text lines of the differences (top level: one for both runs)
DIFF_LOG = "/diff"
#: the errors of scans whose pipeline failed, under each prefix
ERRORS = "errors"

_GONE = (235, 40, 40)       # removed (baseline) / added (candidate)
_MOVED = (255, 150, 0)
_PICK_FAILED = (230, 0, 230)


def side_by_side_blueprint() -> rrb.Blueprint:
    """Two columns (baseline, candidate): image + edges + projected surfaces and markers,
    3D view, plots; the differences as a text log underneath."""

    def column(prefix: str) -> rrb.Vertical:
        image = rrb.Spatial2DView(
            origin=entity(prefix, SCAN),
            contents=[f"+ {entity(prefix, RANGE)}", f"+ {entity(prefix, EDGE_IMAGE)}",
                      f"+ {entity(prefix, SURFACES)}", f"+ {entity(prefix, LINES)}",
                      f"+ {entity(prefix, DIFF_MARKERS)}/**"],
            name=f"{prefix}: range + edges",
        )
        return rrb.Vertical(
            image,
            world_view(prefix, name=f"{prefix}: 3D"),
            rrb.Tabs(counts_view(prefix, name=f"{prefix}: counts"),
                     tests_view(prefix, "median_ratio",
                                name=f"{prefix}: median statistic / critical"),
                     timing_view(prefix, name=f"{prefix}: timing [ms]")),
            row_shares=[2, 3, 2],
        )

    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(column(BASELINE), column(CANDIDATE)),
            rrb.TextLogView(origin=DIFF_LOG, name="differences"),
            row_shares=[6, 1],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=TIMELINE_SCAN),
    )


def _set_time(rec: rr.RecordingStream, index: int, capture_time_ns: int) -> None:
    """The timelines of one scan (as :func:`recorder.rerun.sink.set_scan_time`)."""
    rec.set_time(TIMELINE_SCAN, sequence=int(index))
    if capture_time_ns > 0:
        rec.set_time(TIMELINE_CAPTURE, timestamp=np.datetime64(int(capture_time_ns), "ns"))
    else:
        rec.disable_timeline(TIMELINE_CAPTURE)


class _Stash:
    """What the markers need of each scan, kept while the products stream into Rerun."""

    def __init__(self) -> None:
        self.times: dict[int, int] = {}
        self.surfaces: dict[int, Any] = {}

    def pairs(self, log: Any, rec: rr.RecordingStream, prefix: str
              ) -> Iterator[tuple[Scan, Mapping[str, Any]]]:
        for r in log.scans():
            idx = int(r.scan.index)
            self.times[idx] = int(r.scan.capture_time_ns)
            if r.surfaces is not None:
                self.surfaces[idx] = r.surfaces
            if r.error:
                _set_time(rec, idx, int(r.scan.capture_time_ns))
                e = r.error
                rec.log(entity(prefix, ERRORS), rr.TextLog(
                    f"scan {idx}: {e.get('stage') or 'pipeline'} failed: "
                    f"{e.get('error_type', '')}: {e.get('message', '')}",
                    level=rr.TextLogLevel.ERROR))
            yield r.scan, {**r.products, "timing": r.timing_ms}


def _closed(corners: np.ndarray) -> np.ndarray:
    return np.concatenate([corners, corners[:, :1]], axis=1)


def _markers(rec: rr.RecordingStream, prefix: str, surfaces: Any,
             marks: list[tuple[int, tuple[int, int, int], str]]) -> None:
    """Outline and centre of each marked surface, labelled."""
    path = entity(prefix, DIFF_MARKERS)
    rec.log(path, rr.Clear(recursive=True))
    marks = [m for m in marks if surfaces is not None and 0 <= m[0] < len(surfaces)]
    if not marks:
        return
    ids = np.array([m[0] for m in marks], np.int64)
    colors = np.array([m[1] for m in marks], np.uint8)
    labels = [m[2] for m in marks]
    corners = np.asarray(surfaces.corners, np.float64)[ids]
    rec.log(f"{path}/outlines", rr.LineStrips3D(_closed(corners), colors=colors,
                                                radii=rr.Radius.ui_points(6.0),
                                                labels=labels, show_labels=True))
    rec.log(f"{path}/centers", rr.Points3D(np.asarray(surfaces.centers, np.float64)[ids],
                                           colors=colors, radii=rr.Radius.ui_points(9.0)))


def _scan_marks(sd: ScanDiff) -> tuple[list[Any], list[Any]]:
    base: list[Any] = []
    cand: list[Any] = []
    s = sd.surfaces
    for i in s.removed:
        base.append((i, _GONE, f"#{i} removed"))
    for j in s.added:
        cand.append((j, _GONE, f"#{j} added"))
    for p in s.moved:
        txt = (f"moved {p.dcenter_mm:.0f} mm, {p.dangle_deg:.1f} deg, "
               f"w {p.dwidth_mm:+.0f}, l {p.dlength_mm:+.0f} mm")
        base.append((p.base, _MOVED, f"#{p.base} {txt}"))
        cand.append((p.candidate, _MOVED, f"#{p.candidate} {txt}"))
    for pk in sd.picks:
        if not pk["ok"]:
            base.append((pk["surface"], _PICK_FAILED, f"#{pk['surface']} pick failed"
                         + (f": {pk['reason']}" if pk["reason"] else "")))
    return base, cand


def _scan_line(sd: ScanDiff) -> tuple[str, Any]:
    if sd.status == "identical" and not sd.differences:
        return f"scan {sd.scan}: identical", rr.TextLogLevel.DEBUG
    msgs = [("REGRESSION " if d.regression else "") + d.message for d in sd.differences]
    level = rr.TextLogLevel.ERROR if sd.regression or sd.status == "error" else (
        rr.TextLogLevel.WARN if sd.differences else rr.TextLogLevel.INFO)
    head = f"scan {sd.scan}: {sd.status}" + (f" ({sd.error})" if sd.error else "")
    return head + ("; " + "; ".join(msgs[:12]) if msgs else ""), level


def log_diff_markers(rec: rr.RecordingStream, scan_diffs: Iterable[ScanDiff],
                     times: Mapping[int, int], base_surfaces: Mapping[int, Any],
                     cand_surfaces: Mapping[int, Any]) -> int:
    """Log the markers and the text line of every scan diff; returns how many scans differ."""
    n = 0
    for sd in scan_diffs:
        _set_time(rec, sd.scan, times.get(sd.scan, 0))
        line, level = _scan_line(sd)
        rec.log(DIFF_LOG, rr.TextLog(line, level=level))
        bm, cm = _scan_marks(sd)
        _markers(rec, BASELINE, base_surfaces.get(sd.scan), bm)
        _markers(rec, CANDIDATE, cand_surfaces.get(sd.scan), cm)
        n += bool(sd.differences) or sd.status not in ("identical", "equivalent")
    return n


def log_side_by_side(
    base_log: str | os.PathLike[str] | Any,
    cand_log: str | os.PathLike[str] | Any,
    target: str | None = None,
    diffs: LogDiff | Iterable[ScanDiff] | None = None,
    *,
    rerun: str | None = None,
    tolerances: Tolerances | None = None,
    keep_open: bool = False,
    max_points: int = 20_000,
) -> RerunSink:
    """Log two runs of the same scans side by side in one Rerun recording.

    Parameters
    ----------
    base_log, cand_log : path or recorder.mcap.log.Log
        The baseline and the candidate log.
    target : str
        Where the recording goes, as for :func:`recorder.rerun.sink.open_rerun_sink`:
        ``spawn``, ``save:FILE.rrd`` (or ``save FILE.rrd``), ``connect URL``, ``serve``,
        or several joined by commas.
    rerun : str, optional
        The same as ``target`` (the name of the ``--rerun`` option), for callers that pass
        it by keyword.
    diffs : LogDiff or iterable of ScanDiff, optional
        The comparison to mark; computed with :func:`replay.diff.diff_logs` if not given.
    tolerances : Tolerances, optional
        For computing the diff.
    keep_open : bool
        Return the sink open (a served viewer lives as long as it); by default it is
        closed (files finalized) before returning.

    Returns
    -------
    RerunSink
        ``urls`` says where to look.

    Raises
    ------
    InputError
        A bad target (checked before anything is read).
    """
    from recorder.mcap.log import Log, open_log
    from recorder.rerun.view import log_identity

    if target is None:
        target = rerun
    elif rerun is not None and rerun != target:
        raise InputError("give the Rerun target once (target or rerun), not two")
    if target is None:
        raise InputError("no Rerun target given (spawn, save:FILE.rrd, connect URL, serve)")
    parse_rerun_target(target)
    la = base_log if isinstance(base_log, Log) else open_log(base_log)
    lb = cand_log if isinstance(cand_log, Log) else open_log(cand_log)
    if diffs is None:
        diffs = diff_logs(la.path, lb.path, tolerances)
    scan_diffs = list(diffs.scans if isinstance(diffs, LogDiff) else diffs)
    rid = recording_id_for(f"{log_identity(la.path)}+{log_identity(lb.path)}",
                           f"side-by-side/{la.version}/{lb.version}")
    sink = open_rerun_sink(target, recording_id=rid, threaded=False,
                           blueprint=side_by_side_blueprint(), max_points=max_points)
    if sink is None:
        raise InputError("the Rerun target is none: nothing to log to")
    try:
        rec = sink.rec
        rec.send_recording_name(f"{Path(la.path).name} vs {Path(lb.path).name}")
        sa, sb = _Stash(), _Stash()
        log_recording(rec, sa.pairs(la, rec, BASELINE), prefix=BASELINE,
                      max_points=max_points)
        log_recording(rec, sb.pairs(lb, rec, CANDIDATE), prefix=CANDIDATE,
                      max_points=max_points)
        log_diff_markers(rec, scan_diffs, {**sb.times, **sa.times}, sa.surfaces, sb.surfaces)
        sink.flush()
    except BaseException:
        sink.close()
        raise
    if not keep_open:
        sink.close()
    return sink

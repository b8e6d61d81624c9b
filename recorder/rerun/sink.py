"""The Rerun view of a run: one ``log_*`` per product, and an observer that calls them.

Entity tree
-----------
It mirrors the data flow. Every path may hang under a prefix (``baseline/``, ``candidate/``)
so that two runs can share one recording::

    /  (or /<prefix>)               ViewCoordinates RIGHT_HAND_Z_UP (static): the world frame
    scan                            Transform3D sensor -> world; Pinhole (static intrinsics)
    scan/range                      DepthImage, metres along each pixel's ray, 0 = no return
    scan/edges                      SegmentationImage of EdgeKind (AnnotationContext, static)
    world                           Transform3D sensor -> world; everything under it is in the
                                    sensor frame, as the products are
    world/points                    the organized cloud, decimated
    world/edges/points              edge points, class id = EdgeKind
    world/lines                     3D segments, coloured by EdgeKind
    world/vertices                  vertices; world/vertices/axes: their d1, d2
    world/hypotheses/accepted       rectangles of the attempts that passed verification
    world/hypotheses/rejected       rectangles of the attempts that failed (labels say why)
    world/surfaces                  graspable surfaces, labelled "#id pick k"
    world/surfaces/grasp            grasp points; world/surfaces/normals: the normals
    stats/tests/<measure>           per scan, one series per test kind (TestKind order,
                                    NaN where the scan made no such test): n_tested,
                                    n_accepted, accepted_fraction, median_ratio and
                                    max_ratio of statistic / critical
    stats/counts/<what>             per scan: edge points, lines, vertices, hypotheses, ...
    stats/noise/<what>              per scan: the range sigma of the model in use at the
                                    scan's median range (mm), its row_corr, the NOISE_FIT z,
                                    the source (0 config, 1 scan, 2 fallback); text: how
    stats/selection/objective       the MDL objective m^T Q m
    stats/timing/<stage>            wall-clock per stage, milliseconds

The test statistics are one entity per measure, a batch of one value per test kind in a
fixed order, named by a static ``SeriesLines``: one plot per measure shows one series per
kind, and a scan costs five calls, not five per kind (about 160: nearly half of the sink's
work when each was its own entity). They are logged once per scan, over all of its stages' tests.

Frames
------
The world is the robot base frame when the scan has ``sensor_to_base``; otherwise it is the
sensor frame turned so that the scan's "up" (``-z``, toward a sensor looking down) is +z.
The camera (``scan``) and the sensor-frame products (``world``) carry the same transform,
so the image and the 3D view line up.

Timelines
---------
``scan`` (sequence = ``scan.index``) and ``capture_time`` (timestamp, from
``scan.capture_time_ns``; left out when it is 0, i.e. unknown). Rerun's wall-clock
``log_time`` is turned off: a recording of the same log is the same recording.
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import queue
import re
import shlex
import shutil
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import numpy as np
import numpy.typing as npt
import rerun as rr

from boxloc.config import Config
from boxloc.errors import BoxlocError, InputError
from boxloc.observer import NullObserver
from boxloc.products import (
    STAGES,
    AmbiguityReason,
    AmbiguousSet,
    EdgeKind,
    EdgeMap,
    HeightSource,
    HypothesisSet,
    LineSet,
    NoiseEstimate,
    NoiseSource,
    Result,
    Selection,
    SurfaceSet,
    Verification,
    VerifyReason,
    VertexSet,
)
from boxloc.scan import NoiseModel, PinholeModel, Scan, SensorModel
from boxloc.stats import TestKind, TestTable

# --- entity paths --------------------------------------------------------------------------

SCAN = "scan"
RANGE = "scan/range"
EDGE_IMAGE = "scan/edges"
WORLD = "world"
POINTS = "world/points"
EDGES_3D = "world/edges"
EDGE_POINTS = "world/edges/points"
LINES = "world/lines"
VERTICES = "world/vertices"
VERTEX_AXES = "world/vertices/axes"
HYPOTHESES = "world/hypotheses"
HYP_ACCEPTED = "world/hypotheses/accepted"
HYP_REJECTED = "world/hypotheses/rejected"
SURFACES = "world/surfaces"
SURFACE_GRASP = "world/surfaces/grasp"
SURFACE_NORMALS = "world/surfaces/normals"
#: flat regions not split into boxes (the result's ``ambiguous``): beside the surfaces
AMBIGUOUS = "world/ambiguous"
STATS_TESTS = "stats/tests"
STATS_COUNTS = "stats/counts"
STATS_SELECTION = "stats/selection"
STATS_NOISE = "stats/noise"
STATS_TIMING = "stats/timing"

#: test measures, one entity each under ``stats/tests/<measure>``, a series per kind
TEST_MEASURES = ("n_tested", "n_accepted", "accepted_fraction", "median_ratio", "max_ratio")
#: the kinds in the order of each measure's batch (its series)
TEST_SERIES = tuple(k.name for k in TestKind)
_SERIES_INDEX = {k.value: i for i, k in enumerate(TestKind)}  # a kind's value -> series

TIMELINE_SCAN = "scan"
TIMELINE_CAPTURE = "capture_time"

APP_ID = "boxloc"
#: a cloud larger than this is decimated on a regular pixel grid before logging
DEFAULT_MAX_POINTS = 20_000
#: length of the vertex direction arrows, metres
AXIS_LENGTH = 0.05

# --- colours (RGB) -------------------------------------------------------------------------

_EDGE_COLORS: dict[str, tuple[int, int, int]] = {
    "JUMP": (255, 210, 0),
    "CREASE_CONVEX": (0, 200, 255),
    "CREASE_CONCAVE": (255, 60, 200),
    "GROOVE": (130, 255, 110),
}
_FALLBACK = (200, 200, 200)
_ACCEPTED = (60, 220, 100)
_REJECTED = (230, 70, 60)
_VERTEX = (255, 255, 255)
#: ambiguous regions: magenta, thick and dashed-looking by their own colour (not graspable)
_AMBIGUOUS = (255, 0, 230)
_AXIS_D1 = (255, 140, 40)
_AXIS_D2 = (40, 160, 255)
#: surfaces, by pick order (cycled): white first, then hues unlike the edge kinds' and the
#: range colormap's
_SURFACE_PALETTE = np.array(
    [(255, 255, 255), (255, 150, 200), (190, 150, 255), (255, 190, 120), (150, 255, 230)],
    dtype=np.uint8,
)

# Rows 0-2 of the "look down" frame: world z = -sensor z (the scan's default up),
# world x = sensor x, world y = -sensor y (right-handed).
_LOOK_DOWN = np.diag([1.0, -1.0, -1.0, 1.0])


def entity(prefix: str, path: str) -> str:
    """``path`` under ``prefix`` (``""`` for none), as an absolute entity path."""
    p = prefix.strip("/")
    return f"/{p}/{path}" if p else f"/{path}"


def _root(prefix: str) -> str:
    p = prefix.strip("/")
    return f"/{p}" if p else "/"


def sensor_to_world(scan: Scan) -> np.ndarray:
    """The 4x4 pose of the sensor in the world frame of the view (see the module notes)."""
    if scan.sensor_to_base is not None:
        return np.asarray(scan.sensor_to_base, dtype=np.float64)
    return _LOOK_DOWN.copy()


def _edge_color(kind: int) -> tuple[int, int, int]:
    try:
        return _EDGE_COLORS.get(EdgeKind(int(kind)).name, _FALLBACK)
    except ValueError:
        return _FALLBACK


@functools.cache
def _edge_lut() -> np.ndarray:
    """Every uint8 edge kind's colour, (256, 3) uint8: built once, not per scan (256 enum
    lookups cost about 2 ms)."""
    lut = np.array([_edge_color(k) for k in range(256)], dtype=np.uint8)
    lut.flags.writeable = False
    return lut


def _edge_colors(kinds: np.ndarray) -> np.ndarray:
    return _edge_lut()[np.asarray(kinds, dtype=np.uint8)]


def _closed(corners: np.ndarray) -> np.ndarray:
    """(n, 4, 3) rectangle corners -> (n, 5, 3) closed strips."""
    return np.concatenate([corners, corners[:, :1]], axis=1)


def _strips(a: np.ndarray) -> npt.NDArray[np.float32]:
    """Line strips (n, k, 3) as Rerun stores them (float32: the same values it logs)."""
    return np.asarray(a, np.float32)


def _finite_rows(a: np.ndarray) -> np.ndarray:
    return np.isfinite(a).all(axis=tuple(range(1, a.ndim)))


def _any_values(**columns: Any) -> list[rr.AnyValues]:
    """Per-instance values to show on hover; nothing for an empty batch (Rerun refuses)."""
    if all(np.size(v) == 0 for v in columns.values()):
        return []
    return [rr.AnyValues(**columns)]


def _scalar(rec: rr.RecordingStream, path: str, value: float) -> None:
    if math.isfinite(value):
        rec.log(path, rr.Scalars(float(value)))


# --- timelines and static setup ------------------------------------------------------------


def set_scan_time(rec: rr.RecordingStream, scan: Scan) -> None:
    """Set the ``scan`` and ``capture_time`` timelines for everything logged next.

    The capture time is left out when it is 0 (unknown), rather than pretending 1970.
    """
    rec.set_time(TIMELINE_SCAN, sequence=int(scan.index))
    if scan.capture_time_ns > 0:
        rec.set_time(TIMELINE_CAPTURE, timestamp=np.datetime64(int(scan.capture_time_ns), "ns"))
    else:
        rec.disable_timeline(TIMELINE_CAPTURE)


def log_setup(rec: rr.RecordingStream, *, prefix: str = "") -> None:
    """Static data: the world's axes convention, the edge-kind annotation contexts and the
    test measures' series names."""
    rec.log(_root(prefix), rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    infos = [rr.AnnotationInfo(id=0, label="none", color=(0, 0, 0, 0))]
    for k in EdgeKind:
        if k != EdgeKind.NONE:
            infos.append(rr.AnnotationInfo(id=int(k), label=k.name.lower(),
                                           color=_edge_color(int(k))))
    ctx = rr.AnnotationContext(infos)
    rec.log(entity(prefix, EDGE_IMAGE), ctx, static=True)
    rec.log(entity(prefix, EDGES_3D), ctx, static=True)
    for measure in TEST_MEASURES:
        rec.log(entity(prefix, f"{STATS_TESTS}/{measure}"),
                rr.SeriesLines(names=list(TEST_SERIES)), static=True)


def log_camera(
    rec: rr.RecordingStream, sensor: SensorModel, *, prefix: str = "",
    image_plane_distance: float = 0.3,
) -> None:
    """The camera intrinsics, static. A ray-table sensor has none: its image stays 2D.

    Parameters
    ----------
    image_plane_distance : float
        Where the 3D view draws the image plane of the frustum, metres (cosmetic).
    """
    if isinstance(sensor, PinholeModel):
        rec.log(
            entity(prefix, SCAN),
            rr.Pinhole(image_from_camera=sensor.K, resolution=[sensor.width, sensor.height],
                       camera_xyz=rr.ViewCoordinates.RDF,
                       image_plane_distance=float(image_plane_distance)),
            static=True,
        )


# --- one log_* per product -----------------------------------------------------------------


def _decimated_points(scan: Scan, max_points: int) -> np.ndarray:
    """Valid points on a regular pixel grid, at most about ``max_points``, (n, 3) float32."""
    n_valid = int(np.count_nonzero(scan.valid))
    step = max(1, math.ceil(math.sqrt(n_valid / max(max_points, 1))))
    P = scan.points[::step, ::step].reshape(-1, 3)
    return P[np.isfinite(P).all(axis=1)]


def _height_colors(P_sensor: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Grey levels by height in the world, so the pile reads as a relief."""
    if P_sensor.shape[0] == 0:
        return np.zeros((0, 3), np.uint8)
    z = P_sensor.astype(np.float64) @ T[2, :3] + T[2, 3]
    lo, hi = np.percentile(z, [2.0, 98.0])
    t = np.clip((z - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    g = (70 + 170 * t).astype(np.uint8)
    return np.stack([g, g, g], axis=1)


def log_scan(
    rec: rr.RecordingStream, scan: Scan, *, prefix: str = "",
    max_points: int = DEFAULT_MAX_POINTS,
) -> None:
    """The scan: sensor pose, range image, decimated cloud; clears last scan's results.

    Parameters
    ----------
    scan : Scan
        Range (H, W) float32 metres; its points are in the sensor frame.
    max_points : int
        Upper bound (about) on the points of ``world/points``.
    """
    # Hypotheses and surfaces vary in number and sub-entities from scan to scan.
    rec.log(entity(prefix, HYPOTHESES), rr.Clear(recursive=True))
    rec.log(entity(prefix, SURFACES), rr.Clear(recursive=True))
    T = sensor_to_world(scan)
    tf = rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3])
    rec.log(entity(prefix, SCAN), tf)
    rec.log(entity(prefix, WORLD), tf)
    rng = np.nan_to_num(scan.range, nan=0.0)  # Rerun's "no depth" is 0
    valid = scan.range[scan.valid]
    depth_range = (float(valid.min()), float(valid.max())) if valid.size else None
    rec.log(entity(prefix, RANGE),
            rr.DepthImage(rng, meter=1.0, depth_range=depth_range, colormap="turbo"))
    P = _decimated_points(scan, max_points)
    rec.log(entity(prefix, POINTS),
            rr.Points3D(P, colors=_height_colors(P, T), radii=rr.Radius.ui_points(1.5)))


def log_tests(rec: rr.RecordingStream, tests: TestTable | Sequence[TestTable], *,
              prefix: str = "") -> None:
    """Per test kind: tests made, accepted, and the median/max of statistic / critical.

    Each measure is one batch over :data:`TEST_SERIES` (NaN for a kind not tested), so call
    it once per scan with every stage's tests: a second call at the same time would add a
    second point to each series.
    """
    tables = [t for t in ([tests] if isinstance(tests, TestTable) else tests) if len(t)]
    if not tables:
        return
    kind = np.concatenate([t.kind for t in tables]).astype(np.int64)
    accepted = np.concatenate([t.accepted for t in tables]).astype(bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.concatenate([np.asarray(t.statistic, np.float64)
                                / np.asarray(t.critical, np.float64) for t in tables])
    values = np.full((len(TEST_MEASURES), len(TEST_SERIES)), np.nan)
    # each kind's rows as one slice of the rows sorted by kind (not a mask per kind); the
    # median and maximum of a kind's ratios do not depend on their order
    order = np.argsort(kind, kind="stable")
    kinds, starts = np.unique(kind[order], return_index=True)
    ends = np.r_[starts[1:], len(order)]
    accepted, ratio = accepted[order], ratio[order]
    for k, a, b in zip(kinds, starts, ends):
        if int(k) not in _SERIES_INDEX:
            continue  # a kind this version does not know (a newer log): no series for it
        n = int(b - a)
        n_acc = int(np.count_nonzero(accepted[a:b]))
        r = ratio[a:b]
        r = r[np.isfinite(r)]
        col = _SERIES_INDEX[int(k)]
        values[:, col] = (n, n_acc, n_acc / n, np.median(r) if r.size else np.nan,
                          r.max() if r.size else np.nan)
    base = entity(prefix, STATS_TESTS)
    for measure, row in zip(TEST_MEASURES, values):
        rec.log(f"{base}/{measure}", rr.Scalars(row))


def log_edges(rec: rr.RecordingStream, edges: EdgeMap, *, prefix: str = "") -> None:
    """The edge map as a segmentation over the range image, and the 3D edge points."""
    rec.log(entity(prefix, EDGE_IMAGE), rr.SegmentationImage(edges.labels, opacity=0.9,
                                                             draw_order=10.0))
    rec.log(
        entity(prefix, EDGE_POINTS),
        rr.Points3D(edges.points, class_ids=edges.kinds, radii=rr.Radius.ui_points(1.5)),
        *_any_values(edge_id=np.arange(len(edges), dtype=np.int32),
                     strength=np.asarray(edges.strength, np.float64)),
    )
    _scalar(rec, entity(prefix, f"{STATS_COUNTS}/edge_points"), len(edges))


def log_lines(rec: rr.RecordingStream, lines: LineSet, *, prefix: str = "") -> None:
    """3D segments from the Hough stage, coloured by the edge kind of their support."""
    strips = np.stack([lines.starts, lines.ends], axis=1) if len(lines) else np.zeros((0, 2, 3))
    rec.log(
        entity(prefix, LINES),
        rr.LineStrips3D(_strips(strips), colors=_edge_colors(lines.kinds),
                        radii=rr.Radius.ui_points(2.0),
                        labels=[f"L{i}" for i in range(len(lines))], show_labels=False),
        *_any_values(line_id=np.arange(len(lines), dtype=np.int32),
                     n_support=np.asarray(lines.n_support, np.int32),
                     direction_votes=np.asarray(lines.direction_votes, np.float64),
                     position_votes=np.asarray(lines.position_votes, np.float64)),
    )
    _scalar(rec, entity(prefix, f"{STATS_COUNTS}/lines"), len(lines))
    _scalar(rec, entity(prefix, f"{STATS_COUNTS}/hough_trials"), lines.n_trials)


def log_vertices(rec: rr.RecordingStream, vertices: VertexSet, *, prefix: str = "") -> None:
    """Vertices (orthogonal line pairs meeting at an end) and their two directions."""
    n = len(vertices)
    rec.log(
        entity(prefix, VERTICES),
        rr.Points3D(vertices.points, colors=_VERTEX, radii=rr.Radius.ui_points(4.0),
                    labels=[f"V{i}" for i in range(n)], show_labels=False),
        *_any_values(vertex_id=np.arange(n, dtype=np.int32),
                     line_a=np.asarray(vertices.line_a, np.int32),
                     line_b=np.asarray(vertices.line_b, np.int32)),
    )
    origins = np.concatenate([vertices.points, vertices.points])
    vectors = AXIS_LENGTH * np.concatenate([vertices.d1, vertices.d2])
    colors = np.array([_AXIS_D1] * n + [_AXIS_D2] * n, dtype=np.uint8).reshape(-1, 3)
    rec.log(entity(prefix, VERTEX_AXES),
            rr.Arrows3D(origins=origins, vectors=vectors, colors=colors,
                        radii=rr.Radius.ui_points(1.0)))
    _scalar(rec, entity(prefix, f"{STATS_COUNTS}/vertices"), n)


def attempt_corners(hypotheses: HypothesisSet) -> np.ndarray:
    """Corners of every attempt's rectangle, (k, 4, 3) metres (origin, +x, +x+y, +y)."""
    h = np.asarray(hypotheses.att_hypothesis, dtype=np.intp)
    o, x, y = hypotheses.origins[h], hypotheses.x_axis[h], hypotheses.y_axis[h]
    w = np.asarray(hypotheses.att_width, np.float64)[:, None]
    ln = np.asarray(hypotheses.att_length, np.float64)[:, None]
    return np.stack([o, o + w * x, o + w * x + ln * y, o + ln * y], axis=1)


def _reason_name(r: int) -> str:
    try:
        return VerifyReason(int(r)).name
    except ValueError:
        return str(int(r))


def log_hypotheses(
    rec: rr.RecordingStream, hypotheses: HypothesisSet,
    verification: Verification | None = None, *, prefix: str = "",
) -> None:
    """Every attempt's rectangle, under ``accepted`` or ``rejected`` by its verification.

    Without ``verification`` the verdict is the hypothesis set's own ``att_verified``.
    """
    rec.log(entity(prefix, HYPOTHESES), rr.Clear(recursive=True))
    k = hypotheses.n_attempts
    corners = attempt_corners(hypotheses)
    accepted = np.asarray(hypotheses.att_verified, bool).copy()
    reason = np.where(accepted, int(VerifyReason.ACCEPTED), -1)
    inlier_fraction = np.full(k, np.nan)
    if verification is not None and len(verification):
        j = np.asarray(verification.attempt, np.intp)
        ok = (j >= 0) & (j < k)
        accepted[j[ok]] = np.asarray(verification.accepted, bool)[ok]
        reason[j[ok]] = np.asarray(verification.reason)[ok]
        inlier_fraction[j[ok]] = np.asarray(verification.inlier_fraction)[ok]
    good = _finite_rows(corners)
    for path, sel, color, radius in (
        (HYP_ACCEPTED, accepted & good, _ACCEPTED, 2.0),
        (HYP_REJECTED, ~accepted & good, _REJECTED, 1.0),
    ):
        idx = np.flatnonzero(sel)
        h = np.asarray(hypotheses.att_hypothesis)[idx]
        labels = [
            f"h{int(hh)} a{int(a)} " + ("ok" if r == VerifyReason.ACCEPTED
                                        else (_reason_name(r) if r >= 0 else "unverified"))
            for hh, a, r in zip(h, idx, reason[idx])
        ]
        rec.log(
            entity(prefix, path),
            rr.LineStrips3D(_strips(_closed(corners[idx]) if idx.size else np.zeros((0, 5, 3))),
                            colors=color, radii=rr.Radius.ui_points(radius),
                            labels=labels, show_labels=False),
            *_any_values(hypothesis=h.astype(np.int32), attempt=idx.astype(np.int32),
                         source=np.asarray(hypotheses.att_source, np.int32)[idx],
                         width=np.asarray(hypotheses.att_width, np.float64)[idx],
                         length=np.asarray(hypotheses.att_length, np.float64)[idx],
                         inlier_fraction=inlier_fraction[idx]),
        )
    _scalar(rec, entity(prefix, f"{STATS_COUNTS}/hypotheses"), len(hypotheses))
    _scalar(rec, entity(prefix, f"{STATS_COUNTS}/attempts"), k)


def log_verification(
    rec: rr.RecordingStream, verification: Verification, *, prefix: str = ""
) -> None:
    """The verified count (the rectangles are drawn by :func:`log_hypotheses`; the tests
    with the scan's others, :func:`log_tests`)."""
    _scalar(rec, entity(prefix, f"{STATS_COUNTS}/verified"),
            int(np.count_nonzero(verification.accepted)))


def log_selection(rec: rr.RecordingStream, selection: Selection, *, prefix: str = "") -> None:
    """The MDL selection: candidates, chosen, objective."""
    _scalar(rec, entity(prefix, f"{STATS_COUNTS}/candidates"), len(selection))
    _scalar(rec, entity(prefix, f"{STATS_COUNTS}/chosen"),
            int(np.count_nonzero(selection.chosen)))
    _scalar(rec, entity(prefix, f"{STATS_SELECTION}/objective"), float(selection.objective))


def log_surfaces(rec: rr.RecordingStream, surfaces: SurfaceSet, *, prefix: str = "") -> None:
    """The graspable surfaces, outlined and labelled ``#id pick k``, with grasp points."""
    rec.log(entity(prefix, SURFACES), rr.Clear(recursive=True))
    n = len(surfaces)
    pick = np.asarray(surfaces.pick_order, np.int64)
    colors = _SURFACE_PALETTE[pick % len(_SURFACE_PALETTE)] if n else np.zeros((0, 3), np.uint8)
    corners = np.asarray(surfaces.corners, np.float64)
    rec.log(
        entity(prefix, SURFACES),
        rr.LineStrips3D(_strips(_closed(corners) if n else np.zeros((0, 5, 3))), colors=colors,
                        radii=rr.Radius.ui_points(5.0),
                        labels=[_surface_label(surfaces, i) for i in range(n)],
                        show_labels=True),
        *_any_values(surface_id=np.arange(n, dtype=np.int32), pick_order=pick.astype(np.int32),
                     hypothesis=np.asarray(surfaces.hypothesis, np.int32),
                     score=np.asarray(surfaces.scores, np.float64),
                     width=np.asarray(surfaces.width, np.float64),
                     length=np.asarray(surfaces.length, np.float64),
                     bulge=np.asarray(surfaces.bulge, np.float64),
                     height=np.asarray(surfaces.height, np.float64),
                     height_sigma=np.asarray(surfaces.height_sigma, np.float64),
                     height_source=np.asarray(surfaces.height_source, np.int32),
                     sku=np.asarray(surfaces.sku, np.int32),
                     sku_flagged=np.asarray(surfaces.sku_flagged, bool)),
    )
    rec.log(entity(prefix, SURFACE_GRASP),
            rr.Points3D(surfaces.grasp_points, colors=colors, radii=rr.Radius.ui_points(6.0)))
    rec.log(entity(prefix, SURFACE_NORMALS),
            rr.Arrows3D(origins=surfaces.grasp_points, vectors=0.1 * surfaces.normals,
                        colors=colors, radii=rr.Radius.ui_points(1.5)))
    _scalar(rec, entity(prefix, f"{STATS_COUNTS}/surfaces"), n)


def _surface_label(surfaces: SurfaceSet, i: int) -> str:
    """``#i pick k``, then the box height and its source where measured (``h 250 mm
    side``), and ``NO SKU`` where sizes were listed and none matches."""
    label = f"#{i} pick {int(surfaces.pick_order[i])}"
    h = float(surfaces.height[i])
    if math.isfinite(h):
        try:
            src = HeightSource(int(surfaces.height_source[i])).name.lower()
        except ValueError:
            src = str(int(surfaces.height_source[i]))
        label += f" h {h * 1e3:.0f} mm {src}"
    if bool(surfaces.sku_flagged[i]):
        label += " NO SKU"
    return label


def _ambiguous_label(amb: AmbiguousSet, k: int) -> str:
    """Reason, extent and area of ambiguous region k (as the Foxglove scene labels it)."""
    try:
        reason = AmbiguityReason(int(amb.reason[k])).name.lower().replace("_", " ")
    except ValueError:
        reason = f"reason {int(amb.reason[k])}"
    w, ln = float(amb.width[k]), float(amb.length[k])
    size = (f"{w * 1e3:.0f}x{ln * 1e3:.0f} mm, " if math.isfinite(w) and math.isfinite(ln)
            else "")
    return f"{reason}, {size}{float(amb.area[k]):.3f} m2"


def log_ambiguous(rec: rr.RecordingStream, ambiguous: AmbiguousSet, *,
                  prefix: str = "") -> None:
    """The flat regions the evidence could not split into boxes: outlines in magenta
    (closed line strips, sensor frame), labelled with the reason, extent and area, with
    their hypothesis, attempt and numbers as ``AnyValues``; their tests with the others."""
    rec.log(entity(prefix, AMBIGUOUS), rr.Clear(recursive=True))
    n = len(ambiguous)
    corners = np.asarray(ambiguous.corners, np.float64).reshape(n, 4, 3)
    rec.log(
        entity(prefix, AMBIGUOUS),
        rr.LineStrips3D(_strips(_closed(corners) if n else np.zeros((0, 5, 3))),
                        colors=_AMBIGUOUS, radii=rr.Radius.ui_points(4.0),
                        labels=[f"ambiguous #{k}: {_ambiguous_label(ambiguous, k)}"
                                for k in range(n)],
                        show_labels=True),
        *_any_values(region_id=np.arange(n, dtype=np.int32),
                     hypothesis=np.asarray(ambiguous.hypothesis, np.int32),
                     attempt=np.asarray(ambiguous.attempt, np.int32),
                     reason=np.asarray(ambiguous.reason, np.int32),
                     area=np.asarray(ambiguous.area, np.float64),
                     width=np.asarray(ambiguous.width, np.float64),
                     length=np.asarray(ambiguous.length, np.float64)),
    )
    _scalar(rec, entity(prefix, f"{STATS_COUNTS}/ambiguous"), n)


def log_noise(rec: rr.RecordingStream, noise: NoiseEstimate, *, prefix: str = "") -> None:
    """The noise model the scan's tests used: where it came from, its sigma, its fit."""
    model = NoiseModel(**noise.noise_model())
    r = float(np.median(noise.bin_range)) if noise.bin_range.size else float("nan")
    if math.isfinite(r):
        _scalar(rec, entity(prefix, f"{STATS_NOISE}/sigma_mm"),
                1e3 * float(model.sigma_range(r)))
    _scalar(rec, entity(prefix, f"{STATS_NOISE}/row_corr"), model.row_corr)
    _scalar(rec, entity(prefix, f"{STATS_NOISE}/source"), float(noise.source))
    fit = noise.tests.of_kind(TestKind.NOISE_FIT)
    if len(fit):
        _scalar(rec, entity(prefix, f"{STATS_NOISE}/fit_z"), float(fit.statistic[0]))
    rec.log(entity(prefix, f"{STATS_NOISE}/reason"),
            rr.TextDocument(f"{NoiseSource(noise.source).name}: {noise.reason}"))


def log_timing(
    rec: rr.RecordingStream, timing_ms: Mapping[str, float], *, prefix: str = ""
) -> None:
    """Wall-clock per stage, milliseconds (never compared, only plotted)."""
    for stage, ms in timing_ms.items():
        _scalar(rec, entity(prefix, f"{STATS_TIMING}/{stage}"), float(ms))


# --- whole scans ---------------------------------------------------------------------------

#: the product loggers in pipeline order (hypotheses are drawn with the verification)
_PRODUCT_LOGGERS: tuple[tuple[str, Callable[..., None]], ...] = (
    ("noise", log_noise),
    ("edges", log_edges),
    ("lines", log_lines),
    ("vertices", log_vertices),
    ("verification", log_verification),
    ("selection", log_selection),
    ("surfaces", log_surfaces),
    ("ambiguous", log_ambiguous),
)


def log_products(
    rec: rr.RecordingStream, scan: Scan, products: Mapping[str, Any] | Result, *,
    prefix: str = "", max_points: int = DEFAULT_MAX_POINTS,
) -> None:
    """Log one scan and whatever products it has, in pipeline order.

    Parameters
    ----------
    products : mapping or Result
        ``{stage: product}`` as read back from a log (stages of
        :data:`boxloc.products.STAGES`, ``"ambiguous"``, plus ``"timing"`` or
        ``"timing_ms"``: a mapping of milliseconds, or a :class:`Result`); missing stages
        are skipped.
    """
    if isinstance(products, Result):
        products = {**{s: getattr(products, s) for s in STAGES},
                    "ambiguous": products.ambiguous, "timing": products.timing_ms}
    set_scan_time(rec, scan)
    log_scan(rec, scan, prefix=prefix, max_points=max_points)
    for stage, fn in _PRODUCT_LOGGERS:
        if stage == "verification" and products.get("hypotheses") is not None:
            log_hypotheses(rec, products["hypotheses"], products.get("verification"),
                           prefix=prefix)
        p = products.get(stage)
        if p is not None:
            fn(rec, p, prefix=prefix)
    log_tests(rec, _tests_of(products.values()), prefix=prefix)
    timing = products.get("timing", products.get("timing_ms"))
    if isinstance(timing, Result):
        timing = timing.timing_ms
    if isinstance(timing, Mapping):
        log_timing(rec, timing, prefix=prefix)


def _tests_of(products: Iterable[Any]) -> list[TestTable]:
    """The test tables of the products that have one."""
    return [t for p in products if isinstance(t := getattr(p, "tests", None), TestTable)]


def log_recording(
    rec: rr.RecordingStream, scans_and_products: Iterable[tuple[Scan, Mapping[str, Any]]], *,
    prefix: str = "", max_points: int = DEFAULT_MAX_POINTS,
) -> int:
    """Log a whole log's scans and products into ``rec``; returns the number of scans.

    The static setup (axes, annotation contexts, camera) is logged once, and again whenever
    the sensor model changes.
    """
    log_setup(rec, prefix=prefix)
    last_sensor: dict[str, Any] | None = None
    n = 0
    for scan, products in scans_and_products:
        last_sensor = _log_camera_if_changed(rec, scan, last_sensor, prefix)
        log_products(rec, scan, products, prefix=prefix, max_points=max_points)
        n += 1
    return n


def _log_camera_if_changed(
    rec: rr.RecordingStream, scan: Scan, last: dict[str, Any] | None, prefix: str
) -> dict[str, Any]:
    key = scan.sensor.to_dict()
    if key != last:
        valid = scan.range[scan.valid]
        d = float(np.median(valid)) * 0.25 if valid.size else 0.3
        log_camera(rec, scan.sensor, prefix=prefix, image_plane_distance=d)
    return key


# --- the observer --------------------------------------------------------------------------


#: what the logging thread takes: a call, a flush barrier, or None to stop
_Item = tuple[Callable[..., None], tuple[Any, ...]] | threading.Event | None


class RerunSink(NullObserver):
    """An observer that logs every product of the pipeline to its own Rerun recording.

    Products are converted to Rerun calls on a background thread fed by a bounded queue,
    so the pipeline only pays for a queue put (products are immutable, nothing is copied).
    A full queue blocks the pipeline rather than dropping data. An error in the logging
    thread is raised in the pipeline's thread at the next call, or at :meth:`close`.

    Parameters
    ----------
    rec : rerun.RecordingStream
        The sink's own stream, with its sinks set (see :func:`open_rerun_sink`); never the
        global one.
    prefix : str
        Entity-path prefix for every entity (``""``, ``"baseline"``, ...).
    max_points : int
        Decimation bound of ``world/points``.
    threaded : bool
        Log on a background thread (default) or inline.
    queue_size : int
        Bound of the queue, in observer calls.
    servers : sequence of subprocess.Popen
        Processes this sink started (a served viewer); stopped by :meth:`close`.
    urls : mapping
        Where to look at the recording (``grpc``, ``web``), for the CLI to print.
    """

    def __init__(
        self, rec: rr.RecordingStream, *, prefix: str = "",
        max_points: int = DEFAULT_MAX_POINTS, threaded: bool = True, queue_size: int = 32,
        servers: Sequence[subprocess.Popen[bytes]] = (), urls: Mapping[str, str] | None = None,
    ) -> None:
        self.rec = rec
        self.prefix = prefix
        self.max_points = int(max_points)
        self.urls: dict[str, str] = dict(urls or {})
        self._servers = list(servers)
        self._closed = False
        self._error: BaseException | None = None
        self._setup_done = False
        self._last_sensor: dict[str, Any] | None = None
        self._pending_hypotheses: HypothesisSet | None = None
        self._pending_tests: list[TestTable] = []  # this scan's, logged with its result
        self._queue: queue.Queue[_Item] | None = None
        self._thread: threading.Thread | None = None
        if threaded:
            self._queue = queue.Queue(maxsize=max(1, int(queue_size)))
            self._thread = threading.Thread(target=self._work, name="rerun-sink", daemon=True)
            self._thread.start()

    @property
    def recording_id(self) -> str:
        return self.rec.get_recording_id()

    # -- plumbing --

    def _work(self) -> None:
        assert self._queue is not None
        while True:
            item = self._queue.get()
            if item is None:
                return
            if isinstance(item, threading.Event):
                item.set()  # a flush barrier
                continue
            if self._error is not None:
                continue  # drain without logging once broken
            fn, args = item
            try:
                fn(*args)
            except BaseException as e:  # noqa: BLE001 - handed to the pipeline's thread
                self._error = e

    def _raise_if_failed(self) -> None:
        if self._error is not None:
            err, self._error = self._error, None
            raise BoxlocError(f"Rerun logging failed: {err}") from err

    def _submit(self, fn: Callable[..., None], *args: Any) -> None:
        if self._closed:
            raise BoxlocError("Rerun sink is closed")
        self._raise_if_failed()
        if self._queue is None:
            fn(*args)
        else:
            self._queue.put((fn, args))

    # -- what runs on the logging thread --

    def _do_scan(self, scan: Scan, config: Config | None) -> None:
        self._pending_hypotheses = None  # from a scan whose pipeline stopped half-way
        self._pending_tests = []
        if not self._setup_done:
            log_setup(self.rec, prefix=self.prefix)
            if config is not None:
                from boxloc import __version__

                self.rec.send_property(
                    "boxloc", rr.AnyValues(version=__version__, config_hash=config.hash))
            self._setup_done = True
        self._last_sensor = _log_camera_if_changed(self.rec, scan, self._last_sensor,
                                                   self.prefix)
        set_scan_time(self.rec, scan)
        log_scan(self.rec, scan, prefix=self.prefix, max_points=self.max_points)

    def _do(self, fn: Callable[..., None], scan: Scan, *products: Any) -> None:
        set_scan_time(self.rec, scan)
        fn(self.rec, *products, prefix=self.prefix)
        self._pending_tests += _tests_of(products)

    def _do_tests(self, scan: Scan) -> None:
        set_scan_time(self.rec, scan)
        log_tests(self.rec, self._pending_tests, prefix=self.prefix)
        self._pending_tests = []

    def _do_hypotheses(self, scan: Scan, hyps: HypothesisSet) -> None:
        # Drawn with the verification that follows, which knows each attempt's verdict.
        self._pending_hypotheses = hyps

    def _do_verification(self, scan: Scan, ver: Verification) -> None:
        set_scan_time(self.rec, scan)
        if self._pending_hypotheses is not None:
            log_hypotheses(self.rec, self._pending_hypotheses, ver, prefix=self.prefix)
            self._pending_tests += _tests_of([self._pending_hypotheses])
            self._pending_hypotheses = None
        log_verification(self.rec, ver, prefix=self.prefix)
        self._pending_tests += _tests_of([ver])

    # -- the observer protocol --

    def on_scan(self, scan: Scan, config: Config) -> None:
        self._submit(self._do_scan, scan, config)

    def on_noise(self, scan: Scan, noise: NoiseEstimate) -> None:
        self._submit(self._do, log_noise, scan, noise)

    def on_edges(self, scan: Scan, edges: EdgeMap) -> None:
        self._submit(self._do, log_edges, scan, edges)

    def on_lines(self, scan: Scan, lines: LineSet) -> None:
        self._submit(self._do, log_lines, scan, lines)

    def on_vertices(self, scan: Scan, vertices: VertexSet) -> None:
        self._submit(self._do, log_vertices, scan, vertices)

    def on_hypotheses(self, scan: Scan, hypotheses: HypothesisSet) -> None:
        self._submit(self._do_hypotheses, scan, hypotheses)

    def on_verification(self, scan: Scan, verification: Verification) -> None:
        self._submit(self._do_verification, scan, verification)

    def on_selection(self, scan: Scan, selection: Selection) -> None:
        self._submit(self._do, log_selection, scan, selection)

    def on_surfaces(self, scan: Scan, surfaces: SurfaceSet) -> None:
        self._submit(self._do, log_surfaces, scan, surfaces)

    def on_result(self, scan: Scan, result: Result) -> None:
        # the ambiguous regions come with the result (no stage of their own)
        self._submit(self._do, log_ambiguous, scan, result.ambiguous)
        self._submit(self._do_tests, scan)
        self._submit(self._do, log_timing, scan, result.timing_ms)

    # -- lifetime --

    def flush(self, timeout_s: float = 60.0) -> None:
        """Wait until everything submitted so far has been handed to Rerun and flushed."""
        if self._queue is not None and not self._closed:
            done = threading.Event()
            self._queue.put(done)
            done.wait(timeout_s)
        self._raise_if_failed()
        self.rec.flush(timeout_sec=timeout_s)

    def close(self, timeout_s: float = 60.0) -> None:
        """Log what is queued, flush, finalize files (the .rrd footer), stop served viewers.

        Safe to call twice. A served viewer stops here: keep the sink open while it is
        being watched.
        """
        if self._closed:
            return
        self._closed = True
        try:
            if self._thread is not None and self._queue is not None:
                self._queue.put(None)
                self._thread.join(timeout_s)
            with contextlib.suppress(Exception):
                self.rec.flush(timeout_sec=timeout_s)
            self.rec.disconnect()
        finally:
            for p in self._servers:
                _stop_process(p)
            self._servers.clear()
        self._raise_if_failed()

    def __enter__(self) -> RerunSink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --- where the recording goes --------------------------------------------------------------

_RECORDING_NAMESPACE = uuid.UUID("6f0c7d3e-4a0b-5c1e-9a57-b0c5b10c0001")
DEFAULT_GRPC_PORT = 9876
_URL_SCHEMES = ("rerun://", "rerun+http://", "rerun+https://")
_TARGET_HELP = ("expected spawn[:PORT], connect[:URL|PORT], save:FILE.rrd, serve[:PORT] or none, "
                "or several joined by commas")


def recording_id_for(log_identity: str, version: str) -> str:
    """A deterministic recording id (a UUID string) for one log viewed by one version.

    The same log and version give the same id, so re-opening a log in a running viewer
    replaces its recording instead of adding a second one.
    """
    return str(uuid.uuid5(_RECORDING_NAMESPACE, f"{log_identity}\x00{version}"))


def parse_rerun_target(target: str | Sequence[str]) -> list[tuple[str, str | None]]:
    """Parse a ``--rerun`` value into ``[(kind, argument)]``; ``[]`` for ``none``.

    Accepts ``spawn``, ``spawn:PORT``, ``connect``, ``connect URL``, ``connect:URL``,
    ``connect:PORT``, ``save FILE.rrd``, ``save:FILE.rrd``, ``serve``, ``serve:PORT``,
    ``none``, and several of them joined by commas. A sequence of strings (as a CLI may
    split ``--rerun connect URL``) is joined with spaces first.

    Raises
    ------
    InputError
        For an unknown or malformed target.
    """
    if not isinstance(target, str):
        target = " ".join(str(t) for t in target)
    text = target.strip()
    if not text:
        raise InputError(f"empty Rerun target: {_TARGET_HELP}")
    out: list[tuple[str, str | None]] = []
    for part in (p.strip() for p in text.split(",")):
        if not part:
            raise InputError(f"empty part in Rerun target {target!r}: {_TARGET_HELP}")
        m = re.fullmatch(r"([A-Za-z]+)(?:(?:\s*:\s*|\s+)(.*))?", part, flags=re.S)
        kind = m.group(1).lower() if m else ""
        arg = ((m.group(2) or "").strip() if m else "") or None
        if kind == "none" and arg is None:
            out.append(("none", None))
            continue
        if kind not in ("spawn", "connect", "save", "serve"):
            raise InputError(f"unknown Rerun target {part!r}: {_TARGET_HELP}")
        out.append((kind, _check_arg(kind, arg, part)))
    if ("none", None) in out:
        if len(out) > 1:
            raise InputError(f"Rerun target {target!r}: none cannot be combined with others")
        return []
    kinds = [k for k, _ in out]
    for k in ("spawn", "serve"):
        if kinds.count(k) > 1:
            raise InputError(f"Rerun target {target!r} names {k} twice")
    saves = [a for k, a in out if k == "save"]
    if len(set(saves)) != len(saves):
        raise InputError(f"Rerun target {target!r} saves to the same file twice")
    return out


def _check_arg(kind: str, arg: str | None, part: str) -> str | None:
    if kind in ("spawn", "serve"):
        if arg is not None and not _is_port(arg):
            raise InputError(f"Rerun target {part!r}: {kind} takes an optional port, got {arg!r}")
        return arg
    if kind == "connect":
        if arg is None or _is_port(arg):
            return f"rerun+http://127.0.0.1:{arg or DEFAULT_GRPC_PORT}/proxy"
        if not arg.startswith(_URL_SCHEMES) or not arg.rstrip("/").endswith("/proxy"):
            raise InputError(
                f"Rerun target {part!r}: the URL must start with rerun://, rerun+http:// or "
                f"rerun+https:// and end with /proxy, got {arg!r}")
        return arg
    # save
    if arg is None:
        raise InputError(f"Rerun target {part!r}: save needs a file, e.g. save:run.rrd")
    if Path(arg).suffix.lower() != ".rrd":
        raise InputError(f"Rerun target {part!r}: the file must end in .rrd, got {arg!r}")
    parent = Path(arg).expanduser().resolve().parent
    if not parent.is_dir():
        raise InputError(f"Rerun target {part!r}: directory {str(parent)!r} does not exist")
    return arg


def _is_port(s: str) -> bool:
    return s.isdigit() and 0 < int(s) < 65536


def _probe(url: str, timeout_s: float = 2.0) -> None:
    """Fail fast when nothing listens at a ``rerun+http://host:port/proxy`` URL.

    Otherwise the SDK retries quietly for seconds and then drops the data.
    """
    u = urlsplit(url)
    if u.scheme != "rerun+http" or u.port is None or not u.hostname:
        return  # TLS or default ports: leave it to the SDK
    try:
        with socket.create_connection((u.hostname, u.port), timeout=timeout_s):
            pass
    except OSError as e:
        raise BoxlocError(f"no Rerun viewer listening at {url} ({e.strerror or e})") from None


def rerun_executable() -> str:
    """The ``rerun`` binary of this environment.

    The binary itself, not the ``bin/rerun`` Python wrapper: the wrapper runs the binary
    as a child process, so stopping the wrapper would leave a server running.
    """
    override = os.environ.get("RERUN_CLI_PATH")
    if override and Path(override).is_file():
        return override
    try:
        import rerun_cli

        binary = Path(rerun_cli.__file__).with_name("rerun")
        if binary.is_file() and os.access(binary, os.X_OK):
            return str(binary)
    except ImportError:
        pass
    here = Path(sys.executable).with_name("rerun")
    if here.exists():
        return str(here)
    found = shutil.which("rerun")
    if found is None:
        raise BoxlocError("the rerun executable was not found (is rerun-sdk installed?)")
    return found


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _wait_listening(port: int, proc: subprocess.Popen[bytes], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise BoxlocError(f"the Rerun server exited with code {proc.returncode}")
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.settimeout(0.2)
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.05)
    raise BoxlocError(f"the Rerun server did not listen on 127.0.0.1:{port} "
                      f"within {timeout_s:.0f} s")


def _stop_process(p: subprocess.Popen[bytes], timeout_s: float = 5.0) -> None:
    if p.poll() is None:
        p.terminate()
        try:
            p.wait(timeout_s)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout_s)


def serve_viewer(
    grpc_port: int | None = None, web_port: int | None = None, *, timeout_s: float = 20.0
) -> tuple[subprocess.Popen[bytes], dict[str, str]]:
    """Start a Rerun gRPC proxy and web viewer bound to 127.0.0.1 only.

    The SDK's own ``serve_grpc``/``serve_web_viewer`` bind every interface, so this runs
    ``rerun --serve-web --bind 127.0.0.1`` as a child process instead.

    Returns
    -------
    process : subprocess.Popen
        Stop it with ``terminate()`` (:meth:`RerunSink.close` does).
    urls : dict
        ``grpc`` (for SDKs and native viewers) and ``web`` (open it in a browser).
    """
    gp = grpc_port or free_port()
    wp = web_port or free_port()
    cmd = [rerun_executable(), "--serve-web", "--bind", "127.0.0.1", "--port", str(gp),
           "--web-viewer-port", str(wp)]
    env = {**os.environ, "RERUN_APP_ONLY": "true"}
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, env=env)
    try:
        _wait_listening(gp, proc, timeout_s)
        _wait_listening(wp, proc, timeout_s)
    except BaseException:
        _stop_process(proc)
        raise
    grpc = f"rerun+http://127.0.0.1:{gp}/proxy"
    web = f"http://127.0.0.1:{wp}/?url=" + grpc.replace(":", "%3A").replace("/", "%2F").replace(
        "+", "%2B")
    return proc, {"grpc": grpc, "web": web, "command": shlex.join(cmd)}


def open_rerun_sink(
    target: str | Sequence[str], *, recording_id: str, app_id: str = APP_ID,
    prefix: str = "", threaded: bool = True, max_points: int = DEFAULT_MAX_POINTS,
    blueprint: Any = None,
) -> RerunSink | None:
    """Open a :class:`RerunSink` for a ``--rerun`` target; ``None`` for ``none``.

    Parameters
    ----------
    target : str or sequence of str
        ``spawn`` (a native viewer), ``connect URL`` / ``connect:URL`` (a running viewer or
        proxy), ``save:FILE.rrd`` / ``save FILE.rrd``, ``serve`` (gRPC proxy + web viewer on
        127.0.0.1), ``none``, or several joined by commas (``save:a.rrd,spawn``).
    recording_id : str
        See :func:`recording_id_for`.
    app_id : str
        Rerun application id (recordings of one app share blueprints).
    blueprint : rerun.blueprint.Blueprint, optional
        Default: :func:`recorder.rerun.blueprint.default_blueprint` for ``prefix``.

    Raises
    ------
    InputError
        For a malformed target. :class:`BoxlocError` when a viewer cannot be started.
    """
    parts = parse_rerun_target(target)
    if not parts:
        return None
    from recorder.rerun.blueprint import default_blueprint

    rec = rr.RecordingStream(app_id, recording_id=recording_id)
    rec.set_log_time_enabled(False)  # wall clock would make each recording unique
    rec.set_log_tick_enabled(False)
    sinks: list[Any] = []
    servers: list[subprocess.Popen[bytes]] = []
    urls: dict[str, str] = {}
    try:
        for kind, arg in parts:
            if kind == "save":
                sinks.append(rr.FileSink(str(Path(arg or "").expanduser())))
                urls["file"] = str(arg)
            elif kind == "connect":
                _probe(str(arg))
                sinks.append(rr.GrpcSink(arg))
                urls["grpc"] = str(arg)
            elif kind == "spawn":
                port = int(arg) if arg else DEFAULT_GRPC_PORT
                try:
                    rr.spawn(port=port, connect=False, executable_path=rerun_executable(),
                             recording=rec)
                except Exception as e:
                    raise BoxlocError(f"cannot spawn a Rerun viewer: {e}") from e
                sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{port}/proxy"))
            elif kind == "serve":
                proc, u = serve_viewer(int(arg) if arg else None)
                servers.append(proc)
                urls.update(u)
                sinks.append(rr.GrpcSink(u["grpc"]))
        bp = blueprint if blueprint is not None else default_blueprint(prefix)
        rec.set_sinks(*sinks, default_blueprint=bp)
    except BaseException:
        for p in servers:
            _stop_process(p)
        raise
    return RerunSink(rec, prefix=prefix, threaded=threaded, max_points=max_points,
                     servers=servers, urls=urls)

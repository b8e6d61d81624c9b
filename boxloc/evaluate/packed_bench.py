"""The packed-layer benchmark (issue 21, point 4): tightly packed layers, with and without
the cell's carton list.

``python -m boxloc.evaluate.packed_bench`` (and ``boxloc bench --packed``) runs
:func:`run_packed_bench` on the scenes of :func:`packed_suite`: zero-gap, sharp-edged
layered pallets (``layered``: one carton size per pallet, neighbours touching along whole
faces, ``bevel`` 0), scene ``i`` seen by sensor ``SENSORS[i % 4]`` of the zoo. They are
the ``layered`` cells of :func:`boxloc.simulate.matrix_suite` (the same draws of camera
height, tilt, resolution, lid bulge, tape and labels), in order, so the matrix bench's
layered scans are the first ones here. Those are laid as grids; the next ``layered`` cells
follow as *interlocked* layers (``pattern="weave"``, a third as many: cartons twice as long
as wide in a basket weave, the outline of a grid of the carton that they are not, as real
pallets are laid to interlock). Their figures are reported apart: every target but the two
of interlocked layers is over the grids.

Each scan (scene and draw of the random trials) is localized in two *variants*:
``without_sizes``, the default configuration (``Config()`` with the one site input, the
smallest and largest box, as the matrix bench), and ``with_sizes``, the same plus the
scene's carton list as a user gives it (``--box-sizes FILE``): the distinct carton sizes of
the scene's ground truth, ``width,length,height`` rounded to the millimetre, written as a
CSV file and read back with :func:`boxloc.io.box_sizes.read_box_sizes`. Every variant of
every scan runs in a worker process under the per-scan time limit, as in
:mod:`boxloc.evaluate.matrix_bench` (a timed-out or crashed scan scores as nothing found).
The held-out sensor (``tof``) is reported apart: every overall figure is given for
``development`` (without it) and ``all``.

Scoring (:mod:`boxloc.evaluate.metrics`): precision and recall by
:func:`~boxloc.evaluate.metrics.match_surfaces`, as the matrix bench. A *wrong rectangle*
(:func:`~boxloc.evaluate.metrics.wrong_rectangles`) is a reported surface that overlaps a box
top and matches none with IoU >= 0.5, or that covers at least half of two tops (a rectangle
over exactly two equal tops has IoU 0.5 with each, so the IoU alone cannot call it); the
*wrong-rectangle rate* is their share of the reported surfaces. Ambiguous regions
(``Result.ambiguous``) are counted per scan, and each is scored by the exposed tops it
covers at least half of (:func:`~boxloc.evaluate.metrics.region_cover`): a top that is
missed but lies in an ambiguous region is one the cell knows to fall back on; one missed
outside every region is missed silently. The height error is ``|height - true height|`` of
the true positives whose height source is a side face or a step
(:func:`~boxloc.evaluate.metrics.height_errors`; a height copied from the list is counted
by source but not scored).

Layout of ``bench_packed.json`` (schema ``boxloc.bench_packed/1``; lengths in figures are
millimetres where named ``*_mm``, areas square metres where named ``*_m2``, times
milliseconds where named ``*_ms``):

- ``schema``, ``version``, ``mode`` (``"packed"``), ``n`` scenes, ``seed`` of the suite,
  ``jobs``, ``scan_timeout_s``, ``warmup``, ``threads`` (a worker's thread pinning)
- ``default_configuration``: true; ``config`` (every value of the ``without_sizes`` run),
  ``config_hash``, ``site``: ``min_edge``, ``max_edge`` (metres, the only values set),
  ``source`` and ``observed`` (the smallest and largest top edge in the scenes' truth)
- ``sizes``: how the ``with_sizes`` carton list is made: ``source``, ``rounding_m``,
  ``size_tolerance_m`` (the configuration's), ``tolerance_source``
- ``suite``: ``source`` (the scenes' definition), ``kind``, ``bevel_m``, ``max_gap_m``,
  ``patterns`` (scenes laid as ``grid`` and as ``weave``; ``n`` is the grids')
- ``held_out``: ``sensor``
- ``sensors``, ``variants``, ``lids`` (``flat``, ``bulged``): the axes, in order
- ``seeds``: the draws of the random trials
  (:func:`boxloc.evaluate.scene_bench.draw_figures`, the variants as its methods, per sensor)
- ``groups``: per variant, figures (see below) of the grid layers for ``overall``
  (``development`` and ``all``), ``sensors`` (per sensor; each also has ``held_out``) and
  ``lids`` (per lid: ``development`` and ``all``), and, if the suite has interlocked
  layers, ``interlocked``: their ``overall`` and ``sensors``
- ``targets``: one row per entry of :data:`PACKED_TARGETS`: ``name``, ``variant``,
  ``key``, ``over`` (``sensor`` or ``overall``), ``op``, ``bound``, ``target`` (text),
  ``unit``, ``layers`` (``grid`` or ``interlocked``), and per scope (``development``,
  ``all``) ``value`` (the worst sensor's figure for ``sensor``), ``where`` and ``pass``
  (true, false, or null: no data)
- ``timeouts``: one entry per timed-out run: ``scene``, ``trial_seed``, ``sensor``,
  ``variant``, ``spec_text``, ``phase`` (``simulate``, ``localize`` or ``warmup``),
  ``limit_s``
- ``errors``: ``total`` and ``list`` (``scene``, ``trial_seed``, ``sensor``, ``variant``,
  ``phase``, ``error``) of runs that crashed
- ``timing``: per variant ``stages_ms`` (median, p95 per stage) and ``total_ms`` (median,
  p95); ``per_scan_ms`` (per variant, in the order of ``scenes``; a timed-out run's is the
  limit), ``run_s``
- ``memory``: the workers' peak RSS per run (median and max, MB) and this process's
- ``scenes``: one deterministic row per scan (scene and draw, in suite order): ``index``,
  ``trial_seed``, ``sensor``, ``held_out``, ``lid``, ``spec``, ``spec_text``,
  ``pattern``, ``n_faces``, ``n_exposed``, ``n_boxes``, ``layers``, ``pixels``,
  ``sizes_csv`` (the file
  given to ``with_sizes``), and ``runs``: per variant ``status`` (``ok``, ``error``,
  ``timeout``), ``error``, ``match`` (:meth:`boxloc.evaluate.metrics.Match.to_dict`),
  ``wrong`` (:meth:`boxloc.evaluate.metrics.WrongRectangles.to_dict`), ``ambiguous``
  (``n``, ``area_m2``, ``reason``, ``tops`` covered by each), ``missed_in_ambiguous``,
  ``heights`` (``sources`` counted over the surfaces; ``face``, ``source``, ``err_mm``,
  ``above_floor_mm`` (the top's height above the floor), ``sigma_mm`` of the scored ones)
  and ``sku`` (``matched``, ``flagged``, ``flagged_tp``); no durations, so two runs' rows
  compare equal

Figures of a group (:func:`group_figures`): ``n_scenes``, ``n_scans``, every key of
:func:`boxloc.evaluate.metrics.aggregate_matches` (``n_exposed`` exposed tops, ``tp``,
``fp``, ``fn``, ``n_pred``, ``precision``, ``recall``, ``grasp_err_median_mm``, ...),
``errors``, ``timeouts``, ``time`` (``median_ms``, ``max_ms``), and:

- wrong rectangles: ``wrong_rectangles``, ``wrong_no_match``, ``wrong_spans``,
  ``off_top`` (false surfaces on no top: not wrong rectangles), ``wrong_rate``
  (``wrong_rectangles / n_pred``; 0 with no surface)
- ambiguous regions: ``ambiguous_regions``, ``ambiguous_per_scan``,
  ``ambiguous_area_median_m2``, ``ambiguous_reasons`` (count per
  :class:`boxloc.products.AmbiguityReason` name), ``ambiguous_without_top`` (regions
  covering no exposed top by half), ``tops_in_ambiguous`` (exposed tops covered at least
  half by a region), ``missed_in_ambiguous`` (of them, the tops not found),
  ``missed_silently`` (tops not found and in no region), ``silent_scans`` (scans with
  exposed tops but neither a surface nor a region: to the cell the pallet looks empty)
- heights: ``height_sources`` (reported surfaces per :class:`boxloc.products.HeightSource`
  name), ``height_n`` (true positives scored: side or step), ``height_err_median_mm``,
  ``height_err_p95_mm``, ``height_by_source`` (per scored source: ``n``, ``median_mm``,
  ``p95_mm``), ``height_stack_like`` (scored heights nearer the top's height above the
  floor or the pallet than the box's own: the step seen was the edge of the whole stack)
- carton list: ``sku_matched`` (surfaces matching a listed size), ``sku_flagged``
  (surfaces matching none), ``sku_flagged_tp`` (true tops flagged: false flags)
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from boxloc.config import Config
from boxloc.errors import BoxlocError, InputError
from boxloc.evaluate.matrix_bench import (
    HELD_OUT,
    SCOPES,
    _pct,
    failures,
    matrix_config,
    memory_figures,
    observed_site,
    print_failures,
    print_targets,
    report_head,
    run_line,
    target_scope,
    write_report,
)
from boxloc.evaluate.metrics import (
    HeightErrors,
    Match,
    WrongReason,
    WrongRectangles,
    aggregate_matches,
    height_errors,
    match_surfaces,
    prf,
    region_cover,
    true_box_heights,
    wrong_rectangles,
)
from boxloc.evaluate.scene_bench import (
    PeakRSS,
    _default_localizer,
    _err,
    _fmt,
    _jsonable,
    _MethodRun,
    _spec_dict,
    _spec_text,
    _timing,
    draw_figures,
    trial_configs,
)
from boxloc.evaluate.workers import (
    Localizer,
    bench_console,
    check_run_args,
    run_with_progress,
    warmup_spec,
)
from boxloc.products import AmbiguityReason, HeightSource

SCHEMA = "boxloc.bench_packed/1"
#: The two ways every scan is localized: the default configuration, and with the carton list.
VARIANTS: tuple[str, ...] = ("without_sizes", "with_sizes")
#: Lid shapes the figures are split by: a bulged lid shows its box's outline by itself.
LIDS: tuple[str, ...] = ("flat", "bulged")
#: Scenes of the default run: 24 per sensor.
DEFAULT_N = 96
#: Seconds a run may take (from the end of its simulation) before its worker is killed.
DEFAULT_SCAN_TIMEOUT = 120.0
#: The carton list a user writes: catalogue sizes in whole millimetres.
SIZE_ROUNDING = 0.001
#: Exposed tops an ambiguous region must cover by at least this share to hold them.
REGION_COVER = 0.5
REPORT_NAME = "bench_packed.json"
TABLE_NAME = "bench_packed.txt"


@dataclass(frozen=True)
class PackedTarget:
    """One target of issue 21, point 4: ``key`` of :func:`group_figures` in ``variant``,
    over every sensor (the worst one's value) or overall, on the grid layers or the
    interlocked ones (``layers``)."""

    name: str
    variant: str
    over: str
    key: str
    op: str
    value: float
    unit: str = ""
    layers: str = "grid"

    def text(self) -> str:
        return f"{self.op} {self.value:g}{(' ' + self.unit) if self.unit else ''}"


#: The targets of issue 21, point 4, in one place.
PACKED_TARGETS: tuple[PackedTarget, ...] = (
    PackedTarget("wrong-rectangle rate without sizes, every sensor", "without_sizes",
                 "sensor", "wrong_rate", "<=", 0.01),
    PackedTarget("recall with sizes", "with_sizes", "overall", "recall", ">=", 0.95),
    PackedTarget("precision with sizes", "with_sizes", "overall", "precision", ">=", 0.99),
    PackedTarget("median height error (side or step), without sizes", "without_sizes",
                 "overall", "height_err_median_mm", "<=", 10.0, "mm"),
    PackedTarget("median height error (side or step), with sizes", "with_sizes", "overall",
                 "height_err_median_mm", "<=", 10.0, "mm"),
    # an interlocked layer has the outline of a grid: without seams that show, it is one
    # flat region either way, and a grid laid over it cuts tops in two
    PackedTarget("wrong-rectangle rate on interlocked layers without sizes, every sensor",
                 "without_sizes", "sensor", "wrong_rate", "<=", 0.01, layers="interlocked"),
    PackedTarget("wrong-rectangle rate on interlocked layers with sizes, every sensor",
                 "with_sizes", "sensor", "wrong_rate", "<=", 0.01, layers="interlocked"),
)


# --- the scenes and the carton list ------------------------------------------------------


def packed_suite(n: int, seed: int = 0, interlocked: int = 0) -> list[Any]:
    """The benchmark's scenes: the first ``n`` ``layered`` scenes of ``matrix_suite``, laid
    as grids, then the next ``interlocked`` ones laid as basket weaves
    (``pattern="weave"``: :func:`boxloc.simulate.layouts._layout_weave`).

    Scene ``i`` has sensor ``SENSORS[i % 4]``; ``bevel`` is 0 (sharp edges) and the layout
    has no gap and no jitter (``layered``). The same arguments give the same list, and a
    longer grid suite starts with the shorter one.

    Raises
    ------
    InputError
        If ``n``, ``interlocked`` or ``seed`` is not an integer >= 0.
    """
    from boxloc.simulate import MATRIX_KINDS, SENSORS, matrix_suite

    for name, v in (("size", n), ("interlocked count", interlocked)):
        if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 0:
            raise InputError(f"packed suite {name} must be an integer >= 0, got {v!r}")
    total = int(n) + int(interlocked)
    per_round = len(SENSORS) * len(MATRIX_KINDS)  # each round of the matrix: one per sensor
    rounds = math.ceil(total / len(SENSORS))
    specs = [s for s in matrix_suite(rounds * per_round, seed) if s.kind == "layered"]
    # the matrix draws no bevel on layered scenes; the replace only makes it this suite's rule
    return ([dataclasses.replace(s, bevel=0.0) for s in specs[: int(n)]]
            + [dataclasses.replace(s, bevel=0.0, pattern="weave") for s in specs[int(n):total]])


def default_interlocked(n: int) -> int:
    """Basket-weave scenes the bench adds to ``n`` grid scenes: a third as many (32 to the
    default 96), a multiple of the four sensors."""
    return (int(n) // 3) // 4 * 4


def box_sizes_csv(truth: Any, rounding: float = SIZE_ROUNDING) -> str:
    """The carton list a user of the cell would write for this scene: its CSV text.

    Parameters
    ----------
    truth : GroundTruth
        ``boxes`` (B, 7): size x, y, z at columns 3-5, metres.
    rounding : float
        Sizes are rounded to this, metres (catalogue sizes in whole millimetres).

    Returns
    -------
    str
        ``width,length,height`` then one row per distinct (width <= length, height), sorted.
    """
    b = np.asarray(truth.boxes, dtype=np.float64).reshape(-1, 7)
    digits = max(0, round(-math.log10(rounding)))
    rows = set()
    for sx, sy, sz in b[:, 3:6]:
        w, ln = sorted((float(sx), float(sy)))
        rows.add(tuple(round(round(v / rounding) * rounding, digits) for v in (w, ln, sz)))
    lines = ["width,length,height"] + [f"{w:.{digits}f},{ln:.{digits}f},{h:.{digits}f}"
                                       for w, ln, h in sorted(rows)]
    return "\n".join(lines) + "\n"


def read_sizes_as_a_user(csv_text: str) -> tuple[tuple[float, float, float], ...]:
    """Write ``csv_text`` to a file and read it with the ``--box-sizes`` reader."""
    from boxloc.io.box_sizes import read_box_sizes

    with tempfile.TemporaryDirectory(prefix="boxloc-packed-") as d:
        path = Path(d) / "box_sizes.csv"
        path.write_text(csv_text)
        return read_box_sizes(path)


# --- scoring one run -----------------------------------------------------------------------


@dataclass
class PackedScore:
    """The scores of one run (a variant on a scan), as :func:`score_packed` makes them."""

    match: Match
    wrong: WrongRectangles
    amb_area: np.ndarray
    amb_reason: np.ndarray
    amb_tops: np.ndarray
    tops_in_ambiguous: int
    missed_in_ambiguous: int
    heights: HeightErrors
    #: (k,) the scored tops' heights above the floor, metres (the stack with the pallet)
    above_floor: np.ndarray
    height_sources: dict[str, int]
    sku_matched: int
    sku_flagged: int
    sku_flagged_tp: int

    def to_dict(self) -> dict[str, Any]:
        h = self.heights
        return {
            "match": self.match.to_dict(), "wrong": self.wrong.to_dict(),
            "ambiguous": {"n": int(self.amb_area.shape[0]),
                          "area_m2": [round(float(a), 5) for a in self.amb_area],
                          "reason": [_reason_name(r) for r in self.amb_reason],
                          "tops": [int(t) for t in self.amb_tops]},
            "missed_in_ambiguous": self.missed_in_ambiguous,
            "heights": {"sources": self.height_sources, "face": [int(f) for f in h.face],
                        "source": [HeightSource(int(s)).name.lower() for s in h.source],
                        "err_mm": [round(float(e) * 1e3, 3) for e in h.error],
                        "above_floor_mm": [round(float(a) * 1e3, 3) for a in self.above_floor],
                        "sigma_mm": [None if not math.isfinite(s) else round(float(s) * 1e3, 3)
                                     for s in h.sigma]},
            "sku": {"matched": self.sku_matched, "flagged": self.sku_flagged,
                    "flagged_tp": self.sku_flagged_tp},
        }


def _reason_name(r: Any) -> str:
    try:
        return AmbiguityReason(int(r)).name
    except ValueError:
        return f"REASON_{int(r)}"


def _field(obj: Any, name: str, n: int, fill: Any, dtype: Any) -> np.ndarray:
    """``obj.name`` as an (n,) array, or ``fill`` where the localizer does not give it."""
    v = getattr(obj, name, None)
    if v is None:
        return np.full(n, fill, dtype=dtype)
    return np.asarray(v, dtype=dtype).reshape(n)


def score_packed(result: Any, truth: Any) -> PackedScore:
    """Score one localizer result on a packed scene.

    Parameters
    ----------
    result : Result-like
        ``surfaces`` (a :class:`boxloc.products.SurfaceSet`) and optionally ``ambiguous``
        (a :class:`boxloc.products.AmbiguousSet`: ``corners`` (K, 4, 3), ``area`` (K,),
        ``reason`` (K,)).
    truth : GroundTruth

    Returns
    -------
    PackedScore
    """
    s = result.surfaces
    n = len(s)
    match = match_surfaces(s, truth)
    wrong = wrong_rectangles(s, truth)
    exposed = np.asarray(truth.fully_exposed, dtype=bool).reshape(-1)
    amb = getattr(result, "ambiguous", None)
    k = 0 if amb is None else len(amb)
    corners, area, reason = np.zeros((0, 4, 3)), np.zeros(0), np.zeros(0, np.int64)
    if amb is not None and k:
        corners = np.asarray(amb.corners, np.float64).reshape(k, -1, 3)
        area = np.asarray(amb.area, np.float64).reshape(k)
        reason = np.asarray(amb.reason, np.int64).reshape(k)
    cover = region_cover(corners, truth)  # (K, F)
    held = cover >= REGION_COVER
    in_region = held.any(axis=0) & exposed
    found = np.zeros(exposed.shape[0], dtype=bool)
    found[match.tp_pairs[:, 1]] = True
    source = _field(s, "height_source", n, int(HeightSource.NONE), np.int64)
    hs = height_errors(_field(s, "height", n, np.nan, np.float64), source, match,
                       true_box_heights(truth),
                       sigma=_field(s, "height_sigma", n, np.nan, np.float64))
    sku = _field(s, "sku", n, -1, np.int64)
    boxes = np.asarray(truth.boxes, np.float64).reshape(-1, 7)
    bi = np.asarray(truth.box_index, np.int64)[hs.face]
    above_floor = boxes[bi, 2] + 0.5 * boxes[bi, 5]  # base frame: the floor is z = 0
    flagged = _field(s, "sku_flagged", n, False, bool)
    tp_pred = match.tp_pairs[:, 0]
    return PackedScore(
        match=match, wrong=wrong,
        amb_area=area, amb_reason=reason,
        amb_tops=held[:, exposed].sum(axis=1).astype(np.int64),
        tops_in_ambiguous=int(in_region.sum()),
        missed_in_ambiguous=int((in_region & ~found).sum()),
        heights=hs, above_floor=above_floor,
        height_sources={h.name.lower(): int((source == h).sum()) for h in HeightSource},
        sku_matched=int((sku >= 0).sum()), sku_flagged=int(flagged.sum()),
        sku_flagged_tp=int(flagged[tp_pred].sum()))


# --- one run, in a worker process ----------------------------------------------------------


@dataclass(frozen=True)
class _Job:
    """What a worker runs on a scene: a variant under a configuration (sizes not yet set)."""

    variant: str
    config: Config


@dataclass
class _Run(_MethodRun):
    """One variant on one scan, as the worker measured it."""

    score: PackedScore | None = None


@dataclass
class _Outcome:
    """One run (scene, draw, variant) as the parent sees it."""

    index: int
    trial_seed: int
    sensor: str
    variant: str
    status: str = "ok"
    phase: str | None = None
    error: str | None = None
    run: _Run | None = None
    score: PackedScore | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    wall_ms: float | None = None

    @property
    def group(self) -> str:  # for draw_figures: the draws per sensor
        return self.sensor

    @property
    def match(self) -> Match | None:
        return self.score.match if self.score is not None else None


def _empty_result() -> Any:
    from types import SimpleNamespace

    from boxloc.evaluate.baseline import empty_surface_set

    return SimpleNamespace(surfaces=empty_surface_set(), ambiguous=None)


def _meta(sim: Any) -> dict[str, Any]:
    truth, spec = sim.truth, sim.spec
    h, w = sim.scan.range.shape[:2]
    boxes = np.asarray(truth.boxes, np.float64).reshape(-1, 7)
    base = np.round(boxes[:, 2] - boxes[:, 5] / 2, 3)
    return {"n_faces": int(len(truth)), "n_exposed": int(np.asarray(truth.fully_exposed).sum()),
            "n_boxes": int(boxes.shape[0]), "layers": int(np.unique(base).shape[0]),
            "pixels": int(h * w), "spec": _spec_dict(spec), "spec_text": _spec_text(spec),
            "lid": "bulged" if float(spec.bulge) > 0 else "flat",
            "pattern": spec.pattern,
            "sizes_csv": box_sizes_csv(truth) if boxes.shape[0] else None,
            "edge_min": float(np.min(truth.width)) if len(truth) else None,
            "edge_max": float(np.max(truth.length)) if len(truth) else None,
            "nothing": score_packed(_empty_result(), truth)}


def _run_variant(localizer: Localizer, sim: Any, config: Config) -> _Run:
    run = _Run()
    try:
        with PeakRSS() as pk:
            t0 = time.perf_counter()
            result = localizer(sim.scan, config)
            run.wall_ms = (time.perf_counter() - t0) * 1e3
        run.peak_mb = pk.peak_mb
        run.stage_ms = {k: float(v) for k, v in getattr(result, "timing_ms", {}).items()}
        run.score = score_packed(result, sim.truth)
    except Exception as e:  # noqa: BLE001 - a crash on one scan is a result, not the end
        run.error = _err(e)
    return run


def _packed_task(conn: Connection | None, task: int, spec: Any, job: _Job,
                 localizer: Localizer, cache: dict[str, Any]) -> dict[str, Any]:
    """Simulate the scene (or take it from the worker's cache), make the variant's
    configuration, say when the localizer starts, run and score it.

    The workers' task function (:data:`boxloc.evaluate.workers.TaskFn`); ``cache`` holds
    the scene the worker simulated last, which the scan's next variant needs again.
    """
    from boxloc.simulate import simulate

    try:
        if cache.get("spec") != spec:
            cache.clear()
            sim = simulate(spec)
            cache.update(spec=spec, sim=sim, meta=_meta(sim))
        sim, meta = cache["sim"], cache["meta"]
        config = job.config
        if job.variant == "with_sizes":
            if meta["sizes_csv"] is None:
                raise InputError("the scene has no box: no carton list to give")
            config = dataclasses.replace(config,
                                         box_sizes=read_sizes_as_a_user(meta["sizes_csv"]))
    except Exception as e:  # noqa: BLE001 - a scene that cannot be made is a reported error
        return {"status": "error", "phase": "simulate", "error": _err(e)}
    if conn is not None:
        conn.send(("started", task, meta))
    run = _run_variant(localizer, sim, config)
    if run.error is not None:
        run.score = meta["nothing"]
        return {"status": "error", "phase": "localize", "error": run.error, "run": run,
                "meta": meta}
    return {"status": "ok", "run": run, "meta": meta}


# --- figures -----------------------------------------------------------------------------


def _mm(a: np.ndarray, q: float) -> float | None:
    v = _pct(a, q)
    return None if v is None else v * 1e3


def _height_figures(scores: Sequence[PackedScore]) -> dict[str, Any]:
    from boxloc.simulate import PALLET_SIZE

    err = np.concatenate([s.heights.error for s in scores]) if scores else np.zeros(0)
    src = np.concatenate([s.heights.source for s in scores]) if scores else np.zeros(0)
    est = np.concatenate([s.heights.estimate for s in scores]) if scores else np.zeros(0)
    floor = np.concatenate([s.above_floor for s in scores]) if scores else np.zeros(0)
    # a height nearer the stack's (down to the floor or the pallet) than the box's own: the
    # step seen was the edge of the stack, whose layers a zero-gap side does not show
    stack = np.minimum(np.abs(est - floor), np.abs(est - (floor - PALLET_SIZE[2])))
    by = {}
    for h in (HeightSource.SIDE, HeightSource.STEP):
        e = err[src == h]
        by[h.name.lower()] = {"n": int(e.size), "median_mm": _mm(e, 50), "p95_mm": _mm(e, 95)}
    return {"height_sources": {h.name.lower(): sum(s.height_sources.get(h.name.lower(), 0)
                                                   for s in scores) for h in HeightSource},
            "height_n": int(err.size), "height_err_median_mm": _mm(err, 50),
            "height_err_p95_mm": _mm(err, 95), "height_by_source": by,
            "height_stack_like": int((stack < err).sum())}


def _ambiguous_figures(scores: Sequence[PackedScore], n_scans: int) -> dict[str, Any]:
    area = np.concatenate([s.amb_area for s in scores]) if scores else np.zeros(0)
    reasons = np.concatenate([s.amb_reason for s in scores]) if scores else np.zeros(0)
    tops = np.concatenate([s.amb_tops for s in scores]) if scores else np.zeros(0)
    names = [_reason_name(r) for r in reasons]
    n_found = sum(s.match.tp for s in scores)
    n_exposed = sum(s.match.n_exposed for s in scores)
    in_amb = sum(s.tops_in_ambiguous for s in scores)
    missed_amb = sum(s.missed_in_ambiguous for s in scores)
    # scans with tops to find where the cell got neither a surface nor a region: to it, the
    # pallet looks empty
    silent = sum(s.match.n_exposed > 0 and s.match.n_pred == 0 and s.amb_area.size == 0
                 for s in scores)
    return {"ambiguous_regions": int(area.size),
            "ambiguous_per_scan": area.size / n_scans if n_scans else None,
            "ambiguous_area_median_m2": _pct(area, 50),
            "ambiguous_reasons": {r: names.count(r) for r in sorted(set(names))},
            "ambiguous_without_top": int((tops == 0).sum()),
            "tops_in_ambiguous": in_amb, "missed_in_ambiguous": missed_amb,
            "missed_silently": n_exposed - n_found - missed_amb, "silent_scans": silent}


def group_figures(outs: Sequence[_Outcome]) -> dict[str, Any]:
    """The figures of a group of runs of one variant (see the module docstring)."""
    scores = [o.score for o in outs if o.score is not None]
    agg = aggregate_matches(s.match for s in scores)
    n_pred = agg["n_pred"]
    wrong = {r: sum(s.wrong.count(r) for s in scores) for r in WrongReason}
    n_wrong = wrong[WrongReason.NO_MATCH] + wrong[WrongReason.SPANS]
    walls = np.asarray([o.wall_ms for o in outs if o.wall_ms is not None], np.float64)
    return {"n_scenes": len({o.index for o in outs}), **agg,
            "errors": sum(o.status == "error" for o in outs),
            "timeouts": sum(o.status == "timeout" for o in outs),
            "time": {"median_ms": _pct(walls, 50),
                     "max_ms": float(walls.max()) if walls.size else None},
            "wrong_rectangles": n_wrong, "wrong_no_match": wrong[WrongReason.NO_MATCH],
            "wrong_spans": wrong[WrongReason.SPANS], "off_top": wrong[WrongReason.OFF_TOP],
            "wrong_rate": n_wrong / n_pred if n_pred else 0.0,
            **_ambiguous_figures(scores, agg["n_scans"]),
            **_height_figures(scores),
            "sku_matched": sum(s.sku_matched for s in scores),
            "sku_flagged": sum(s.sku_flagged for s in scores),
            "sku_flagged_tp": sum(s.sku_flagged_tp for s in scores)}


def _by_sensor(outs: Sequence[_Outcome], sensors: Sequence[str], held_out: str
               ) -> dict[str, Any]:
    """``overall`` (``development``, ``all``) and ``sensors`` figures of some runs."""
    return {
        "overall": {"development": group_figures([o for o in outs if o.sensor != held_out]),
                    "all": group_figures(outs)},
        "sensors": {s: {"held_out": s == held_out,
                        **group_figures([o for o in outs if o.sensor == s])}
                    for s in sensors if any(o.sensor == s for o in outs)},
    }


def _groups(outs: Sequence[_Outcome], sensors: Sequence[str], variants: Sequence[str],
            held_out: str) -> dict[str, Any]:
    """Per variant: the grid layers' figures (``overall``, ``sensors``, ``lids``) and, if
    the suite has any, the interlocked layers' (``interlocked``: ``overall``, ``sensors``)."""
    out: dict[str, Any] = {}
    for v in variants:
        mine = [o for o in outs if o.variant == v]
        grid = [o for o in mine if o.meta.get("pattern", "grid") == "grid"]
        woven = [o for o in mine if o.meta.get("pattern", "grid") != "grid"]
        lids = {}
        for lid in LIDS:
            sel = [o for o in grid if o.meta.get("lid") == lid]
            if sel:
                lids[lid] = {"development": group_figures([o for o in sel
                                                           if o.sensor != held_out]),
                             "all": group_figures(sel)}
        out[v] = {**_by_sensor(grid, sensors, held_out), "lids": lids}
        if woven:
            out[v]["interlocked"] = _by_sensor(woven, sensors, held_out)
    return out


def evaluate_packed_targets(groups: dict[str, Any]) -> list[dict[str, Any]]:
    """Each of :data:`PACKED_TARGETS` in both scopes: the worst group's value, where, pass."""
    rows = []
    for t in PACKED_TARGETS:
        row: dict[str, Any] = {"name": t.name, "variant": t.variant, "key": t.key,
                               "over": t.over, "op": t.op, "bound": t.value,
                               "target": t.text(), "unit": t.unit, "layers": t.layers}
        g = groups.get(t.variant)
        if g is not None and t.layers != "grid":
            g = g.get(t.layers)
        for scope in SCOPES:
            row[scope] = ({"value": None, "where": None, "pass": None} if g is None else
                          target_scope(g, t.over, scope, t.key, t.op, t.value))
        rows.append(row)
    return rows


# --- the run -----------------------------------------------------------------------------


def run_packed_bench(
    n: int = DEFAULT_N,
    seed: int = 0,
    *,
    out: Path | str | None = None,
    jobs: int = 1,
    seeds: int = 1,
    held_out: str = HELD_OUT,
    scan_timeout: float | None = DEFAULT_SCAN_TIMEOUT,
    variants: Sequence[str] = VARIANTS,
    specs: Sequence[Any] | None = None,
    localizer: Localizer | None = None,
    warmup: bool = True,
    progress: bool = True,
    console: Any = None,
    interlocked: int | None = None,
) -> dict[str, Any]:
    """The packed-layer benchmark, with and without the carton list.

    Parameters
    ----------
    n, seed : int
        The scenes are :func:`packed_suite` ``(n, seed, interlocked)``: ``n`` grid layers,
        sensors in turn (n = 96 is 24 per sensor), then the interlocked ones.
    interlocked : int, optional
        Basket-weave scenes after the grids (default :func:`default_interlocked`: 32 to
        96), reported apart (``groups[variant]["interlocked"]``).
    out : path, optional
        Directory for ``bench_packed.json`` and ``bench_packed.txt`` (the printed tables).
    jobs : int
        Worker processes (>= 1). The rows and figures do not depend on it (times do).
    seeds : int
        Draws of the random trials per scene (``trial_seed`` +0..seeds-1), pooled.
    held_out : str
        The sensor model left out of development; reported apart.
    scan_timeout : float or None
        Seconds one variant on one scan may run (after its simulation) before its worker
        is killed and the run counts as a timed-out failure; None: no limit.
    variants : sequence of str
        Some of :data:`VARIANTS`, run in that order on every scan.
    specs : sequence of SceneSpec, optional
        These scenes instead of the suite (tests use tiny ones).
    localizer : callable, optional
        ``(scan, config) -> Result``-like; default the pipeline. Runs in the workers.
    warmup : bool
        Each worker runs the localizer once on a 160 x 120 copy of the first scene first.
    progress : bool
        Show a progress bar and print the tables (rich, stderr).
    console : rich.console.Console, optional

    Returns
    -------
    dict
        The report (see the module docstring).

    Raises
    ------
    InputError
        On n < 1, jobs < 1, seeds < 1, a non-positive timeout, an unknown sensor or an
        unknown variant.
    """
    from boxloc.simulate import SENSORS

    check_run_args(jobs, scan_timeout, held_out)
    variants = tuple(variants)
    bad = [v for v in variants if v not in VARIANTS]
    if bad or not variants or len(set(variants)) != len(variants):
        raise InputError(f"variants must be some of {', '.join(VARIANTS)}, got "
                         f"{', '.join(variants) or 'none'}")
    variants = tuple(v for v in VARIANTS if v in variants)
    if specs is None:
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise InputError(f"bench needs n >= 1 scenes, got {n!r}")
        specs = packed_suite(n, seed, default_interlocked(n) if interlocked is None
                             else interlocked)
    specs = list(specs)
    if not specs:
        raise InputError("bench needs at least one scene")
    cfg, site = matrix_config(specs)
    draws = trial_configs(cfg, seeds)
    import boxloc.pipeline  # noqa: F401 - imported once here, shared by the forked workers

    tasks = [(i, spec, _Job(v, d)) for i, spec in enumerate(specs) for d in draws
             for v in variants]
    outs: list[_Outcome | None] = [None] * len(tasks)
    con = bench_console(console, progress)

    def on_done(t: int, res: dict[str, Any]) -> None:
        i, spec, job = tasks[t]
        o = _Outcome(index=i, trial_seed=job.config.trial_seed, sensor=str(spec.sensor),
                     variant=job.variant, status=res["status"], phase=res.get("phase"),
                     error=res.get("error"), run=res.get("run"))
        meta = res.get("meta")
        if meta is None:  # killed or crashed before the scene existed: make it here
            meta = _parent_meta(spec)
        o.meta = meta
        if o.run is not None:
            o.score, o.wall_ms = o.run.score, o.run.wall_ms
        if o.score is None and meta.get("nothing") is not None:
            o.score = meta["nothing"]
        if res.get("wall_ms") is not None:
            o.wall_ms = res["wall_ms"]
        outs[t] = o

    def summary(t: int) -> str:
        o = outs[t]
        assert o is not None
        return (run_line(o, "variant", tasks[t][1])
                + (f", ambiguous {o.score.amb_area.size}" if o.score else ""))

    def describe(t: int) -> str:
        i, spec, job = tasks[t]
        return f"scene {i} ({spec.sensor}, {job.variant}, {spec.width}x{spec.height})"

    warm = (warmup_spec(specs), cfg) if warmup else None
    info, run_s = run_with_progress(tasks, _packed_task, localizer or _default_localizer, jobs,
                                    scan_timeout, warm, on_done,
                                    console=con if progress else None, label="packed",
                                    describe=describe, summary=summary)
    done = [o for o in outs if o is not None]
    assert len(done) == len(tasks)
    report = _report(done, specs, cfg, site, n=sum(s.pattern == "grid" for s in specs),
                     seed=seed, jobs=jobs, held_out=held_out, scan_timeout=scan_timeout,
                     warmup=warmup,
                     trial_seeds=[d.trial_seed for d in draws], info=info, run_s=run_s,
                     sensors=SENSORS, variants=variants)
    write_report(report, out, REPORT_NAME, TABLE_NAME, print_packed_report,
                 con if progress else None, width=280)
    return report


def _parent_meta(spec: Any) -> dict[str, Any]:
    """The scene's truth summary, simulated here (its worker was lost before it said)."""
    from boxloc.simulate import simulate

    try:
        return _meta(simulate(spec))
    except Exception:  # noqa: BLE001 - the simulator's error is already the run's error
        return {"n_faces": 0, "n_exposed": 0, "n_boxes": 0, "layers": 0,
                "pixels": int(spec.width * spec.height), "spec": _spec_dict(spec),
                "spec_text": _spec_text(spec),
                "lid": "bulged" if float(spec.bulge) > 0 else "flat",
                "pattern": spec.pattern, "sizes_csv": None,
                "edge_min": None, "edge_max": None, "nothing": None}


def _report(outs: list[_Outcome], specs: Sequence[Any], cfg: Config, site: dict[str, Any], *,
            n: int, seed: int, jobs: int, held_out: str, scan_timeout: float | None,
            warmup: bool, trial_seeds: list[int], info: dict[str, Any], run_s: float,
            sensors: Sequence[str], variants: Sequence[str]) -> dict[str, Any]:
    from boxloc.simulate import PATTERNS

    present_s = [s for s in sensors if any(o.sensor == s for o in outs)]
    groups = _groups(outs, present_s, variants, held_out)
    rows: list[dict[str, Any]] = []
    by_scan: dict[tuple[int, int], dict[str, Any]] = {}
    for o in outs:
        m = o.meta
        key = (o.index, o.trial_seed)
        if key not in by_scan:
            by_scan[key] = {
                "index": o.index, "trial_seed": o.trial_seed, "sensor": o.sensor,
                "held_out": o.sensor == held_out, "lid": m.get("lid"),
                "pattern": m.get("pattern", "grid"), "spec": m.get("spec"),
                "spec_text": m.get("spec_text"), "n_faces": m.get("n_faces"),
                "n_exposed": m.get("n_exposed"), "n_boxes": m.get("n_boxes"),
                "layers": m.get("layers"), "pixels": m.get("pixels"),
                "sizes_csv": m.get("sizes_csv"), "runs": {}}
            rows.append(by_scan[key])
        by_scan[key]["runs"][o.variant] = {
            "status": o.status, "error": o.error,
            **(o.score.to_dict() if o.score is not None else {})}
    timeouts, errors = failures(outs, "variant", scan_timeout, info)
    timing: dict[str, Any] = {}
    for v in variants:
        mine = [o for o in outs if o.variant == v]
        tm = _timing([o.run if o.run is not None else _Run(wall_ms=o.wall_ms) for o in mine])
        timing[v] = {"stages_ms": tm["stages_ms"], "total_ms": tm["total_ms"]}
    report: dict[str, Any] = {
        **report_head(SCHEMA, "packed", cfg, observed_site(site, outs), n=n, seed=seed,
                      jobs=jobs, scan_timeout=scan_timeout, warmup=warmup, info=info),
        "sizes": {"source": "the scene's ground truth: its distinct carton sizes (width <= "
                            "length, height), as a CSV file read with read_box_sizes",
                  "rounding_m": SIZE_ROUNDING, "size_tolerance_m": cfg.size_tolerance,
                  "tolerance_source": "Config() default"},
        "suite": {"source": "the layered scenes of boxloc.simulate.matrix_suite(n, seed), in "
                            "order, laid as grids, then the next ones laid as basket weaves "
                            "(packed_suite)",
                  "kind": "layered", "bevel_m": 0.0, "max_gap_m": 0.0,
                  "patterns": {p: sum(s.pattern == p for s in specs) for p in PATTERNS}},
        "held_out": {"sensor": held_out},
        "sensors": present_s, "variants": list(variants), "lids": list(LIDS),
        "seeds": draw_figures({v: [o for o in outs if o.variant == v] for v in variants},
                              list(variants), trial_seeds, present_s),
        "groups": groups,
        "targets": evaluate_packed_targets(groups),
        "timeouts": timeouts,
        "errors": {"total": len(errors), "list": errors},
        "timing": {**timing,
                   "per_scan_ms": {v: [None if o.wall_ms is None else round(o.wall_ms, 3)
                                       for o in outs if o.variant == v] for v in variants},
                   "run_s": round(run_s, 3)},
        "memory": memory_figures(outs),
        "scenes": rows,
    }
    return _jsonable(report)


# --- printing ----------------------------------------------------------------------------


_COLUMNS = ("", "scans", "tops", "TP / FP / FN", "P", "R", "wrong: n / rate",
            "no-match / spans / off-top", "ambig./scan", "missed: in ambig. / silent",
            "silent scans",
            "height n", "height err med / p95 [mm]", "source side / step / sku / none",
            "flagged (TP)", "time med / max [s]", "t-out / err")


def _row(name: str, fig: dict[str, Any]) -> list[str]:
    p, r, _ = prf(fig["tp"], fig["n_pred"], fig["n_exposed"])
    hs = fig["height_sources"]
    t = fig["time"]
    aps = fig["ambiguous_per_scan"]
    return [name, str(fig["n_scans"]), str(fig["n_exposed"]),
            f"{fig['tp']} / {fig['fp']} / {fig['fn']}",
            _fmt(p) if fig["n_pred"] else "-", _fmt(r) if fig["n_exposed"] else "-",
            f"{fig['wrong_rectangles']} / {fig['wrong_rate']:.3f}",
            f"{fig['wrong_no_match']} / {fig['wrong_spans']} / {fig['off_top']}",
            "-" if aps is None else f"{aps:.2f}",
            f"{fig['missed_in_ambiguous']} / {fig['missed_silently']}",
            str(fig["silent_scans"]),
            str(fig["height_n"]),
            f"{_fmt(fig['height_err_median_mm'], 'mm')} / {_fmt(fig['height_err_p95_mm'], 'mm')}",
            " / ".join(str(hs.get(k, 0)) for k in ("side", "step", "sku", "none")),
            f"{fig['sku_flagged']} ({fig['sku_flagged_tp']})",
            " / ".join("-" if t[k] is None else f"{t[k] / 1e3:.2f}"
                       for k in ("median_ms", "max_ms")),
            f"{fig['timeouts']} / {fig['errors']}"]


def print_packed_report(report: dict[str, Any], console: Any) -> None:
    """Print the report: the targets (PASS/FAIL), then per variant a table by sensor and lid."""
    from rich.markup import escape
    from rich.table import Table

    ho = report["held_out"]["sensor"]
    cfg = report["config"]
    pat = report.get("suite", {}).get("patterns", {})
    print_targets(report, console, (
        f"boxloc bench --packed: {report['n']} zero-gap sharp-edged layered pallets "
        f"({pat.get('grid', report['n'])} grids, {pat.get('weave', 0)} basket weaves) x "
        f"{len(report['seeds']['trial_seeds'])} draw(s), seed {report['seed']}, default "
        f"configuration (min_edge {cfg['min_edge']:g} m, max_edge {cfg['max_edge']:g} m), "
        f"with_sizes: + the scene's carton list; held out: {ho}"))

    for v, g in report["groups"].items():
        vt = Table(title=escape(f"{v}: per sensor ({ho}: held out) and per lid"))
        for i, c in enumerate(_COLUMNS):
            vt.add_column(escape(c), justify="left" if i == 0 else "right", no_wrap=i == 0)
        for s, fig in g["sensors"].items():
            vt.add_row(*_row(s + (" (held out)" if fig["held_out"] else ""), fig))
        vt.add_row(*_row(f"all but {ho}", g["overall"]["development"]))
        vt.add_row(*_row(f"all, {ho} included", g["overall"]["all"]))
        for lid, fig in g["lids"].items():
            vt.add_row(*_row(f"{lid} lids, all", fig["all"]))
        woven = g.get("interlocked")
        if woven is not None:
            for s, fig in woven["sensors"].items():
                vt.add_row(*_row(f"interlocked, {s}" + (" (held out)" if fig["held_out"]
                                                        else ""), fig))
            vt.add_row(*_row(f"interlocked, all but {ho}", woven["overall"]["development"]))
            vt.add_row(*_row(f"interlocked, all, {ho} included", woven["overall"]["all"]))
        console.print(vt)
        ov = g["overall"]["all"]
        reasons = ", ".join(f"{k} {c}" for k, c in ov["ambiguous_reasons"].items())
        console.print(escape(f"{v}: ambiguous regions by reason: {reasons or 'none'}; regions "
                             f"over no exposed top: {ov['ambiguous_without_top']}; scored "
                             f"heights nearer the stack's than the box's: "
                             f"{ov['height_stack_like']} of {ov['height_n']}"))

    _print_draws(console, report["seeds"], list(report["variants"]))
    tm = report["timing"]
    for v in report["variants"]:
        tot = tm[v]["total_ms"]
        console.print(escape(f"time per scan [ms], {v}: median {_fmt(tot['median'], 'ms')}, "
                             f"p95 {_fmt(tot['p95'], 'ms')}"))
    console.print(escape(f"the run took {tm['run_s']:.0f} s on {report['jobs']} job(s)"))
    print_failures(report, console, "variant")


def _print_draws(console: Any, draws: dict[str, Any], variants: Sequence[str]) -> None:
    """The per-draw table, per sensor and variant (only when there is more than one draw)."""
    from rich.markup import escape
    from rich.table import Table

    if draws["n"] < 2:
        return
    t = Table(title=f"per draw of the random trials ({draws['n']} trial seeds; the figures "
                    "above pool them): TP / FP / FN, recall / precision")
    t.add_column("trial_seed", justify="right")
    cols = [(g, v) for g in draws["per_seed"][0]["groups"] for v in variants]
    for g, v in cols:
        t.add_column(escape(f"{g}: {v}"), justify="right")
    for d in draws["per_seed"]:
        cells = [str(d["trial_seed"])]
        for g, v in cols:
            e = d["groups"][g][v]
            cells.append(f"{e['tp']} / {e['fp']} / {e['fn']}, "
                         f"{_fmt(e['recall'])} / {_fmt(e['precision'])}")
        t.add_row(*cells)
    console.print(t)


# --- the command line ----------------------------------------------------------------------


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m boxloc.evaluate.packed_bench``: run the bench, print and write the report.

    Returns the exit code: 0 done, 2 bad input (one line on stderr).
    """
    ap = argparse.ArgumentParser(
        prog="python -m boxloc.evaluate.packed_bench",
        description="Packed-layer benchmark (issue 21): zero-gap, sharp-edged layered "
                    "pallets for every sensor of the zoo, default configuration, with and "
                    "without the scene's carton list.")
    ap.add_argument("--n", type=int, default=DEFAULT_N,
                    help=f"grid scenes, sensors in turn (default {DEFAULT_N})")
    ap.add_argument("--interlocked", type=int, default=None,
                    help="basket-weave scenes after them (default a third of --n)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the suite")
    ap.add_argument("--out", type=Path, default=None, help="directory for the report")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes")
    ap.add_argument("--seeds", type=int, default=1, help="draws of the random trials")
    ap.add_argument("--held-out", default=HELD_OUT, help="the held-out sensor")
    ap.add_argument("--scan-timeout", type=float, default=DEFAULT_SCAN_TIMEOUT,
                    help="seconds per run; 0: no limit")
    ap.add_argument("--variants", default=",".join(VARIANTS),
                    help="comma-separated: without_sizes, with_sizes (default both)")
    ap.add_argument("--no-warmup", action="store_true", help="skip the workers' warm-up")
    a = ap.parse_args(argv)
    try:
        run_packed_bench(a.n, a.seed, out=a.out, jobs=a.jobs, seeds=a.seeds,
                         held_out=a.held_out,
                         scan_timeout=None if a.scan_timeout == 0 else a.scan_timeout,
                         variants=[v.strip() for v in a.variants.split(",") if v.strip()],
                         warmup=not a.no_warmup, interlocked=a.interlocked)
    except BoxlocError as e:
        print(f"boxloc bench --packed: {str(e).splitlines()[0]}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())

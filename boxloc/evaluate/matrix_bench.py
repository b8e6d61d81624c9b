"""The matrix benchmark: sensor x scene kind, with the default configuration only.

``boxloc bench --matrix`` runs :func:`run_matrix_bench` on the scenes of
:func:`boxloc.simulate.matrix_suite` (scene ``i``: sensor ``SENSORS[i % 4]``, kind
``MATRIX_KINDS[(i // 4) % 8]``), each scan in a worker process under a wall-time limit, and
scores every scan with :func:`boxloc.evaluate.metrics.match_surfaces` (the simulated bench's
:func:`boxloc.evaluate.scene_bench._run_boxloc`: timing, peak RSS, match, edge report).

The configuration is ``Config()`` with one site input, the smallest and largest box
(``min_edge``, ``max_edge``): the simulator's documented box footprint range
(``SceneSpec.min_edge``, ``SceneSpec.max_edge``), a physical fact of the scenes, the same for
every scene. No other setting and no noise model fitted elsewhere: the verb refuses
``--set`` and ``--config`` with ``--matrix``, so every figure here is a default-configuration
figure. ``--seeds N`` runs each scene with ``trial_seed`` +0..N-1 (other draws of the random
trials, not other settings); every figure pools the draws.

One sensor model is held out of the localizer's development (``held_out``, default ``tof``):
its cells are reported separately, and every overall figure and target is given twice,
``development`` (without it) and ``all`` (with it).

A scan that takes longer than ``scan_timeout`` seconds (from the end of its simulation) is
stopped by killing its worker process; it counts as a failure: nothing found (every exposed
top missed, no surface on a no-box scan but not a clean one either), its time the limit (a
lower bound), and it is listed under ``timeouts``. A crash of the localizer likewise scores
as nothing found and is listed under ``errors``. The scans' results do not depend on
``jobs``: every scan is seeded from its own content, and the rows keep the suite's order.

Layout of ``bench_matrix.json`` (schema ``boxloc.bench_matrix/1``; lengths in the figures
are millimetres where named ``*_mm``, times milliseconds where named ``*_ms``):

- ``schema``, ``version``, ``mode`` (``"matrix"``), ``n`` scenes, ``seed`` of the suite,
  ``jobs``, ``scan_timeout_s``, ``warmup``, ``threads`` (a worker's thread pinning)
- ``default_configuration``: true (the verb refuses anything else); ``config`` (every value
  as run), ``config_hash``, ``site``: ``min_edge``, ``max_edge`` (metres, the only values
  set), ``source`` and ``observed`` (the smallest and largest top edge in the scenes' truth)
- ``held_out``: ``sensor``, ``cells`` (the keys of its cells)
- ``sensors``, ``kinds``, ``no_box_kinds``: the axes, in order
- ``seeds``: the draws of the random trials (:func:`boxloc.evaluate.scene_bench.draw_figures`
  per sensor)
- ``groups``: figures (see below) for ``overall`` (``development`` and ``all``),
  ``sensors`` (per sensor), ``kinds`` (per kind: ``development`` and ``all``) and ``cells``
  (key ``"sensor/kind"``; each also has ``sensor``, ``kind``, ``held_out``)
- ``targets``: one row per entry of :data:`MATRIX_TARGETS`: ``name``, ``key``, ``over``
  (``cell``, ``sensor`` or ``overall``), ``op``, ``bound``, ``target`` (text), ``unit``,
  and per scope (``development``, ``all``) ``value`` (the worst group's figure for
  ``cell``/``sensor``), ``where`` (that group) and ``pass`` (true, false, or null: no data)
- ``timeouts``: one entry per timed-out scan: ``scene``, ``trial_seed``, ``sensor``,
  ``kind``, ``spec_text``, ``phase`` (``simulate``, ``localize`` or ``warmup``), ``limit_s``
- ``errors``: ``total`` and ``list`` (``scene``, ``trial_seed``, ``sensor``, ``kind``,
  ``phase``, ``error``) of scans that crashed (localizer, simulator, worker process)
- ``timing``: ``stages_ms`` (median, p95 per stage over the scans that finished),
  ``total_ms`` (median, p95 over all scans), ``per_scan_ms`` (in the order of ``scenes``; a
  timed-out scan's is the limit, so a maximum or ratio over it is a lower bound), ``run_s``,
  ``funnel_ms`` (``median``, ``max``, ``total`` of the loss funnel's time per scan, computed
  after the timed run, and its ``share`` of those scans' localizer time)
- ``memory``: the workers' peak RSS per scan (median and max, MB) and this process's
- ``scenes``: one deterministic row per scan (scene and draw, in suite order): ``index``,
  ``trial_seed``, ``sensor``, ``kind``, ``held_out``, ``spec``, ``spec_text``,
  ``n_faces``, ``n_exposed``, ``pixels``, ``status`` (``ok``, ``error``, ``timeout``),
  ``error``, ``match`` (:meth:`boxloc.evaluate.metrics.Match.to_dict`), ``edges``
  (:func:`boxloc.evaluate.metrics.edge_report`, null without an edge map), ``funnel``
  (:meth:`boxloc.evaluate.funnel.FaceLosses.to_dict`: per exposed face the stage that lost
  it, its evidence and ``separable``; ``{"error": ...}`` if the diagnostic failed, null
  without stage products); no durations, so two runs' rows compare equal

Figures of a group (:func:`group_figures`): ``n_scenes``, ``n_scans``, every key of
:func:`boxloc.evaluate.metrics.aggregate_matches` (``n_exposed`` exposed tops, ``tp``, ``fp``,
``fn`` misses, ``n_pred`` surfaces found, ``precision``, ``recall``,
``grasp_err_median_mm``, ``grasp_err_p95_mm``, ...), ``errors``, ``timeouts``, ``time``
(``median_ms``, ``p99_ms``, ``max_ms``, ``max_over_median``) and ``no_box`` (null without a
scan of a no-box kind):
``n_scans``, ``false_surfaces``, ``false_surfaces_per_scan``, ``zero_surface_scans``,
``zero_surface_share`` (a timed-out or crashed scan is not a clean one), ``edge_scans``
(the scans with an edge map), ``pixels`` (their image pixels), ``edge_points`` (pixels
labelled an edge in ``result.edges``), ``false_edge_points`` (those farther than 1 px from
a true edge: the bare pallet of ``empty`` has real edges), ``edge_points_per_pixel``,
``false_edge_points_per_pixel``; ``funnel``: where the exposed tops were lost
(:func:`boxloc.evaluate.funnel.funnel_figures`): ``faces``, ``stages`` (tops per stage that
lost them: ``edges``, ``lines``, ``vertex``, ``hyp``, ``verify``, ``select``, ``found`` = the
true positives, and ``none`` for a miss on a scan without stage products: timed out,
crashed), ``verify_reasons`` (the :class:`boxloc.products.VerifyReason` of the best attempt
of each ``verify`` loss), ``hyp_sources`` (the
:class:`boxloc.products.DimensionSource` of the best overlapping attempt of each ``hyp``
loss; ``none``: no attempt overlaps; ``REGION``: one flat region over several tops),
``separable`` (tops with no side that is a flush seam the
noise-free render cannot show: :func:`boxloc.evaluate.funnel.separable_faces`; a scene whose
lids have a bevel or a bulge has none), ``separable_tp``, ``separable_recall`` and
``inseparable_misses`` (missed tops that no method could separate without a list of box
sizes), ``funnel_errors`` (scans whose diagnostic failed); ``false_kinds``: the false
positives by what they are (:class:`boxloc.evaluate.metrics.FalseKind`: ``no_top``,
``covered``, ``seen_in_part``, ``wrong_rectangle``, ``normal``).

The funnel (:func:`boxloc.evaluate.funnel.loss_stages`) runs in the worker on every scan
that finished, after its timed localizer run, so it changes no time figure; printed, it is
one loss line per sensor under the per-sensor table.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from boxloc import __version__
from boxloc.config import Config
from boxloc.errors import InputError
from boxloc.evaluate.funnel import (
    CHI2_2_MEDIAN,
    CHI2_2_P99,
    NO_PRODUCTS,
    STAGE_NAMES,
    Z_MEDIAN,
    Z_P99,
    funnel_figures,
    line_direction_figures,
    line_direction_z,
    loss_stages,
    separable_faces,
    vertex_normal_chi2,
    vertex_normal_figures,
)
from boxloc.evaluate.metrics import (
    Match,
    aggregate_matches,
    false_kind_counts,
    false_kinds,
    prf,
)
from boxloc.evaluate.scene_bench import (
    _default_localizer,
    _err,
    _fmt,
    _jsonable,
    _MethodRun,
    _run_boxloc,
    _spec_dict,
    _spec_text,
    _timing,
    draw_figures,
    print_draws,
    process_max_rss_mb,
    trial_configs,
)
from boxloc.evaluate.workers import (
    Localizer,
    bench_console,
    check_run_args,
    run_with_progress,
    warmup_spec,
)

SCHEMA = "boxloc.bench_matrix/1"
#: The sensor model left out of the localizer's development (issue 20, part 5).
HELD_OUT = "tof"
#: Scene kinds with no box: every surface found there is false.
NO_BOX_KINDS: tuple[str, ...] = ("empty", "floor")
#: Scenes of the default suite: 10 per cell.
DEFAULT_N = 320
#: Seconds a scan may take (from the end of its simulation) before its worker is killed.
DEFAULT_SCAN_TIMEOUT = 120.0
#: The two scopes of every overall figure and target.
SCOPES: tuple[str, ...] = ("development", "all")
REPORT_NAME = "bench_matrix.json"
TABLE_NAME = "bench_matrix.txt"


@dataclass(frozen=True)
class MatrixTarget:
    """One target of the matrix benchmark.

    ``key`` is a figure of :func:`group_figures` (a dotted path into it); ``over`` says
    which groups it must hold in: ``"cell"`` (every sensor x kind cell), ``"sensor"`` (every
    sensor) or ``"overall"``; for the first two the worst group's figure is the value.
    The bound is ``value``, or ``alpha_times`` times the configuration's ``alpha``.
    """

    name: str
    over: str
    key: str
    op: str
    value: float | None = None
    alpha_times: float | None = None
    unit: str = ""

    def bound(self, config: Config) -> float:
        if self.alpha_times is not None:
            return self.alpha_times * config.alpha
        assert self.value is not None
        return self.value

    def text(self, config: Config) -> str:
        b = self.bound(config)
        if self.alpha_times is not None:
            return f"{self.op} {self.alpha_times:g} alpha = {b:g}"
        return f"{self.op} {b:g}{(' ' + self.unit) if self.unit else ''}"


#: The targets of issue 20, in one place.
MATRIX_TARGETS: tuple[MatrixTarget, ...] = (
    MatrixTarget("precision in every cell", "cell", "precision", ">=", 0.98),
    MatrixTarget("recall overall", "overall", "recall", ">=", 0.9),
    MatrixTarget("no-box scans with zero surfaces, every sensor", "sensor",
                 "no_box.zero_surface_share", ">=", 0.99),
    MatrixTarget("median grasp error", "overall", "grasp_err_median_mm", "<=", 3.0, unit="mm"),
    MatrixTarget("slowest scan / median scan", "overall", "time.max_over_median", "<=", 10.0),
    MatrixTarget("false edge points per pixel on no-box scans, every sensor", "sensor",
                 "no_box.false_edge_points_per_pixel", "<=", alpha_times=2.0),
)


# --- the site input ----------------------------------------------------------------------


def site_box_range() -> tuple[float, float]:
    """The simulator's documented box footprint range, metres: ``SceneSpec``'s defaults of
    ``min_edge`` and ``max_edge`` (``matrix_suite`` never changes them)."""
    from boxloc.simulate import SceneSpec

    spec = SceneSpec()
    return float(spec.min_edge), float(spec.max_edge)


def matrix_config(specs: Sequence[Any]) -> tuple[Config, dict[str, Any]]:
    """``Config()`` with the site's box range, and the ``site`` section that says so.

    Raises
    ------
    InputError
        If a scene's box range is not the simulator's documented one (the one site input
        must be the same for every scene).
    """
    lo, hi = site_box_range()
    for s in specs:
        if (getattr(s, "min_edge", lo), getattr(s, "max_edge", hi)) != (lo, hi):
            raise InputError(f"matrix scene with box range {s.min_edge}-{s.max_edge} m, not "
                             f"the simulator's {lo}-{hi} m: one site input for every scene")
    site = {"min_edge": lo, "max_edge": hi,
            "source": "boxloc.simulate.SceneSpec min_edge/max_edge defaults: the box "
                      "footprint range every matrix scene is drawn from"}
    return Config(min_edge=lo, max_edge=hi), site


# --- one scan, in a worker process ---------------------------------------------------------


@dataclass
class _Outcome:
    """One scan (scene and draw) as the parent sees it."""

    index: int
    trial_seed: int
    sensor: str
    kind: str
    status: str = "ok"
    phase: str | None = None
    error: str | None = None
    run: _MethodRun | None = None
    match: Match | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    wall_ms: float | None = None
    #: :meth:`boxloc.evaluate.funnel.FaceLosses.to_dict`, ``{"error": ...}`` if the funnel
    #: failed, None without stage products (timed out, crashed, surfaces-only localizer)
    funnel: dict[str, Any] | None = None
    funnel_ms: float | None = None

    @property
    def group(self) -> str:  # for draw_figures: the draws per sensor
        return self.sensor

    @property
    def edges(self) -> dict[str, Any] | None:
        return self.run.edges if self.run is not None else None


def _nothing_found(truth: Any) -> Match:
    """The match of "found nothing" (a crashed or timed-out scan)."""
    from boxloc.evaluate.scene_bench import _empty_match

    return _empty_match(truth)


def _flush_seams_show(spec: Any) -> bool:
    """Whether the scene's lids give a flush seam relief: a bevel (a groove) or a bulge (a
    valley); see :func:`boxloc.evaluate.funnel.separable_faces`."""
    return bool(getattr(spec, "bevel", 0.0) > 0 or getattr(spec, "bulge", 0.0) > 0)


def _meta(sim: Any) -> dict[str, Any]:
    from boxloc.simulate.truth import resting_on

    truth = sim.truth
    h, w = sim.scan.range.shape[:2]
    t = truth if len(truth) else None
    exposed = np.flatnonzero(np.asarray(truth.fully_exposed, dtype=bool))
    separable = separable_faces(truth, sim.scan.sensor, exposed,
                                flush_seams_show=_flush_seams_show(sim.spec))
    return {"n_faces": int(len(truth)), "n_exposed": int(exposed.size),
            "pixels": int(h * w), "spec": _spec_dict(sim.spec), "spec_text": _spec_text(sim.spec),
            "edge_min": float(np.min(t.width)) if t is not None else None,
            "edge_max": float(np.max(t.length)) if t is not None else None,
            "nothing": _nothing_found(truth),
            "exposed_faces": [int(f) for f in exposed],
            "separable": [bool(v) for v in separable],
            "covered_faces": [int(f) for f in np.flatnonzero(resting_on(truth))]}


def _funnel(result: Any, sim: Any, match: Match | None, separable: list[bool]
            ) -> tuple[dict[str, Any] | None, float | None]:
    """The scan's loss funnel (:func:`boxloc.evaluate.funnel.loss_stages`) as JSON and its
    time in ms; None without stage products. Computed after the timed localizer run."""
    if result is None or match is None or getattr(result, "verification", None) is None:
        return None, None
    t0 = time.perf_counter()
    try:
        fl = loss_stages(result, sim.truth, sim.scan.sensor, match=match,
                         separable=separable).to_dict()
        fl["vertex_normal_chi2"] = [round(float(v), 4)
                                    for v in vertex_normal_chi2(result.vertices, sim.truth)]
        z, kinds = line_direction_z(result.lines, sim.truth)
        fl["line_direction_z"] = [round(float(v), 4) for v in z]
        fl["line_kinds"] = [int(k) for k in kinds]
    except Exception as e:  # noqa: BLE001 - a diagnostic's crash must not lose the scan
        return {"error": _err(e)}, None
    return fl, (time.perf_counter() - t0) * 1e3


def _scan_task(conn: Connection | None, task: int, spec: Any, config: Config,
               localizer: Localizer, cache: dict[str, Any] | None = None) -> dict[str, Any]:
    """Simulate one scene and run the localizer on it (``conn``: say when it starts).

    The workers' task function (:data:`boxloc.evaluate.workers.TaskFn`); ``cache`` goes
    unused: each task simulates its scene.
    """
    from boxloc.simulate import simulate

    try:
        sim = simulate(spec)
        meta = _meta(sim)
    except Exception as e:  # noqa: BLE001 - a scene that cannot be made is a reported error
        return {"status": "error", "phase": "simulate", "error": _err(e)}
    if conn is not None:
        conn.send(("started", task, meta))
    results: list[Any] = []

    def keep(scan: Any, cfg: Config) -> Any:  # the Result, for the funnel after the timing
        results.append(localizer(scan, cfg))
        return results[-1]

    run = _run_boxloc(keep, sim.scan, sim.truth, config)
    if run.error is not None:
        run.match = meta["nothing"]
        return {"status": "error", "phase": "localize", "error": run.error, "run": run,
                "meta": meta}
    funnel, funnel_ms = _funnel(results[-1] if results else None, sim, run.match,
                                meta["separable"])
    return {"status": "ok", "run": run, "meta": meta, "funnel": funnel, "funnel_ms": funnel_ms}


# --- figures -----------------------------------------------------------------------------


def _pct(a: np.ndarray, q: float) -> float | None:
    return float(np.percentile(a, q)) if a.size else None


def _time_figures(outs: Sequence[_Outcome]) -> dict[str, Any]:
    walls = np.asarray([o.wall_ms for o in outs if o.wall_ms is not None], dtype=np.float64)
    med, mx = _pct(walls, 50), (float(walls.max()) if walls.size else None)
    return {"median_ms": med, "p99_ms": _pct(walls, 99), "max_ms": mx,
            "max_over_median": (mx / med) if med and mx is not None else None}


def _no_box_figures(outs: Sequence[_Outcome]) -> dict[str, Any] | None:
    sel = [o for o in outs if o.kind in NO_BOX_KINDS]
    if not sel:
        return None
    n = len(sel)
    false_surfaces = sum(o.match.n_pred for o in sel if o.match is not None)
    clean = sum(o.status == "ok" and o.match is not None and o.match.n_pred == 0 for o in sel)
    # (pixels, edge pixels, of which near a true edge) of the scans with an edge map
    counts = [(int(o.meta["pixels"]), int(e["any"]["n_pred"]), int(e["any"]["correct"]))
              for o in sel if o.status == "ok" and (e := o.edges) is not None]
    pixels = sum(c[0] for c in counts)
    pts = sum(c[1] for c in counts)
    false_pts = sum(c[1] - c[2] for c in counts)
    return {"n_scans": n, "false_surfaces": false_surfaces,
            "false_surfaces_per_scan": false_surfaces / n, "zero_surface_scans": clean,
            "zero_surface_share": clean / n, "edge_scans": len(counts), "pixels": pixels,
            "edge_points": pts, "false_edge_points": false_pts,
            "edge_points_per_pixel": pts / pixels if pixels else None,
            "false_edge_points_per_pixel": false_pts / pixels if pixels else None}


def _scan_funnel(o: _Outcome) -> tuple[list[str], list[bool], list[bool],
                                        dict[str, dict[str, int]]]:
    """One scan's exposed faces for :func:`boxloc.evaluate.funnel.funnel_figures`: stage
    names, separable, true positive, and the reasons of its ``verify`` losses and sources of
    its ``hyp`` losses. Without a funnel a face is ``found`` if it is a true positive, else
    ``none``."""
    faces = [int(f) for f in o.meta.get("exposed_faces", [])]
    separable = [bool(v) for v in o.meta.get("separable", [])]
    tp = set() if o.match is None else {int(f) for f in np.asarray(o.match.tp_pairs)[:, 1]}
    found = [f in tp for f in faces]
    fl = o.funnel
    if fl is not None and "stage" in fl and list(fl["face"]) == faces:
        names = [str(s) for s in fl["stage"]]
        why: dict[str, dict[str, int]] = {"verify": {}, "hyp": {}}
        for name, r, src in zip(names, fl["best_reason"], fl["best_source"], strict=True):
            label = {"verify": r, "hyp": src}.get(name, "")
            if name in why:
                key = NO_PRODUCTS if label is None else str(label)
                why[name][key] = why[name].get(key, 0) + 1
        return names, separable, found, why
    return ["found" if f else NO_PRODUCTS for f in found], separable, found, {}


def _false_kinds(outs: Sequence[_Outcome]) -> dict[str, int]:
    """The false positives of the scans by :class:`~boxloc.evaluate.metrics.FalseKind`
    (over the scans whose scene records the covered faces)."""
    kinds = []
    for o in outs:
        if o.match is None or "covered_faces" not in o.meta:
            continue
        covered = np.zeros(int(o.match.n_faces), dtype=bool)
        covered[np.asarray(o.meta["covered_faces"], dtype=np.int64)] = True
        kinds.append(false_kinds(o.match, covered))
    return false_kind_counts(kinds)


def group_figures(outs: Sequence[_Outcome]) -> dict[str, Any]:
    """The figures of a group of scans (see the module docstring)."""
    agg = aggregate_matches(o.match for o in outs if o.match is not None)
    funnel = funnel_figures(_scan_funnel(o) for o in outs)
    funnel["funnel_errors"] = sum(o.funnel is not None and "error" in o.funnel for o in outs)
    fls = [o.funnel for o in outs if o.funnel is not None]
    funnel["vertex_normals"] = vertex_normal_figures(
        [v for f in fls for v in f.get("vertex_normal_chi2", [])])
    funnel["line_directions"] = line_direction_figures(
        [v for f in fls for v in f.get("line_direction_z", [])],
        [k for f in fls for k in f.get("line_kinds", [])])
    return {"n_scenes": len({o.index for o in outs}), **agg,
            "false_kinds": _false_kinds(outs),
            "errors": sum(o.status == "error" for o in outs),
            "timeouts": sum(o.status == "timeout" for o in outs),
            "time": _time_figures(outs), "no_box": _no_box_figures(outs), "funnel": funnel}


def _groups(outs: Sequence[_Outcome], sensors: Sequence[str], kinds: Sequence[str],
            held_out: str) -> dict[str, Any]:
    dev = [o for o in outs if o.sensor != held_out]
    cells: dict[str, Any] = {}
    for s in sensors:
        for k in kinds:
            sel = [o for o in outs if o.sensor == s and o.kind == k]
            if sel:
                cells[f"{s}/{k}"] = {"sensor": s, "kind": k, "held_out": s == held_out,
                                     **group_figures(sel)}
    return {
        "overall": {"development": group_figures(dev), "all": group_figures(outs)},
        "sensors": {s: {"held_out": s == held_out,
                        **group_figures([o for o in outs if o.sensor == s])}
                    for s in sensors if any(o.sensor == s for o in outs)},
        "kinds": {k: {"development": group_figures([o for o in dev if o.kind == k]),
                      "all": group_figures([o for o in outs if o.kind == k])}
                  for k in kinds if any(o.kind == k for o in outs)},
        "cells": cells,
    }


def _get(fig: dict[str, Any] | None, key: str) -> Any:
    for part in key.split("."):
        if not isinstance(fig, dict):
            return None
        fig = fig.get(part)
    return fig


def target_scope(groups: dict[str, Any], over: str, scope: str, key: str, op: str,
                 bound: float) -> dict[str, Any]:
    """One target in one scope: the worst group's figure, where it is, and the verdict.

    Parameters
    ----------
    groups : dict
        ``overall`` (per scope), ``sensors`` and (for ``over == "cell"``) ``cells``, each
        group with ``held_out``.
    over : str
        ``"overall"``, ``"sensor"`` or ``"cell"``: the groups the target must hold in.
    scope : str
        ``"development"`` (the held-out sensor's groups left out) or ``"all"``.
    key : str
        A figure of the groups, dotted into nested dicts.
    op : str
        ``">="`` (the worst group is the smallest value) or ``"<="`` (the largest).
    bound : float

    Returns
    -------
    dict
        ``value``, ``where`` and ``pass`` (all None without a value).
    """
    if over == "overall":
        cands = [("overall", groups["overall"][scope])]
    else:
        table = groups["cells" if over == "cell" else "sensors"]
        cands = [(name, g) for name, g in table.items() if scope == "all" or not g["held_out"]]
    vals = [(name, _get(g, key)) for name, g in cands]
    vals = [(name, v) for name, v in vals if v is not None]
    if not vals:
        return {"value": None, "where": None, "pass": None}
    where, v = (min if op == ">=" else max)(vals, key=lambda nv: nv[1])
    ok = v >= bound if op == ">=" else v <= bound
    return {"value": v, "where": where, "pass": bool(ok)}


def evaluate_matrix_targets(groups: dict[str, Any], config: Config,
                            held_out: str) -> list[dict[str, Any]]:
    """Each of :data:`MATRIX_TARGETS` in both scopes: the worst group's value, where, pass."""
    rows = []
    for t in MATRIX_TARGETS:
        b = t.bound(config)
        row: dict[str, Any] = {"name": t.name, "key": t.key, "over": t.over, "op": t.op,
                               "bound": b, "target": t.text(config), "unit": t.unit}
        for scope in SCOPES:
            row[scope] = target_scope(groups, t.over, scope, t.key, t.op, b)
        rows.append(row)
    return rows


# --- the run -----------------------------------------------------------------------------


def run_matrix_bench(
    n: int = DEFAULT_N,
    seed: int = 0,
    *,
    out: Path | str | None = None,
    jobs: int = 1,
    seeds: int = 1,
    held_out: str = HELD_OUT,
    scan_timeout: float | None = DEFAULT_SCAN_TIMEOUT,
    specs: Sequence[Any] | None = None,
    localizer: Localizer | None = None,
    warmup: bool = True,
    progress: bool = True,
    console: Any = None,
) -> dict[str, Any]:
    """The sensor x scene-kind benchmark with the default configuration.

    Parameters
    ----------
    n, seed : int
        The scenes are ``boxloc.simulate.matrix_suite(n, seed)``.
    out : path, optional
        Directory for ``bench_matrix.json`` and ``bench_matrix.txt`` (the printed tables).
    jobs : int
        Worker processes (>= 1). The rows and figures do not depend on it (times do).
    seeds : int
        Draws of the random trials per scene (``trial_seed`` +0..seeds-1), pooled.
    held_out : str
        The sensor model left out of development; reported apart and recorded.
    scan_timeout : float or None
        Seconds a scan may run (after its simulation) before its worker is killed and the
        scan counts as a timed-out failure; None: no limit.
    specs : sequence of SceneSpec, optional
        These scenes instead of the suite (tests use tiny ones).
    localizer : callable, optional
        ``(scan, config) -> Result``-like; default the pipeline. Runs in the workers (fork:
        any callable; spawn: a picklable one).
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
        On n < 1, jobs < 1, seeds < 1, a non-positive timeout or an unknown sensor.
    """
    from boxloc.simulate import MATRIX_KINDS, SENSORS, matrix_suite

    check_run_args(jobs, scan_timeout, held_out)
    if specs is None:
        if n < 1:
            raise InputError(f"bench needs n >= 1 scenes, got {n}")
        specs = matrix_suite(n, seed)
    specs = list(specs)
    if not specs:
        raise InputError("bench needs at least one scene")
    cfg, site = matrix_config(specs)
    draws = trial_configs(cfg, seeds)
    import boxloc.pipeline  # noqa: F401 - imported once here, shared by the forked workers

    tasks = [(i, spec, d) for i, spec in enumerate(specs) for d in draws]
    outs: list[_Outcome | None] = [None] * len(tasks)
    con = bench_console(console, progress)

    def on_done(t: int, res: dict[str, Any]) -> None:
        i, spec, d = tasks[t]
        o = _Outcome(index=i, trial_seed=d.trial_seed, sensor=str(spec.sensor),
                     kind=str(spec.kind), status=res["status"], phase=res.get("phase"),
                     error=res.get("error"), run=res.get("run"), funnel=res.get("funnel"),
                     funnel_ms=res.get("funnel_ms"))
        meta = res.get("meta")
        if meta is None:  # killed or crashed before the scene existed: make it here
            meta = _parent_meta(spec)
        o.meta = meta
        if o.run is not None:
            o.match, o.wall_ms = o.run.match, o.run.wall_ms
        if o.match is None and meta.get("nothing") is not None:
            o.match = meta["nothing"]
        if res.get("wall_ms") is not None:
            o.wall_ms = res["wall_ms"]
        outs[t] = o

    def summary(t: int) -> str:
        return run_line(outs[t], "kind", tasks[t][1])

    def describe(t: int) -> str:
        i, spec, _ = tasks[t]
        return f"scene {i} ({spec.sensor}, {spec.kind}, {spec.width}x{spec.height})"

    warm = (warmup_spec(specs), cfg) if warmup else None
    info, run_s = run_with_progress(tasks, _scan_task, localizer or _default_localizer, jobs,
                                    scan_timeout, warm, on_done,
                                    console=con if progress else None, label="matrix",
                                    describe=describe, summary=summary)
    done = [o for o in outs if o is not None]
    assert len(done) == len(tasks)
    report = _report(done, specs, cfg, site, n=len(specs), seed=seed, jobs=jobs,
                     held_out=held_out, scan_timeout=scan_timeout, warmup=warmup,
                     trial_seeds=[d.trial_seed for d in draws], info=info, run_s=run_s,
                     sensors=SENSORS, kinds=MATRIX_KINDS)
    write_report(report, out, REPORT_NAME, TABLE_NAME, print_matrix_report,
                 con if progress else None)
    return report


def write_report(report: dict[str, Any], out: Path | str | None, report_name: str,
                 table_name: str, printer: Callable[[dict[str, Any], Any], None],
                 console: Any, width: int = 200) -> None:
    """A bench's report as ``out/report_name`` (JSON) and its tables as ``out/table_name``
    (plain text, ``width`` columns), and the tables on ``console`` (None: not printed)."""
    if out is not None:
        d = Path(out)
        d.mkdir(parents=True, exist_ok=True)
        (d / report_name).write_text(json.dumps(report, indent=1) + "\n")
        from rich.console import Console

        with (d / table_name).open("w") as fh:
            printer(report, Console(file=fh, width=width, no_color=True))
    if console is not None:
        printer(report, console)
        if out is not None:
            console.print(f"wrote {Path(out) / report_name} and {Path(out) / table_name}")


def run_line(o: Any, axis: str, spec: Any) -> str:
    """A finished run in one line (for a log, which sees no progress bar): its scene,
    sensor, other axis (the attribute ``axis``: ``kind``, ``variant``), image size, status,
    time and TP / FP / FN."""
    m = o.match
    return (f"scene {o.index} ({o.sensor}, {getattr(o, axis)}, {spec.width}x{spec.height}): "
            f"{o.status}"
            + (f", {o.wall_ms / 1e3:.1f} s" if o.wall_ms is not None else "")
            + (f", TP {m.tp} FP {m.fp} FN {m.fn}" if m is not None else ""))


def report_head(schema: str, mode: str, cfg: Config, site: dict[str, Any], *, n: int,
                seed: int, jobs: int, scan_timeout: float | None, warmup: bool,
                info: dict[str, Any]) -> dict[str, Any]:
    """The first keys of a default-configuration bench's report (matrix, packed), in order:
    the run's inputs and the one configuration."""
    return {"schema": schema, "version": __version__, "mode": mode, "n": n, "seed": seed,
            "jobs": jobs, "scan_timeout_s": scan_timeout, "warmup": warmup,
            "threads": info.get("threads"),
            "default_configuration": True, "config": cfg.to_dict(), "config_hash": cfg.hash,
            "site": site}


def failures(outs: Sequence[Any], axis: str, scan_timeout: float | None,
             info: dict[str, Any]) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The report's ``timeouts`` and ``errors`` lists, one entry per run that failed.

    ``outs`` have ``index``, ``trial_seed``, ``sensor``, ``status``, ``phase``, ``error``,
    ``meta`` and the attribute ``axis`` (the runs' other axis: ``kind``, ``variant``); the
    workers lost while warming up (``info["warmup_timeouts"]``) are one more timeout entry.
    """
    timeouts, errors = [], []
    for o in outs:
        base = {"scene": o.index, "trial_seed": o.trial_seed, "sensor": o.sensor,
                axis: getattr(o, axis)}
        if o.status == "timeout":
            timeouts.append({**base, "spec_text": o.meta.get("spec_text"), "phase": o.phase,
                             "limit_s": scan_timeout})
        elif o.status == "error":
            errors.append({**base, "phase": o.phase, "error": o.error})
    if info.get("warmup_timeouts"):
        timeouts.append({"scene": None, "trial_seed": None, "sensor": None, axis: None,
                         "spec_text": None, "phase": "warmup", "limit_s": scan_timeout,
                         "count": info["warmup_timeouts"]})
    return timeouts, errors


def observed_site(site: dict[str, Any], outs: Sequence[Any]) -> dict[str, Any]:
    """``site`` with ``observed``: the smallest and largest top edge in the scenes' truth."""
    lo = [float(o.meta["edge_min"]) for o in outs if o.meta.get("edge_min") is not None]
    hi = [float(o.meta["edge_max"]) for o in outs if o.meta.get("edge_max") is not None]
    return {**site, "observed": {"min_edge": min(lo) if lo else None,
                                 "max_edge": max(hi) if hi else None}}


def memory_figures(outs: Sequence[Any]) -> dict[str, Any]:
    """The report's ``memory``: the workers' peak RSS per run and this process's, MB."""
    peaks = np.asarray([o.run.peak_mb for o in outs if o.run and o.run.peak_mb], np.float64)
    return {"worker_peak_rss_mb_median": _pct(peaks, 50),
            "worker_peak_rss_mb_max": float(peaks.max()) if peaks.size else None,
            "process_max_rss_mb": process_max_rss_mb()}


def _parent_meta(spec: Any) -> dict[str, Any]:
    """The scene's truth summary, simulated here (its worker was lost before it said)."""
    from boxloc.simulate import simulate

    try:
        return _meta(simulate(spec))
    except Exception:  # noqa: BLE001 - the simulator's error is already the scan's error
        return {"n_faces": 0, "n_exposed": 0, "pixels": int(spec.width * spec.height),
                "spec": _spec_dict(spec), "spec_text": _spec_text(spec), "edge_min": None,
                "edge_max": None, "nothing": None}


def _report(outs: list[_Outcome], specs: Sequence[Any], cfg: Config, site: dict[str, Any], *,
            n: int, seed: int, jobs: int, held_out: str, scan_timeout: float | None,
            warmup: bool, trial_seeds: list[int], info: dict[str, Any], run_s: float,
            sensors: Sequence[str], kinds: Sequence[str]) -> dict[str, Any]:
    present_s = [s for s in sensors if any(o.sensor == s for o in outs)]
    present_k = [k for k in kinds if any(o.kind == k for o in outs)]
    groups = _groups(outs, present_s, present_k, held_out)
    rows = []
    for o in outs:
        m = o.meta
        rows.append({"index": o.index, "trial_seed": o.trial_seed, "sensor": o.sensor,
                     "kind": o.kind, "held_out": o.sensor == held_out, "spec": m.get("spec"),
                     "spec_text": m.get("spec_text"), "n_faces": m.get("n_faces"),
                     "n_exposed": m.get("n_exposed"), "pixels": m.get("pixels"),
                     "status": o.status, "error": o.error,
                     "match": o.match.to_dict() if o.match is not None else None,
                     "edges": o.edges, "funnel": o.funnel})
    timeouts, errors = failures(outs, "kind", scan_timeout, info)
    runs = [o.run if o.run is not None else _MethodRun(wall_ms=o.wall_ms) for o in outs]
    timing = _timing(runs)
    f_ms = np.asarray([o.funnel_ms for o in outs if o.funnel_ms is not None], np.float64)
    walls = sum(o.wall_ms for o in outs if o.funnel_ms is not None and o.wall_ms is not None)
    report: dict[str, Any] = {
        **report_head(SCHEMA, "matrix", cfg, observed_site(site, outs), n=n, seed=seed,
                      jobs=jobs, scan_timeout=scan_timeout, warmup=warmup, info=info),
        "held_out": {"sensor": held_out,
                     "cells": [k for k, c in groups["cells"].items() if c["held_out"]]},
        "sensors": present_s, "kinds": present_k, "no_box_kinds": list(NO_BOX_KINDS),
        "seeds": draw_figures({"boxloc": outs}, ["boxloc"], trial_seeds, present_s),
        "groups": groups,
        "targets": evaluate_matrix_targets(groups, cfg, held_out),
        "timeouts": timeouts,
        "errors": {"total": len(errors), "list": errors},
        "timing": {"stages_ms": timing["stages_ms"], "total_ms": timing["total_ms"],
                   "per_scan_ms": [None if o.wall_ms is None else round(o.wall_ms, 3)
                                   for o in outs],
                   "run_s": round(run_s, 3),
                   "funnel_ms": {"median": _pct(f_ms, 50), "max": _pct(f_ms, 100),
                                 "total": float(f_ms.sum()),
                                 "share": float(f_ms.sum()) / walls if walls else None}},
        "memory": memory_figures(outs),
        "scenes": rows,
    }
    return _jsonable(report)


# --- printing ----------------------------------------------------------------------------


def _pr(fig: dict[str, Any]) -> tuple[str, str]:
    """Precision and recall; a group with nothing to find or nothing found says so."""
    p, r, _ = prf(fig["tp"], fig["n_pred"], fig["n_exposed"])
    return (_fmt(p) if fig["n_pred"] else "-", _fmt(r) if fig["n_exposed"] else "-")


def _row(name: str, fig: dict[str, Any]) -> list[str]:
    p, r = _pr(fig)
    t, nb = fig["time"], fig["no_box"]
    ratio = t["max_over_median"]
    cells = [name, str(fig["n_scenes"]), str(fig["n_exposed"]),
             f"{fig['tp']} / {fig['fp']} / {fig['fn']}", p, r,
             f"{_fmt(fig['grasp_err_median_mm'], 'mm')} / {_fmt(fig['grasp_err_p95_mm'], 'mm')}",
             " / ".join("-" if t[k] is None else f"{t[k] / 1e3:.2f}"
                        for k in ("median_ms", "p99_ms", "max_ms")),
             "-" if ratio is None else f"{ratio:.1f}",
             f"{fig['timeouts']} / {fig['errors']}"]
    if nb is None:
        cells += ["", "", ""]
    else:
        epp = [nb["edge_points_per_pixel"], nb["false_edge_points_per_pixel"]]
        cells += [f"{nb['false_surfaces_per_scan']:.2f}", f"{nb['zero_surface_share']:.2f}",
                  " / ".join("-" if v is None else f"{v:.4f}" for v in epp)]
    return cells


_COLUMNS = ("", "scenes", "tops", "TP / FP / FN", "P", "R", "grasp med / p95 [mm]",
            "time med / p99 / max [s]", "max/med", "t-out / err", "no-box FS/scan",
            "no-box zero", "no-box edge/px all / false")


def _table(title: str) -> Any:
    from rich.markup import escape
    from rich.table import Table

    t = Table(title=escape(title))
    for i, c in enumerate(_COLUMNS):
        t.add_column(escape(c), justify="left" if i == 0 else "right")
    return t


def funnel_line(fig: dict[str, Any]) -> str:
    """One group's loss funnel in one line: exposed tops per stage that lost them (pipeline
    order, empty stages left out), the verify losses' reasons, the separable tops' recall."""
    f = fig.get("funnel")
    if not f or not f["faces"]:
        return "no exposed tops"
    parts = []
    for name in (*STAGE_NAMES, NO_PRODUCTS):
        n = f["stages"].get(name, 0)
        if not n:
            continue
        txt = f"{name} {n}"
        detail = {"verify": f["verify_reasons"], "hyp": f.get("hyp_sources")}.get(name)
        if detail:
            top = sorted(detail.items(), key=lambda kv: (-kv[1], kv[0]))
            txt += " (" + ", ".join(f"{k} {v}" for k, v in top) + ")"
        parts.append(txt)
    rec = f["separable_recall"]
    return (f"{f['faces']} tops: " + ", ".join(parts)
            + f"; separable {f['separable']}: recall "
            + ("-" if rec is None else f"{rec:.3f}")
            + f", misses not separable {f['inseparable_misses']}"
            + (f", funnel errors {f['funnel_errors']}" if f.get("funnel_errors") else ""))


def vertex_normal_line(fig: dict[str, Any]) -> str:
    """One group's vertex-normal calibration
    (:func:`boxloc.evaluate.funnel.vertex_normal_figures`)."""
    v = (fig.get("funnel") or {}).get("vertex_normals")
    if not v or not v["n"]:
        return "no vertex at an exposed top's corner"
    out = (f"{v['n']} vertices: median {v['median']:.2f}, "
           f"beyond the 1 % value {v['beyond_p99']:.3f}")
    lines = (fig.get("funnel") or {}).get("line_directions") or {}
    for name, g in lines.items():
        if g["n"]:
            out += (f"; {name} lines {g['n']}: median |z| {g['median_abs']:.2f}, "
                    f"beyond {Z_P99:.2f} {g['beyond_p99']:.3f}")
    return out


def print_funnel(report: dict[str, Any], console: Any) -> None:
    """The loss line of every sensor and of both overall scopes."""
    from rich.markup import escape

    g, ho = report["groups"], report["held_out"]["sensor"]
    console.print("where the exposed tops were lost (boxloc.evaluate.funnel; found = TP):")
    rows = [(s + (" (held out)" if fig["held_out"] else ""), fig)
            for s, fig in g["sensors"].items()]
    rows += [(f"all but {ho}", g["overall"]["development"]),
             (f"all, {ho} included", g["overall"]["all"])]
    width = max(len(name) for name, _ in rows)
    for name, fig in rows:
        console.print(escape(f"  {name:<{width}}  {funnel_line(fig)}"), soft_wrap=True)
    console.print(escape(
        "vertex normals at a true top's corner against its normal, over their covariance "
        f"(chi2(2) if calibrated: median {CHI2_2_MEDIAN:.2f}, 1 % beyond {CHI2_2_P99:.2f}); "
        "lines along its sides out of its plane, over their sigma (N(0, 1) if calibrated: "
        f"median |z| {Z_MEDIAN:.2f}, 1 % beyond {Z_P99:.2f}):"))
    for name, fig in rows:
        console.print(escape(f"  {name:<{width}}  {vertex_normal_line(fig)}"), soft_wrap=True)
    console.print("what the false surfaces are (boxloc.evaluate.metrics.FalseKind):")
    for name, fig in rows:
        console.print(escape(f"  {name:<{width}}  {false_kind_line(fig)}"), soft_wrap=True)


def false_kind_line(fig: dict[str, Any]) -> str:
    """One group's false surfaces by kind, e.g. ``15 false: wrong_rectangle 10, no_top 4,
    covered 1``; the kinds with none left out."""
    kinds = fig.get("false_kinds") or {}
    parts = [f"{k} {v}" for k, v in sorted(kinds.items(), key=lambda kv: -kv[1]) if v]
    return f"{fig.get('fp', 0)} false" + (": " + ", ".join(parts) if parts else "")


def print_targets(report: dict[str, Any], console: Any, title: str) -> None:
    """The targets table under ``title``: per scope the value (and the worst group) and
    PASS, FAIL or n/a."""
    from rich.markup import escape
    from rich.table import Table

    ho = report["held_out"]["sensor"]
    t = Table(title=escape(title))
    t.add_column("target")
    t.add_column("bound", justify="right")
    for scope in SCOPES:
        label = f"without {ho}" if scope == "development" else f"with {ho}"
        t.add_column(escape(f"{label}: value (where)"), justify="right")
        t.add_column("", justify="center")
    mark = {True: "[green]PASS[/]", False: "[red]FAIL[/]", None: "[dim]n/a[/]"}
    for row in report["targets"]:
        cells = [escape(row["name"]), escape(row["target"])]
        for scope in SCOPES:
            s = row[scope]
            v = s["value"]
            txt = "-" if v is None else (f"{v:.4g}" if isinstance(v, float) else str(v))
            if s["where"] is not None and row["over"] != "overall":
                txt += f" ({s['where']})"
            cells += [escape(txt), mark[s["pass"]]]
        t.add_row(*cells)
    console.print(t)


def print_failures(report: dict[str, Any], console: Any, axis: str,
                   timeout_seed: bool = False) -> None:
    """One line per timed-out and per crashed run; ``axis`` names the runs' other axis
    (``kind``, ``variant``), ``timeout_seed`` puts the draw in a timeout's line."""
    from rich.markup import escape

    for to in report["timeouts"]:
        if to["phase"] == "warmup":
            console.print(escape(f"[timeout] {to['count']} worker warm-up(s) over the limit"))
        else:
            seed = f"trial_seed {to['trial_seed']}, " if timeout_seed else ""
            console.print(escape(f"[timeout] scene {to['scene']} ({seed}{to['sensor']}, "
                                 f"{to[axis]}) over {to['limit_s']:g} s in {to['phase']}: "
                                 f"{to['spec_text']}"))
    for e in report["errors"]["list"]:
        console.print(escape(f"[error] scene {e['scene']} ({e['sensor']}, {e[axis]}) "
                             f"{e['phase']}: {e['error']}"))


def print_matrix_report(report: dict[str, Any], console: Any) -> None:
    """Print the report: targets (PASS/FAIL), per sensor, per kind, the cells, timeouts."""
    from rich.markup import escape

    g, ho = report["groups"], report["held_out"]["sensor"]
    cfg = report["config"]
    print_targets(report, console, (
        f"boxloc bench --matrix: {report['n']} scenes x {len(report['seeds']['trial_seeds'])} "
        f"draw(s), seed {report['seed']}, default configuration (min_edge "
        f"{cfg['min_edge']:g} m, max_edge {cfg['max_edge']:g} m, the site input; nothing "
        f"else set), held out: {ho}"))

    st = _table(f"per sensor ({ho}: held out)")
    for s, fig in g["sensors"].items():
        st.add_row(*_row(s + (" (held out)" if fig["held_out"] else ""), fig))
    st.add_row(*_row(f"all but {ho}", g["overall"]["development"]))
    st.add_row(*_row(f"all, {ho} included", g["overall"]["all"]))
    console.print(st)
    print_funnel(report, console)

    kt = _table(f"per scene kind, without {ho} (the held-out sensor)")
    for k, fig in g["kinds"].items():
        kt.add_row(*_row(k, fig["development"]))
    console.print(kt)

    for held, title in ((False, "cells (sensor/kind), development sensors"),
                        (True, f"held out: the {ho} cells")):
        ct = _table(title)
        for key, fig in g["cells"].items():
            if fig["held_out"] == held:
                ct.add_row(*_row(key, fig))
        console.print(ct)

    print_draws(console, report["seeds"], ["boxloc"])
    tm = report["timing"]
    tot = tm["total_ms"]
    console.print(escape(f"time per scan [ms], all scans: median {_fmt(tot['median'], 'ms')}, "
                         f"p95 {_fmt(tot['p95'], 'ms')}; the run took "
                         f"{tm['run_s']:.0f} s on {report['jobs']} job(s)"))
    mem = report["memory"]
    console.print(escape(f"peak RSS of a worker [MB]: median "
                         f"{_fmt(mem['worker_peak_rss_mb_median'], 'MB')}, max "
                         f"{_fmt(mem['worker_peak_rss_mb_max'], 'MB')}"))
    print_failures(report, console, "kind", timeout_seed=True)

"""The benchmark on real labelled scans (mOSD): the localizer and the open3d peer, same frames.

``boxloc bench --real DIR`` runs :func:`run_real_bench`: every organized PCD/PLY in DIR that
has a ``label`` field is read, its top faces are derived from the labels
(:func:`boxloc.evaluate.real.top_faces`), both methods run on it and are scored with
:func:`boxloc.evaluate.real.score_real` (image IoU >= 0.5 with an exposed face's region, normal
within 15 degrees). The synthetic benchmark (:mod:`boxloc.evaluate.scene_bench`) is separate;
this module borrows its timing, memory and report helpers.

Inputs both methods get, and the report says which:

* **noise** -- ``"auto"`` (default): the config as given, so with its default
  ``noise_auto`` each scan's own model (:mod:`boxloc.stages.scan_noise`), nothing fitted on the
  benchmarked frames; ``"estimate"``: the range-noise model fitted to the frames
  themselves with :func:`boxloc.calibrate.noise.estimate_noise` (flat tiles, kept inside one label
  segment), then its ``edge_px`` measured on them with
  :func:`boxloc.calibrate.edgeblur.estimate_edge_px` (no labels), and pinned -- fitted on the frames
  it scores, so not a default-configuration figure; ``"config"``: the config's ``noise``
  pinned as given (e.g. from a calibrated TOML). The ground truth
  (:func:`boxloc.evaluate.real.top_faces`) and the poses always use a model fitted with the labels:
  they are the benchmark's, not the localizer's.
* **squareness** -- ``"cross"`` (default): the prior ``angle_tolerance`` measured with
  :func:`boxloc.calibrate.squareness.estimate_angle_tolerance` on the frames of the *other* groups
  (the box frames are scored with the tolerance of the stacked ones and vice versa), so no
  frame is scored with a prior fitted on it; ``"estimate"``: measured on all the frames,
  those scored included; ``"config"``: as given.
* **pose** -- ``"plane"`` (default): ``sensor_to_base`` from each frame's dominant plane
  (:func:`boxloc.evaluate.real.support_plane_pose`, no labels), the stand-in for a robot cell's
  camera calibration. mOSD's Kinect looks down at ~50 degrees, so without it "up" is the
  sensor's -z and every top is tilted past the default ``max_tilt``. ``"none"``: scans as read.

Layout of ``bench_real.json`` (lengths in mm, angles in degrees, times in ms):

- ``version``, ``data_dir``, ``n_frames``, ``config`` (as run, noise included),
  ``config_hash``, ``noise`` (source, model, fit summary, ``edge_blur``), ``squareness`` (source,
  ``angle_tolerance_deg``, corners used, spread), ``pose``, ``threads``,
  ``warmup``, ``crash_policy``, ``truth_rule``
- ``seeds``: ``n`` draws of the random trials (``trial_seed`` the config's, +1, ...),
  ``trial_seeds``, ``per_seed`` (each draw's TP, FP, FN, precision and recall per group
  and method) and ``spread`` (their min, max and mean)
- ``summary``: pooled figures per method (:func:`boxloc.evaluate.metrics.aggregate_matches`), over
  every frame and draw
- ``groups``: the same per frame group (``boxes`` = learn0-16, ``stacked`` = learn17-24,
  ``other``), each with ``n_frames`` and per-method ``errors``
- ``targets``: recall >= 0.9 and precision >= 0.95 on the box frames, no crash on any
  frame: name, target, value, baseline value, pass
- ``timing``: per method, median/p95 per stage and of the wall time, per-frame wall times
- ``memory``: per-method peak RSS and the process's ``ru_maxrss``
- ``errors``: counts per method and the list (frame, method, trial seed, message)
- ``skipped``: files not benchmarked and why (no labels, unreadable)
- ``frames``: one deterministic row per frame and draw (``trial_seed``, truth summary,
  per-method counts, status of every prediction, per-TP errors; no durations)
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from boxloc import __version__
from boxloc.config import Config
from boxloc.errors import InputError
from boxloc.evaluate.metrics import Match, aggregate_matches, percentiles_ms
from boxloc.evaluate.scene_bench import (
    LABELS,
    METHODS,
    PeakRSS,
    Target,
    _err,
    _fmt,
    _jsonable,
    _limit_threads,
    _max,
    draw_figures,
    print_draws,
    print_timing,
    process_max_rss_mb,
    progress_bar,
    trial_configs,
)
from boxloc.scan import NoiseModel, Scan

__all__ = ["REAL_TARGETS", "GROUPS", "list_frames", "run_real_bench", "print_real_report"]

#: Frame groups, in report order (see :func:`boxloc.evaluate.real.frame_group`).
GROUPS: tuple[str, ...] = ("boxes", "stacked", "other")
#: The issue's targets: on the box frames, and no crash anywhere.
REAL_TARGETS: tuple[Target, ...] = (
    Target("recall (box frames)", "boxes.recall", ">=", 0.9),
    Target("precision (box frames)", "boxes.precision", ">=", 0.95),
    Target("crashes (all frames)", "crashes", "<=", 0.0),
)
#: Files that can carry a per-point label field.
LABELLED_SUFFIXES: tuple[str, ...] = (".pcd", ".ply")

TRUTH_RULE = (
    "top face = the object's plane (sequential RANSAC in its label mask) whose normal is "
    "closest to the table's, within 20 deg; region = that plane's pixels; exposed unless "
    "another object rests on it (above it, reaching no lower than 2 cm below it, and over "
    "its footprint). TP: image IoU >= 0.5 between the rectangle's seen pixels and the "
    "region of an exposed face, and normal within 15 deg; centre error vs the region's "
    "centroid."
)


def _natural_key(p: Path) -> tuple[Any, ...]:
    """learn2 before learn10."""
    return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name))


def list_frames(data_dir: str | Path, frames: Sequence[str] | None = None) -> list[Path]:
    """The labelled-format files of ``data_dir`` in natural order, optionally only ``frames``
    (file stems or names).

    Raises
    ------
    InputError
        If the directory does not exist, holds no PCD/PLY, or a requested frame is missing.
    """
    d = Path(data_dir)
    if not d.is_dir():
        raise InputError(f"--real {d}: not a directory")
    files = sorted((f for f in d.iterdir()
                    if f.is_file() and f.suffix.lower() in LABELLED_SUFFIXES), key=_natural_key)
    if not files:
        raise InputError(f"no labelled scans ({', '.join(LABELLED_SUFFIXES)}) in {d}")
    if frames is None:
        return files
    by_name = {f.stem: f for f in files} | {f.name: f for f in files}
    missing = [n for n in frames if n not in by_name]
    if missing:
        raise InputError(f"frame(s) not in {d}: {', '.join(missing)}")
    return [by_name[n] for n in frames]


@dataclass
class _Frame:
    name: str
    group: str
    scan: Scan
    labels: np.ndarray
    truth: Any = None


@dataclass
class _Run:
    """One method on one frame."""

    match: Match | None = None
    stage_ms: dict[str, float] = field(default_factory=dict)
    wall_ms: float | None = None
    peak_mb: float | None = None
    error: str | None = None
    group: str = ""
    trial_seed: int = 0


def _default_localizer(scan: Scan, config: Config) -> Any:
    from boxloc.pipeline import find_graspable_surfaces

    return find_graspable_surfaces(scan, config)


def _run(call: Callable[[], tuple[Any, dict[str, float]]], frame: _Frame) -> _Run:
    from boxloc.evaluate.real import score_real

    run = _Run(group=frame.group)
    try:
        with PeakRSS() as pk:
            t0 = time.perf_counter()
            surfaces, stages = call()
            run.wall_ms = (time.perf_counter() - t0) * 1e3
        run.peak_mb = pk.peak_mb
        run.stage_ms = {k: float(v) for k, v in stages.items()}
        run.match = score_real(surfaces, frame.truth, frame.scan)
    except Exception as e:  # noqa: BLE001 - a crash on one frame is a result, not the end
        run.error = _err(e)
    return run


def _calls(method: str, frame: _Frame, config: Config,
           localizer: Callable[[Scan, Config], Any]) -> Callable[[], tuple[Any, dict[str, float]]]:
    if method == "boxloc":
        def call() -> tuple[Any, dict[str, float]]:
            result = localizer(frame.scan, config)
            return result.surfaces, dict(getattr(result, "timing_ms", {}))
    else:
        def call() -> tuple[Any, dict[str, float]]:
            from boxloc.evaluate.baseline import baseline_surfaces

            timing: dict[str, float] = {}
            return baseline_surfaces(frame.scan, config=config, timing=timing), timing
    return call


def _empty_match(frame: _Frame) -> Match:
    from boxloc.evaluate.baseline import empty_surface_set
    from boxloc.evaluate.real import score_real

    return score_real(empty_surface_set(), frame.truth, frame.scan)


def _load(paths: Sequence[Path], config: Config,
          skipped: list[dict[str, Any]]) -> list[_Frame]:
    from boxloc.evaluate.real import frame_group
    from boxloc.io import read_labels, read_scan

    frames: list[_Frame] = []
    for p in paths:
        try:
            scan = read_scan(p, index=len(frames), max_pixels=config.max_pixels)
            labels = read_labels(p, max_pixels=config.max_pixels)
        except InputError as e:
            skipped.append({"file": p.name, "reason": str(e).splitlines()[0]})
            continue
        frames.append(_Frame(p.stem, frame_group(p.stem), scan, labels))
    if not frames:
        raise InputError("no labelled scan could be read: "
                         + "; ".join(f"{s['file']}: {s['reason']}" for s in skipped[:3]))
    return frames


def _truth_noise(frames: list[_Frame]) -> NoiseModel:
    """The model the ground truth and the poses use: fitted with the labels (tiles within
    one segment). The benchmark's own, never handed to the localizer by default."""
    from boxloc.calibrate.noise import estimate_noise

    model, _ = estimate_noise([f.scan for f in frames], labels=[f.labels for f in frames])
    return model


def _noise(frames: list[_Frame], config: Config, source: str) -> tuple[Config, dict[str, Any]]:
    if source == "auto":
        return config, {"source": "auto: the config as given" + (
            " (noise_auto: each scan's own model)" if config.noise_auto else " (pinned)"),
            "model": config.noise.to_dict()}
    if source == "config":
        pinned = dataclasses.replace(config, noise_auto=False)
        return pinned, {"source": "config (pinned)", "model": config.noise.to_dict()}
    if source != "estimate":
        raise InputError(f"noise must be 'auto', 'estimate' or 'config', got {source!r}")
    from boxloc.calibrate.edgeblur import estimate_edge_px
    from boxloc.calibrate.noise import estimate_noise

    scans = [f.scan for f in frames]
    model, rep = estimate_noise(scans, labels=[f.labels for f in frames])
    # the edge blur, over the range noise just fitted (what the covariances already explain)
    edge_px, erep = estimate_edge_px(scans, dataclasses.replace(config, noise=model))
    model = dataclasses.replace(model, edge_px=edge_px)
    info = {
        "source": "estimate_noise on the benchmarked frames (tiles within one label segment)",
        "model": model.to_dict(),
        "fit_rel_rms": rep.get("fit_rel_rms"),
        "n_points": rep.get("n_points"), "n_tiles_used": rep.get("n_tiles_used"),
        "bins": [{"range_m": r["range"], "std_mm": r["std"] * 1e3,
                  "model_mm": r["model_std"] * 1e3, "used": r["used"]}
                 for r in rep.get("rows", [])],
        "edge_blur": {"source": "estimate_edge_px on the benchmarked frames (no labels)",
                      **erep},
    }
    return dataclasses.replace(config, noise=model, noise_auto=False), info


def _squareness(frames: list[_Frame], config: Config,
                source: str) -> tuple[dict[str, Config], dict[str, Any]]:
    """The config of each frame group, with its ``angle_tolerance``, and the report."""
    groups = sorted({f.group for f in frames})
    if source == "config":
        return {g: config for g in groups}, {
            "source": "config", "angle_tolerance_deg": math.degrees(config.angle_tolerance)}
    if source not in ("estimate", "cross"):
        raise InputError(f"squareness must be 'cross', 'estimate' or 'config', got {source!r}")
    from boxloc.calibrate.squareness import estimate_angle_tolerance

    if source == "estimate":
        tol, rep = estimate_angle_tolerance([f.scan for f in frames], config)
        info = {"source": "estimate_angle_tolerance on the benchmarked frames (no labels)",
                "angle_tolerance_deg": math.degrees(tol),
                **{k: v for k, v in rep.items() if k != "per_scan"}}
        return {g: dataclasses.replace(config, angle_tolerance=tol) for g in groups}, info
    per: dict[str, Config] = {}
    info = {"source": "estimate_angle_tolerance on the other groups' frames (no labels): "
                      "no frame is scored with a prior fitted on it", "per_group": {}}
    for g in groups:
        others = [f.scan for f in frames if f.group != g]
        if not others:  # one group only: nothing to fit on that is not scored
            per[g] = config
            info["per_group"][g] = {"fitted_on": "none (config)",
                                    "angle_tolerance_deg": math.degrees(config.angle_tolerance)}
            continue
        tol, rep = estimate_angle_tolerance(others, config)
        per[g] = dataclasses.replace(config, angle_tolerance=tol)
        info["per_group"][g] = {
            "fitted_on": sorted({f.group for f in frames if f.group != g}),
            "angle_tolerance_deg": math.degrees(tol),
            **{k: v for k, v in rep.items() if k != "per_scan"}}
    return per, info


def _pose(frames: list[_Frame], noise: NoiseModel, pose: str) -> str:
    if pose == "none":
        return "none: scans as read (up = sensor -z unless the file has a pose)"
    if pose != "plane":
        raise InputError(f"pose must be 'plane' or 'none', got {pose!r}")
    from boxloc.evaluate.real import support_plane_pose

    for f in frames:
        T = support_plane_pose(f.scan, noise=noise)
        f.scan = dataclasses.replace(f.scan, sensor_to_base=T)
    return "plane: sensor_to_base from each frame's dominant plane (no labels)"


def run_real_bench(
    data_dir: str | Path,
    *,
    config: Config | None = None,
    out: Path | str | None = None,
    baseline: bool = True,
    progress: bool = True,
    noise: str = "auto",
    squareness: str = "cross",
    pose: str = "plane",
    frames: Sequence[str] | None = None,
    localizer: Callable[[Scan, Config], Any] | None = None,
    console: Any = None,
    warmup: bool = True,
    seeds: int = 1,
) -> dict[str, Any]:
    """Benchmark the localizer (and the open3d baseline) on real labelled scans.

    Parameters
    ----------
    data_dir : path
        A directory of organized PCD/PLY files with a ``label`` field (mOSD).
    config : Config, optional
        The localizer's configuration (its noise is pinned to a fit when
        ``noise="estimate"``).
    out : path, optional
        Directory for ``bench_real.json`` (created); nothing is written without it.
    baseline : bool
        Also run the open3d baseline on the same frames.
    progress : bool
        Show a progress bar and print the report (rich, on stderr).
    noise : {"auto", "estimate", "config"}
        Where the noise model comes from (module docstring).
    squareness : {"cross", "estimate", "config"}
        Where ``angle_tolerance`` comes from (module docstring).
    pose : {"plane", "none"}
        Whether to give each scan a ``sensor_to_base`` from its dominant plane.
    frames : sequence of str, optional
        Only these frames (file stems), in this order.
    localizer : callable, optional
        ``(scan, config) -> Result``-like; default the pipeline.
    console : rich.console.Console, optional
    warmup : bool
        Run both methods once on the first frame, untimed (JIT compilation, lazy imports).
    seeds : int
        Run both methods this many times on every frame, with ``trial_seed`` = the config's,
        +1, +2, ... (other draws of their random trials; the noise model and
        ``angle_tolerance`` are estimated once). The summary, groups and targets pool all
        runs, so they are the expected figures over draws; ``seeds`` reports each draw's.

    Returns
    -------
    dict
        The report (module docstring), as written to ``bench_real.json``.

    Raises
    ------
    InputError
        Bad directory, no readable labelled scan, a missing frame, a bad option.
    """
    from boxloc.evaluate.real import top_faces

    cfg = config or Config()
    trial_configs(cfg, seeds)  # a bad count is refused before any frame is read
    paths = list_frames(data_dir, frames)
    skipped: list[dict[str, Any]] = []
    errors: list[dict[str, Any]] = []
    threads = _limit_threads()
    con = console
    if con is None and progress:
        from rich.console import Console

        con = Console(stderr=True)
    if con is not None and progress:
        con.print(f"reading {len(paths)} frame(s) from {data_dir}")
    loaded = _load(paths, cfg, skipped)
    cfg_run, noise_info = _noise(loaded, cfg, noise)
    group_cfg, square_info = _squareness(loaded, cfg_run, squareness)
    truth_noise = _truth_noise(loaded)
    pose_info = _pose(loaded, truth_noise, pose)
    scored: list[_Frame] = []
    for f in loaded:
        try:
            f.truth = top_faces(f.scan, f.labels, noise=truth_noise)
        except Exception as e:  # noqa: BLE001 - a frame without truth is reported, not fatal
            errors.append({"frame": f.name, "group": f.group, "method": "truth",
                           "error": _err(e)})
            continue
        scored.append(f)

    loc = localizer or _default_localizer
    methods = METHODS if baseline else METHODS[:1]
    draws = {g: trial_configs(c, seeds) for g, c in group_cfg.items()}
    runs: dict[str, list[_Run]] = {m: [] for m in methods}
    rows: list[dict[str, Any]] = []
    bar, task = (progress_bar(con, "bench --real", len(scored) * seeds) if progress
                 else (None, None))
    try:
        if warmup and scored:
            for m in methods:
                with contextlib.suppress(Exception):
                    _calls(m, scored[0], group_cfg[scored[0].group], loc)()
        for f in scored:
            for c in draws[f.group]:
                row: dict[str, Any] = {"frame": f.name, "group": f.group,
                                       "index": f.scan.index, "trial_seed": c.trial_seed,
                                       "truth": f.truth.to_dict()}
                for m in methods:
                    if bar is not None:
                        bar.update(task, description=f"{f.name}: {m}"
                                   + (f" (trial_seed {c.trial_seed})" if seeds > 1 else ""))
                    r = _run(_calls(m, f, c, loc), f)
                    r.trial_seed = c.trial_seed
                    if r.error is not None:
                        errors.append({"frame": f.name, "group": f.group, "method": m,
                                       "trial_seed": c.trial_seed, "error": r.error})
                        r.match = _empty_match(f)
                    runs[m].append(r)
                    mrow: dict[str, Any] = {"error": r.error}
                    mrow.update(r.match.to_dict() if r.match is not None else {})
                    row[m] = mrow
                rows.append(row)
                if bar is not None:
                    bar.advance(task)
    finally:
        if bar is not None:
            bar.stop()

    counts = {k: 0 for k in ("truth", *methods)}
    for err in errors:
        counts[err["method"]] = counts.get(err["method"], 0) + 1
    report: dict[str, Any] = {
        "version": __version__,
        "data_dir": str(data_dir),
        "n_frames": len(scored),
        "seeds": draw_figures(runs, methods,
                              [c.trial_seed for c in next(iter(draws.values()))], GROUPS),
        "config": cfg_run.to_dict(),
        "config_hash": cfg_run.hash,
        "group_configs": {g: {"angle_tolerance_deg": math.degrees(c.angle_tolerance),
                              "config_hash": c.hash} for g, c in group_cfg.items()},
        "truth_noise": truth_noise.to_dict(),
        "noise": noise_info,
        "squareness": square_info,
        "pose": pose_info,
        "threads": threads,
        "warmup": warmup,
        "crash_policy": "a method that crashes on a frame scores as predicting nothing there",
        "truth_rule": TRUTH_RULE,
        "summary": {m: aggregate_matches(r.match for r in runs[m] if r.match) for m in methods},
        "groups": _groups(runs, methods),
        "timing": {m: _timing(runs[m]) for m in methods},
        "memory": {
            **{f"{m}_peak_rss_mb": _max([r.peak_mb for r in runs[m]]) for m in methods},
            "process_max_rss_mb": process_max_rss_mb(),
        },
        "errors": {"count": counts, "total": len(errors), "list": errors},
        "skipped": skipped,
    }
    report["targets"] = evaluate_real_targets(report)
    report["frames"] = rows
    report = _jsonable(report)
    if out is not None:
        d = Path(out)
        d.mkdir(parents=True, exist_ok=True)
        (d / "bench_real.json").write_text(json.dumps(report, indent=1) + "\n")
    if progress and con is not None:
        print_real_report(report, con)
        if out is not None:
            con.print(f"wrote {Path(out) / 'bench_real.json'}")
    return report


def _timing(runs: Sequence[_Run]) -> dict[str, Any]:
    stages: dict[str, list[float]] = {}
    for r in runs:
        for k, v in r.stage_ms.items():
            stages.setdefault(k, []).append(v)
    return {
        "stages_ms": {k: percentiles_ms(v) for k, v in stages.items()},
        "total_ms": percentiles_ms([r.wall_ms for r in runs if r.wall_ms is not None]),
        "per_frame_ms": [None if r.wall_ms is None else round(r.wall_ms, 3) for r in runs],
    }


def _groups(runs: dict[str, list[_Run]], methods: Sequence[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for g in GROUPS:
        n = sum(r.group == g for r in runs[methods[0]])
        if n == 0:
            continue
        entry: dict[str, Any] = {"n_frames": n}
        for m in methods:
            sel = [r for r in runs[m] if r.group == g]
            entry[m] = aggregate_matches(r.match for r in sel if r.match)
            entry[m]["errors"] = sum(r.error is not None for r in sel)
        out[g] = entry
    return out


def _real_figures(report: dict[str, Any], method: str) -> dict[str, Any]:
    figs: dict[str, Any] = {}
    for g, entry in report["groups"].items():
        for k, v in entry.get(method, {}).items():
            figs[f"{g}.{k}"] = v
    if method in report["summary"]:
        figs["crashes"] = float(report["errors"]["count"].get(method, 0))
    return figs


def evaluate_real_targets(report: dict[str, Any]) -> list[dict[str, Any]]:
    """Check the localizer against :data:`REAL_TARGETS`; ``pass`` is None when the figure
    is missing (e.g. no box frame was benchmarked)."""
    mine = _real_figures(report, "boxloc")
    theirs = _real_figures(report, "baseline") if "baseline" in report["summary"] else {}
    rows = []
    for t in REAL_TARGETS:
        v = mine.get(t.key)
        assert t.value is not None
        ok = None if v is None else (v >= t.value if t.op == ">=" else v <= t.value)
        rows.append({"name": t.name, "key": t.key, "target": f"{t.op} {t.value:g}",
                     "value": v, "baseline": theirs.get(t.key), "unit": t.unit, "pass": ok})
    return rows


def print_real_report(report: dict[str, Any], console: Any) -> None:
    """Print the report as rich tables: targets and figures per group, frames, timing."""
    from rich.markup import escape
    from rich.table import Table

    methods = list(report["summary"])
    mark = {True: "[green]pass[/]", False: "[red]miss[/]", None: "[dim]n/a[/]"}
    t = Table(title=escape(f"boxloc bench --real: {report['n_frames']} frames of "
                           f"{report['data_dir']}, config {report['config_hash']}"))
    t.add_column("figure")
    for m in methods:
        t.add_column(LABELS[m], justify="right")
    t.add_column("target", justify="right")
    t.add_column("", justify="center")
    for row in report["targets"]:
        cells = [escape(row["name"]), _fmt(row["value"])]
        if "baseline" in methods:
            cells.append(_fmt(row["baseline"]))
        t.add_row(*cells, row["target"], mark[row["pass"]])
    for g, entry in report["groups"].items():
        for key, label in (("precision", "precision"), ("recall", "recall"), ("f1", "F1"),
                           ("tp", "TP"), ("fp", "FP"), ("fn", "FN"),
                           ("normal_err_median_deg", "normal err median [deg]"),
                           ("normal_err_p95_deg", "normal err p95 [deg]"),
                           ("center_err_median_mm", "centre err median [mm]")):
            cells = [escape(f"{g} ({entry['n_frames']}): {label}")]
            cells += [_fmt(entry[m].get(key), "mm" if key.endswith("_mm") else "")
                      for m in methods]
            t.add_row(*cells, "", "")
    console.print(t)

    draws = report.get("seeds", {"n": 1})
    print_draws(console, draws, methods)

    ft = Table(title="per frame: TP / FP / FN (exposed / faces)"
               + (f", summed over {draws['n']} draws" if draws["n"] > 1 else ""))
    ft.add_column("frame")
    ft.add_column("group")
    ft.add_column("exposed / faces", justify="right")
    for m in methods:
        ft.add_column(LABELS[m], justify="right")
    by_frame: dict[str, list[dict[str, Any]]] = {}
    for row in report["frames"]:
        by_frame.setdefault(row["frame"], []).append(row)
    for rs in by_frame.values():
        cells = [rs[0]["frame"], rs[0]["group"],
                 f"{rs[0]['truth']['n_exposed']} / {rs[0]['truth']['n_faces']}"]
        for m in methods:
            crashes = sum(bool(r[m].get("error")) for r in rs)
            if crashes == len(rs):
                cells.append("[red]crash[/]")
                continue
            tp, fp, fn = (sum(r[m].get(k, 0) for r in rs) for k in ("tp", "fp", "fn"))
            cells.append(f"{tp} / {fp} / {fn}" + (f" [red]({crashes} crash)[/]" if crashes
                                                  else ""))
        ft.add_row(*cells)
    console.print(ft)

    print_timing(console, report["timing"], "frame")
    nz = report["noise"]["model"]
    console.print(escape(f"noise ({report['noise']['source']}): ")
                  + ", ".join(f"{k} {v:.3g}" for k, v in nz.items()))
    sq = report.get("squareness", {})
    for name, s in ({"": sq} if "angle_tolerance_deg" in sq else sq.get("per_group", {})).items():
        console.print(escape(f"angle_tolerance{' of ' + name if name else ''} "
                             f"({s.get('fitted_on', sq.get('source'))}): "
                             f"{s['angle_tolerance_deg']:.2f} deg"
                             + (f" from {s['n_corners']} corners, spread "
                                f"{s['sigma_deg']:.2f} deg, propagated "
                                f"{s['propagated_deg']:.2f} deg" if "n_corners" in s else "")))
    console.print(escape(f"pose: {report['pose']}"))
    errs = report["errors"]
    if errs["total"]:
        console.print(f"[red]{errs['total']} error(s)[/]: " + ", ".join(
            f"{k} {v}" for k, v in errs["count"].items() if v))
        for e in errs["list"][:10]:
            console.print(escape(f"  {e['frame']} {e['method']}: {e['error']}"))
    for s in report["skipped"]:
        console.print(escape(f"skipped {s['file']}: {s['reason']}"))

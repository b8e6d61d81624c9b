"""The benchmark: the localizer against the open3d peer on simulated scenes with ground truth.

``run_bench`` simulates ``scene_suite(n, seed)``, runs :func:`boxloc.pipeline.find_graspable_
surfaces` and :func:`boxloc.evaluate.baseline.baseline_surfaces` on every scene, scores both with
:mod:`boxloc.evaluate.metrics`, times them, measures their peak memory, prints the figures side by
side against the targets and writes ``bench.json``.

Layout of ``bench.json`` (all lengths metres inside, figures named ``*_mm`` / ``*_deg`` /
``*_ms`` / ``*_mb`` are in those units):

- ``version``, ``config``, ``config_hash``, ``n``, ``seed``, ``scene_noise``, ``threads``,
  ``warmup``, ``crash_policy`` (a method that crashes on a scene scores as finding nothing)
- ``seeds``: the draws of the random trials each scene was run with (``trial_seed`` the
  config's, +1, ...; ``--seeds N``): ``n``, ``trial_seeds``, ``per_seed`` figures and their
  ``spread`` (:func:`draw_figures`); every figure below pools the draws
- ``summary``: ``{"boxloc": {...}, "baseline": {...}}`` pooled figures
  (:func:`boxloc.evaluate.metrics.aggregate_matches`)
- ``edges``: pooled edge-pixel precision/recall of the localizer (any / jump / crease)
- ``per_kind``: the same figures per scene kind
- ``timing``: per method, median/p95 per stage and of the total, and the per-scene totals
- ``memory``: per-method peak RSS (sampled during its calls) and the process's ``ru_maxrss``.
  RSS is the whole process's: it includes the simulator, and open3d once the baseline has
  imported it (``--no-baseline`` gives the localizer's figure without open3d).
- ``targets``: one row per target: name, target, value, baseline value, pass (true/false/null)
- ``errors``: counts per method and the list (scene, method, trial seed, message)
- ``scenes``: one deterministic row per scene and draw (spec, ``trial_seed``, counts,
  per-TP errors; no durations,
  no timestamps: durations live in ``timing`` so that two runs' ``scenes`` compare equal)
- ``sections``: the extra sections (see below)

Extension point
---------------
Packages add sections to the benchmark without boxloc importing them: register a callable
under the ``boxloc.bench`` entry-point group (``[project.entry-points."boxloc.bench"]``,
``name = "pkg.module:function"``). Each is called after the scenes are scored as
``function(ctx: BenchContext) -> dict`` and its (JSON-ready) dict is stored under
``sections[name]`` and printed. A section that raises is reported in ``errors``, not fatal.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import resource
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

import numpy as np

from boxloc import __version__
from boxloc.config import Config
from boxloc.errors import InputError
from boxloc.evaluate.metrics import (
    Match,
    aggregate_edges,
    aggregate_matches,
    edge_report,
    match_surfaces,
    percentiles_ms,
)
from boxloc.jsonable import jsonable as _jsonable

METHODS: tuple[str, ...] = ("boxloc", "baseline")
LABELS: dict[str, str] = {"boxloc": "boxloc", "baseline": "open3d baseline"}
ENTRY_POINT_GROUP = "boxloc.bench"


@dataclass(frozen=True)
class Target:
    """One pass/miss line of the report.

    ``key`` names a figure of :func:`_figures`; ``op`` is ``"<="`` or ``">="`` against
    ``value``, or ``"beats"``: better than the baseline's same figure (``better`` says
    which direction is better: ``"higher"`` or ``"lower"``).
    """

    name: str
    key: str
    op: str
    value: float | None = None
    better: str = "higher"
    unit: str = ""


TARGETS: tuple[Target, ...] = (
    Target("precision", "precision", ">=", 0.99),
    Target("recall", "recall", ">=", 0.95),
    Target("median grasp error", "grasp_err_median_mm", "<=", 5.0, unit="mm"),
    Target("p95 grasp error", "grasp_err_p95_mm", "<=", 15.0, unit="mm"),
    Target("median dimension error", "dim_err_median_mm", "<=", 5.0, unit="mm"),
    Target("median time per scan", "time_median_ms", "<=", 500.0, unit="ms"),
    Target("peak RSS", "peak_rss_mb", "<=", 1024.0, unit="MB"),
    Target("F1 better than baseline", "f1", "beats", better="higher"),
    Target("grasp error better than baseline", "grasp_err_median_mm", "beats", better="lower",
           unit="mm"),
)


@dataclass
class BenchContext:
    """What an extra section gets: the run's parameters and the report so far.

    Attributes
    ----------
    n, seed : int
    config : Config
    specs : list of SceneSpec
        The scenes, in order (``boxloc.simulate.simulate(spec)`` rebuilds one).
    out : Path or None
        The output directory, if any (a section may write its own files there).
    report : dict
        The report without ``sections`` (read it, do not modify it).
    """

    n: int
    seed: int
    config: Config
    specs: list[Any]
    out: Path | None
    report: dict[str, Any]


BenchSection = Callable[[BenchContext], dict[str, Any]]


def discover_sections() -> list[tuple[str, BenchSection]]:
    """Extra sections registered under the ``boxloc.bench`` entry-point group, by name.

    A section whose import fails is returned as a function that re-raises, so the failure is
    reported like any section failure.
    """
    found: list[tuple[str, BenchSection]] = []
    for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        try:
            fn = ep.load()
        except Exception as e:  # noqa: BLE001 - a broken plugin must not stop the bench
            msg = f"cannot load {ep.value}: {type(e).__name__}: {e}"

            def fn(ctx: BenchContext, _msg: str = msg) -> dict[str, Any]:
                raise ImportError(_msg)

        found.append((ep.name, fn))
    return found


# --- memory ------------------------------------------------------------------------------


class PeakRSS:
    """Context manager sampling this process's resident set size in a thread.

    ``peak_mb`` is the largest sample (including the values at entry and exit). Sampling
    (every ``interval`` s) can miss spikes shorter than the interval; the process-wide
    ``ru_maxrss`` is reported alongside as the upper bound.
    """

    def __init__(self, interval: float = 0.002) -> None:
        import psutil

        self._proc = psutil.Process()
        self._interval = interval
        self._stop = threading.Event()
        self._peak = 0
        self._thread: threading.Thread | None = None

    def _sample(self) -> None:
        self._peak = max(self._peak, self._proc.memory_info().rss)

    def _run(self) -> None:
        while not self._stop.wait(self._interval):
            self._sample()

    def __enter__(self) -> PeakRSS:
        self._sample()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self._sample()

    @property
    def peak_mb(self) -> float:
        return self._peak / 2**20


def process_max_rss_mb() -> float:
    """``getrusage(RUSAGE_SELF).ru_maxrss`` in MB (Linux reports KiB, macOS bytes)."""
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 2**20 if sys.platform == "darwin" else r / 2**10


# --- one scene ---------------------------------------------------------------------------


@dataclass
class _MethodRun:
    """One method on one scene."""

    match: Match | None = None
    edges: dict[str, Any] | None = None
    stage_ms: dict[str, float] = field(default_factory=dict)
    wall_ms: float | None = None
    peak_mb: float | None = None
    error: str | None = None
    kind: str = ""
    trial_seed: int = 0


def _err(e: BaseException) -> str:
    """One line: the exception type, message and the innermost frame."""
    tb = traceback.extract_tb(e.__traceback__)
    where = f" ({Path(tb[-1].filename).name}:{tb[-1].lineno})" if tb else ""
    msg = str(e).splitlines()[0] if str(e) else ""
    return f"{type(e).__name__}: {msg}{where}"


def _default_localizer(scan: Any, config: Config) -> Any:
    from boxloc.pipeline import find_graspable_surfaces

    return find_graspable_surfaces(scan, config)


def _run_boxloc(localizer: Callable[[Any, Config], Any], scan: Any, truth: Any,
                config: Config) -> _MethodRun:
    run = _MethodRun()
    try:
        with PeakRSS() as pk:
            t0 = time.perf_counter()
            result = localizer(scan, config)
            run.wall_ms = (time.perf_counter() - t0) * 1e3
        run.peak_mb = pk.peak_mb
        run.stage_ms = {k: float(v) for k, v in getattr(result, "timing_ms", {}).items()}
        run.match = match_surfaces(result.surfaces, truth)
        edges = getattr(result, "edges", None)
        if edges is not None:
            run.edges = edge_report(edges.labels, truth.edge_labels)
    except Exception as e:  # noqa: BLE001 - a crash on one scene is a result, not the end
        run.error = _err(e)
    return run


def _run_baseline(scan: Any, truth: Any, config: Config) -> _MethodRun:
    from boxloc.evaluate.baseline import baseline_surfaces

    run = _MethodRun()
    try:
        timing: dict[str, float] = {}
        with PeakRSS() as pk:
            t0 = time.perf_counter()
            surfaces = baseline_surfaces(scan, config=config, timing=timing)
            run.wall_ms = (time.perf_counter() - t0) * 1e3
        run.peak_mb = pk.peak_mb
        run.stage_ms = timing
        run.match = match_surfaces(surfaces, truth)
    except Exception as e:  # noqa: BLE001
        run.error = _err(e)
    return run


def _empty_match(truth: Any) -> Match:
    """The match of "found nothing": a crashed method scores as having predicted nothing."""
    from boxloc.evaluate.baseline import empty_surface_set

    return match_surfaces(empty_surface_set(), truth)


# --- the run -----------------------------------------------------------------------------


def _spec_dict(spec: Any) -> dict[str, Any]:
    if hasattr(spec, "to_dict"):
        return _jsonable(spec.to_dict())
    if dataclasses.is_dataclass(spec) and not isinstance(spec, type):
        return _jsonable(dataclasses.asdict(spec))
    return {"repr": repr(spec)}


def _spec_text(spec: Any) -> str | None:
    """The one-line form that ``boxloc.simulate.parse_spec`` reads back, if there is one."""
    try:
        from boxloc.simulate import format_spec

        return str(format_spec(spec))
    except Exception:  # noqa: BLE001 - informational only
        return None


def _limit_threads() -> dict[str, Any]:
    """Say which thread pools are in force (the time target is per core).

    The pools are pinned by the environment, before the libraries load (the bench's CLI and
    scripts/profile_stages.py set it). numba's pool size is reported, not set: boxloc's
    kernels are serial, and starting numba's threading layer only to shrink it made numba
    refuse every later compile in the process once NUMBA_NUM_THREADS changed (as the
    stream and replay pools set it for their workers).
    """
    info: dict[str, Any] = {
        k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS",
                                       "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    }
    try:
        from numba.core import config as numba_config

        # set at import from the environment (numba fills its config module dynamically)
        info["numba_threads"] = int(numba_config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]
    except Exception:  # noqa: BLE001 - numba missing
        info["numba_threads"] = None
    return info


def run_bench(
    n: int = 100,
    seed: int = 0,
    *,
    config: Config | None = None,
    out: Path | str | None = None,
    baseline: bool = True,
    progress: bool = True,
    specs: Sequence[Any] | None = None,
    scene_noise: bool = True,
    localizer: Callable[[Any, Config], Any] | None = None,
    sections: Sequence[tuple[str, BenchSection]] | None = None,
    console: Any = None,
    warmup: bool = True,
    seeds: int = 1,
) -> dict[str, Any]:
    """Benchmark the localizer (and the open3d baseline) on simulated scenes.

    Parameters
    ----------
    n, seed : int
        The scenes are ``boxloc.simulate.scene_suite(n, seed)``.
    config : Config, optional
        The localizer's configuration (also gives the baseline its priors).
    out : path, optional
        Directory for ``bench.json`` (created); nothing is written without it.
    baseline : bool
        Also run the open3d baseline.
    progress : bool
        Show a progress bar and print the report (rich, on stderr).
    specs : sequence of SceneSpec, optional
        Run these scenes instead of ``scene_suite(n, seed)`` (tests use tiny ones).
    scene_noise : bool
        Give both methods each scene's true noise model (a calibrated sensor) instead of
        ``config.noise``. ``config_hash`` is always that of ``config`` as given.
    localizer : callable, optional
        ``(scan, config) -> Result``-like (``.surfaces``, ``.edges``, ``.timing_ms``);
        default :func:`boxloc.pipeline.find_graspable_surfaces`.
    sections : sequence of (name, callable), optional
        Extra sections; default: those of the ``boxloc.bench`` entry-point group.
    console : rich.console.Console, optional
        Where to print; default stderr.
    warmup : bool
        Run both methods once on the first scene before timing anything, so JIT compilation
        and lazy imports (numba kernels, open3d) do not land in the first scene's time.
    seeds : int
        Run both methods this many times on every scene, with ``trial_seed`` = the config's,
        +1, +2, ... (other draws of their random trials). Summary, per kind, timing and
        targets pool all runs, so they are the expected figures over draws; ``seeds``
        reports each draw's (:func:`draw_figures`).

    Returns
    -------
    dict
        The report (see the module docstring), as written to ``bench.json``.

    Raises
    ------
    InputError
        If ``n < 1`` or the simulator is unavailable.
    """
    cfg = config or Config()
    trial_seeds = [c.trial_seed for c in trial_configs(cfg, seeds)]
    if specs is None:
        if n < 1:
            raise InputError(f"bench needs n >= 1 scenes, got {n}")
        try:
            from boxloc.simulate import scene_suite
        except ImportError as e:
            raise InputError(f"the simulator (boxloc.simulate) is unavailable: {e}") from None
        specs = scene_suite(n, seed)
    specs = list(specs)
    try:
        from boxloc.simulate import simulate
    except ImportError as e:
        raise InputError(f"the simulator (boxloc.simulate) is unavailable: {e}") from None

    threads = _limit_threads()
    loc = localizer or _default_localizer
    methods = METHODS if baseline else METHODS[:1]
    runs: dict[str, list[_MethodRun]] = {m: [] for m in methods}
    rows: list[dict[str, Any]] = []
    errors: list[dict[str, Any]] = []

    con = console
    if con is None and progress:
        from rich.console import Console

        con = Console(stderr=True)
    bar, task = progress_bar(con, "bench", len(specs) * seeds) if progress else (None, None)
    try:
        if warmup and specs:
            _warm_up(specs[0], loc, cfg, baseline)
        for i, spec in enumerate(specs):
            kind = str(getattr(spec, "kind", "?"))
            row: dict[str, Any] = {"index": i, "kind": kind,
                                   "seed": getattr(spec, "seed", None), "spec": _spec_dict(spec)}
            try:
                sim = simulate(spec)
            except Exception as e:  # noqa: BLE001
                errors.append({"scene": i, "kind": kind, "method": "simulate", "error": _err(e)})
                row["error"] = _err(e)
                rows.append(row)
                if bar is not None:
                    bar.advance(task, seeds)
                continue
            scan, truth = sim.scan, sim.truth
            # the resolved spec (drawn distance and tilt filled in) reproduces the scan
            row["spec"] = _spec_dict(getattr(sim, "spec", spec))
            row["spec_text"] = _spec_text(getattr(sim, "spec", spec))
            scfg = cfg
            noise = getattr(spec, "noise", None)
            if scene_noise and noise is not None and noise != cfg.noise:
                scfg = dataclasses.replace(cfg, noise=noise)
            row["n_faces"] = int(np.asarray(truth.centers).shape[0])
            row["n_exposed"] = int(np.asarray(truth.fully_exposed).sum())
            for dcfg in trial_configs(scfg, seeds):
                drow = dict(row, trial_seed=dcfg.trial_seed)
                for m in methods:
                    if bar is not None:
                        bar.update(task, description=f"scene {i} ({kind}): {m}"
                                   + (f" (trial_seed {dcfg.trial_seed})" if seeds > 1 else ""))
                    r = (_run_boxloc(loc, scan, truth, dcfg) if m == "boxloc"
                         else _run_baseline(scan, truth, dcfg))
                    if r.error is not None:
                        errors.append({"scene": i, "kind": kind, "method": m,
                                       "trial_seed": dcfg.trial_seed, "error": r.error})
                        r.match = _empty_match(truth)
                    r.kind = kind
                    r.trial_seed = dcfg.trial_seed
                    runs[m].append(r)
                    mrow: dict[str, Any] = {"error": r.error}
                    mrow.update(r.match.to_dict() if r.match is not None else {})
                    if m == "boxloc":
                        mrow["edges"] = r.edges
                    drow[m] = mrow
                rows.append(drow)
                if bar is not None:
                    bar.advance(task)
    finally:
        if bar is not None:
            bar.stop()

    report: dict[str, Any] = {
        "version": __version__,
        "n": len(specs),
        "seed": seed,
        "seeds": draw_figures(runs, methods, trial_seeds),
        "config": cfg.to_dict(),
        "config_hash": cfg.hash,
        "scene_noise": scene_noise,
        "threads": threads,
        "warmup": warmup,
        "crash_policy": "a method that crashes on a scene scores as predicting nothing there",
        "summary": {m: aggregate_matches(r.match for r in runs[m] if r.match) for m in methods},
        "edges": aggregate_edges([r.edges for r in runs["boxloc"] if r.edges is not None]),
        "per_kind": _per_kind(runs, methods),
        # boxloc against the baseline on the faces both found
        "common_grasp": (common_grasp(zip((r.match for r in runs["boxloc"]),
                                          (r.match for r in runs["baseline"])))
                         if "baseline" in methods else None),
        "timing": {m: _timing(runs[m]) for m in methods},
        "memory": {
            **{f"{m}_peak_rss_mb": _max([r.peak_mb for r in runs[m]]) for m in methods},
            "process_max_rss_mb": process_max_rss_mb(),
        },
    }
    report["targets"] = evaluate_targets(report)
    ctx = BenchContext(n=len(specs), seed=seed, config=cfg, specs=specs,
                       out=Path(out) if out is not None else None, report=report)
    extra: dict[str, Any] = {}
    for name, fn in (discover_sections() if sections is None else list(sections)):
        try:
            extra[name] = fn(ctx)
        except Exception as e:  # noqa: BLE001 - a broken section must not lose the bench
            errors.append({"scene": None, "kind": None, "method": f"section:{name}",
                           "error": _err(e)})
    report["sections"] = extra
    counts = {m: 0 for m in ("simulate", *methods)}
    for err in errors:
        counts[err["method"]] = counts.get(err["method"], 0) + 1
    report["errors"] = {"count": counts, "total": len(errors), "list": errors}
    report["scenes"] = rows
    report = _jsonable(report)
    if out is not None:
        d = Path(out)
        d.mkdir(parents=True, exist_ok=True)
        (d / "bench.json").write_text(json.dumps(report, indent=1, sort_keys=False) + "\n")
    if progress and con is not None:
        print_report(report, con)
        if out is not None:
            con.print(f"wrote {Path(out) / 'bench.json'}")
    return report


def _warm_up(spec: Any, localizer: Callable[[Any, Config], Any], config: Config,
             baseline: bool) -> None:
    """One untimed run of each method; failures here are ignored (the real run reports them)."""
    from boxloc.simulate import simulate

    try:
        scan = simulate(spec).scan
    except Exception:  # noqa: BLE001
        return
    with contextlib.suppress(Exception):
        localizer(scan, config)
    if baseline:
        from boxloc.evaluate.baseline import baseline_surfaces

        with contextlib.suppress(Exception):
            baseline_surfaces(scan, config=config)


def _max(vals: Sequence[float | None]) -> float | None:
    v = [x for x in vals if x is not None]
    return max(v) if v else None


def _timing(runs: Sequence[_MethodRun]) -> dict[str, Any]:
    """Median and p95 per stage (ms), and of the wall time of the whole call."""
    stages: dict[str, list[float]] = {}
    for r in runs:
        for k, v in r.stage_ms.items():
            stages.setdefault(k, []).append(v)
    walls = [r.wall_ms for r in runs if r.wall_ms is not None]
    return {
        "stages_ms": {k: percentiles_ms(v) for k, v in stages.items()},
        "total_ms": percentiles_ms(walls),
        "per_scene_total_ms": [None if r.wall_ms is None else round(r.wall_ms, 3) for r in runs],
    }


def common_grasp(pairs: Iterable[tuple[Match | None, Match | None]]) -> dict[str, Any]:
    """Grasp-point error of two methods on the faces both found (true positives of both).

    A method that finds only the easy faces has a lower median over its own true
    positives; on the same faces the comparison is like for like.

    Parameters
    ----------
    pairs : iterable of (Match, Match)
        The two methods' matches of each scene (None: the method failed there).

    Returns
    -------
    dict
        ``n`` faces, and per method (``a``, ``b``) the median and p95 in millimetres.
    """
    ea: list[float] = []
    eb: list[float] = []
    for ma, mb in pairs:
        if ma is None or mb is None:
            continue
        ga = {int(f): float(e) for f, e in zip(ma.tp_pairs[:, 1], ma.grasp_err)}
        gb = {int(f): float(e) for f, e in zip(mb.tp_pairs[:, 1], mb.grasp_err)}
        for f in sorted(set(ga) & set(gb)):
            ea.append(ga[f])
            eb.append(gb[f])
    out: dict[str, Any] = {"n": len(ea)}
    for key, e in (("a", ea), ("b", eb)):
        a = np.asarray(e, dtype=np.float64)
        out[f"{key}_median_mm"] = float(np.median(a) * 1e3) if len(a) else None
        out[f"{key}_p95_mm"] = float(np.percentile(a, 95) * 1e3) if len(a) else None
    return out


def trial_configs(config: Config, seeds: int) -> list[Config]:
    """``config`` with ``trial_seed`` its own, +1, ..., +seeds-1: the draws a bench runs.

    Raises
    ------
    InputError
        If ``seeds`` is not an integer >= 1.
    """
    if isinstance(seeds, bool) or not isinstance(seeds, int) or seeds < 1:
        raise InputError(f"seeds must be an integer >= 1, got {seeds!r}")
    return [dataclasses.replace(config, trial_seed=config.trial_seed + d) for d in range(seeds)]


#: Figures listed per draw of the random trials.
DRAW_KEYS = ("tp", "fp", "fn", "precision", "recall", "f1")


def draw_figures(runs: dict[str, list[Any]], methods: Sequence[str], trial_seeds: list[int],
                 groups: Sequence[str] | None = None) -> dict[str, Any]:
    """Each draw's figures and their spread over the draws.

    ``runs`` are per method, each with ``.trial_seed``, ``.match`` (and ``.group`` when
    ``groups`` is given: figures per group then). Returns ``n``, ``trial_seeds``,
    ``per_seed`` (``trial_seed`` and ``{method: figures}``, or ``{group: {method:
    figures}}`` under ``groups``) and ``spread`` (min, max and mean of precision, recall
    and F1 over the draws, nested the same way; None where no draw has the figure).
    """
    def figures(sel: list[Any]) -> dict[str, Any]:
        a = aggregate_matches(r.match for r in sel if r.match)
        return {k: a[k] for k in DRAW_KEYS}

    def by_method(k: int, g: str | None) -> dict[str, Any]:
        return {m: figures([r for r in runs[m] if r.trial_seed == k
                            and (g is None or r.group == g)]) for m in methods}

    present = None if groups is None else [
        g for g in groups if any(r.group == g for r in runs[methods[0]])]
    per: list[dict[str, Any]] = []
    for k in trial_seeds:
        if present is None:
            per.append({"trial_seed": k, "figures": by_method(k, None)})
        else:
            per.append({"trial_seed": k, "groups": {g: by_method(k, g) for g in present}})

    def spread(get: Callable[[dict[str, Any]], dict[str, Any]]) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for m in methods:
            out[m] = {}
            for key in ("precision", "recall", "f1"):
                v = [get(d)[m][key] for d in per if get(d)[m][key] is not None]
                out[m][key] = ({"min": min(v), "max": max(v), "mean": float(np.mean(v))}
                               if v else None)
        return out

    def of_group(g: str) -> Callable[[dict[str, Any]], dict[str, Any]]:
        return lambda d: d["groups"][g]

    return {"n": len(trial_seeds), "trial_seeds": list(trial_seeds), "per_seed": per,
            "spread": (spread(lambda d: d["figures"]) if present is None else
                       {g: spread(of_group(g)) for g in present})}


def print_draws(console: Any, draws: dict[str, Any], methods: Sequence[str]) -> None:
    """The per-draw table (only when there is more than one draw)."""
    from rich.markup import escape
    from rich.table import Table

    if draws["n"] < 2:
        return
    t = Table(title=f"per draw of the random trials ({draws['n']} trial seeds; the figures "
                    "above pool them): TP / FP / FN, recall / precision")
    t.add_column("trial_seed", justify="right")
    first = draws["per_seed"][0]
    cols = ([(None, m) for m in methods] if "figures" in first else
            [(g, m) for g in first["groups"] for m in methods])
    for g, m in cols:
        t.add_column(escape((f"{g}: " if g else "") + LABELS[m]), justify="right")
    for d in draws["per_seed"]:
        cells = [str(d["trial_seed"])]
        for g, m in cols:
            e = d["figures"][m] if g is None else d["groups"][g][m]
            cells.append(f"{e['tp']} / {e['fp']} / {e['fn']}, "
                         f"{_fmt(e['recall'])} / {_fmt(e['precision'])}")
        t.add_row(*cells)
    console.print(t)


def _per_kind(runs: dict[str, list[_MethodRun]], methods: Sequence[str]) -> dict[str, Any]:
    kinds = sorted({r.kind for r in runs[methods[0]]})
    out: dict[str, Any] = {}
    for k in kinds:
        entry: dict[str, Any] = {}
        for m in methods:
            sel = [r for r in runs[m] if r.kind == k]
            agg = aggregate_matches(r.match for r in sel if r.match)
            entry[m] = agg
            entry[m]["errors"] = sum(r.error is not None for r in sel)
        entry["n_scenes"] = sum(r.kind == k for r in runs[methods[0]])
        out[k] = entry
    return out


# --- targets and report ------------------------------------------------------------------


def _figures(report: dict[str, Any], method: str) -> dict[str, Any]:
    """The flat figures of one method that targets refer to."""
    s = dict(report["summary"].get(method, {}))
    s["time_median_ms"] = report["timing"].get(method, {}).get("total_ms", {}).get("median")
    s["peak_rss_mb"] = report["memory"].get(f"{method}_peak_rss_mb")
    return s


def evaluate_targets(report: dict[str, Any]) -> list[dict[str, Any]]:
    """Check the localizer's figures against :data:`TARGETS`.

    ``pass`` is None (n/a) when the figure is missing, or for "beats" when the baseline did
    not run. A missing localizer figure where the baseline has one is a miss.
    """
    mine = _figures(report, "boxloc")
    theirs = _figures(report, "baseline") if "baseline" in report["summary"] else None
    rows = []
    for t in TARGETS:
        v = mine.get(t.key)
        b = theirs.get(t.key) if theirs is not None else None
        ok: bool | None
        if t.op == "beats":
            if theirs is None:
                ok = None
            elif v is None:
                ok = False if b is not None else None
            elif b is None:
                ok = True
            else:
                ok = v > b if t.better == "higher" else v < b
            target = "> baseline" if t.better == "higher" else "< baseline"
        else:
            assert t.value is not None
            ok = None if v is None else (v >= t.value if t.op == ">=" else v <= t.value)
            target = f"{t.op} {t.value:g}{(' ' + t.unit) if t.unit else ''}"
        rows.append({"name": t.name, "key": t.key, "target": target, "value": v,
                     "baseline": b, "unit": t.unit, "pass": ok})
    return rows


def _fmt(v: Any, unit: str = "") -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        if unit in ("mm", "ms", "MB"):
            return f"{v:.1f}"
        return f"{v:.3f}"
    return str(v)


def print_report(report: dict[str, Any], console: Any) -> None:
    """Print the report as rich tables: targets, per kind, timing, errors, extra sections."""
    from rich.markup import escape
    from rich.table import Table

    has_base = "baseline" in report["summary"]
    t = Table(title=f"boxloc bench: {report['n']} scenes, seed {report['seed']}, "
                    f"config {report['config_hash']}")
    t.add_column("figure")
    t.add_column("boxloc", justify="right")
    if has_base:
        t.add_column("open3d baseline", justify="right")
    t.add_column("target", justify="right")
    t.add_column("", justify="center")
    mark = {True: "[green]pass[/]", False: "[red]miss[/]", None: "[dim]n/a[/]"}
    for row in report["targets"]:
        name = escape(row["name"] + (f" [{row['unit']}]" if row["unit"] else ""))
        cells = [name, _fmt(row["value"], row["unit"])]
        if has_base:
            cells.append(_fmt(row["baseline"], row["unit"]))
        cells += [row["target"], mark[row["pass"]]]
        t.add_row(*cells)
    s = report["summary"]
    for key, label in (("tp", "true positives"), ("fp", "false positives"),
                       ("fn", "false negatives"), ("normal_err_median_deg", "median normal [deg]"),
                       ("center_err_median_mm", "median centre error [mm]")):
        cells = [escape(label), _fmt(s["boxloc"].get(key))]
        if has_base:
            cells.append(_fmt(s["baseline"].get(key)))
        t.add_row(*cells, "", "")
    cg = report.get("common_grasp")
    if has_base and cg and cg["n"]:
        t.add_row(escape(f"grasp error on the {cg['n']} faces both find, median / p95 [mm]"),
                  f"{_fmt(cg['a_median_mm'], 'mm')} / {_fmt(cg['a_p95_mm'], 'mm')}",
                  f"{_fmt(cg['b_median_mm'], 'mm')} / {_fmt(cg['b_p95_mm'], 'mm')}", "", "")
    e = report.get("edges", {})
    if e.get("n_scans"):
        for k in ("any", "jump", "crease"):
            cells = [f"edges {k}: precision / recall",
                     f"{e[k]['precision']:.3f} / {e[k]['recall']:.3f}"]
            if has_base:
                cells.append("-")
            t.add_row(*cells, "", "")
    console.print(t)

    pk = Table(title=escape("per scene kind: precision / recall, median grasp error [mm]"))
    pk.add_column("kind")
    pk.add_column("scenes", justify="right")
    for m in report["summary"]:
        pk.add_column(f"{m} P / R", justify="right")
    for m in report["summary"]:
        pk.add_column(f"{m} grasp", justify="right")
    for kind, entry in report["per_kind"].items():
        cells = [kind, str(entry["n_scenes"])]
        for m in report["summary"]:
            a = entry[m]
            err = f" ({a['errors']} err)" if a.get("errors") else ""
            cells.append(f"{a['precision']:.2f} / {a['recall']:.2f}{err}")
        cells += [_fmt(entry[m]["grasp_err_median_mm"], "mm") for m in report["summary"]]
        pk.add_row(*cells)
    console.print(pk)

    print_draws(console, report.get("seeds", {"n": 1}), list(report["summary"]))
    print_timing(console, report["timing"], "scan")
    mem = report["memory"]
    console.print(escape("peak RSS [MB]: ") + ", ".join(f"{k.removesuffix('_mb')} {_fmt(v, 'MB')}"
                                                for k, v in mem.items()))

    for name, sec in report.get("sections", {}).items():
        st = Table(title=escape(f"section: {name}"))
        st.add_column("key")
        st.add_column("value", justify="right")
        for k, v in _flatten(sec):
            val = _fmt(v) if not isinstance(v, list | dict) else json.dumps(v)[:80]
            st.add_row(escape(k), escape(val))
        console.print(st)

    errs = report["errors"]
    if errs["total"]:
        console.print(f"[red]{errs['total']} error(s)[/]: " + ", ".join(
            f"{k} {v}" for k, v in errs["count"].items() if v))
        for e in errs["list"][:10]:
            console.print(escape(f"  scene {e['scene']} ({e['kind']}) {e['method']}: "
                                 f"{e['error']}"))
        if errs["total"] > 10:
            console.print(f"  ... and {errs['total'] - 10} more in bench.json")


def _flatten(d: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    out: list[tuple[str, Any]] = []
    for k, v in d.items():
        if isinstance(v, dict):
            out += _flatten(v, f"{prefix}{k}.")
        else:
            out.append((f"{prefix}{k}", v))
    return out


def progress_bar(console: Any, label: str, total: int) -> tuple[Any, Any]:
    """A started rich progress bar and its task (stop it with ``bar.stop()``)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

    bar = Progress("[progress.description]{task.description}", BarColumn(),
                   MofNCompleteColumn(), TimeElapsedColumn(), console=console, transient=True)
    bar.start()
    return bar, bar.add_task(label, total=total)


def print_timing(console: Any, timing: dict[str, Any], unit: str = "scan") -> None:
    """The per-stage time table (median / p95, ms) of each method of a report."""
    from rich.markup import escape
    from rich.table import Table

    tt = Table(title=escape(f"time per {unit} [ms] (median / p95)"))
    tt.add_column("method")
    tt.add_column("stage")
    tt.add_column("median / p95", justify="right")
    for m, tm in timing.items():
        for stage, v in tm["stages_ms"].items():
            tt.add_row(LABELS[m], escape(stage),
                       f"{_fmt(v['median'], 'ms')} / {_fmt(v['p95'], 'ms')}")
        tot = tm["total_ms"]
        tt.add_row(LABELS[m], "[b]wall total[/]",
                   f"{_fmt(tot['median'], 'ms')} / {_fmt(tot['p95'], 'ms')}")
    console.print(tt)


def run_sections(
    names: Sequence[str],
    n: int = 100,
    seed: int = 0,
    *,
    config: Config | None = None,
    out: Path | str | None = None,
    progress: bool = True,
    console: Any = None,
) -> dict[str, Any]:
    """Run only the named extra sections, without scoring the scenes (``bench --replay``).

    The sections get a :class:`BenchContext` whose ``report`` has no scene figures. The
    report (``version``, ``n``, ``seed``, ``config``, ``sections``, ``errors``) is printed and,
    with ``out``, written to ``out/bench.json``.

    Raises
    ------
    InputError
        If a named section is not registered (its package is not installed).
    """
    found = dict(discover_sections())
    for name in names:
        if name not in found:
            raise InputError(f"no bench section {name!r} (the package that provides it is not "
                             "installed)")
    cfg = config or Config()
    from boxloc.simulate import scene_suite

    report: dict[str, Any] = {"version": __version__, "n": n, "seed": seed,
                              "config": cfg.to_dict(), "config_hash": cfg.hash,
                              "threads": _limit_threads()}
    ctx = BenchContext(n=n, seed=seed, config=cfg, specs=scene_suite(n, seed),
                       out=Path(out) if out is not None else None, report=dict(report))
    sections: dict[str, Any] = {}
    errors: list[dict[str, Any]] = []
    for name in names:
        try:
            sections[name] = found[name](ctx)
        except Exception as e:  # noqa: BLE001 - reported, like in run_bench
            errors.append({"scene": None, "kind": None, "method": f"section:{name}",
                           "error": _err(e)})
    report["sections"] = sections
    report["errors"] = {"total": len(errors), "list": errors}
    report = _jsonable(report)
    if out is not None:
        d = Path(out)
        d.mkdir(parents=True, exist_ok=True)
        (d / "bench.json").write_text(json.dumps(report, indent=1) + "\n")
    if progress:
        from rich.console import Console
        from rich.markup import escape
        from rich.table import Table

        con = console or Console(stderr=True)
        for name, sec in report["sections"].items():
            st = Table(title=escape(f"section: {name}"))
            st.add_column("key")
            st.add_column("value", justify="right")
            for k, v in _flatten(sec):
                st.add_row(escape(k), escape(_fmt(v) if not isinstance(v, list | dict)
                                             else json.dumps(v)[:80]))
            con.print(st)
        for err in errors:
            con.print(escape(f"[error] {err['method']}: {err['error']}"))
    return report

"""The bare-plane benchmark: do the localizer's tests keep their size on real noise?

Issue 20, part 2: "on bare planes for every sensor model, edge points per pixel <= 2 alpha,
and zero surfaces in at least 99 of 100 scans". A scene with no box is the null hypothesis
of nearly every test the localizer runs: whatever a level-alpha test rejects there is a
false alarm, and the rate at which it does is the test's real size under that sensor's
noise (correlated, heavy-tailed, quantized), which may differ from the nominal alpha.

:func:`run_bare_bench` draws, for every sensor of the zoo (:data:`boxloc.simulate.SENSORS`),
``n`` bare scenes, alternating the two no-box kinds (``floor``: bare floor; ``empty``: a bare
pallet on the floor), with the camera, resolution, bevel, bulge and decoration drawn as
:func:`boxloc.simulate.matrix_suite` draws them (distance 1-3.5 m, tilt 0-30 deg, 320x240 to
1280x960; the noise scale 0.5-3x and the stereo class left to the scene seed). Every scan is
localized with the default configuration and the matrix bench's one site input, the box
footprint range (:func:`boxloc.evaluate.matrix_bench.matrix_config`); nothing else set.

Figures per sensor (and pooled):

- ``edge_points_per_pixel``: pixels labelled an edge over image pixels (the bare pallet
  of ``empty`` has real edges, so ``false_edge_points_per_pixel`` counts only those farther
  than 1 px from a true edge); target <= 2 alpha.
- ``zero_surface_scans`` of ``n_scans`` (a timed-out or crashed scan is not clean);
  target >= 99 %.
- ``tests``: per :class:`boxloc.stats.TestKind` recorded in any product of the run, rows
  (tested), rejected, and their ratio. Whether a ratio is a test's size depends on the
  kind: :data:`NULL_KIND_NAMES` are level-alpha tests whose null holds at every row on a
  bare plane (``rate`` is compared against alpha); the others are decisions whose
  rejection is not a false alarm there, or tests applied only to candidates that earlier
  false alarms made (their rate is conditional), reported for reading only. The edge
  stage records a row only where it found an edge point (every JUMP and CREASE row there
  is a rejection of "no jump" / "no fold": its ``accepted`` is always true), so for its
  kinds ``rejected`` counts rows whose statistic exceeds the critical value and
  ``per_sample`` divides them by the scan-line samples tested (valid pixels x 2 scan
  directions): the edge stage's false-alarm rate per sample.
- ``noise_fit``: scans whose NOISE_FIT test rejected the model in use, of the scans with
  one (the scan's residuals do not fit the model the later stages used).

A scan that takes longer than ``scan_timeout`` seconds (from the end of its simulation) is
killed; it counts as not clean and is listed under ``timeouts``.

Layout of ``bench_bare.json`` (schema ``boxloc.bench_bare/1``): ``schema``, ``version``,
``n`` (scenes per sensor), ``seed``, ``jobs``, ``scan_timeout_s``, ``alpha``, ``config``,
``config_hash``, ``site``, ``sensors``, ``null_kinds`` (names), ``groups`` (``sensors``:
per sensor, and ``all``: the figures above plus ``time``: median and max ms), ``targets``
(per sensor and target: ``value``, ``bound``, ``pass``), ``timeouts``, ``errors``, ``run_s``,
``scenes`` (one row per scan, in order: ``index``, ``sensor``, ``kind``, ``spec_text``,
``pixels``, ``status``, ``error``, ``surfaces``, ``edge_points``, ``false_edge_points``,
``tests``: ``{kind name: [tested, rejected]}``, ``samples``, ``noise_fit``: true (fits),
false, or null (no NOISE_FIT row), ``noise_source``, ``wall_ms``).

Run: ``python -m boxloc.evaluate.bare_bench --n 100 --seed 0 --jobs 2 --out DIR``.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from boxloc import __version__
from boxloc.config import Config
from boxloc.errors import InputError
from boxloc.evaluate.workers import Localizer, bench_console, check_run_args, run_tasks

SCHEMA = "boxloc.bench_bare/1"
REPORT_NAME = "bench_bare.json"
TABLE_NAME = "bench_bare.txt"
#: The two scene kinds with no box, alternated per sensor.
BARE_KINDS: tuple[str, ...] = ("floor", "empty")
DEFAULT_N = 100
DEFAULT_SCAN_TIMEOUT = 120.0
#: Test kinds that are level-alpha tests whose null holds at every recorded row on a bare
#: plane, so that rejected / tested estimates their size. NOISE_FIT: one row per scan, the
#: model in use against the scan's own flat residuals (the null holds when the model is
#: right). JUMP and CREASE rows are only the edge stage's detections (their size is
#: ``per_sample``, and edge points per pixel); POINT_ON_LINE, LINES_MEET, COPLANAR and the
#: verification tests are applied only to candidates that earlier false alarms made
#: (conditional, not a size); NO_RETURN, BUDGET, FACE_EXTENT, EDGE_SUPPORT and the like are
#: decisions, not tests.
NULL_KIND_NAMES: tuple[str, ...] = ("NOISE_FIT",)
#: Kinds of the edge stage's table, which records detections only (see the docstring).
EDGE_KIND_NAMES: tuple[str, ...] = ("JUMP", "CREASE")


def bare_suite(n: int, seed: int = 0, sensors: Sequence[str] | None = None) -> list[Any]:
    """``n`` bare scenes per sensor, interleaved (scene ``i``: sensor ``i % S``, kind
    ``BARE_KINDS[(i // S) % 2]``), every other draw as :func:`matrix_suite` makes it.

    Raises
    ------
    InputError
        On n < 1, seed < 0 or an unknown sensor.
    """
    from boxloc.simulate import SENSORS
    from boxloc.simulate.suites import draw_matrix_spec

    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise InputError(f"--n must be an integer >= 1, got {n!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise InputError(f"--seed must be an integer >= 0, got {seed!r}")
    sens = tuple(sensors) if sensors is not None else SENSORS
    for s in sens:
        if s not in SENSORS:
            raise InputError(f"unknown sensor {s!r}: one of {', '.join(SENSORS)}")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xB4E2]))
    return [draw_matrix_spec(rng, sens[i % len(sens)],
                             BARE_KINDS[(i // len(sens)) % len(BARE_KINDS)])
            for i in range(n * len(sens))]


# --- one scan ----------------------------------------------------------------------------


def _test_tables(result: Any) -> list[Any]:
    """Every TestTable of the result's products."""
    out = []
    for name in ("noise", "edges", "lines", "vertices", "hypotheses", "verification",
                 "selection", "surfaces", "ambiguous"):
        prod = getattr(result, name, None)
        t = getattr(prod, "tests", None)
        if t is not None:
            out.append(t)
    return out


def scan_figures(result: Any, truth_labels: np.ndarray,
                 valid: int | None = None) -> dict[str, Any]:
    """The bare-plane figures of one localized scan, from its recorded products.

    Parameters
    ----------
    result : boxloc.products.Result (or alike)
    truth_labels : (H, W) uint8
        The simulator's true edge labels.
    valid : int, optional
        Pixels with a return (each is a sample of a row and of a column scan line).
    """
    from boxloc.evaluate.metrics import edge_report
    from boxloc.stats import TestKind

    tests: dict[str, list[int]] = {}
    edges = getattr(result, "edges", None)
    edge_id = id(getattr(edges, "tests", None))
    for t in _test_tables(result):
        kinds = np.asarray(t.kind)
        acc = np.asarray(t.accepted, dtype=bool)
        if id(t) == edge_id and hasattr(t, "statistic"):
            # detections only: the null is rejected where the statistic passed its critical
            acc = ~(np.asarray(t.statistic) > np.asarray(t.critical))
        for k in np.unique(kinds):
            sel = kinds == k
            name = TestKind(int(k)).name
            row = tests.setdefault(name, [0, 0])
            row[0] += int(sel.sum())
            row[1] += int((~acc[sel]).sum())
    n_pts = n_false = None
    if edges is not None:
        rep = edge_report(edges.labels, truth_labels)["any"]
        n_pts, n_false = int(rep["n_pred"]), int(rep["n_pred"] - rep["correct"])
    noise = getattr(result, "noise", None)
    fit: bool | None = None
    if noise is not None and len(noise.tests):
        fit = bool(np.all(noise.tests.accepted))
    return {"surfaces": int(len(result.surfaces)), "edge_points": n_pts,
            "false_edge_points": n_false, "tests": dict(sorted(tests.items())),
            "noise_fit": fit, "samples": None if valid is None else 2 * int(valid),
            "noise_source": None if noise is None else int(noise.source)}


def _scan_task(conn: Connection | None, task: int, spec: Any, config: Config,
               localizer: Localizer, cache: dict[str, Any] | None = None) -> dict[str, Any]:
    """Simulate and localize one scene; ``conn`` is told when the localizer starts.

    The workers' task function (:data:`boxloc.evaluate.workers.TaskFn`); ``cache`` goes
    unused: every scan runs in a process of its own.
    """
    from boxloc.evaluate.scene_bench import _err
    from boxloc.simulate import simulate

    try:
        sim = simulate(spec)
    except Exception as e:  # noqa: BLE001 - a scene that cannot be made is a reported error
        return {"status": "error", "phase": "simulate", "error": _err(e)}
    if conn is not None:
        conn.send(("started", task, None))
    try:
        t0 = time.perf_counter()
        result = localizer(sim.scan, config)
        wall = (time.perf_counter() - t0) * 1e3
        rng = np.asarray(sim.scan.range, np.float64)
        valid = int((np.isfinite(rng) & (rng > 0)).sum())
        figs = scan_figures(result, sim.truth.edge_labels, valid)
    except Exception as e:  # noqa: BLE001 - a crash on one scene is a result
        return {"status": "error", "phase": "localize", "error": _err(e)}
    return {"status": "ok", "wall_ms": wall, **figs}


# --- figures -----------------------------------------------------------------------------


def group_figures(rows: Sequence[dict[str, Any]], alpha: float) -> dict[str, Any]:
    """Pooled figures of some scans (see the module docstring)."""
    n = len(rows)
    ok = [r for r in rows if r["status"] == "ok"]
    clean = sum(r["surfaces"] == 0 for r in ok)
    with_edges = [r for r in ok if r["edge_points"] is not None]
    pixels = sum(r["pixels"] for r in with_edges)
    pts = sum(r["edge_points"] for r in with_edges)
    false_pts = sum(r["false_edge_points"] for r in with_edges)
    tests: dict[str, dict[str, Any]] = {}
    for r in ok:
        for k, (t, rej) in r["tests"].items():
            d = tests.setdefault(k, {"tested": 0, "rejected": 0})
            d["tested"] += t
            d["rejected"] += rej
    samples = sum(r["samples"] or 0 for r in ok)
    for k, d in tests.items():
        d["rate"] = d["rejected"] / d["tested"] if d["tested"] else None
        d["level_alpha_null"] = k in NULL_KIND_NAMES
        if k in EDGE_KIND_NAMES:
            d["per_sample"] = d["rejected"] / samples if samples else None
    fits = [r["noise_fit"] for r in ok if r["noise_fit"] is not None]
    walls = np.asarray([r["wall_ms"] for r in rows if r.get("wall_ms") is not None], float)
    return {
        "n_scans": n, "ok": len(ok),
        "timeouts": sum(r["status"] == "timeout" for r in rows),
        "errors": sum(r["status"] == "error" for r in rows),
        "surfaces": sum(r["surfaces"] for r in ok),
        "zero_surface_scans": clean, "zero_surface_share": clean / n if n else None,
        "pixels": pixels, "edge_points": pts, "false_edge_points": false_pts,
        "edge_points_per_pixel": pts / pixels if pixels else None,
        "false_edge_points_per_pixel": false_pts / pixels if pixels else None,
        "edge_points_per_pixel_over_alpha": pts / pixels / alpha if pixels else None,
        "tests": dict(sorted(tests.items())),
        "noise_fit": {"scans": len(fits), "rejected": sum(not f for f in fits),
                      "rate": (sum(not f for f in fits) / len(fits)) if fits else None},
        "time": {"median_ms": float(np.median(walls)) if walls.size else None,
                 "max_ms": float(walls.max()) if walls.size else None},
    }


def _targets(groups: dict[str, Any], alpha: float) -> list[dict[str, Any]]:
    out = []
    for s, g in groups["sensors"].items():
        for name, key, op, bound in (
                ("edge points per pixel", "edge_points_per_pixel", "<=", 2 * alpha),
                ("false edge points per pixel", "false_edge_points_per_pixel", "<=",
                 2 * alpha),
                ("scans with zero surfaces", "zero_surface_share", ">=", 0.99)):
            v = g[key]
            ok = None if v is None else (v <= bound if op == "<=" else v >= bound)
            out.append({"sensor": s, "name": name, "key": key, "op": op, "bound": bound,
                        "value": v, "pass": ok})
    return out


def run_bare_bench(n: int = DEFAULT_N, seed: int = 0, *, out: str | Path | None = None,
                   jobs: int = 1, scan_timeout: float | None = DEFAULT_SCAN_TIMEOUT,
                   sensors: Sequence[str] | None = None, specs: Sequence[Any] | None = None,
                   localizer: Localizer | None = None, progress: bool = False,
                   console: Any = None) -> dict[str, Any]:
    """Run the bare-plane benchmark (see the module docstring).

    Parameters
    ----------
    n : int
        Bare scenes per sensor.
    seed : int
        Seeds :func:`bare_suite`.
    out : path, optional
        Directory for ``bench_bare.json`` and ``bench_bare.txt``.
    jobs : int
        Scans run at once, each in its own process.
    scan_timeout : float or None
        Seconds a scan may run before it is killed (a timed-out scan is not clean).
    sensors : sequence of str, optional
        A subset of the zoo (default: all).
    specs : sequence of SceneSpec, optional
        These scenes instead of the suite (tests use tiny ones).
    localizer : callable, optional
        ``(scan, config) -> Result``; default the pipeline. Runs in a forked process.
    progress : bool
        Print one line per scan and the table (rich, stderr).

    Returns
    -------
    dict
        The report.

    Raises
    ------
    InputError
        On n < 1, jobs < 1, a non-positive timeout or an unknown sensor.
    """
    from boxloc.evaluate.matrix_bench import matrix_config, write_report
    from boxloc.evaluate.scene_bench import _default_localizer, _jsonable, _spec_text

    check_run_args(jobs, scan_timeout)
    specs = list(specs) if specs is not None else bare_suite(n, seed, sensors)
    if not specs:
        raise InputError("bench needs at least one scene")
    cfg, site = matrix_config(specs)
    import boxloc.pipeline  # noqa: F401 - imported once here, shared by the forked children

    con = bench_console(console, progress)
    rows: list[dict[str, Any] | None] = [None] * len(specs)

    def on_done(i: int, res: dict[str, Any]) -> None:
        s = specs[i]
        row = {"index": i, "sensor": str(s.sensor), "kind": str(s.kind),
               "spec_text": _spec_text(s), "pixels": int(s.width * s.height),
               "status": res["status"], "error": res.get("error"),
               "surfaces": res.get("surfaces", 0), "edge_points": res.get("edge_points"),
               "false_edge_points": res.get("false_edge_points"),
               "tests": res.get("tests", {}), "noise_fit": res.get("noise_fit"),
               "samples": res.get("samples"), "noise_source": res.get("noise_source"),
               "wall_ms": res.get("wall_ms")}
        rows[i] = row
        if con is not None:
            done = sum(r is not None for r in rows)
            epp = (row["edge_points"] / row["pixels"]) if row["edge_points"] is not None else None
            con.print(f"[{done}/{len(specs)}] scene {i} ({row['sensor']}, {row['kind']}, "
                      f"{s.width}x{s.height}): {row['status']}, surfaces {row['surfaces']}, "
                      f"edge/px {'-' if epp is None else f'{epp:.4f}'}"
                      + (f", {row['wall_ms'] / 1e3:.1f} s" if row["wall_ms"] else ""),
                      markup=False, highlight=False)

    t0 = time.monotonic()
    # every scan in a process of its own and no warm-up: no scan sees another's state,
    # and each one's time includes its process's first calls
    run_tasks([(i, s, cfg) for i, s in enumerate(specs)], _scan_task,
              localizer or _default_localizer, jobs, scan_timeout, None, on_done, fresh=True,
              timeout_error="no result within {limit:g} s")
    run_s = time.monotonic() - t0
    done = [r for r in rows if r is not None]
    assert len(done) == len(specs)
    present = list(dict.fromkeys(r["sensor"] for r in done))
    groups = {"sensors": {s: group_figures([r for r in done if r["sensor"] == s], cfg.alpha)
                          for s in present},
              "all": group_figures(done, cfg.alpha)}
    report = _jsonable({
        "schema": SCHEMA, "version": __version__, "n": n,
        "n_scans": len(done), "seed": seed, "jobs": jobs, "scan_timeout_s": scan_timeout,
        "alpha": cfg.alpha, "config": cfg.to_dict(), "config_hash": cfg.hash, "site": site,
        "sensors": present, "kinds": list(BARE_KINDS), "null_kinds": list(NULL_KIND_NAMES),
        "groups": groups, "targets": _targets(groups, cfg.alpha),
        "timeouts": [{"scene": r["index"], "sensor": r["sensor"], "spec_text": r["spec_text"]}
                     for r in done if r["status"] == "timeout"],
        "errors": [{"scene": r["index"], "sensor": r["sensor"], "error": r["error"]}
                   for r in done if r["status"] == "error"],
        "run_s": round(run_s, 3), "scenes": done})
    write_report(report, out, REPORT_NAME, TABLE_NAME, print_bare_report, con)
    return report


def _f(v: Any, fmt: str = ".4f") -> str:
    return "-" if v is None else format(v, fmt)


def print_bare_report(report: dict[str, Any], console: Any) -> None:
    """The per-sensor table, the targets, and the rejection rate of every test kind."""
    from rich.markup import escape
    from rich.table import Table

    a = report["alpha"]
    g = report["groups"]
    t = Table(title=escape(
        f"boxloc bare-plane bench: {report['n_scans']} scans, seed {report['seed']}, default "
        f"configuration (min_edge {report['config']['min_edge']:g} m, max_edge "
        f"{report['config']['max_edge']:g} m), alpha {a:g}"))
    for c in ("sensor", "scans", "t-out / err", "zero-surface scans", "surfaces",
              f"edge/px (<= {2 * a:g})", "false edge/px", "NOISE_FIT rejected",
              "time med / max [s]"):
        t.add_column(escape(c), justify="left" if c == "sensor" else "right")
    for name, fig in [*g["sensors"].items(), ("all", g["all"])]:
        nf, tm = fig["noise_fit"], fig["time"]
        t.add_row(escape(name), str(fig["n_scans"]), f"{fig['timeouts']} / {fig['errors']}",
                  f"{fig['zero_surface_scans']} / {fig['n_scans']} "
                  f"({_f(fig['zero_surface_share'], '.2f')})",
                  str(fig["surfaces"]), _f(fig["edge_points_per_pixel"]),
                  _f(fig["false_edge_points_per_pixel"]),
                  f"{nf['rejected']} / {nf['scans']}",
                  " / ".join(_f(None if v is None else v / 1e3, ".1f")
                             for v in (tm["median_ms"], tm["max_ms"])))
    console.print(t)
    kinds = sorted({k for fig in g["sensors"].values() for k in fig["tests"]})
    kt = Table(title=escape(f"rejected / tested per test kind (* a level-alpha test under "
                            f"the null on a bare plane: compare with alpha {a:g})"))
    kt.add_column("kind")
    for s in g["sensors"]:
        kt.add_column(escape(s), justify="right")
    for k in kinds:
        cells = [escape(k + (" *" if k in report["null_kinds"] else ""))]
        for fig in g["sensors"].values():
            d = fig["tests"].get(k)
            cells.append("-" if d is None else
                         f"{d['rejected']} / {d['tested']} ({_f(d['rate'], '.3f')})"
                         + (f", {_f(d['per_sample'], '.5f')}/sample" if "per_sample" in d
                            else ""))
        kt.add_row(*cells)
    console.print(kt)
    mark = {True: "PASS", False: "FAIL", None: "n/a"}
    for r in report["targets"]:
        console.print(escape(f"{r['sensor']}: {r['name']} {_f(r['value'])} {r['op']} "
                             f"{r['bound']:g}: {mark[r['pass']]}"), highlight=False)
    for to in report["timeouts"]:
        console.print(escape(f"[timeout] scene {to['scene']} ({to['sensor']}): "
                             f"{to['spec_text']}"))
    for e in report["errors"]:
        console.print(escape(f"[error] scene {e['scene']} ({e['sensor']}): {e['error']}"))


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m boxloc.evaluate.bare_bench",
                                description="Bare-plane benchmark: test sizes on real noise.")
    p.add_argument("--n", type=int, default=DEFAULT_N, help="bare scenes per sensor")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--scan-timeout", type=float, default=DEFAULT_SCAN_TIMEOUT)
    p.add_argument("--sensor", action="append", default=None,
                   help="only this sensor (repeatable)")
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    try:
        run_bare_bench(a.n, a.seed, out=a.out, jobs=a.jobs, scan_timeout=a.scan_timeout,
                       sensors=a.sensor, progress=True)
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())

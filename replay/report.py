"""Formatting of diffs: a terminal table, ``diff.jsonl``, ``summary.json``, ``report.html``.

Comparison is :mod:`replay.diff`'s; everything here only reads :class:`replay.diff.LogDiff`.

* :func:`print_table`: one row per scan that is not identical, the pooled scores, then the
  timing on a table of its own (wall clock: shown, never a difference), then the verdict.
* :func:`write_outputs`: ``diff.jsonl`` (one JSON object per compared scan),
  ``summary.json`` (counts, verdict, exit code, pooled scores, timing, tolerances) and
  ``report.html``, a self-contained page for people with inline SVG plots (error
  distributions base vs candidate, per-scan changes, stage timing). No plotting library:
  the plots are a few hand-written SVG elements, so the page stays small (well under 1 MB).
* :func:`exit_code`: the contract, 0 no regression, 1 regression, 2 error.
* :func:`bless`: ``--update-refs``: the candidate's logs become the reference logs; a
  reference that is replaced is kept under ``<refs>/.boxloc-bak/`` first.
"""

from __future__ import annotations

import html
import json
import math
import os
import shutil
from collections import Counter
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from boxloc.errors import InputError
from replay.diff import (
    LogDiff,
    ScanDiff,
    Tolerances,
    _jsonable,
    list_logs,
    regression,
)

EXIT_OK = 0
EXIT_REGRESSION = 1
EXIT_ERROR = 2

SUMMARY_VERSION = 1
#: scans listed one by one in the terminal and in the HTML page (the files have them all)
MAX_ROWS = 200
#: where :func:`bless` keeps the references it replaces (inside the refs directory)
BACKUP_DIR = ".boxloc-bak"


# --- exit code -------------------------------------------------------------------------------


def exit_code(diffs: Sequence[LogDiff], tolerances: Tolerances | None = None) -> int:
    """0: no regression; 1: a regression under ``tolerances``; 2: an error (a log that could
    not be read or compared, or scans that are not the same input)."""
    if any(d.has_error for d in diffs):
        return EXIT_ERROR
    return EXIT_REGRESSION if regression(diffs, tolerances) else EXIT_OK


# --- small helpers ---------------------------------------------------------------------------


def _fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else f"{v:.{digits}f}"
    return str(v)


def _arrow(a: Any, b: Any, digits: int = 3) -> str:
    return _fmt(a, digits) if a == b else f"{_fmt(a, digits)} -> {_fmt(b, digits)}"


def _scan_cells(s: ScanDiff) -> dict[str, str]:
    """The short texts of one scan's row (shared by the terminal and the HTML table)."""
    counts = ", ".join(f"{k} {_arrow(x, y)}" for k, (x, y) in s.counts.items()
                       if x != y and k in ("lines", "vertices", "hypotheses", "verified",
                                           "chosen", "ambiguous"))
    items = ", ".join(f"{k} -{len(m.only_base)}/+{len(m.only_candidate)}"
                      for k, m in s.items.items() if m.only_base or m.only_candidate)
    sf = s.surfaces
    surf = " ".join(t for t in (f"+{len(sf.added)}" if sf.added else "",
                                f"-{len(sf.removed)}" if sf.removed else "",
                                f"~{len(sf.moved)}" if sf.moved else "") if t)
    if sf.pick_order_changed:
        surf += " order" if sf.pick_order_significant else " order(=)"
    pr = ""
    if s.scores:
        b, c = s.scores["base"], s.scores["candidate"]
        pr = f"{b['tp']}/{b['n_pred']}/{b['n_exposed']}"
        if (b["tp"], b["n_pred"]) != (c["tp"], c["n_pred"]):
            pr += f" -> {c['tp']}/{c['n_pred']}/{c['n_exposed']}"
    picks = ", ".join(f"#{p['surface']} {'ok' if p['ok'] else 'failed'}: {p['fate']}"
                      for p in s.picks)
    status = s.status if not s.error else f"error: {s.error}"
    return {"status": status, "counts": counts, "items": items,
            "flipped": str(len(s.flipped)) if s.flipped else "",
            "surfaces": surf.strip(), "scores": pr, "picks": picks,
            "regression": "REGRESSION" if s.regression else ""}


def timing_summary(diffs: Iterable[LogDiff]) -> dict[str, dict[str, dict[str, float | None]]]:
    """Per stage: median and 95th percentile of the wall-clock ms of each run."""
    acc: dict[str, dict[str, list[float]]] = {}
    for ld in diffs:
        for s in ld.scans:
            for side in ("base", "candidate"):
                for stage, ms in s.timing.get(side, {}).items():
                    if ms is not None and math.isfinite(ms):
                        acc.setdefault(stage, {"base": [], "candidate": []})[side].append(ms)
    out: dict[str, dict[str, dict[str, float | None]]] = {}
    for stage, sides in acc.items():
        out[stage] = {}
        for side, v in sides.items():
            a = np.asarray(v, np.float64)
            out[stage][side] = {
                "median": float(np.median(a)) if a.size else None,
                "p95": float(np.percentile(a, 95)) if a.size else None, "n": int(a.size)}
    return out


def _pooled_all(diffs: Sequence[LogDiff]) -> dict[str, Any] | None:
    """Counts summed over the logs with ground truth, and precision/recall from them."""
    from boxloc.evaluate.metrics import prf

    tot: dict[str, dict[str, int]] = {"base": Counter(), "candidate": Counter()}
    n = 0
    for ld in diffs:
        if not ld.pooled:
            continue
        n += 1
        for side in ("base", "candidate"):
            for k in ("tp", "n_pred", "n_exposed"):
                tot[side][k] += int(ld.pooled[side][k])
    if not n:
        return None
    out: dict[str, Any] = {"n_logs": n}
    for side, c in tot.items():
        p, r, f1 = prf(c["tp"], c["n_pred"], c["n_exposed"])
        out[side] = {"tp": c["tp"], "fp": c["n_pred"] - c["tp"], "fn": c["n_exposed"] - c["tp"],
                     "precision": p, "recall": r, "f1": f1}
    return out


# --- the terminal ----------------------------------------------------------------------------


def print_table(diffs: Sequence[LogDiff], console: Any = None, *,
                bless_command: str | None = None, all_scans: bool = False) -> None:
    """Print the comparison: changed scans, pooled scores, timing, the verdict.

    Parameters
    ----------
    console : rich.console.Console, optional
        Default: a console on stdout.
    bless_command : str, optional
        Printed after a regression: the command that accepts the candidate.
    all_scans : bool
        List identical scans too.
    """
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    con = console or Console()
    tol = diffs[0].tolerances if diffs else None
    for ld in diffs:
        title = f"{ld.base} vs {ld.candidate}"
        if ld.error:
            con.print(f"[bold red]error[/]: {escape(title)}: {escape(ld.error)}",
                      highlight=False)
            continue
        t = Table(title=escape(title), title_justify="left", show_lines=False)
        shown = [s for s in ld.scans if all_scans or s.status != "identical" or s.picks]
        any_picks = any(s.picks for s in shown)
        t.add_column("scan", no_wrap=True)
        t.add_column("", no_wrap=True)  # the verdict first: never cropped
        for col in ("status", "surfaces", "tp/pred/exp"):
            t.add_column(col, no_wrap=True)
        t.add_column("stages", overflow="fold", ratio=1, min_width=12)
        if any_picks:
            t.add_column("picks", overflow="fold")
        for s in shown[:MAX_ROWS]:
            sc = _scan_cells(s)
            stages = "; ".join(x for x in (sc["counts"], sc["items"] and "unmatched " + sc["items"],
                                           sc["flipped"] and sc["flipped"] + " test(s) flipped")
                               if x)
            cells = [sc["status"], sc["surfaces"], sc["scores"], stages]
            if any_picks:
                cells.append(sc["picks"])
            style = "red" if s.regression or s.status == "error" else None
            t.add_row(str(s.scan), "REG" if s.regression else "",
                      *(escape(x) for x in cells), style=style)
        n_id = sum(1 for s in ld.scans if s.status == "identical")
        t.caption = ("surfaces: +added -removed ~moved, order(=) within one layer; "
                     "tp/pred/exp: true positives / predicted / exposed faces (ground truth); "
                     "REG: regression\n"
                     f"{len(ld.scans)} scan(s): {n_id} identical, "
                     f"{sum(1 for s in ld.scans if s.status == 'equivalent')} within tolerance, "
                     f"{sum(1 for s in ld.scans if s.status == 'changed')} changed"
                     + (f"; {len(shown) - MAX_ROWS} more row(s) in diff.jsonl"
                        if len(shown) > MAX_ROWS else ""))
        if shown:
            con.print(t)
        else:
            con.print(f"{escape(title)}: {t.caption}", highlight=False)
        if ld.config_changes:
            con.print("config: " + escape(", ".join(f"{k} {_arrow(a, b, 6)}" for k, (a, b)
                                                    in ld.config_changes.items())),
                      highlight=False)
        for d in ld.differences:
            mark = "[red]REGRESSION[/] " if d.regression else ""
            con.print(f"  {mark}{escape(d.message)}", highlight=False)
        picks = [(s.scan, p) for s in ld.scans for p in s.picks]
        for scan, p in picks[:MAX_ROWS]:
            con.print(escape(f"  scan {scan} surface #{p['surface']} "
                             f"({'picked' if p['ok'] else 'pick failed'}"
                             f"{': ' + p['reason'] if p['reason'] else ''}): {p['fate']} in "
                             "the candidate"), highlight=False)
    timing = timing_summary(diffs)
    if timing:
        t = Table(title=escape("timing [ms], wall clock: its own channel, never a difference"),
                  title_justify="left")
        for col in ("stage", "base median", "candidate median", "base p95", "candidate p95"):
            t.add_column(col, justify="right")
        for stage, v in timing.items():
            b, c = v.get("base", {}), v.get("candidate", {})
            t.add_row(escape(stage), _fmt(b.get("median"), 1), _fmt(c.get("median"), 1),
                      _fmt(b.get("p95"), 1), _fmt(c.get("p95"), 1))
        con.print(t)
    code = exit_code(diffs, tol)
    regs = [d for ld in diffs for d in ld.all_differences if d.regression]
    if code == EXIT_ERROR:
        con.print("[bold red]ERROR[/]: the runs could not be compared (exit 2)")
    elif code == EXIT_REGRESSION:
        con.print(f"[bold red]REGRESSION[/]: {len(regs)} difference(s) beyond tolerance "
                  "(exit 1)")
        for d in regs[:20]:
            where = f"scan {d.scan}: " if d.scan is not None else ""
            con.print(f"  {escape(where + d.message)}  [dim]({d.rule})[/]", highlight=False)
        if bless_command:
            con.print(escape(f"if the change is intended, bless the candidate: "
                             f"{bless_command}"), highlight=False)
    else:
        n_diff = sum(len(ld.all_differences) for ld in diffs)
        con.print(f"[bold green]OK[/]: no regression ({n_diff} difference(s) reported, "
                  "none beyond tolerance)")


# --- files -----------------------------------------------------------------------------------


def summary(diffs: Sequence[LogDiff], tolerances: Tolerances | None = None) -> dict[str, Any]:
    """The ``summary.json`` content."""
    tol = tolerances or (diffs[0].tolerances if diffs else None)
    scans = [s for ld in diffs for s in ld.scans]
    status = Counter(s.status for s in scans)
    kinds = Counter(d.kind for ld in diffs for d in ld.all_differences)
    regs = [d for ld in diffs for d in ld.all_differences if d.regression]
    return _jsonable({
        "version": SUMMARY_VERSION,
        "exit_code": exit_code(diffs, tol),
        "regression": regression(diffs, tol),
        "error": any(ld.has_error for ld in diffs),
        "n_logs": len(diffs),
        "n_scans": len(scans),
        "scans": {k: status.get(k, 0) for k in ("identical", "equivalent", "changed",
                                                 "missing", "extra", "error")},
        "n_scans_regressed": sum(1 for s in scans if s.regression),
        "differences_by_kind": dict(sorted(kinds.items())),
        "regressions": [{"log": ld.name, **d.to_json()} for ld in diffs
                        for d in ld.all_differences if d.regression][:1000],
        "n_regressions": len(regs),
        "scores": _pooled_all(diffs),
        "failed_picks": [{"log": ld.name, "scan": s.scan, **p} for ld in diffs
                         for s in ld.scans for p in s.picks if not p["ok"]],
        "logs": [{
            "name": ld.name, "base": str(ld.base), "candidate": str(ld.candidate),
            "error": ld.error, "n_scans": len(ld.scans), "regression": ld.regression,
            "identical": ld.identical, "config_changes": ld.config_changes,
            "versions": ld.versions, "pooled_scores": ld.pooled,
            "differences": [d.to_json() for d in ld.differences],
        } for ld in diffs],
        # wall clock, reported for people; never part of the verdict
        "timing_ms": timing_summary(diffs),
        "tolerances": tol.to_dict() if tol else None,
    })


def write_outputs(diffs: Sequence[LogDiff], out_dir: str | os.PathLike[str],
                  *, title: str = "boxloc diff") -> dict[str, Any]:
    """Write ``diff.jsonl``, ``summary.json`` and ``report.html`` into ``out_dir``.

    Returns the summary (as written to ``summary.json``).

    Raises
    ------
    InputError
        ``out_dir`` exists and is not a directory.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: not a directory")
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "diff.jsonl", "w", encoding="utf-8") as f:
        for ld in diffs:
            for s in ld.scans:
                f.write(json.dumps(s.to_json(), sort_keys=True, allow_nan=False) + "\n")
    summ = summary(diffs)
    summ["files"] = {"diff_jsonl": "diff.jsonl", "summary_json": "summary.json",
                     "report_html": "report.html"}
    (out / "summary.json").write_text(json.dumps(summ, indent=2, sort_keys=True,
                                                 allow_nan=False) + "\n", encoding="utf-8")
    (out / "report.html").write_text(render_html(diffs, summ, title=title), encoding="utf-8")
    return summ


# --- the HTML report -------------------------------------------------------------------------

_BASE_COLOR = "#4477aa"
_CAND_COLOR = "#ee6677"
_CSS = """
body{font-family:system-ui,sans-serif;margin:1.5em;color:#222;max-width:1200px}
h1{font-size:1.4em}h2{font-size:1.15em;margin-top:1.6em}h3{font-size:1em}
table{border-collapse:collapse;font-size:.85em;margin:.5em 0}
td,th{border:1px solid #ccc;padding:2px 6px;text-align:left;vertical-align:top}
th{background:#f0f0f0}.reg{background:#fde0e0}.ok{color:#171}.bad{color:#b11;font-weight:bold}
.muted{color:#777}.plots{display:flex;flex-wrap:wrap;gap:1em}code{background:#f4f4f4}
"""


def _e(x: Any) -> str:
    return html.escape(str(x))


def _svg_frame(w: int, h: int, title: str, body: list[str]) -> str:
    return (f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" '
            f'viewBox="0 0 {w} {h}" font-family="sans-serif" font-size="11">'
            f'<text x="{w / 2:.0f}" y="14" text-anchor="middle" font-size="12" '
            f'font-weight="bold">{_e(title)}</text>' + "".join(body) + "</svg>")


def _legend(x: float, y: float, names: Sequence[tuple[str, str]]) -> list[str]:
    out = []
    for i, (name, color) in enumerate(names):
        yy = y + 14 * i
        out.append(f'<rect x="{x:.0f}" y="{yy - 8:.0f}" width="10" height="10" '
                   f'fill="{color}"/><text x="{x + 14:.0f}" y="{yy:.0f}">{_e(name)}</text>')
    return out


def _nice_max(v: float, *, integer: bool = False) -> float:
    """A round axis maximum >= v; for counts, a multiple of 4 (the axis has 4 intervals)."""
    if integer:
        return float(max(4, 4 * math.ceil(v / 4))) if math.isfinite(v) else 4.0
    if v <= 0 or not math.isfinite(v):
        return 1.0
    e = 10 ** math.floor(math.log10(v))
    for m in (1, 2, 2.5, 5, 10):
        if m * e >= v:
            return m * e
    return 10 * e


def svg_bars(categories: Sequence[str], series: dict[str, Sequence[float]],
             colors: Sequence[str], title: str, ylabel: str = "", *, width: int = 560,
             height: int = 260, stacked: bool = False, integer: bool = False) -> str:
    """A grouped (or stacked) bar chart as an SVG string."""
    left, right, top, bottom = 50, 10, 24, 60
    pw, ph = width - left - right, height - top - bottom
    n, k = len(categories), len(series)
    vals = [list(map(float, v)) for v in series.values()]
    if stacked:
        vmax = max((sum(v[i] for v in vals) for i in range(n)), default=0.0)
    else:
        vmax = max((x for v in vals for x in v), default=0.0)
    vmax = _nice_max(vmax, integer=integer)
    body = []
    for t in range(5):  # the grid under everything else
        tick = vmax * t / 4
        y = top + ph - ph * t / 4
        body.append(f'<text x="{left - 4}" y="{y + 4:.0f}" text-anchor="end">{tick:g}</text>'
                    f'<line x1="{left}" y1="{y:.0f}" x2="{left + pw}" y2="{y:.0f}" '
                    'stroke="#eee"/>')
    body += [f'<line x1="{left}" y1="{top + ph}" x2="{left + pw}" y2="{top + ph}" '
             'stroke="#333"/>',
             f'<line x1="{left}" y1="{top}" x2="{left}" y2="{top + ph}" stroke="#333"/>']
    if ylabel:
        body.append(f'<text x="12" y="{top + ph / 2:.0f}" transform="rotate(-90 12 '
                    f'{top + ph / 2:.0f})" text-anchor="middle">{_e(ylabel)}</text>')
    gw = pw / max(n, 1)
    bw = gw * 0.8 / (1 if stacked else max(k, 1))
    step = max(1, math.ceil(n / 30))  # at most ~30 category labels
    for i, cat in enumerate(categories):
        x0 = left + gw * i + gw * 0.1
        base = 0.0
        for s, v in enumerate(vals):
            h = ph * v[i] / vmax
            if stacked:
                y = top + ph - ph * (base + v[i]) / vmax
                x = x0
                base += v[i]
            else:
                y = top + ph - h
                x = x0 + bw * s
            if h > 0:
                body.append(f'<rect x="{x:.1f}" y="{y:.1f}" width="{bw:.1f}" height="{h:.1f}" '
                            f'fill="{colors[s % len(colors)]}"><title>{_e(cat)}: '
                            f'{_e(list(series)[s])} {v[i]:g}</title></rect>')
        if i % step == 0:
            cx = left + gw * (i + 0.5)
            body.append(f'<text x="{cx:.0f}" y="{top + ph + 12}" text-anchor="end" '
                        f'transform="rotate(-45 {cx:.0f} {top + ph + 12})">{_e(cat)}</text>')
    body += _legend(left + pw - 120, top + 10, list(zip(series, colors)))
    return _svg_frame(width, height, title, body)


def svg_hist(series: dict[str, Sequence[float]], colors: Sequence[str], title: str,
             xlabel: str, *, bins: int = 20, width: int = 560, height: int = 260) -> str:
    """Overlaid histograms (outlined steps) of several samples as an SVG string."""
    left, right, top, bottom = 50, 10, 24, 40
    pw, ph = width - left - right, height - top - bottom
    allv = np.concatenate([np.asarray(v, np.float64) for v in series.values()] or [np.zeros(0)])
    allv = allv[np.isfinite(allv)]
    hi = float(allv.max()) if allv.size else 1.0
    lo = min(0.0, float(allv.min())) if allv.size else 0.0
    hi = lo + _nice_max(hi - lo)
    edges = np.linspace(lo, hi, bins + 1)
    hists = [np.histogram(np.asarray(v, np.float64), edges)[0] for v in series.values()]
    cmax = _nice_max(float(max((h.max() for h in hists if h.size), default=1)), integer=True)
    body = [f'<line x1="{left}" y1="{top + ph}" x2="{left + pw}" y2="{top + ph}" '
            'stroke="#333"/>',
            f'<line x1="{left}" y1="{top}" x2="{left}" y2="{top + ph}" stroke="#333"/>',
            f'<text x="{left + pw / 2:.0f}" y="{height - 6}" text-anchor="middle">'
            f'{_e(xlabel)}</text>']
    for t in range(5):
        x = left + pw * t / 4
        y = top + ph - ph * t / 4
        body.append(f'<text x="{x:.0f}" y="{top + ph + 12}" text-anchor="middle">'
                    f'{lo + (hi - lo) * t / 4:g}</text>'
                    f'<text x="{left - 4}" y="{y + 4:.0f}" text-anchor="end">'
                    f'{cmax * t / 4:g}</text>')
    for s, h in enumerate(hists):
        pts = [f"{left:.1f},{top + ph:.1f}"]
        for i, c in enumerate(h):
            x0 = left + pw * i / bins
            x1 = left + pw * (i + 1) / bins
            y = top + ph - ph * c / cmax
            pts += [f"{x0:.1f},{y:.1f}", f"{x1:.1f},{y:.1f}"]
        pts.append(f"{left + pw:.1f},{top + ph:.1f}")
        body.append(f'<polyline points="{" ".join(pts)}" fill="none" stroke-width="2" '
                    f'stroke="{colors[s % len(colors)]}"/>')
    names = [f"{k} (n={len(v)})" for k, v in series.items()]
    body += _legend(left + pw - 150, top + 10, list(zip(names, colors)))
    return _svg_frame(width, height, title, body)


def _plots(diffs: Sequence[LogDiff]) -> list[str]:
    out: list[str] = []
    colors = [_BASE_COLOR, _CAND_COLOR]
    # error distributions of the true positives, base vs candidate
    for key, label in (("center_err_mm", "centre error of true positives [mm]"),
                       ("width_err_mm", "width error of true positives [mm]"),
                       ("length_err_mm", "length error of true positives [mm]")):
        b = [v for ld in diffs for s in ld.scans if s.scores
             for v in s.scores["base"].get(key, []) if v is not None]
        c = [v for ld in diffs for s in ld.scans if s.scores
             for v in s.scores["candidate"].get(key, []) if v is not None]
        if b or c:
            out.append(svg_hist({"baseline": b, "candidate": c}, colors, label, "mm"))
    # per-scan changes of the result
    changed = [(ld, s) for ld in diffs for s in ld.scans
               if s.surfaces.added or s.surfaces.removed or s.surfaces.moved]
    if changed:
        cats = [f"{s.scan}" if len(diffs) == 1 else f"{ld.name}:{s.scan}"
                for ld, s in changed[:MAX_ROWS]]
        out.append(svg_bars(cats, {
            "added": [len(s.surfaces.added) for _, s in changed[:MAX_ROWS]],
            "removed": [len(s.surfaces.removed) for _, s in changed[:MAX_ROWS]],
            "moved": [len(s.surfaces.moved) for _, s in changed[:MAX_ROWS]],
        }, ["#228833", "#ee6677", "#ccbb44"], "surfaces changed per scan", "surfaces",
            stacked=True, integer=True))
        moves = [p.dcenter_mm for _, s in changed for p in s.surfaces.moved]
        if moves:
            out.append(svg_hist({"moved surfaces": moves}, ["#ccbb44"],
                                "centre displacement of moved surfaces", "mm"))
    # intermediate stages: count per scan, base vs candidate, for the changed scans
    stage_scans = [(ld, s) for ld in diffs for s in ld.scans if s.status == "changed"]
    if stage_scans:
        cats = ["lines", "vertices", "hypotheses", "verified", "chosen"]
        tot_b = [sum(s.counts.get(k, (0, 0))[0] or 0 for _, s in stage_scans) for k in cats]
        tot_c = [sum(s.counts.get(k, (0, 0))[1] or 0 for _, s in stage_scans) for k in cats]
        out.append(svg_bars(cats, {"baseline": tot_b, "candidate": tot_c}, colors,
                            f"stage counts over the {len(stage_scans)} changed scan(s)",
                            "items", integer=True))
    timing = timing_summary(diffs)
    if timing:
        stages = list(timing)
        out.append(svg_bars(stages, {
            "baseline": [timing[s].get("base", {}).get("median") or 0.0 for s in stages],
            "candidate": [timing[s].get("candidate", {}).get("median") or 0.0
                          for s in stages],
        }, colors, "median stage time (wall clock, never a difference)", "ms"))
    return out


def render_html(diffs: Sequence[LogDiff], summ: dict[str, Any], *,
                title: str = "boxloc diff") -> str:
    """The self-contained HTML report (inline CSS and SVG, no external resources)."""
    code = summ["exit_code"]
    verdict = {0: ('<span class="ok">OK: no regression</span>'),
               1: ('<span class="bad">REGRESSION</span>'),
               2: ('<span class="bad">ERROR: the runs could not be compared</span>')}[code]
    p: list[str] = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{_e(title)}"
                    f"</title><style>{_CSS}</style></head><body>",
                    f"<h1>{_e(title)}</h1><p>{verdict} (exit code {code})</p>"]
    sc = summ["scans"]
    p.append("<table><tr><th>logs</th><th>scans</th><th>identical</th><th>within tolerance"
             "</th><th>changed</th><th>missing</th><th>extra</th><th>error</th>"
             "<th>regressions</th></tr>"
             f"<tr><td>{summ['n_logs']}</td><td>{summ['n_scans']}</td>"
             f"<td>{sc['identical']}</td><td>{sc['equivalent']}</td><td>{sc['changed']}</td>"
             f"<td>{sc['missing']}</td><td>{sc['extra']}</td><td>{sc['error']}</td>"
             f"<td>{summ['n_regressions']}</td></tr></table>")
    if summ.get("scores"):
        s = summ["scores"]
        p.append("<h2>Scores (ground truth)</h2><table><tr><th></th><th>tp</th><th>fp</th>"
                 "<th>fn</th><th>precision</th><th>recall</th><th>F1</th></tr>")
        for side in ("base", "candidate"):
            v = s[side]
            p.append(f"<tr><td>{side}</td><td>{v['tp']}</td><td>{v['fp']}</td>"
                     f"<td>{v['fn']}</td><td>{v['precision']:.3f}</td>"
                     f"<td>{v['recall']:.3f}</td><td>{v['f1']:.3f}</td></tr>")
        p.append("</table>")
    if summ["regressions"]:
        p.append("<h2>Regressions</h2><ul>")
        for r in summ["regressions"][:MAX_ROWS]:
            where = f"scan {r['scan']}: " if r["scan"] is not None else ""
            p.append(f"<li>{_e(r['log'])}: {_e(where)}{_e(r['message'])} "
                     f"<span class='muted'>({_e(r['rule'])})</span></li>")
        p.append("</ul>")
    if summ["failed_picks"]:
        p.append("<h2>Failed picks of the baseline</h2><ul>")
        for fp in summ["failed_picks"][:MAX_ROWS]:
            p.append(f"<li>{_e(fp['log'])} scan {fp['scan']} surface #{fp['surface']}"
                     f"{': ' + _e(fp['reason']) if fp['reason'] else ''} &rarr; "
                     f"<b>{_e(fp['fate'])}</b> in the candidate</li>")
        p.append("</ul>")
    plots = _plots(diffs)
    if plots:
        p.append("<h2>Plots</h2><div class='plots'>" + "".join(plots) + "</div>")
    for ld in diffs:
        p.append(f"<h2>{_e(ld.name)}</h2><p class='muted'>{_e(ld.base)} vs "
                 f"{_e(ld.candidate)}</p>")
        if ld.error:
            p.append(f"<p class='bad'>error: {_e(ld.error)}</p>")
            continue
        if ld.versions:
            p.append("<p class='muted'>" + ", ".join(f"{_e(k)} {_e(v)}" for k, v in
                                                    ld.versions.items() if v) + "</p>")
        if ld.config_changes:
            p.append("<p>config: " + ", ".join(f"<code>{_e(k)}</code> {_e(_arrow(a, b, 6))}"
                                              for k, (a, b) in ld.config_changes.items())
                     + "</p>")
        if ld.differences:
            p.append("<ul>" + "".join(
                f"<li class='{'reg' if d.regression else ''}'>{_e(d.message)}</li>"
                for d in ld.differences) + "</ul>")
        rows = [s for s in ld.scans if s.status != "identical" or s.picks]
        p.append(f"<p>{len(ld.scans)} scan(s), {len(ld.scans) - len(rows)} identical and "
                 "not listed.</p>")
        if rows:
            p.append("<table><tr><th>scan</th><th>status</th><th>counts</th>"
                     "<th>unmatched items</th><th>flipped tests</th><th>surfaces</th>"
                     "<th>tp/pred/exposed</th><th>picks</th><th>differences</th></tr>")
            for s in rows[:MAX_ROWS]:
                c = _scan_cells(s)
                diffs_html = "<br>".join(
                    ("<b>" if d.regression else "") + _e(d.message)
                    + ("</b>" if d.regression else "") for d in s.differences[:30])
                p.append(f"<tr class='{'reg' if s.regression else ''}'><td>{s.scan}</td>"
                         + "".join(f"<td>{_e(c[k])}</td>" for k in (
                             "status", "counts", "items", "flipped", "surfaces", "scores",
                             "picks")) + f"<td>{diffs_html}</td></tr>")
            p.append("</table>")
            if len(rows) > MAX_ROWS:
                p.append(f"<p class='muted'>{len(rows) - MAX_ROWS} more scan(s) in "
                         "diff.jsonl.</p>")
    tm = summ.get("timing_ms") or {}
    if tm:
        p.append("<h2>Timing (wall clock; its own channel, never a difference)</h2><table>"
                 "<tr><th>stage</th><th>base median [ms]</th><th>candidate median [ms]</th>"
                 "<th>base p95</th><th>candidate p95</th></tr>")
        for stage, v in tm.items():
            b, c = v.get("base") or {}, v.get("candidate") or {}
            p.append(f"<tr><td>{_e(stage)}</td><td>{_fmt(b.get('median'), 1)}</td>"
                     f"<td>{_fmt(c.get('median'), 1)}</td><td>{_fmt(b.get('p95'), 1)}</td>"
                     f"<td>{_fmt(c.get('p95'), 1)}</td></tr>")
        p.append("</table>")
    p.append("<p class='muted'>Tolerances: " + _e(summ["tolerances"] and
                                                  json.dumps(summ["tolerances"])) + "</p>")
    p.append("</body></html>\n")
    return "".join(p)


# --- blessing a candidate --------------------------------------------------------------------


def _backup(target: Path) -> Path:
    """Move ``target`` (and its pick-outcome sidecar) into ``<dir>/.boxloc-bak/``.

    The backup is ``NAME-001.mcap``, ``-002``, ... (the first free number); the sidecar
    follows its log, since the outcomes describe that log's surfaces.
    """
    from recorder.annotate import sidecar_path

    bak = target.parent / BACKUP_DIR
    bak.mkdir(exist_ok=True)
    k = 1
    while (bak / f"{target.stem}-{k:03d}{target.suffix}").exists():
        k += 1
    dest = bak / f"{target.stem}-{k:03d}{target.suffix}"
    os.replace(target, dest)
    side = sidecar_path(target)
    if side.exists():
        os.replace(side, sidecar_path(dest))
    return dest


def _copy_atomic(src: Path, dest: Path) -> None:
    tmp = dest.with_name(f".{dest.name}.tmp{os.getpid()}")
    try:
        shutil.copyfile(src, tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, dest)
    finally:
        if tmp.exists():
            tmp.unlink()


def bless(candidate: str | os.PathLike[str], refs: str | os.PathLike[str]) -> list[Path]:
    """``--update-refs``: make the candidate's logs the reference logs.

    Parameters
    ----------
    candidate : path
        A ``.mcap`` log or a directory of them.
    refs : path
        The reference directory (created if needed), or, for a single candidate log, the
        reference file itself (``.../NAME.mcap``).

    Returns
    -------
    list of Path
        The reference files written.

    Notes
    -----
    Nothing is overwritten without a copy: a reference that is replaced is first moved to
    ``<refs>/.boxloc-bak/NAME-NNN.mcap`` (the first free NNN), together with its pick-outcome
    sidecar; a sidecar of the candidate is copied with it. Each copy is written to a
    temporary file and renamed, so a reference is never half-written.

    Raises
    ------
    InputError
        A missing candidate, a directory without logs, or a directory blessed into a file.
    """
    from recorder.annotate import sidecar_path

    cand, ref = Path(candidate), Path(refs)
    if not cand.exists():
        raise InputError(f"candidate not found: {cand}")
    if cand.is_dir():
        logs = list(list_logs(cand).values())
        if not logs:
            raise InputError(f"no .mcap logs in {cand}")
        if ref.suffix.lower() == ".mcap":
            raise InputError(f"cannot bless the directory {cand} into the file {ref}")
        pairs = [(p, ref / p.name) for p in logs]
    elif ref.suffix.lower() == ".mcap":
        pairs = [(cand, ref)]
    else:
        pairs = [(cand, ref / cand.name)]
    pairs[0][1].parent.mkdir(parents=True, exist_ok=True)
    written = []
    for src, dest in pairs:
        if dest.exists() and os.path.samefile(src, dest):
            written.append(dest)  # the candidate already is the reference
            continue
        if dest.exists():
            _backup(dest)
        _copy_atomic(src, dest)
        side = sidecar_path(src)
        if side.exists():
            _copy_atomic(side, sidecar_path(dest))
        written.append(dest)
    return written

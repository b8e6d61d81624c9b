"""Regenerate the docs' benchmark tables (and the log's channel table) from their sources.

A figure lives in one place: the bench's JSON report. The README and docs/benchmarks.md
only show it, between markers that this script owns::

    <!-- bench:matrix:summary -->
    ...generated, do not edit...
    <!-- /bench -->

Usage (from the repository's root, with the project's venv)::

    .venv/bin/python scripts/bench_tables.py [--matrix FILE] [--real FILE] [--sim FILE]
                                             [--packed FILE] [--bare FILE]
                                             [--speed FILE] [--footprint FILE]
                                             [--date D] [--commit C] [--command CMD]
    .venv/bin/python scripts/bench_tables.py --check

1. Each report given (``bench_matrix.json`` of ``boxloc bench --matrix``, ``bench_real.json``
   of ``bench --real``, ``bench.json`` of ``bench``, ``bench_packed.json`` of ``bench
   --packed``, ``bench_bare.json`` of ``python -m boxloc.evaluate.bare_bench``,
   ``bench_speed.json`` of ``scripts/profile_stages.py --out``, and, as
   ``bench_footprint.json``, the ``bench.json`` of ``boxloc bench --section recording``) is
   checked against its schema, trimmed of its per-scan rows (``scenes``, ``frames``,
   per-scan times: the raw file is hundreds of kB) and written to ``docs/results/<its
   name>`` with a ``provenance`` section: the date, the commit and the command that produced
   it. The reports (but the speed report, which records its own) carry none of the three,
   so they come from ``--date``, ``--commit`` and ``--command`` when given, else the date
   is the file's modification time, the commit the last one before the run began (marked
   ``inferred``: the run may have had uncommitted changes) and the command is
   reconstructed from the report's fields (the options that change a figure).
2. Every marked region of README.md and docs/*.md is rewritten from ``docs/results/``; a
   region whose report is absent says how to make it. Rewriting is idempotent.

``--check`` writes nothing and exits 1 if a file would change (a test runs it). A report of
the wrong schema, an unknown region or a region left open exits 2 with one line.

Regions: ``bench:matrix:{summary,targets,kinds,cells,stages,false}``,
``bench:real:{summary,targets,draws,inputs,stages}``,
``bench:sim:{summary,kinds,draws,stages}``, ``bench:packed:{summary,targets}``,
``bench:bare:{summary,targets,tests}``, ``bench:speed:summary``,
``bench:footprint:{summary,channels}`` (the summary also reads the speed report's peak RSS),
each closed by ``<!-- /bench -->``; and
``log:channels`` (from :data:`recorder.mcap.channels.CHANNELS`), closed by ``<!-- /log -->``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import hashlib
import json
import math
import os
import re
import subprocess
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

ROOT = Path(__file__).resolve().parent.parent
RESULTS_DIR = Path("docs") / "results"
#: The Markdown files whose regions are rewritten (docs/*.md are added when present).
TOP_FILES = ("README.md",)

REGION = re.compile(r"<!-- (bench|log):([a-z]+(?::[a-z]+)?) -->\n(.*?)<!-- /\1 -->",
                    re.DOTALL)
OPEN = re.compile(r"<!-- (bench|log):([a-z:]+) -->")


class ToolError(Exception):
    """A problem with an input: reported as one line, exit status 2."""


# --- the kinds of report -----------------------------------------------------------------


@dataclass(frozen=True)
class Kind:
    """One kind of bench report.

    Attributes
    ----------
    name : str
        ``matrix``, ``real``, ``sim``, ``packed`` or ``bare``: the option (``--matrix``)
        and the regions' middle word.
    file : str
        Its file name, in the bench's output directory and in docs/results.
    schema : str or None
        The report's ``schema`` field (the matrix, packed and bare reports have one); reports
        without it
        are told apart by ``required`` keys and the absence of ``schema``.
    required : tuple of str
        Top-level keys the tables read.
    drop : tuple of str
        Dotted keys trimmed from the committed copy (per-scan rows).
    make : str
        How to make the report (a region's text while it is absent).
    source : str or None
        The name of the file the bench writes, when not ``file``.
    uses : tuple of str
        Other kinds whose reports this kind's tables also read (keyword arguments of the
        renderers, None while absent).
    """

    name: str
    file: str
    schema: str | None
    required: tuple[str, ...]
    drop: tuple[str, ...]
    make: str
    source: str | None = None
    uses: tuple[str, ...] = ()


KINDS: dict[str, Kind] = {
    "matrix": Kind("matrix", "bench_matrix.json", "boxloc.bench_matrix/1",
                   ("n", "seed", "sensors", "kinds", "held_out", "seeds", "groups", "targets",
                    "timing", "memory", "timeouts", "errors"),
                   ("scenes", "timing.per_scan_ms"),
                   "boxloc bench --matrix --jobs 2 --out DIR"),
    "real": Kind("real", "bench_real.json", None,
                 ("data_dir", "n_frames", "seeds", "config", "config_hash", "noise",
                  "squareness", "pose", "summary", "groups", "targets", "timing", "errors"),
                 ("frames", "timing.boxloc.per_frame_ms", "timing.baseline.per_frame_ms"),
                 "boxloc bench --real ../shared/data/mosd --set min_edge=0.035 --seeds 8 "
                 "--out DIR"),
    "sim": Kind("sim", "bench.json", None,
                ("n", "seed", "seeds", "config", "config_hash", "summary", "per_kind",
                 "targets", "timing", "memory", "errors"),
                ("scenes", "timing.boxloc.per_scene_total_ms",
                 "timing.baseline.per_scene_total_ms"),
                "boxloc bench --n 100 --out DIR"),
    "packed": Kind("packed", "bench_packed.json", "boxloc.bench_packed/1",
                   ("n", "seed", "sensors", "variants", "held_out", "groups", "targets",
                    "timing", "timeouts", "errors"),
                   ("scenes", "timing.per_scan_ms"),
                   "boxloc bench --packed --n 96 --out DIR"),
    "bare": Kind("bare", "bench_bare.json", "boxloc.bench_bare/1",
                 ("n", "seed", "alpha", "sensors", "null_kinds", "groups", "targets",
                  "timeouts", "errors"),
                 ("scenes",),
                 "python -m boxloc.evaluate.bare_bench --n 100 --jobs 2 --out DIR"),
    "speed": Kind("speed", "bench_speed.json", "boxloc.bench_speed/1",
                  ("suite", "n", "seed", "size", "scans", "stages_ms", "wall_ms", "baseline",
                   "targets", "memory", "machine"),
                  ("per_scan_ms",),
                  "nice .venv/bin/python scripts/profile_stages.py --suite matrix --n 32 "
                  "--out DIR/bench_speed.json"),
    "footprint": Kind("footprint", "bench_footprint.json", None,
                      ("n", "seed", "config", "config_hash", "sections"), (),
                      "boxloc bench --section recording --out DIR", source="bench.json",
                      uses=("speed",)),
}


def check_report(report: Any, kind: Kind, where: str) -> None:
    """Raise ToolError (one line) unless ``report`` is a report of ``kind``."""
    if not isinstance(report, dict):
        raise ToolError(f"{where}: not a bench report (a JSON object), got "
                        f"{type(report).__name__}")
    schema = report.get("schema")
    if kind.schema is not None and schema != kind.schema:
        raise ToolError(f"{where}: schema {schema!r}, expected {kind.schema!r} "
                        f"(a {kind.file}: {kind.make})")
    if kind.schema is None and schema is not None:
        raise ToolError(f"{where}: a {schema} report, not a {kind.file}")
    missing = [k for k in kind.required if k not in report]
    if missing:
        raise ToolError(f"{where}: not a {kind.file} report: no {', '.join(missing)}")
    if kind.name == "sim" and report.get("mode") is not None:
        raise ToolError(f"{where}: a {report['mode']!r} report, not a {kind.file}")
    if kind.name == "footprint" and not isinstance(
            (report.get("sections") or {}).get("recording"), dict):
        raise ToolError(f"{where}: no recording section (make it with `{kind.make}`)")


def load_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise ToolError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ToolError(f"{path}: not readable JSON ({e})") from None


# --- ingest: trim, stamp, commit-ready copy -------------------------------------------------


def _drop(report: dict[str, Any], dotted: str) -> bool:
    *head, last = dotted.split(".")
    d: Any = report
    for k in head:
        d = d.get(k) if isinstance(d, dict) else None
    if isinstance(d, dict) and last in d:
        del d[last]
        return True
    return False


def _git(root: Path, *args: str) -> str | None:
    try:
        out = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True,
                             timeout=30, check=True)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def _run_seconds(report: dict[str, Any]) -> float:
    """How long the run took, seconds, as far as the report says (0 if it does not)."""
    t = report.get("timing", {})
    if isinstance(t.get("run_s"), int | float):
        return float(t["run_s"])
    tp = ((report.get("sections") or {}).get("recording") or {}).get("throughput") or {}
    if tp.get("runs"):  # the recording section: its throughput runs, a lower bound
        return sum(float(r.get("wall_s") or 0) + float(r.get("first_scans_wall_s") or 0)
                   for r in tp["runs"])
    total = 0.0
    for m in t.values() if isinstance(t, dict) else ():
        for key in ("per_frame_ms", "per_scene_total_ms"):
            if isinstance(m, dict) and isinstance(m.get(key), list):
                total += sum(v for v in m[key] if isinstance(v, int | float)) / 1e3
    return total


def _config_sets(config: dict[str, Any], skip: set[str]) -> list[str]:
    """``--set k=v`` for every config value that differs from today's default."""
    from boxloc.config import Config

    default = Config().to_dict()
    out = []

    def walk(cur: dict[str, Any], ref: dict[str, Any], prefix: str) -> None:
        for k, v in cur.items():
            key = prefix + k
            if key in skip or key == "workers":
                continue
            if isinstance(v, dict) and isinstance(ref.get(k), dict):
                walk(v, ref[k], key + ".")
            elif k in ref and v != ref[k]:
                val = str(v).lower() if isinstance(v, bool) else f"{v:g}" if isinstance(
                    v, float) else str(v)
                out.append(f"--set {key}={val}")

    walk(config, default, "")
    return out


def reconstruct_command(report: dict[str, Any], kind: Kind) -> str:
    """The ``boxloc bench`` command line that produced ``report``, from its fields."""
    seeds = int(report.get("seeds", {}).get("n", 1))
    if kind.name == "speed":
        return (f"python scripts/profile_stages.py --suite {report['suite']} --n {report['n']} "
                f"--seed {report['seed']} --size {report['size']}"
                + (" --no-baseline" if report.get("baseline") is None else "")
                # a report without its box range ran Config() alone
                + ("" if report.get("box_range") else " --box-range defaults")
                + " --out DIR/bench_speed.json")
    if kind.name == "footprint":
        return " ".join([f"boxloc bench --section recording --n {report['n']} --seed "
                         f"{report['seed']}", *_config_sets(report["config"], set()),
                         "--out DIR"])
    if kind.name == "packed":
        from boxloc.evaluate.packed_bench import default_interlocked

        weave = report.get("suite", {}).get("patterns", {}).get("weave")
        if weave is not None and weave != default_interlocked(report["n"]):
            return (f"python -m boxloc.evaluate.packed_bench --n {report['n']} --interlocked "
                    f"{weave} --seed {report['seed']} --seeds {seeds} "
                    f"--jobs {report.get('jobs', 1)} --held-out {report['held_out']['sensor']} "
                    f"--scan-timeout {report.get('scan_timeout_s', 120):g} --out DIR")
        return (f"boxloc bench --packed --n {report['n']} --seed {report['seed']} "
                f"--seeds {seeds} --jobs {report.get('jobs', 1)} "
                f"--held-out {report['held_out']['sensor']} "
                f"--scan-timeout {report.get('scan_timeout_s', 120):g} --out DIR")
    if kind.name == "bare":
        return (f"python -m boxloc.evaluate.bare_bench --n {report['n']} --seed "
                f"{report['seed']} --jobs {report.get('jobs', 1)} "
                f"--scan-timeout {report.get('scan_timeout_s', 120):g} --out DIR")
    if kind.name == "matrix":
        return (f"boxloc bench --matrix --n {report['n']} --seed {report['seed']} "
                f"--seeds {seeds} --jobs {report.get('jobs', 1)} "
                f"--held-out {report['held_out']['sensor']} "
                f"--scan-timeout {report.get('scan_timeout_s', 120):g} --out DIR")
    if kind.name == "real":
        noise = str(report["noise"].get("source", ""))
        nflag = ("auto" if noise.startswith("auto") else "config" if noise.startswith(
            "config") else "estimate")
        sq = str(report["squareness"].get("source", ""))
        sflag = ("config" if sq == "config" else "cross" if "other groups" in sq
                 else "estimate")
        pflag = str(report["pose"]).split(":", 1)[0]
        skip = {"angle_tolerance"} if sflag != "config" else set()
        if nflag != "auto":  # the harness pins the model (and fits it with estimate)
            skip |= {"noise_auto"} | ({"noise"} if nflag == "estimate" else set())
        parts = [f"boxloc bench --real {report['data_dir']}",
                 *_config_sets(report["config"], skip), f"--seeds {seeds}",
                 f"--noise {nflag}", f"--squareness {sflag}", f"--pose {pflag}"]
        if "baseline" not in report["summary"]:
            parts.append("--no-baseline")
        return " ".join(parts + ["--out DIR"])
    parts = [f"boxloc bench --n {report['n']} --seed {report['seed']}",
             *_config_sets(report["config"], set()), f"--seeds {seeds}"]
    if "baseline" not in report["summary"]:
        parts.append("--no-baseline")
    return " ".join(parts + ["--out DIR"])


def ingest(path: Path, kind: Kind, root: Path, *, date: str | None, commit: str | None,
           command: str | None) -> Path:
    """Check, trim and stamp the report at ``path``; write it to docs/results. Returns
    the path written."""
    report = load_json(path)
    check_report(report, kind, str(path))
    raw_bytes = path.read_bytes()
    prov = dict(report.get("provenance") or {})
    if date is None and "date" not in prov:
        end = dt.datetime.fromtimestamp(path.stat().st_mtime, dt.UTC)
        date = end.strftime("%Y-%m-%d %H:%M UTC")
    if commit is None and "commit" not in prov:
        start = path.stat().st_mtime - _run_seconds(report)
        found = _git(root, "log", "-1", "--format=%h", f"--before=@{int(start)}")
        prov["commit"] = found or "unknown"
        prov["commit_inferred"] = True
    elif commit is not None:
        prov["commit"], prov["commit_inferred"] = commit, False
    if date is not None:
        prov["date"] = date
    if command is not None:
        prov["command"], prov["command_reconstructed"] = command, False
    elif "command" not in prov:
        prov["command"] = reconstruct_command(report, kind)
        prov["command_reconstructed"] = True
    prov.setdefault("raw_sha256", hashlib.sha256(raw_bytes).hexdigest())
    dropped = [k for k in kind.drop if _drop(report, k)]
    prov["trimmed"] = sorted(set(prov.get("trimmed", [])) | set(dropped))
    report["provenance"] = prov
    out = root / RESULTS_DIR / kind.file
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1, ensure_ascii=False) + "\n")
    return out


# --- formatting --------------------------------------------------------------------------------


def num(v: Any, digits: int = 3) -> str:
    """A figure, or an en dash for none (no data)."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return str(v)
    return f"{v:.{digits}f}"


def secs(ms: Any) -> str:
    return "–" if ms is None else f"{ms / 1e3:.2f}"


def verdict(ok: Any) -> str:
    return "n/a" if ok is None else "pass" if ok else "miss"


def table(head: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    def cell(s: str) -> str:
        return s.replace("|", "\\|").replace("\n", " ")

    lines = ["| " + " | ".join(cell(h) for h in head) + " |",
             "|" + "|".join("---" for _ in head) + "|"]
    lines += ["| " + " | ".join(cell(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def stamp(report: dict[str, Any], kind: Kind, link: str) -> str:
    p = report.get("provenance", {})
    commit = p.get("commit", "unknown") + (" (inferred)" if p.get("commit_inferred") else "")
    if p.get("dirty") == "true":
        commit += " with uncommitted changes"
    cmd = p.get("command") or reconstruct_command(report, kind)
    how = " (reconstructed)" if p.get("command_reconstructed") else ""
    return (f"*{p.get('date', 'date unknown')}, commit {commit}, boxloc "
            f"{report.get('version', '?')}, config {report.get('config_hash', '?')}: "
            f"`{cmd}`{how}; [report]({link}).*")


def counts(g: dict[str, Any]) -> str:
    return f"{g.get('tp', 0)} / {g.get('fp', 0)} / {g.get('fn', 0)}"


def precision(g: dict[str, Any]) -> str:
    """Precision, or a dash where nothing was found (the reports then say 1.0)."""
    return "–" if g.get("n_pred", g.get("tp", 0) + g.get("fp", 0)) == 0 else num(
        g.get("precision"))


def recall(g: dict[str, Any]) -> str:
    """Recall, or a dash where there was nothing to find."""
    return "–" if g.get("n_exposed", g.get("tp", 0) + g.get("fn", 0)) == 0 else num(
        g.get("recall"))


# --- matrix tables -----------------------------------------------------------------------------


def _matrix_rows(groups: list[tuple[str, dict[str, Any]]], edges: bool = True
                 ) -> list[list[str]]:
    rows = []
    for label, g in groups:
        t, nb = g.get("time") or {}, g.get("no_box")
        row = [label, num(g.get("n_scans")), num(g.get("n_exposed")), counts(g),
               precision(g), recall(g),
               f"{num(g.get('grasp_err_median_mm'), 1)} / {num(g.get('grasp_err_p95_mm'), 1)}",
               f"{secs(t.get('median_ms'))} / {secs(t.get('max_ms'))}",
               f"{g.get('timeouts', 0)} / {g.get('errors', 0)}"]
        row.append(num(nb.get("zero_surface_share"), 2) if nb else "")
        if edges:
            row.append(num(nb.get("false_edge_points_per_pixel"), 4) if nb else "")
        rows.append(row)
    return rows


MATRIX_HEAD = ["", "scans", "exposed tops", "TP / FP / FN", "precision", "recall",
               "grasp error median / p95 (mm)", "time median / max (s)", "timeouts / errors",
               "no-box scans with 0 surfaces", "false edge points per pixel (no box)"]


def _sensor_groups(r: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """The matrix report's groups per sensor (the held-out one marked), then both overall
    scopes, with their row labels."""
    held = r["held_out"]["sensor"]
    g = r["groups"]
    rows = [(s + (" (held out)" if s == held else ""), g["sensors"][s]) for s in r["sensors"]
            if s in g["sensors"]]
    return rows + [(f"**all but {held}**", g["overall"]["development"]),
                   ("**all sensors**", g["overall"]["all"])]


def matrix_summary(r: dict[str, Any]) -> str:
    return table(["sensor", *MATRIX_HEAD[1:-1]], _matrix_rows(_sensor_groups(r), edges=False))


def matrix_false(r: dict[str, Any]) -> str:
    """The false surfaces per sensor by what they are (``false_kinds``,
    :class:`boxloc.evaluate.metrics.FalseKind`)."""
    from boxloc.evaluate.metrics import FalseKind

    kinds = [k.name.lower() for k in FalseKind if k != FalseKind.NONE]
    rows = []
    for label, fig in _sensor_groups(r):
        fk = fig.get("false_kinds")
        if fk is None:
            continue
        rows.append([label, num(fig.get("fp")), *[num(fk.get(k)) for k in kinds]])
    head = ["sensor", "false surfaces", "no top", "on a covered top",
            "a free top seen in part (IoU >= 0.5)", "wrong rectangle (IoU < 0.5)", "normal off"]
    assert len(head) == 2 + len(kinds)
    return table(head, rows)


def matrix_targets(r: dict[str, Any]) -> str:
    held = r["held_out"]["sensor"]
    rows = []
    for t in r["targets"]:
        cells = [t["name"], t.get("target", "")]
        for scope in ("development", "all"):
            s = t.get(scope) or {}
            where = f" ({s['where']})" if s.get("where") not in (None, "overall") else ""
            digits = 4 if "edge" in t.get("key", "") else 3
            cells += [num(s.get("value"), digits) + where, verdict(s.get("pass"))]
        rows.append(cells)
    return table(["target", "bound", f"without {held}", "", f"with {held}", ""], rows)


def matrix_kinds(r: dict[str, Any]) -> str:
    held = r["held_out"]["sensor"]
    kinds = r["groups"]["kinds"]
    rows = [(k, kinds[k]["development"]) for k in r["kinds"] if k in kinds]
    head = [f"kind (without {held})", *MATRIX_HEAD[1:]]
    return table(head, _matrix_rows(rows))


def matrix_cells(r: dict[str, Any]) -> str:
    cells = r["groups"]["cells"]
    rows = [(k + (" (held out)" if v.get("held_out") else ""), v) for k, v in cells.items()]
    return table(["sensor/kind", *MATRIX_HEAD[1:]], _matrix_rows(rows))


def matrix_normals(r: dict[str, Any]) -> str:
    """The vertex normals' calibration per sensor: chi2(2) of each normal's error over its
    own covariance at a true top's corner (``funnel.vertex_normals``); and of the lines
    along the tops' sides, their direction out of the top's plane over its sigma, N(0, 1),
    jump and crease lines apart (``funnel.line_directions``)."""
    from boxloc.evaluate.funnel import CHI2_2_MEDIAN, CHI2_2_P99, LINE_GROUPS, Z_MEDIAN, Z_P99

    rows = []
    for label, fig in _sensor_groups(r):
        f = fig.get("funnel") or {}
        v = f.get("vertex_normals") or {}
        row = [label, num(v.get("n")), num(v.get("median"), 2), num(v.get("beyond_p99"), 3)]
        for kind in LINE_GROUPS:
            lg = (f.get("line_directions") or {}).get(kind) or {}
            row += [num(lg.get("n")), num(lg.get("median_abs"), 2), num(lg.get("beyond_p99"), 3)]
        rows.append(row)
    rows.append(["calibrated", "", f"{CHI2_2_MEDIAN:.2f}", "0.010",
                 *(["", f"{Z_MEDIAN:.2f}", "0.010"] * len(LINE_GROUPS))])
    head = ["sensor", "vertices at a true top's corner", "median chi2(2)",
            f"beyond {CHI2_2_P99:.2f}"]
    for kind in LINE_GROUPS:
        head += [f"{kind} lines along its sides", "median abs(z)", f"beyond {Z_P99:.2f}"]
    return table(head, rows)


def _stage_table(stages: dict[str, Any], methods: dict[str, dict[str, Any]]) -> str:
    names: list[str] = []
    for m in methods.values():
        names += [k for k in m.get("stages_ms", {}) if k not in names]
    head = ["stage", *[f"{m}: median / p95 (ms)" for m in methods]]
    rows = []
    for s in names:
        row = [s]
        for m in methods.values():
            v = m.get("stages_ms", {}).get(s)
            row.append(f"{num(v.get('median'), 1)} / {num(v.get('p95'), 1)}" if v else "")
        rows.append(row)
    tot = ["whole scan, wall clock"]
    for m in methods.values():
        t = m.get("total_ms") or {}
        tot.append(f"{num(t.get('median'), 1)} / {num(t.get('p95'), 1)}")
    rows.append(tot)
    return table(head, rows)


def matrix_stages(r: dict[str, Any]) -> str:
    t, mem = r["timing"], r["memory"]
    out = [_stage_table(t.get("stages_ms", {}), {"boxloc": t}),
           "",
           f"Stage times are over the scans that finished; the whole-scan time counts a "
           f"timed-out scan at its limit ({r.get('scan_timeout_s', '?')} s). The run took "
           f"{num(t.get('run_s'), 0)} s with {r.get('jobs', '?')} worker process(es); a "
           f"worker's peak RSS: median {num(mem.get('worker_peak_rss_mb_median'), 0)} MB, "
           f"max {num(mem.get('worker_peak_rss_mb_max'), 0)} MB."]
    touts = r.get("timeouts") or []
    errs = (r.get("errors") or {}).get("list") or []
    if touts:
        out += ["", f"Timed out ({len(touts)}): " + ", ".join(
            f"scene {x['scene']} ({x['sensor']}/{x['kind']}, {x['phase']})" for x in touts)
            + "."]
    if errs:
        out += ["", f"Errors ({len(errs)}): " + "; ".join(
            f"scene {x['scene']} ({x['sensor']}/{x['kind']}, {x['phase']}): {x['error']}"
            for x in errs) + "."]
    return "\n".join(out)


# --- real tables -------------------------------------------------------------------------------


def _spread(r: dict[str, Any], group: str, method: str, key: str) -> str:
    s = r["seeds"]
    if s.get("n", 1) < 2:
        return ""
    v = s.get("spread", {}).get(group, {}).get(method, {}).get(key)
    return f" ({num(v['min'])}–{num(v['max'])})" if v else ""


def real_summary(r: dict[str, Any]) -> str:
    methods = [m for m in ("boxloc", "baseline") if m in r["summary"]]
    head = ["frames", "exposed tops", *[f"{m}: {f}" for m in methods
                                        for f in ("TP / FP / FN", "recall", "precision")],
            "boxloc: normal / centre error median"]
    labels = {"boxes": "box frames (learn0–16)", "stacked": "stacked frames (learn17–24)",
              "other": "other frames"}
    rows = []
    for gname, g in r["groups"].items():
        n_draws = max(1, int(r["seeds"].get("n", 1)))
        b = g.get("boxloc", {})
        row = [labels.get(gname, gname),
               num(b["n_exposed"] // n_draws) if isinstance(b.get("n_exposed"), int) else "–"]
        for m in methods:
            gm = g.get(m, {})
            row += [counts(gm), recall(gm) + _spread(r, gname, m, "recall"),
                    precision(gm) + _spread(r, gname, m, "precision")]
        row.append(f"{num(b.get('normal_err_median_deg'), 2)}° / "
                   f"{num(b.get('center_err_median_mm'), 1)} mm")
        rows.append(row)
    n = int(r["seeds"].get("n", 1))
    times = ", ".join(f"{m} {num((r['timing'].get(m, {}).get('total_ms') or {}).get('median'), 0)}"
                      " ms" for m in methods)
    crashes = ", ".join(f"{m} {r['errors'].get('count', {}).get(m, 0)}" for m in methods)
    note = (f"{r['n_frames']} frames × {n} draw(s) of the random trials (`trial_seed` "
            f"{', '.join(str(s) for s in r['seeds'].get('trial_seeds', []))}), pooled"
            + ("; in parentheses the worst and best draw" if n > 1 else "")
            + f". Median time per frame: {times}. Crashes: {crashes}.")
    return table(head, rows) + "\n\n" + note


def real_targets(r: dict[str, Any]) -> str:
    rows = [[t["name"], t.get("target", ""), num(t.get("value")), num(t.get("baseline")),
             verdict(t.get("pass"))] for t in r["targets"]]
    return table(["target", "bound", "boxloc", "open3d baseline", ""], rows)


def real_draws(r: dict[str, Any]) -> str:
    s = r["seeds"]
    methods = [m for m in ("boxloc", "baseline") if m in r["summary"]]
    groups = list(r["groups"])
    head = ["`trial_seed`", *[f"{g}: {m} TP / FP / FN" for g in groups for m in methods]]
    rows = [[str(p["trial_seed"]), *[counts(p["groups"].get(g, {}).get(m, {}))
                                     for g in groups for m in methods]]
            for p in s.get("per_seed", [])]
    return table(head, rows)


def real_inputs(r: dict[str, Any]) -> str:
    nz, sq = r["noise"], r["squareness"]
    # with noise_auto each scan fits its own model: the config's is only the fallback
    auto = bool(r["config"].get("noise_auto")) and str(nz.get("source", "")).startswith("auto")
    model = nz.get("model", {})
    terms = ", ".join(f"{k} = {v:g}" for k, v in model.items() if isinstance(v, int | float))
    if "per_group" in sq:
        def on(v: Any) -> str:
            return ", ".join(v) if isinstance(v, list) else str(v)

        tol = "; ".join(f"{g}: {num(v.get('angle_tolerance_deg'), 2)}° (fitted on "
                        f"{on(v.get('fitted_on'))})" for g, v in sq["per_group"].items())
    else:
        tol = f"{num(sq.get('angle_tolerance_deg'), 2)}°"
    rows = [["data", f"`{r['data_dir']}`, {r['n_frames']} frames"
             + (f", {len(r.get('skipped') or [])} skipped" if r.get("skipped") else "")],
            ["noise model", f"{nz.get('source', '?')}; "
             + ("fallback" if auto else "model") + f": {terms}"],
            ["`angle_tolerance`", f"{sq.get('source', '?')}: {tol}"],
            ["pose", str(r["pose"])],
            ["config", f"{r['config_hash']} (the benchmark's, before any per-group prior)"]]
    return table(["input", "value"], rows)


def real_stages(r: dict[str, Any]) -> str:
    methods = {m: r["timing"][m] for m in ("boxloc", "baseline") if m in r["timing"]}
    return _stage_table({}, methods)


# --- simulated (bench.json) tables -----------------------------------------------------------


def sim_summary(r: dict[str, Any]) -> str:
    has_base = "baseline" in r["summary"]
    rows = []
    for t in r["targets"]:
        unit = t.get("unit") or ""
        digits = 1 if unit in ("mm", "ms", "MB") else 3
        u = f" {unit}" if unit else ""
        rows.append([t["name"], num(t.get("value"), digits) + u,
                     num(t.get("baseline"), digits) + u if has_base else "–",
                     t.get("target", ""), verdict(t.get("pass"))])
    s = r["summary"]["boxloc"]
    rows.insert(2, ["TP / FP / FN", counts(s),
                    counts(r["summary"]["baseline"]) if has_base else "–", "", ""])
    edges = (r.get("edges") or {}).get("any")
    if edges:
        rows.append(["edge pixels: precision / recall (any edge, 1 px)",
                     f"{num(edges.get('precision'), 2)} / {num(edges.get('recall'), 2)}",
                     "", "", ""])
    n = int(r["seeds"].get("n", 1))
    note = (f"{r['n']} simulated scenes (suite seed {r['seed']}) × {n} draw(s) of the random "
            "trials, pooled.")
    return table(["figure", "boxloc", "open3d baseline", "target", ""], rows) + "\n\n" + note


def sim_kinds(r: dict[str, Any]) -> str:
    methods = [m for m in ("boxloc", "baseline") if m in r["summary"]]
    head = ["kind", "scenes", *[f"{m}: {f}" for m in methods
                                for f in ("TP / FP / FN", "precision / recall", "grasp median")]]
    rows = []
    for k, e in r["per_kind"].items():
        row = [k, num(e.get("n_scenes"))]
        for m in methods:
            g = e.get(m, {})
            row += [counts(g), f"{precision(g)} / {recall(g)}",
                    f"{num(g.get('grasp_err_median_mm'), 1)} mm"]
        rows.append(row)
    return table(head, rows)


def sim_draws(r: dict[str, Any]) -> str:
    methods = [m for m in ("boxloc", "baseline") if m in r["summary"]]
    head = ["`trial_seed`", *[f"{m}: TP / FP / FN" for m in methods],
            *[f"{m}: precision / recall" for m in methods]]
    rows = []
    for p in r["seeds"].get("per_seed", []):
        f = p.get("figures", {})
        rows.append([str(p["trial_seed"]), *[counts(f.get(m, {})) for m in methods],
                     *[f"{precision(f.get(m, {}))} / {recall(f.get(m, {}))}"
                       for m in methods]])
    return table(head, rows)


def sim_stages(r: dict[str, Any]) -> str:
    methods = {m: r["timing"][m] for m in ("boxloc", "baseline") if m in r["timing"]}
    mem = r.get("memory", {})
    peaks = ", ".join(f"{m} {num(mem.get(f'{m}_peak_rss_mb'), 0)} MB" for m in methods)
    return _stage_table({}, methods) + f"\n\nPeak RSS of the whole process: {peaks}."


# --- packed layers (bench_packed.json) ------------------------------------------------------


PACKED_VARIANTS = {"without_sizes": "without sizes", "with_sizes": "with sizes"}


def _heights(g: dict[str, Any]) -> str:
    """Height error median / p95 (mm) over the tops whose height came from a side or a
    step, with their count."""
    if not g.get("height_n"):
        return "– (0)"
    return (f"{num(g.get('height_err_median_mm'), 1)} / {num(g.get('height_err_p95_mm'), 1)}"
            f" ({g['height_n']})")


def _sources(g: dict[str, Any]) -> str:
    hs = g.get("height_sources") or {}
    return " / ".join(str(hs.get(k, 0)) for k in ("side", "step", "sku", "none"))


def _wrong(g: dict[str, Any]) -> str:
    """Wrong rectangles over the rectangles reported (count), or a dash where none was."""
    if not g.get("n_pred", g.get("tp", 0) + g.get("fp", 0)):
        return "–"
    return f"{num(g.get('wrong_rate'))} ({g.get('wrong_rectangles', 0)})"


def packed_summary(r: dict[str, Any]) -> str:
    held = r["held_out"]["sensor"]
    rows = []
    for v in r["variants"]:
        gv = r["groups"].get(v)
        if gv is None:
            continue
        groups = [(s + (" (held out)" if s == held else ""), gv["sensors"][s])
                  for s in r["sensors"] if s in gv["sensors"]]
        groups += [(f"**all but {held}**", gv["overall"]["development"]),
                   ("**all sensors**", gv["overall"]["all"])]
        woven = gv.get("interlocked")
        if woven is not None:  # basket-weave layers, reported apart
            groups += [(f"interlocked, {s}" + (" (held out)" if s == held else ""),
                        woven["sensors"][s]) for s in r["sensors"] if s in woven["sensors"]]
            groups += [(f"**interlocked, all but {held}**", woven["overall"]["development"]),
                       ("**interlocked, all sensors**", woven["overall"]["all"])]
        for label, g in groups:
            rows.append([PACKED_VARIANTS.get(v, v), label, num(g.get("n_scans")), counts(g),
                         precision(g), recall(g), _wrong(g),
                         num(g.get("ambiguous_per_scan"), 2), num(g.get("silent_scans")),
                         _heights(g), _sources(g)])
    head = ["variant", "sensor", "scans", "TP / FP / FN", "precision", "recall",
            "wrong-rectangle rate (count)", "ambiguous regions per scan", "silent scans",
            "height error median / p95 (mm) (n)",
            "reported tops' height source: side / step / sku / none"]
    pat = r.get("suite", {}).get("patterns", {})
    woven = (f" The *interlocked* rows are {pat['weave']} more layers of cartons twice as "
             "long as wide laid as basket weaves (the outline of a grid of the carton, which "
             "they are not); every other row is the grid layers'."
             if pat.get("weave") else "")
    note = (f"Layered pallets with no gaps between cartons: {r['n']} scenes (suite seed "
            f"{r['seed']}) over {len(r['sensors'])} sensor models, "
            f"{int(r.get('seeds', {}).get('n', 1))} draw(s) of the random trials. *Without "
            "sizes* runs the default configuration; *with sizes* also gives the scene's carton "
            "sizes (`box_sizes`). A wrong rectangle is a reported top that is no box's top "
            "(rate over the tops reported); an ambiguous region is a flat region reported as "
            "not splittable into tops; a silent scan has exposed tops but reports neither a "
            "surface nor a region (to the cell the pallet looks empty). Height errors are over "
            "the true positives whose height came from a visible side or a step to a "
            "neighbour; the sources count every reported top (a *sku* height is the given "
            "size's)." + woven)
    return table(head, rows) + "\n\n" + note


def packed_targets(r: dict[str, Any]) -> str:
    held = r["held_out"]["sensor"]
    rows = []
    for t in r["targets"]:
        unit = t.get("unit") or ""
        u = f" {unit}" if unit else ""
        cells = [t["name"], t.get("target", "")]
        for scope in ("development", "all"):
            s = t.get(scope) or {}
            where = f" ({s['where']})" if s.get("where") not in (None, "overall") else ""
            cells += [num(s.get("value"), 1 if unit == "mm" else 3) + u + where,
                      verdict(s.get("pass"))]
        rows.append(cells)
    return (table(["target (issue 21 point 4)", "bound", f"without {held}", "",
                   f"with {held}", ""], rows)
            + "\n\nA bound over every sensor shows its worst sensor in parentheses.")


# --- bare planes (bench_bare.json) -----------------------------------------------------------


def _bare_groups(r: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    g = r["groups"]
    out = [(s, g["sensors"][s]) for s in r["sensors"] if s in g["sensors"]]
    return out + [("**all sensors**", g["all"])]


def bare_summary(r: dict[str, Any]) -> str:
    alpha = float(r["alpha"])
    rows = []
    for label, g in _bare_groups(r):
        t, nf = g.get("time") or {}, g.get("noise_fit") or {}
        edge = g.get("edge_points_per_pixel")
        zero = g.get("zero_surface_share")
        rows.append([label, num(g.get("n_scans")),
                     f"{g.get('timeouts', 0)} / {g.get('errors', 0)}",
                     f"{g.get('zero_surface_scans', 0)} / {g.get('ok', 0)} ({num(zero, 2)})",
                     verdict(None if zero is None else zero >= 0.99),
                     num(g.get("surfaces")), num(edge, 4),
                     verdict(None if edge is None else edge <= 2 * alpha),
                     num(g.get("false_edge_points_per_pixel"), 4),
                     f"{nf.get('rejected', 0)} / {nf.get('scans', 0)} ({num(nf.get('rate'))})",
                     f"{secs(t.get('median_ms'))} / {secs(t.get('max_ms'))}"])
    head = ["sensor", "scans", "timeouts / errors", "scans with 0 surfaces", ">= 99 %",
            "surfaces", "edge points per pixel", f"<= 2 alpha = {2 * alpha:g}",
            "false edge points per pixel", "NOISE_FIT rejected / tested",
            "time median / max (s)"]
    kinds = ", ".join(r.get("kinds", []))
    note = (f"{r['n']} bare scenes per sensor model ({kinds}; suite seed {r['seed']}), "
            f"alpha {alpha:g}: no box in view, so every surface is a false alarm. Edge points "
            "per pixel count every pixel labelled an edge (a bare pallet has real edges); a "
            "false edge point is one farther than 1 px from a true edge.")
    return table(head, rows) + "\n\n" + note


def bare_targets(r: dict[str, Any]) -> str:
    rows = [[t["sensor"], t["name"], f"{t.get('op', '')} {num(t.get('bound'), 2)}",
             num(t.get("value"), 4), verdict(t.get("pass"))] for t in r["targets"]]
    return table(["sensor", "target", "bound", "value", ""], rows)


def bare_tests(r: dict[str, Any]) -> str:
    alpha = float(r["alpha"])
    null = set(r["null_kinds"])
    groups = [(s, r["groups"]["sensors"][s]) for s in r["sensors"]
              if s in r["groups"]["sensors"]]
    names: list[str] = []
    for _, g in groups:
        names += [k for k in g.get("tests", {}) if k not in names]
    rows = []
    for k in sorted(names):
        row = [f"`{k}`" + (" *" if k in null else "")]
        for _, g in groups:
            e = g.get("tests", {}).get(k)
            if not e or not e.get("tested"):
                row.append("–")
                continue
            cell = f"{e['rejected']} / {e['tested']} ({num(e.get('rate'))})"
            if "per_sample" in e:
                cell += f", {num(e['per_sample'], 5)} per sample"
            if k in null:
                cell += f" = {num(float(e.get('rate', 0.0)) / alpha, 1)} alpha"
            row.append(cell)
        rows.append(row)
    note = (f"Rejected / tested per test kind, from the scans' records. * marks a test that "
            f"is level alpha under the null a bare plane is ({', '.join(sorted(null))}): its "
            f"rate should be near alpha = {alpha:g}, shown as a multiple of alpha. The other "
            "kinds test hypotheses the pipeline built from a bare plane's false edges or "
            "regions, not a null, so their rate is not compared with alpha. `JUMP` and "
            "`CREASE` count detections only (every recorded one is a rejection); their per-"
            "sample rate is over 2 × the valid pixels (two directions).")
    return table(["test kind", *[s for s, _ in groups]], rows) + "\n\n" + note


# --- speed (bench_speed.json, scripts/profile_stages.py) ---------------------------------------


def _ms(v: Any) -> str:
    return num(v, 1)


def _times(x: Any) -> str:
    return "–" if x is None else f"{x:.2f}×"


def speed_summary(r: dict[str, Any]) -> str:
    rows = []
    for name, f in r["stages_ms"].items():
        share = f.get("share")
        label = "**total**" if name == "total" else name
        rows.append([label, _ms(f.get("median")), _ms(f.get("p99")), _ms(f.get("max")),
                     "" if share is None else f"{100 * share:.0f} %"])
    base = r.get("baseline")
    if base is not None:
        bw, ratio = base.get("wall_ms") or {}, base.get("ratio") or {}
        errs = len(base.get("errors") or [])
        rows.append(["open3d baseline, same scans" + (f" ({errs} crashed)" if errs else ""),
                     _ms(bw.get("median")), _ms(bw.get("p99")), _ms(bw.get("max")), ""])
        rows.append(["boxloc / baseline (time)", _times(ratio.get("median")),
                     _times(ratio.get("p99")), "", ""])
    goals = {t.get("key"): t for t in r["targets"]}
    rows.append(["target (issue 22)", *[
        f"≤ {num(goals[k].get('bound_ms'), 0)}: {verdict(goals[k].get('pass'))}"
        if k in goals else "" for k in ("median", "p99")], "", ""])
    m, mc = r["memory"], r["machine"]
    br = r.get("box_range")  # absent before the report said it: Config() alone
    config = (f"defaults with the site's box range {br[0]}–{br[1]} m (as the matrix "
              "bench)" if br else "the bare defaults")
    hot = r.get("compiled_while_timed")  # absent before the profile counted it
    if hot:
        config += f", {hot} numba compilation(s) timed"
    note = (f"{r['scans']} scans of `{r['suite']}_suite({r['n']}, {r['seed']})` at "
            f"{r['size']}, {config}; one process and thread, after a warm-up; stages "
            f"from `Result.timing_ms`. Peak RSS {num(m.get('process_max_rss_mb'), 0)} "
            f"MB. {mc.get('cpu_count')} cores shared with other jobs (load average "
            f"{num(mc.get('load_average_1min_before'), 1)} before, "
            f"{num(mc.get('load_average_1min_after'), 1)} after): times vary 10–20 % "
            "between runs, the slowest scans' more.")
    return (table(["stage", "median (ms)", "p99 (ms)", "max (ms)", "share of median total"],
                  rows) + "\n\n" + note)


# --- footprint (bench_footprint.json, boxloc bench --section recording) ------------------------


def _goal(sec: dict[str, Any], metric: str, percent: bool = False) -> tuple[str, str]:
    """The bound and verdict of the section's target on ``metric``, or two empty cells.

    The recording section names a target by its condition (``"mcap_fraction <= 0.05"``,
    ``"run --workers 2 >= 1.8x scans/s of --workers 1"``): the bound is what follows the
    metric, its operator as a sign, a fraction as a percentage when ``percent``.
    """
    signs = {"<=": "≤", ">=": "≥", "==": "="}
    for key, ok in (sec.get("targets") or {}).items():
        m = re.fullmatch(re.escape(metric) + r"\s*(<=|>=|==)\s*(\S+)(.*)", key)
        if m is None:
            continue
        op, value, rest = m.groups()
        if op == "==":
            return "equal", verdict(ok)
        if percent:
            try:
                value = f"{100 * float(value):g} %"
            except ValueError:
                pass
        value = re.sub(r"^(\d+(?:\.\d+)?)x$", r"\1×", value)
        return f"{signs[op]} {value}{rest}", verdict(ok)
    return "", ""


def _pct(v: Any) -> str:
    return "–" if v is None else f"{100 * v:.1f} %"


def footprint_summary(r: dict[str, Any], speed: dict[str, Any] | None = None) -> str:
    sec = r["sections"]["recording"]
    tp = sec.get("throughput") or {}
    runs = {int(x["workers"]): x for x in tp.get("runs", [])}
    mx = sec.get("matrix") or {}
    rows = []
    if mx:
        sensors = ", ".join(f"{k} {num(v / 1e6, 2)}" for k, v in mx["by_sensor"].items())
        rows.append([f"MCAP log per 640×480 scan, sensor × scene matrix ({mx['scans']} "
                     "scans, file / scans)",
                     f"{num(mx['bytes_per_scan'] / 1e6, 3)} MB (a scan: median "
                     f"{num(mx['median_scan_bytes'] / 1e6, 2)}, largest "
                     f"{num(mx['max_scan_bytes'] / 1e6, 2)}; by sensor {sensors})",
                     *_goal(sec, "matrix_bytes_per_scan")])
    rows += [["MCAP log per 640×480 scan, scene suite (file / scans)",
              f"{num(sec.get('mcap_bytes_per_scan', 0) / 1e6, 2)} MB (largest scan "
              f"{num(sec.get('mcap_max_scan_bytes', 0) / 1e6, 2)} MB)",
              *_goal(sec, "mcap_bytes_per_scan")],
             ["MCAP: time in the recorder / pipeline",
              f"{_pct(sec.get('mcap_fraction'))} (end to end "
              f"{_pct(sec.get('mcap_end_to_end_fraction'))})",
              *_goal(sec, "mcap_fraction", True)],
             ["Rerun: the sink's work / pipeline",
              f"{_pct(sec.get('rerun_fraction'))} (end to end "
              f"{_pct(sec.get('rerun_end_to_end_fraction'))})",
              *_goal(sec, "rerun_fraction", True)],
             ["Rerun .rrd per scan", f"{num(sec.get('rrd_bytes_per_scan', 0) / 1e6, 2)} MB",
              "", ""]]
    if runs:
        shares = " / ".join(num(runs[w].get("core_share"), 2) for w in sorted(runs))
        rounds = len(tp.get("rounds") or [None])

        def fig(key: str) -> str:  # the median, and the rounds' smallest and largest
            r = tp.get(key + "_range")
            rng = f" ({_times(r[0])}–{_times(r[1])})" if rounds > 1 and r else ""
            return _times(tp.get(key)) + rng

        text = (f"median of {rounds} rounds: {fig('speedup')}, steady "
                f"{fig('steady_speedup')}; core shares {shares}" if rounds > 1 else
                f"{fig('speedup')} (steady {fig('steady_speedup')}; core shares {shares})")
        rows.append([f"`run --workers 2` / `--workers 1`, scans/s ({tp.get('scans')} scans)",
                     text, *_goal(sec, "run --workers 2")])
        rows.append(["`--workers 2` log = `--workers 1` log", num(tp.get("same_log")),
                     *_goal(sec, "run --workers 2 log")])
    if speed is not None:
        p = speed.get("provenance", {})
        rows.append([f"peak RSS, one process at {speed.get('size')}",
                     f"{num(speed['memory'].get('process_max_rss_mb'), 0)} MB (speed run, "
                     f"{p.get('commit', 'unknown')})", "", ""])
    load = tp.get("load_average_1min")
    matrix = (f"The matrix: its first {mx['scans']} scenes (seed {mx['seed']}) at 640×480, "
              "its configuration, every product recorded; the rest: the " if mx else "The ")
    note = (f"{matrix}first {sec.get('scans')} scans of `scene_suite({r['n']}, {r['seed']})` "
            "(640×480). A time share is the sink's own work over the pipeline's time (end to "
            "end is noisier). Throughput: `boxloc run DIR --record LOG` on "
            f"{tp.get('cpu_count')} cores (load average {num(load, 1)}); a core share below 1 "
            "means other work took the rest.")
    return table(["figure", "measured", "target (issue 22)", ""], rows) + "\n\n" + note


def footprint_channels(r: dict[str, Any], **_uses: Any) -> str:
    # every table of the kind is given the reports it uses (Kind.uses); this one reads none
    sec = r["sections"]["recording"]
    mx = sec.get("matrix") or {}
    ch = mx.get("kb_per_scan_by_channel") or sec.get("mcap_kb_per_scan_by_channel") or {}
    total = sum(float(v) for v in ch.values()) or 1.0
    rows = [[f"`{t}`", num(float(v), 1), f"{100 * float(v) / total:.1f} %"]
            for t, v in sorted(ch.items(), key=lambda kv: -float(kv[1]))]
    what = (f"The matrix's first {mx['scans']} scenes at 640×480 (seed {mx['seed']}). "
            if mx else "")
    return (table(["channel", "kB per scan (zstd, alone)", "share"], rows)
            + f"\n\n{what}Each channel's messages of a scan compressed alone at the "
            "recorder's level; "
            "the log compresses a scan's channels together, so they add up to about its "
            "size, not exactly.")



RENDERERS: dict[str, dict[str, Callable[..., str]]] = {
    "matrix": {"summary": matrix_summary, "targets": matrix_targets, "kinds": matrix_kinds,
               "cells": matrix_cells, "stages": matrix_stages,
               "normals": matrix_normals, "false": matrix_false},
    "real": {"summary": real_summary, "targets": real_targets, "draws": real_draws,
             "inputs": real_inputs, "stages": real_stages},
    "sim": {"summary": sim_summary, "kinds": sim_kinds, "draws": sim_draws,
            "stages": sim_stages},
    "packed": {"summary": packed_summary, "targets": packed_targets},
    "bare": {"summary": bare_summary, "targets": bare_targets, "tests": bare_tests},
    "speed": {"summary": speed_summary},
    "footprint": {"summary": footprint_summary, "channels": footprint_channels},
}


# --- the log's channel table -------------------------------------------------------------------


def channels_table() -> str:
    """The MCAP channels, from :data:`recorder.mcap.channels.CHANNELS` (the source of truth)."""
    from recorder.mcap import encode
    from recorder.mcap.channels import CHANNELS

    rows = [[f"`{c.topic}`", f"`{c.schema_name}`" + (
        f" (`{c.record_schema}`)" if c.record else ""), c.message_encoding,
             f"{c.role.value}, {c.scope.value}", c.content] for c in CHANNELS]
    return (table(["topic", "MCAP schema (record)", "encoding", "role, scope", "content"], rows)
            + f"\n\nRecord schema version {encode.SCHEMA_VERSION}.")


# --- regions -----------------------------------------------------------------------------------


class Reports:
    """The committed reports under docs/results, loaded and checked once."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self._cache: dict[str, dict[str, Any] | None] = {}

    def get(self, kind: Kind) -> dict[str, Any] | None:
        if kind.name not in self._cache:
            path = self.root / RESULTS_DIR / kind.file
            rep = None
            if path.is_file():
                rep = load_json(path)
                check_report(rep, kind, str(path.relative_to(self.root)))
            self._cache[kind.name] = rep
        return self._cache[kind.name]


def render_region(family: str, name: str, reports: Reports, doc: Path) -> str:
    """The generated text of one region of ``doc``."""
    if family == "log":
        if name != "channels":
            raise ToolError(f"{doc}: unknown region log:{name}")
        return channels_table()
    kind_name, _, table_name = name.partition(":")
    kind = KINDS.get(kind_name)
    fn = RENDERERS.get(kind_name, {}).get(table_name)
    if kind is None or fn is None:
        raise ToolError(f"{doc}: unknown region bench:{name} (known: " + ", ".join(
            f"bench:{k}:{t}" for k, ts in RENDERERS.items() for t in ts) + ")")
    rep = reports.get(kind)
    path = reports.root / RESULTS_DIR / kind.file
    link = os.path.relpath(path, doc.parent).replace(os.sep, "/")
    if rep is None:
        return (f"*No report yet. Run `{kind.make}`, then `python scripts/bench_tables.py "
                f"--{kind.name} DIR/{kind.source or kind.file}` (it writes "
                f"`{RESULTS_DIR.as_posix()}/{kind.file}` and this table).*")
    try:
        body = fn(rep, **{k: reports.get(KINDS[k]) for k in kind.uses})
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise ToolError(f"{path.relative_to(reports.root)}: cannot make bench:{name} "
                        f"({type(e).__name__}: {e})") from None
    return stamp(rep, kind, link) + "\n\n" + body


def rewrite(text: str, reports: Reports, doc: Path) -> str:
    """``text`` with every region regenerated."""
    closed = {m.start() for m in REGION.finditer(text)}
    for m in OPEN.finditer(text):
        if m.start() not in closed:
            raise ToolError(f"{doc}: region {m.group(1)}:{m.group(2)} is not closed by "
                            f"<!-- /{m.group(1)} --> on a line of its own")

    def sub(m: re.Match[str]) -> str:
        body = render_region(m.group(1), m.group(2), reports, doc)
        return f"<!-- {m.group(1)}:{m.group(2)} -->\n{body}\n<!-- /{m.group(1)} -->"

    return REGION.sub(sub, text)


def documents(root: Path) -> list[Path]:
    docs = [root / f for f in TOP_FILES if (root / f).is_file()]
    return docs + sorted((root / "docs").glob("*.md"))


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        """A bad option: one line and exit status 2, not the usage block."""
        print(f"bench_tables: {message} (see --help)", file=sys.stderr)
        raise SystemExit(2)


def main(argv: Sequence[str] | None = None) -> int:
    ap = _Parser(description=__doc__.split("\n\n")[0])
    for k in KINDS.values():
        ap.add_argument(f"--{k.name}", type=Path, metavar="FILE",
                        help=f"a {k.file} to check, trim and copy to docs/results")
    ap.add_argument("--date", help="when the report's run ended (default: the file's time)")
    ap.add_argument("--commit", help="the commit it ran (default: inferred from the time)")
    ap.add_argument("--command", help="the command that made it (default: reconstructed)")
    ap.add_argument("--check", action="store_true",
                    help="write nothing; exit 1 if a file is not what it would be")
    ap.add_argument("--root", type=Path, default=ROOT, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    root: Path = args.root.resolve()
    given = [(KINDS[k], getattr(args, k)) for k in KINDS if getattr(args, k) is not None]
    try:
        if args.check and given:
            raise ToolError("--check compares the docs with docs/results; ingest separately")
        if args.command and len(given) > 1:
            raise ToolError("--command names one report's command: give one report with it")
        if not given and (args.date or args.commit or args.command):
            raise ToolError("--date, --commit and --command stamp a report given with "
                            + ", ".join(f"--{k}" for k in KINDS))
        for kind, path in given:
            out = ingest(path, kind, root, date=args.date, commit=args.commit,
                         command=args.command)
            print(f"wrote {out.relative_to(root)} ({out.stat().st_size // 1024} kB)")
        reports = Reports(root)
        stale = []
        for doc in documents(root):
            text = doc.read_text()
            new = rewrite(text, reports, doc)
            if new != text:
                stale.append(doc.relative_to(root))
                if not args.check:
                    doc.write_text(new)
    except ToolError as e:
        print(f"bench_tables: {e}", file=sys.stderr)
        return 2
    if args.check:
        if stale:
            print("bench_tables: out of date (run python scripts/bench_tables.py): "
                  + ", ".join(map(str, stale)), file=sys.stderr)
            return 1
        return 0
    for p in stale:
        print(f"rewrote {p}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))  # recorder and boxloc from this checkout
    sys.exit(main())

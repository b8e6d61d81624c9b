"""Command-line verbs of the recorder, plugged into ``boxloc`` (entry-point group
``boxloc.commands``): ``run``, ``info``, ``annotate`` and ``recover``.

Every verb is a thin layer over a library function; errors are :class:`BoxlocError` with a
one-line message, which the ``boxloc`` group prints before exiting with code 2.
"""

from __future__ import annotations

import dataclasses
import json
import signal
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import click

from boxloc.cli import config_options, load_config, scan_options
from boxloc.errors import BoxlocError, InputError

# --- --rerun MODE [TARGET] -----------------------------------------------------------------


RERUN_MODES = ("spawn", "connect", "save", "serve", "none")


class _RerunOption(click.Option):
    """``--rerun MODE``, where ``connect`` and ``save`` may take their target as the next
    word (``--rerun connect URL``, ``--rerun save FILE.rrd``), as well as ``connect:URL``
    or ``save=FILE``."""

    def add_to_parser(self, parser: Any, ctx: click.Context) -> None:
        super().add_to_parser(parser, ctx)
        for name in self.opts:
            popt = getattr(parser, "_long_opt", {}).get(name)
            if popt is None:
                continue
            orig = popt.process

            def process(value: Any, state: Any, orig: Any = orig) -> None:
                rargs = getattr(state, "rargs", None)
                if value in ("connect", "save") and rargs and _is_target(value, rargs[0]):
                    value = f"{value} {rargs.pop(0)}"
                orig(value, state)

            popt.process = process


def _is_target(mode: str, word: str) -> bool:
    """Whether the word after ``--rerun connect|save`` is its target (not SOURCE)."""
    if word.startswith("-"):
        return False
    if mode == "save":
        return word.endswith(".rrd")
    return "://" in word or word.startswith(("rerun+", "localhost", "127.", "[")) or (
        ":" in word and word.rsplit(":", 1)[-1].split("/")[0].isdigit())


def normalize_rerun(value: str) -> str:
    """``"save out.rrd"``, ``"save=out.rrd"``, ``"save:out.rrd"`` -> ``"save out.rrd"``.

    Several targets joined by commas (``save:a.rrd,spawn``) are passed on as they are; the
    Rerun sink checks them.
    """
    v = value.strip()
    if "," in v:
        return v
    for sep in (" ", "=", ":"):
        mode, s, rest = v.partition(sep)
        if s and mode in RERUN_MODES:
            return f"{mode} {rest.strip()}".strip()
    if v not in RERUN_MODES:
        raise InputError(f"--rerun must be one of spawn, connect [URL], save FILE.rrd, serve, "
                         f"none; got {value!r}")
    if v == "save":
        raise InputError("--rerun save needs a file: --rerun save FILE.rrd")
    return v


# --- sources -------------------------------------------------------------------------------


@dataclasses.dataclass
class Source:
    """The scans of a SOURCE, with their count when known and the log's config (for logs)."""

    scans: Iterator[Any]
    total: int | None
    log_config: Any = None
    kind: str = "file"


def rosbag_options(f: Any) -> Any:
    """``--depth-topic``, ``--info-topic``, ``--base-frame``: which frames of a ROS 2 bag."""
    f = click.option("--base-frame", default=None, metavar="FRAME",
                     help="ROS 2 bag: the frame of the sensor pose from /tf, /tf_static "
                          "(default: the root of the camera frame's tree).")(f)
    f = click.option("--info-topic", default=None, metavar="TOPIC",
                     help="ROS 2 bag: the CameraInfo topic (default: beside the depth topic).")(f)
    f = click.option("--depth-topic", default=None, metavar="TOPIC",
                     help="ROS 2 bag: the depth Image or organized PointCloud2 topic (needed "
                          "when the bag has several).")(f)
    return f


def open_source(source: str, *, count: int, seed: int | None, intrinsics: str | None,
                depth_scale: float | None, max_pixels: int, depth_topic: str | None = None,
                info_topic: str | None = None, base_frame: str | None = None) -> Source:
    """Turn SOURCE into scans: ``sim:KIND[:k=v,...]``, a scan file or directory, a ROS 2
    bag (:func:`boxloc.io.rosbag.open_bag`, opened and checked here), or a log."""
    if source.startswith("sim:"):
        from boxloc.simulate import parse_spec, simulate

        spec = parse_spec(source[4:])
        first = spec.seed if seed is None else seed

        def sims() -> Iterator[Any]:
            for i in range(count):
                scan = simulate(spec, seed=first + i).scan
                yield dataclasses.replace(scan, index=i)

        return Source(sims(), count, kind="sim")
    p = Path(source)
    from boxloc.io.rosbag import is_rosbag

    if is_rosbag(p):
        from boxloc.io.rosbag import open_bag

        bag = open_bag(p, depth_topic=depth_topic, info_topic=info_topic,
                       base_frame=base_frame, intrinsics=intrinsics, depth_scale=depth_scale,
                       max_pixels=max_pixels)
        return Source(iter(bag), bag.count, kind="rosbag")
    if p.suffix.lower() == ".mcap":
        from recorder.mcap.log import open_log

        log = open_log(p)
        total = None
        if log.summary is not None and log.summary.statistics is not None:
            from recorder.mcap import channels as C
            ids = [cid for cid, ch in log.summary.channels.items() if ch.topic == C.SCAN_INFO]
            total = sum(log.summary.statistics.channel_message_counts.get(i, 0) for i in ids)
        return Source((r.scan for r in log.scans()), total, log.config, kind="log")
    from boxloc.io import SUPPORTED_SUFFIXES, read_scans

    total = None
    if p.is_dir():
        total = sum(1 for f in p.iterdir() if f.is_file() and f.suffix.lower()
                    in SUPPORTED_SUFFIXES)
    return Source(read_scans(p, intrinsics=intrinsics, depth_scale=depth_scale,
                             max_pixels=max_pixels), total, kind="file")


@contextmanager
def _stop_requests() -> Iterator[list[int]]:
    """SIGINT and SIGTERM ask the run to stop after the scan in progress.

    The first signal only sets a flag (the yielded list gets the signal number), so the
    pipeline is never interrupted inside a stage (a KeyboardInterrupt raised inside a numba
    kernel surfaces as a SystemError); the loop stops at the next scan boundary and the log
    is finished cleanly. A second signal interrupts at once.
    """
    requested: list[int] = []

    def handler(signum: int, frame: Any) -> None:
        if requested:
            raise KeyboardInterrupt
        requested.append(signum)

    old: dict[int, Any] = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            old[sig] = signal.signal(sig, handler)
        except (ValueError, OSError):  # not the main thread
            pass
    try:
        yield requested
    finally:
        for signum, h in old.items():
            signal.signal(signum, h)


def _progress(enabled: bool, total: int | None) -> Any:
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
    )

    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TimeElapsedColumn(), console=Console(stderr=True), disable=not enabled,
                    transient=False)


@click.command("run")
@click.argument("source")
@click.option("--count", type=click.IntRange(min=1), default=1, show_default=True,
              help="Number of simulated scans (sim: sources; seeds SEED, SEED+1, ...).")
@click.option("--seed", type=int, default=None, help="First simulator seed (default: the spec's).")
@click.option("--record", "record", type=click.Path(), default=None,
              metavar="DIR|FILE.mcap", help="Record everything to MCAP: a file, or a directory "
              "that receives one file per session (rotated parts numbered).")
@click.option("--rerun", "rerun", cls=_RerunOption, default="none", show_default=True,
              metavar="spawn|connect URL|save FILE.rrd|serve|none",
              help="Also show or save the run in Rerun.")
@click.option("--rotate-size", type=click.FloatRange(min=0.001), default=None, metavar="MB",
              help="Start a new MCAP file when the current one reaches MB megabytes.")
@click.option("--rotate-duration", type=click.FloatRange(min=0.001), default=None,
              metavar="SECONDS", help="Start a new MCAP file after SECONDS of log time.")
@click.option("--force", is_flag=True,
              help="Overwrite an existing --record FILE (and --publish-ros2 file).")
@click.option("--workers", type=int, default=None, help="Processes for per-vertex work.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar or per-scan lines.")
@click.option("--publish-ros2", "publish_ros2", type=click.Path(dir_okay=False), default=None,
              metavar="OUT.mcap", help="Also write the surfaces as a ROS 2 bag: PoseArray "
              "/boxloc/grasp_poses and MarkerArray /boxloc/surfaces, on each scan's stamp "
              "and frame.")
@rosbag_options
@scan_options
@config_options
def run(source: str, count: int, seed: int | None, record: str | None, rerun: str,
        rotate_size: float | None, rotate_duration: float | None, force: bool,
        workers: int | None, quiet: bool, publish_ros2: str | None, depth_topic: str | None,
        info_topic: str | None, base_frame: str | None, intrinsics: str | None,
        depth_scale: float | None, config_path: str | None,
        overrides: tuple[str, ...]) -> None:
    """Run the localizer on SOURCE, recording every scan and product.

    SOURCE is a simulator spec (sim:KIND[:key=value,...], with --count), a scan file, a
    directory of scans, a ROS 2 bag (a rosbag2 directory, .mcap or .db3; --depth-topic,
    --info-topic, --base-frame), or an MCAP log (its scans are re-run; with the log's config
    unless --config is given). Ctrl-C (or SIGTERM) stops after closing the log cleanly.
    """
    from boxloc.observer import FanOut
    from boxloc.pipeline import find_graspable_surfaces
    from boxloc.stages.scan_noise import fit_warning
    from recorder.mcap.sink import McapRecorder, RecordingError

    rerun_target = normalize_rerun(rerun)
    cfg = load_config(config_path, overrides, workers=workers)
    src = open_source(source, count=count, seed=seed, intrinsics=intrinsics,
                      depth_scale=depth_scale, max_pixels=cfg.max_pixels,
                      depth_topic=depth_topic, info_topic=info_topic, base_frame=base_frame)
    if src.log_config is not None and config_path is None:
        cfg = src.log_config.with_overrides(list(overrides)) if overrides else src.log_config
        if workers is not None:
            cfg = cfg.with_overrides({"workers": workers})
    n_ok = n_failed = n_surfaces = 0
    rec: McapRecorder | None = None
    t_start = time.perf_counter()
    with ExitStack() as stack:
        session = f"boxloc-{datetime.now(UTC).strftime('%Y%m%dT%H%M%SZ')}"
        if record:
            rec = stack.enter_context(McapRecorder(
                record, config=cfg, overwrite=force,
                rotate_bytes=None if rotate_size is None else int(rotate_size * 1e6),
                rotate_seconds=rotate_duration))
            session = rec.session
        observers: list[Any] = [rec] if rec is not None else []
        if publish_ros2:
            from recorder.mcap.ros2_publish import Ros2Publisher

            pub = Ros2Publisher(publish_ros2, overwrite=force)
            stack.callback(pub.close)
            observers.append(pub)
        if rerun_target != "none":
            try:
                from recorder.rerun.sink import open_rerun_sink
            except ImportError as e:
                raise InputError(f"--rerun {rerun_target}: Rerun output is unavailable ({e})"
                                 ) from None
            sink = open_rerun_sink(rerun_target, recording_id=session, app_id="boxloc")
            if sink is not None:
                stack.callback(sink.close)
                observers.append(sink)
        obs = FanOut(*observers)
        stop = stack.enter_context(_stop_requests())
        show = not quiet and (src.total is None or src.total > 1)
        progress = stack.enter_context(_progress(show, src.total))
        task = progress.add_task("scans", total=src.total)
        try:
            for scan in src.scans:
                t0 = time.perf_counter()
                try:
                    result = find_graspable_surfaces(scan, cfg, observer=obs)
                except (RecordingError, KeyboardInterrupt):
                    raise
                except Exception as e:  # the scan's failure is its result: record, go on
                    n_failed += 1
                    if rec is not None:
                        rec.on_error(scan, e)
                    msg = str(e).splitlines()[0] if str(e) else ""
                    progress.console.print(f"scan {scan.index}: failed: "
                                           f"{type(e).__name__}: {msg}", markup=False)
                else:
                    n_ok += 1
                    n_surfaces += len(result.surfaces)
                    if result.noise is not None and (w := fit_warning(result.noise)):
                        progress.console.print(f"scan {scan.index}: warning: {w}", markup=False)
                    if not quiet and not show:
                        progress.console.print(
                            f"scan {scan.index}: {len(result.surfaces)} surface(s) in "
                            f"{time.perf_counter() - t0:.1f} s")
                progress.advance(task)
                if stop:
                    raise KeyboardInterrupt
        except KeyboardInterrupt:
            progress.console.print("interrupted: closing the log")
            raise
        finally:
            stack.close()
            _report(rec, n_ok, n_failed, n_surfaces, time.perf_counter() - t_start, quiet)


def _report(rec: Any, n_ok: int, n_failed: int, n_surfaces: int, seconds: float,
            quiet: bool) -> None:
    if quiet and rec is None:
        return
    line = f"{n_ok + n_failed} scan(s), {n_surfaces} surface(s)"
    if n_failed:
        line += f", {n_failed} failed"
    line += f" in {seconds:.1f} s"
    if rec is not None:
        paths = ", ".join(str(p) for p in rec.paths) or "(nothing recorded)"
        line += f"; log: {paths}"
    click.echo(line, err=True)


# --- info ----------------------------------------------------------------------------------


def _utc(ns: int) -> str:
    return datetime.fromtimestamp(ns / 1e9, UTC).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3] + " UTC"


def _sensor_json(text: str | None) -> Any:
    """The recorded sensor description, or its text when it is not JSON (informational)."""
    from recorder.mcap.encode import parse_json

    if not text:
        return None
    try:
        return parse_json(text, "the recorded sensor")
    except BoxlocError:
        return text[:200]


def log_info(path: str | Path) -> dict[str, Any]:
    """Everything ``boxloc info`` shows, as plain data."""
    from recorder.mcap.log import open_log

    log = open_log(path, allow_truncated=True)
    run = log.run
    scans = log.index()
    span = log.time_span()
    outcomes = log.outcomes()
    latest = log.latest_outcomes()
    n_scans = len(scans)
    info: dict[str, Any] = {
        "path": str(log.path),
        "size_bytes": log.size,
        "bytes_per_scan": round(log.size / n_scans) if n_scans else None,
        "complete": log.complete,
        "truncated": log.truncated,
        "damage": log.damage,
        "library": log.header.library,
        "versions": {k: run.get(k, "") for k in (
            "boxloc_version", "git_commit", "git_dirty", "layout_version", "schema_version",
            "python", "numpy", "mcap", "protobuf")},
        "config_hash": run.get("config_hash", ""),
        "host": run.get("host", ""),
        "session": run.get("session", ""),
        "part": run.get("part", ""),
        "created_utc": run.get("created_utc", ""),
        "sensor": _sensor_json(run.get("sensor")),
        "recovered": log.metadata.get("boxloc.recovery"),
        "time_span": None if span is None else {
            "start_ns": span[0], "end_ns": span[1], "duration_s": (span[1] - span[0]) / 1e9,
            "start": _utc(span[0]), "end": _utc(span[1])},
        "scans": {
            "count": n_scans,
            "failed": sum(1 for s in scans if s.error),
            "surfaces": sum(s.n_surfaces for s in scans),
            "items": [{"index": s.index, "log_time_ns": s.log_time_ns,
                       "surfaces": s.n_surfaces, "error": s.error} for s in scans],
        },
        "channels": [{"topic": c.topic, "schema": c.schema_name, "encoding":
                      c.message_encoding, "record": c.record, "messages": c.message_count}
                     for c in log.channels()],
        "attachments": [{"name": a.name, "media_type": a.media_type, "size": a.size}
                        for a in log.attachments()],
        "outcomes": {
            "reports": len(outcomes),
            "ok": sum(1 for o in latest.values() if o.ok),
            "failed": sum(1 for o in latest.values() if not o.ok),
            "latest": [o.to_json() for _, o in sorted(latest.items())],
        },
    }
    return info


def _escaped(x: Any) -> Any:
    """Every string of ``x`` with Rich markup escaped: a log's names and metadata are data,
    never markup (``[/]`` would raise, ``[link=...]`` would make a link)."""
    from rich.markup import escape

    if isinstance(x, str):
        return escape(x)
    if isinstance(x, dict):
        return {k: _escaped(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_escaped(v) for v in x]
    return x


def _print_info(info: dict[str, Any]) -> None:
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    sensor = escape(json.dumps(info["sensor"])) if info["sensor"] else ""
    info = _escaped(info)
    con = Console()
    v = info["versions"]
    state = "complete" if info["complete"] else "TRUNCATED (no summary): `boxloc recover` it"
    con.print(f"[bold]{info['path']}[/]  {info['size_bytes'] / 1e6:.2f} MB, {state}")
    if info["damage"]:
        con.print(f"  damage: {'; '.join(info['damage'][:3])}")
    dirty = {"true": " (dirty)", "false": ""}.get(v["git_dirty"], f" (dirty: {v['git_dirty']})")
    con.print(f"  boxloc {v['boxloc_version']}, git {v['git_commit'][:12]}{dirty}, "
              f"layout {v['layout_version']}, schemas {v['schema_version']}; "
              f"config {info['config_hash']}")
    con.print(f"  recorded on {info['host']} at {info['created_utc']} "
              f"(session {info['session']}, part {info['part']}); {info['library']}")
    if sensor:
        con.print(f"  sensor: {sensor}")
    if info["recovered"]:
        r = info["recovered"]
        con.print(f"  recovered from {r.get('source')}: {r.get('scans')} scan(s) kept, "
                  f"{r.get('dropped_scans')} dropped")
    sp = info["time_span"]
    if sp:
        con.print(f"  time: {sp['start']} .. {sp['end']} ({sp['duration_s']:.3f} s)")
    sc = info["scans"]
    per = info["bytes_per_scan"]
    con.print(f"  scans: {sc['count']} ({sc['failed']} failed), {sc['surfaces']} surface(s)"
              + (f", {per / 1e6:.2f} MB per scan" if per else ""))
    t = Table(title="scans", title_justify="left")
    for col in ("scan", "log time", "surfaces", "picks", "error"):
        t.add_column(col)
    picks: dict[int, list[str]] = {}
    for o in info["outcomes"]["latest"]:
        picks.setdefault(o["scan_index"], []).append(
            f"#{o['surface_id']} {'ok' if o['ok'] else 'failed'}")
    items = sc["items"]
    shown = items if len(items) <= 40 else items[:20] + items[-20:]
    for s in shown:
        t.add_row(str(s["index"]), _utc(s["log_time_ns"]), str(s["surfaces"]),
                  ", ".join(picks.get(s["index"], [])), s["error"] or "")
    if len(items) > 40:
        t.caption = f"{len(items) - 40} scan(s) not shown (use --json)"
    con.print(t)
    t = Table(title="channels", title_justify="left")
    for col in ("topic", "schema (record)", "messages"):
        t.add_column(col)
    for c in info["channels"]:
        schema = c["schema"] if c["record"] in ("", c["schema"]) else c["record"]
        t.add_row(c["topic"], f"{schema} ({c['encoding']})", str(c["messages"]))
    con.print(t)
    if info["attachments"]:
        con.print("  attachments: " + ", ".join(f"{a['name']} ({a['size']} B)"
                                                for a in info["attachments"]))
    oc = info["outcomes"]
    con.print(f"  pick outcomes: {oc['reports']} report(s); latest per surface: "
              f"{oc['ok']} ok, {oc['failed']} failed")
    if oc["latest"]:
        t = Table(title="pick outcomes (latest per surface)", title_justify="left")
        for col in ("scan", "surface", "pick", "reason", "source", "from"):
            t.add_column(col)
        for o in oc["latest"]:
            t.add_row(str(o["scan_index"]), str(o["surface_id"]), "ok" if o["ok"] else "failed",
                      o["reason"], o["source"], o["origin"])
        con.print(t)


@click.command("info")
@click.argument("log_path", metavar="LOG.mcap", type=click.Path(dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of tables.")
def info(log_path: str, as_json: bool) -> None:
    """Show a log's scans, channels, versions, time span, size and pick outcomes."""
    data = log_info(log_path)
    if as_json:
        click.echo(json.dumps(data, indent=2))
    else:
        _print_info(data)


# --- annotate ------------------------------------------------------------------------------


@click.command("annotate")
@click.argument("log_path", metavar="LOG.mcap", type=click.Path(dir_okay=False))
@click.option("--scan", "scan_index", type=click.IntRange(min=0), required=True,
              help="Scan index.")
@click.option("--surface", "surface_id", type=click.IntRange(min=0), required=True,
              help="Surface id within the scan (its row; 0 = first picked).")
@click.option("--pick", type=click.Choice(["ok", "failed"]), required=True,
              help="Whether the pick succeeded.")
@click.option("--reason", default="", help="Why (free text).")
def annotate(log_path: str, scan_index: int, surface_id: int, pick: str, reason: str) -> None:
    """Record a pick outcome for a surface of a log (in its sidecar; the log is untouched)."""
    from recorder.annotate import append_outcome, sidecar_path

    o = append_outcome(log_path, scan_index, surface_id, pick == "ok", reason)
    click.echo(f"scan {o.scan_index} surface {o.surface_id}: {pick}"
               + (f" ({reason})" if reason else "") + f" -> {sidecar_path(log_path)}")


# --- recover -------------------------------------------------------------------------------


@click.command("recover")
@click.argument("log_path", metavar="LOG.mcap", type=click.Path(dir_okay=False))
@click.option("--output", "-o", type=click.Path(dir_okay=False), default=None,
              help="The new log (default: LOG.recovered.mcap).")
@click.option("--force", is_flag=True, help="Overwrite the output if it exists.")
def recover(log_path: str, output: str | None, force: bool) -> None:
    """Rebuild a complete log from a truncated or damaged one, into a new file.

    Every scan that was flushed (every complete scan) is kept; the input is never modified.
    """
    from recorder.mcap.recover import recover_log

    report = recover_log(log_path, output, overwrite=force)
    click.echo(report.summary())
    if report.scans == 0 and not report.source_complete:
        click.echo("warning: no complete scan could be recovered", err=True)

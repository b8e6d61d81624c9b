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
from contextlib import ExitStack, closing, contextmanager
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
    """The scans of a SOURCE, with their count when known and the log's config (for logs).

    ``scans`` yields :class:`~boxloc.scan.Scan` objects and, in their place, a
    :class:`ReadError` for an input of the source that could not be read (a bad file of a
    directory, the damage that ends a bag or a log); nothing after an error is lost.
    """

    scans: Iterator[Any]
    total: int | None
    log_config: Any = None
    kind: str = "file"


@dataclasses.dataclass(frozen=True)
class ReadError:
    """An input that could not be read, in its place among the scans.

    ``last``: nothing follows it, so it is the run's final error rather than a warning.
    """

    message: str
    last: bool = False


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


def _guarded(scans: Iterator[Any]) -> Iterator[Any]:
    """The scans, then the error that ended them (a damaged bag or log) as a ReadError."""
    try:
        yield from scans
    except BoxlocError as e:
        yield ReadError(str(e))


def _read_files(files: list[Path], **kw: Any) -> Iterator[Any]:
    """Each file's scan (``index`` = its place in ``files``), or its ReadError."""
    from boxloc.io import read_scan

    for i, f in enumerate(files):
        try:
            yield read_scan(f, index=i, **kw)
        except BoxlocError as e:
            yield ReadError(str(e))


def open_source(source: str, *, count: int, seed: int | None, intrinsics: str | None,
                depth_scale: float | None, max_pixels: int, depth_topic: str | None = None,
                info_topic: str | None = None, base_frame: str | None = None) -> Source:
    """Turn SOURCE into scans: ``sim:KIND[:k=v,...]``, a scan file or directory, a ROS 2
    bag (:func:`boxloc.io.rosbag.open_bag`, opened and checked here), or a log.

    A source that does not exist or cannot be opened raises :class:`InputError` here, before
    any scan is run; what goes wrong while reading comes as :class:`ReadError` items.
    """
    if source.startswith("sim:"):
        from boxloc.simulate import parse_spec
        from recorder.stream import SimScan

        spec = parse_spec(source[4:])
        first = spec.seed if seed is None else seed
        # made where they run (the parent, or the worker of --workers N): Job.make_scan
        sims = (SimScan(spec, first + i, i) for i in range(count))
        return Source(sims, count, kind="sim")
    p = Path(source)
    if not p.exists():
        raise InputError(f"SOURCE not found: {p}")
    from boxloc.io.rosbag import is_rosbag

    if is_rosbag(p):
        from boxloc.io.rosbag import open_bag

        bag = open_bag(p, depth_topic=depth_topic, info_topic=info_topic,
                       base_frame=base_frame, intrinsics=intrinsics, depth_scale=depth_scale,
                       max_pixels=max_pixels)
        return Source(_guarded(iter(bag)), bag.count, kind="rosbag")
    if p.suffix.lower() == ".mcap":
        from recorder.mcap.log import open_log

        log = open_log(p)
        total = None
        if log.summary is not None and log.summary.statistics is not None:
            from recorder.mcap import channels as C
            ids = [cid for cid, ch in log.summary.channels.items() if ch.topic == C.SCAN_INFO]
            total = sum(log.summary.statistics.channel_message_counts.get(i, 0) for i in ids)
        return Source(_guarded(r.scan for r in log.scans()), total, log.config, kind="log")
    from boxloc.io import SUPPORTED_SUFFIXES

    files = [p]
    if p.is_dir():  # file by file, as boxloc.io.read_scans, so that one bad file is skipped
        files = sorted(f for f in p.iterdir()
                       if f.is_file() and f.suffix.lower() in SUPPORTED_SUFFIXES)
        if not files:
            raise InputError(f"no scan files ({', '.join(SUPPORTED_SUFFIXES)}) in "
                             f"directory {p}")
    return Source(_read_files(files, intrinsics=intrinsics, depth_scale=depth_scale,
                              max_pixels=max_pixels), len(files), kind="file")


def _box_sizes(path: str | None) -> tuple[Any, dict[str, tuple[str, bytes]] | None]:
    """``--box-sizes FILE``: the parsed carton list and the file as the log's attachment
    (``(None, None)`` without one). A bad file is a one-line InputError, before any work."""
    if path is None:
        return None, None
    from boxloc.io.box_sizes import read_box_sizes
    from recorder.mcap.sink import box_sizes_attachment

    return read_box_sizes(path), box_sizes_attachment(path)


def _source_config(src: Source, cfg: Any, config_path: str | None,
                   overrides: tuple[str, ...]) -> Any:
    """The config a source's scans run with: a log's own (with ``--set``) unless
    ``--config`` is given, else the command line's."""
    if src.log_config is not None and config_path is None:
        return src.log_config.with_overrides(list(overrides)) if overrides else src.log_config
    return cfg


def _stream(sources: list[Source], configs: list[Any], *, renumber: bool) -> Iterator[Any]:
    """Every source's scans in order, as :class:`recorder.stream.Job`, with ReadErrors in
    their place; the last item, when it is an error, is marked ``last``.

    With ``renumber`` (several sources) scans are numbered 0, 1, ... across all of them, as
    ``boxloc import`` numbers them, so that no two scans of the log share an index.
    """
    from recorder.stream import Job

    n = 0
    held: ReadError | None = None  # an error waits to see whether anything follows it
    for src, cfg in zip(sources, configs):
        for item in src.scans:
            if held is not None:
                yield held
                held = None
            if isinstance(item, ReadError):
                held = item
                continue
            scan = item
            if renumber and scan.index != n:
                scan = dataclasses.replace(scan, index=n)
            n += 1
            yield Job(scan, cfg)
    if held is not None:
        yield dataclasses.replace(held, last=True)


@contextmanager
def _stop_requests() -> Iterator[list[int]]:
    """SIGINT and SIGTERM ask the run to stop after the scans in progress.

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

    # soft_wrap: an error line names a file; wrapped at 80 columns it would be two lines
    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TimeElapsedColumn(), console=Console(stderr=True, soft_wrap=True),
                    disable=not enabled, transient=False)


@click.command("run")
@click.argument("sources", metavar="SOURCE...", nargs=-1, required=True)
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
@click.option("--workers", type=click.IntRange(min=0), default=1, show_default=True,
              help="Processes that run scans in parallel (0: one per CPU). The log is the "
                   "same as with 1, bit for bit, in scan order.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar or per-scan lines.")
@click.option("--publish-ros2", "publish_ros2", type=click.Path(dir_okay=False), default=None,
              metavar="OUT.mcap", help="Also write the surfaces as a ROS 2 bag: PoseArray "
              "/boxloc/grasp_poses and MarkerArray /boxloc/surfaces, on each scan's stamp "
              "and frame.")
@click.option("--box-sizes", "box_sizes", type=click.Path(dir_okay=False), default=None,
              metavar="FILE",
              help="The carton sizes the cell handles: a CSV with the header "
                   "width,length,height (metres; height may be empty). Part of the recorded "
                   "config, and attached to the log as box_sizes.csv.")
@rosbag_options
@scan_options
@config_options
def run(sources: tuple[str, ...], count: int, seed: int | None, record: str | None,
        rerun: str, rotate_size: float | None, rotate_duration: float | None, force: bool,
        workers: int, quiet: bool, publish_ros2: str | None, box_sizes: str | None,
        depth_topic: str | None,
        info_topic: str | None, base_frame: str | None, intrinsics: str | None,
        depth_scale: float | None, config_path: str | None,
        overrides: tuple[str, ...]) -> None:
    """Run the localizer on each SOURCE in turn, recording every scan and product.

    SOURCE is a simulator spec (sim:KIND[:key=value,...], with --count), a scan file, a
    directory of scans, a ROS 2 bag (a rosbag2 directory, .mcap or .db3; --depth-topic,
    --info-topic, --base-frame), or an MCAP log (its scans are re-run; with the log's config
    unless --config is given). Several SOURCEs are run in the order given (`boxloc run
    a.npz b.npz scans/`), their scans numbered 0, 1, ... across them. An input that cannot
    be read is reported and the run goes on; the exit code is then 2.

    --workers N runs N scans at a time in worker processes; the log keeps scan order and is
    the same, bit for bit, as with one. Ctrl-C (or SIGTERM) stops after the scans in
    progress, closing the log cleanly.
    """
    from recorder.stream import default_workers, ordered_runs, start_early

    n_workers = workers or default_workers()  # 0: one per CPU
    if n_workers > 1:
        # The workers' server imports the pipeline (a second) while this process reads the
        # config and opens the sources; unused if there turns out to be one scan.
        start_early()
    rerun_target = normalize_rerun(rerun)
    cfg = load_config(config_path, overrides)
    sizes, attachments = _box_sizes(box_sizes)
    if sizes is not None:
        cfg = dataclasses.replace(cfg, box_sizes=sizes)
    opened = [open_source(s, count=count, seed=seed, intrinsics=intrinsics,
                          depth_scale=depth_scale, max_pixels=cfg.max_pixels,
                          depth_topic=depth_topic, info_topic=info_topic,
                          base_frame=base_frame) for s in sources]
    configs = [_source_config(src, cfg, config_path, overrides) for src in opened]
    if sizes is not None:  # a log source's own config too: the file is the cell's list now
        configs = [dataclasses.replace(c, box_sizes=sizes) for c in configs]
    totals = [src.total for src in opened]
    total = None if None in totals else sum(t for t in totals if t is not None)
    if total is not None:  # no worker to start for fewer scans; one scan runs in here
        n_workers = max(1, min(n_workers, total))
    if n_workers == 1:
        from boxloc.pipeline import find_graspable_surfaces
        from boxloc.stages.scan_noise import fit_warning
    from boxloc.observer import FanOut
    from recorder.mcap.sink import McapRecorder, RecordingError
    from recorder.stream import Encoding

    items = _stream(opened, configs, renumber=len(opened) > 1)
    n_ok = n_failed = n_surfaces = 0
    errors: list[ReadError] = []
    rec: McapRecorder | None = None
    t_start = time.perf_counter()
    with ExitStack() as stack:
        session = f"boxloc-{datetime.now(UTC).strftime('%Y%m%dT%H%M%SZ')}"
        if record:
            rec = stack.enter_context(McapRecorder(
                record, config=configs[0], overwrite=force,
                rotate_bytes=None if rotate_size is None else int(rotate_size * 1e6),
                rotate_seconds=rotate_duration, attachments=attachments))
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
        # a scan the worker encoded goes to the recorder as bytes, its calls to the others
        others = FanOut(*observers[1:]) if rec is not None else obs
        write = rec.write_encoded if rec is not None else None
        stop = stack.enter_context(_stop_requests())
        show = not quiet and (total is None or total > 1)
        progress = stack.enter_context(_progress(show, total))
        task = progress.add_task("scans" if n_workers == 1 else f"scans ({n_workers} workers)",
                                 total=total)
        runs: Iterator[tuple[Any, Any]]
        if n_workers > 1:
            # closed first (LIFO) when the run ends early: the workers are stopped at once
            encoding = None if rec is None else Encoding(rec.max_points, rec.config)
            runs = stack.enter_context(closing(ordered_runs(items, n_workers,
                                                            stop=lambda: bool(stop),
                                                            encoding=encoding)))
        else:
            runs = ((item, None) for item in items)
        try:
            for item, done in runs:
                if isinstance(item, ReadError):
                    errors.append(item)
                    if not item.last:  # the final one is the run's error, after the log
                        progress.console.print(f"error: {item.message} (going on)",
                                               markup=False)
                    continue
                scan = _scan_of(item, done)
                if isinstance(scan, ReadError):  # a simulated scan that could not be made
                    errors.append(scan)
                    progress.console.print(f"error: {scan.message} (going on)", markup=False)
                    continue
                t0 = time.perf_counter()
                try:
                    if done is None:
                        result = find_graspable_surfaces(scan, item.config, observer=obs)
                    elif done.encoded:  # the worker encoded it: the recorder writes bytes
                        result = done.replay(scan, others, write=write)
                    else:  # run in a worker: the observers get its calls now, in order
                        result = done.replay(scan, obs)
                except (RecordingError, KeyboardInterrupt):
                    raise
                except Exception as e:  # the scan's failure is its result: record, go on
                    n_failed += 1
                    if rec is not None and not (done is not None and done.encoded):
                        rec.on_error(scan, e)  # (an encoded scan ends with its error)
                    msg = str(e).splitlines()[0] if str(e) else ""
                    progress.console.print(f"scan {scan.index}: failed: "
                                           f"{type(e).__name__}: {msg}", markup=False)
                else:
                    n_ok += 1
                    n_surfaces += len(result.surfaces)
                    if done is not None:
                        w = done.warning
                    else:
                        w = fit_warning(result.noise) if result.noise is not None else None
                    if w:
                        progress.console.print(f"scan {scan.index}: warning: {w}", markup=False)
                    if not quiet and not show:
                        seconds = time.perf_counter() - t0 if done is None else done.seconds
                        progress.console.print(
                            f"scan {scan.index}: {len(result.surfaces)} surface(s) in "
                            f"{seconds:.1f} s")
                progress.advance(task)
                if stop and n_workers == 1:
                    raise KeyboardInterrupt
            if stop:  # the workers finished the scans they had; all are recorded
                raise KeyboardInterrupt
        except KeyboardInterrupt:
            progress.console.print("interrupted: closing the log")
            raise
        finally:
            stack.close()
            _report(rec, n_ok, n_failed, n_surfaces, time.perf_counter() - t_start, quiet)
    if errors:
        raise InputError(_errors_line(errors))


def _scan_of(item: Any, done: Any) -> Any:
    """The scan of a job, from its worker (a simulated one made there) or made here; a
    :class:`ReadError` for a simulated scan that could not be made."""
    if done is not None and done.unread is not None:
        return ReadError(done.unread)
    if done is not None and done.scan is not None:
        return done.scan
    try:
        return item.make_scan()
    except BoxlocError as e:
        return ReadError(str(e))


def _errors_line(errors: list[ReadError]) -> str:
    """The run's one-line error: the last unreadable input's message when nothing followed
    it (as a run of that input alone says), or how many were reported above."""
    last, others = errors[-1], len(errors) - 1
    if last.last:
        return last.message + (f" ({others} other input(s) could not be read either, "
                               "reported above)" if others else "")
    return f"{len(errors)} input(s) could not be read (reported above); every other scan ran"


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

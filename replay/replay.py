"""Replay one log: re-run the pipeline on the scans it stores and record a new log.

The replay unit is a plain function over one log, :func:`replay_log`, with picklable
arguments and result, so any executor (in-process, local processes, a Dask cluster) runs it
(after openpilot's ``process_replay``). It reads only the *inputs* of the original run (the
sensor model, the scan info and the range image of each scan, never a product), runs
:func:`boxloc.pipeline.find_graspable_surfaces` with the log's recorded config (or a given
one) plus overrides, and records everything with :class:`recorder.mcap.sink.McapRecorder`.

Guarantees
----------
- The input log is only ever opened for reading.
- An existing file is never overwritten: the new log is written under a temporary name in
  the output directory and published by a hard link (which fails if the name is taken).
  A retried task (a lost worker) therefore never sees a half-written file of its own.
- Output log times derive from the input scans' capture times, never from the clock
  (:func:`recorder.mcap.channels.scan_log_time`), so the same replay gives the same products
  and the same times.
- A stage that raises on one scan becomes that scan's recorded result (``/boxloc/error``)
  and its :class:`ScanStatus`; the other scans are still replayed.
- A log that cannot be read (not MCAP, truncated, damaged, unknown schema) becomes the
  outcome's ``error``, naming the log; nothing is published for it. A log with no scans
  is skipped with a warning.
- Nothing recorded is lost at another revision either: the run there gets the same carton
  list (``box_sizes``: the log's, or ``--box-sizes``), and the new log keeps the carton
  file (``box_sizes.csv``) even when that revision's recorder does not write it (this code
  adds it, :func:`recorder.mcap.sink.copy_log_adding`). A revision that predates a config
  key the replay needs (see :mod:`replay.versions`) runs without it; a one-line warning
  says so, and the new log records it (:data:`REPLAY_CARRIED_METADATA`).
- A revision older than log schema 1.6 cannot read the range of a 1.6 log: it replays a
  copy with the range as it reads it (bit for bit the same), made in a staging directory
  beside the output and removed after; the new log records the original input.
"""

from __future__ import annotations

import contextlib
import glob
import hashlib
import json
import math
import os
import secrets
import shutil
import time
import traceback
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from boxloc.config import Config
from boxloc.errors import BoxlocError, InputError, LogError

if TYPE_CHECKING:
    from boxloc.scan import Scan
    from recorder.mcap.log import Log
    from replay.versions import Version

#: Metadata record of a replayed log: what it was made from and how.
REPLAY_METADATA = "boxloc.replay"
#: Suffix of the temporary files new logs are written to before they are published.
PARTIAL_SUFFIX = ".partial.mcap"
#: Suffix of the private directories a revision's replay writes into, when this code
#: completes its log before publishing it (removed after; leftovers by remove_partials).
STAGING_SUFFIX = ".staging"
#: Metadata record of a log another revision wrote that this code completed: what it added
#: (``attachments``, JSON list), what that revision could not apply (``not_applied``, JSON
#: object of config keys and values), the ``warnings`` (JSON list), this code (``by``,
#: JSON) and, when the revision read a copy of the input made for older readers (it cannot
#: read log schema 1.6), ``input_copy`` (JSON: the original ``input`` and its
#: ``input_sha256``; the revision's :data:`REPLAY_METADATA` names the copy).
REPLAY_CARRIED_METADATA = "boxloc.replay.carried"


# --- outcome ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class ScanStatus:
    """What the replay of one scan gave.

    Attributes
    ----------
    index : int
        The scan's index in its log.
    capture_time_ns : int
        Its capture time, integer nanoseconds (0 when unknown).
    ok : bool
        The pipeline finished.
    n_surfaces : int
        Graspable surfaces found (0 when not ``ok``).
    error : str or None
        ``"<ExceptionType>: <message> (<file>:<line>)"`` when the pipeline raised (the log
        records the stage).
    """

    index: int
    capture_time_ns: int
    ok: bool
    n_surfaces: int = 0
    error: str | None = None


@dataclass(frozen=True)
class ReplayOutcome:
    """The result of :func:`replay_log` on one log (plain data: picklable, JSON-able).

    Attributes
    ----------
    input : str
        The log replayed.
    output : str or None
        The new log, or None if nothing was published (error, or no scans).
    n_scans : int
        Scans replayed.
    scans : tuple of ScanStatus
        One per scan, in log order.
    error : str or None
        Why the log could not be replayed (one line, naming the log).
    warnings : tuple of str
        Things worth saying that are not errors (e.g. a log with no scans).
    version : dict
        What ran: ``kind`` (``current`` or ``git``), ``boxloc_version``, ``git_commit``,
        ``git_dirty``, and for a revision ``ref`` and ``mode``.
    config_hash : str or None
        Hash of the config the scans were run with.
    seconds : float
        Wall-clock duration (informational; never part of a result).
    cpu_seconds : float
        CPU time of the process that replayed it (for a revision: of its subprocess);
        with ``seconds``, shows how much of a core the replay got.
    """

    input: str
    output: str | None = None
    n_scans: int = 0
    scans: tuple[ScanStatus, ...] = ()
    error: str | None = None
    warnings: tuple[str, ...] = ()
    version: dict[str, Any] = field(default_factory=dict)
    config_hash: str | None = None
    seconds: float = 0.0
    cpu_seconds: float = 0.0

    @property
    def status(self) -> str:
        """``"error"`` (unreadable log), ``"skipped"`` (no scans) or ``"ok"``."""
        if self.error is not None:
            return "error"
        if self.output is None:
            return "skipped"
        return "ok"

    @property
    def n_failed(self) -> int:
        """Scans whose pipeline raised (recorded as such in the new log)."""
        return sum(not s.ok for s in self.scans)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["scans"] = [asdict(s) for s in self.scans]
        d["warnings"] = list(self.warnings)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ReplayOutcome:
        """Inverse of :meth:`to_dict`; keys this version does not know are ignored (an
        outcome may come from another revision's worker)."""
        known = {f.name for f in fields(cls)}
        d = {k: v for k, v in d.items() if k in known}
        d["scans"] = tuple(ScanStatus(**s) for s in d.get("scans", ()))
        d["warnings"] = tuple(d.get("warnings", ()))
        return cls(**d)


# --- inputs ----------------------------------------------------------------------------------


def collect_logs(args: Iterable[str | os.PathLike[str]]) -> list[Path]:
    """The logs named by ``args``: files as given, directories' ``*.mcap`` (sorted, not
    recursive; temporary ``*.partial.mcap`` files are left out). A ROS 2 bag (a rosbag2
    directory, or a bag's ``.mcap``/``.db3`` file) is one input: its frames are replayed.

    Raises
    ------
    InputError
        A path that does not exist, or a directory without logs.
    """
    from boxloc.io.rosbag import is_rosbag

    out: list[Path] = []
    for a in args:
        p = Path(a)
        if p.is_dir() and not is_rosbag(p):  # a rosbag2 directory is one input
            found = sorted(q for q in p.glob("*.mcap")
                           if q.is_file() and not q.name.endswith(PARTIAL_SUFFIX))
            if not found:
                raise InputError(f"no .mcap logs in directory {p}")
            out.extend(found)
        elif p.exists():
            out.append(p)
        else:
            raise InputError(f"log not found: {p}")
    if not out:
        raise InputError("no logs given")
    seen: set[Path] = set()
    unique = []
    for p in out:  # the same log named twice is replayed once
        r = p.resolve()
        if r not in seen:
            seen.add(r)
            unique.append(p)
    return unique


def plan_outputs(paths: Sequence[Path], out_dir: Path) -> list[str]:
    """One output file name per input log: ``<stem>.mcap``, ``<stem>-1.mcap``, ... when two
    inputs share a stem.

    Raises
    ------
    InputError
        If an output file already exists (it is never overwritten) or would be an input.
    """
    names: list[str] = []
    taken: set[str] = set()
    inputs = {Path(p).resolve() for p in paths}
    for p in paths:
        stem, k = Path(p).stem, 0
        name = f"{stem}.mcap"
        while name in taken:
            k += 1
            name = f"{stem}-{k}.mcap"
        taken.add(name)
        target = Path(out_dir) / name
        if target.resolve() in inputs:
            raise InputError(f"--out {out_dir} would write {target} over an input log; "
                             "choose another output directory")
        if target.exists():
            raise InputError(f"{target} exists; refusing to overwrite it (choose another --out)")
        names.append(name)
    return names


def check_schema(log: Log) -> None:
    """Refuse a log whose schema major version this code does not read, with a clear message.

    Raises
    ------
    LogError
        Naming the log, the version found and the version read.
    """
    from recorder.mcap import channels as C
    from recorder.mcap import encode as E
    run = log.run
    found = run.get("schema_version")
    if found is not None:
        major = found.split(".", 1)[0]
        if major != str(E.SCHEMA_MAJOR):
            raise LogError(
                f"{log.path} was written with log schema version {found}; this boxloc reads "
                f"version {E.SCHEMA_MAJOR}.x only (replay it with the boxloc version that "
                f"wrote it: --rev {run.get('git_commit', 'COMMIT')})")
    layout = run.get("layout_version")
    if layout is not None and layout != C.LAYOUT_VERSION:
        raise LogError(f"{log.path} has log layout version {layout}; this boxloc reads layout "
                       f"version {C.LAYOUT_VERSION} only")


def iter_input_scans(log: Log) -> Iterator[Scan]:
    """The scans stored in ``log``, bit for bit, reading only the inputs of the run.

    Only the ``/scan/sensor``, ``/scan/info`` and ``/scan/range`` records are decoded: the
    recorded products are never read (a replay must not depend on them).

    Raises
    ------
    LogError
        A malformed record, a scan without its range or sensor model, or (at the end of
        the iteration) damage found in the log.
    """
    from recorder.mcap import channels as C
    from recorder.mcap import encode as E
    lim = log.limits
    sensors: dict[str, Any] = {}
    info: Any = None
    problem: LogError | None = None
    for m in log.messages({C.SCAN_SENSOR, C.SCAN_INFO, C.SCAN_RANGE}):
        if problem is not None:
            # Read on: if the log is damaged (a skipped chunk explains the problem), the
            # reader says so at the end, which is the better message.
            continue
        try:
            if m.topic == C.SCAN_INFO:
                if info is not None:
                    raise LogError(f"{log.path}: scan {info.index} has no range image")
                info = E.decode_scan_info(m.data, lim)
                continue
            scan = _take(m, sensors, info, log, lim)
        except LogError as e:
            problem = e
            continue
        if scan is not None:
            info = None
            yield scan
    if problem is not None:
        raise problem
    if info is not None:
        raise LogError(f"{log.path}: scan {info.index} has no range image")


def _take(m: Any, sensors: dict[str, Any], info: Any, log: Log, lim: Any) -> Scan | None:
    """Take a sensor model (None) or a range image, which completes a scan (the scan)."""
    from recorder.mcap import channels as C
    from recorder.mcap import encode as E
    if m.topic == C.SCAN_SENSOR:
        digest, model = E.decode_sensor(m.data, lim)
        sensors[digest] = model
        return None
    if info is None:
        raise LogError(f"{log.path}: a range image outside any scan")
    if m.sequence != info.index & 0xFFFFFFFF:
        raise LogError(f"{log.path}: range image of sequence {m.sequence} inside scan "
                       f"{info.index}")
    sensor = sensors.get(info.sensor_hash)
    if sensor is None:
        raise LogError(f"{log.path}: scan {info.index} uses sensor model "
                       f"{info.sensor_hash}, which is not in the log")
    return E.build_scan(info, E.decode_range(m.data, lim), sensor)


def box_sizes_override(sizes: Sequence[Sequence[float]]) -> str:
    """A carton list as the ``key=value`` override ``box_sizes=[[w, l, h], [w, l], ...]``
    (metres; a row of two where the height is unknown), exact: every float is written with
    ``repr``, which TOML reads back to the same bits. An override (not a config of its own)
    reaches every executor and revision the way ``--set`` does.
    """
    rows = []
    for row in sizes:
        w, ln, h = (float(v) for v in row)
        rows.append(f"[{w!r}, {ln!r}]" if math.isnan(h) else f"[{w!r}, {ln!r}, {h!r}]")
    return f"box_sizes=[{', '.join(rows)}]"


def resolve_config(log: Log, config: Config | None,
                   overrides: Sequence[str] | dict[str, Any] = ()) -> tuple[Config, str]:
    """The config to replay ``log`` with and where it came from.

    ``config`` when given, else the log's recorded config (``Log.config``), else the
    defaults; then ``overrides`` (``key=value`` strings or a dict).
    """
    if config is not None:
        cfg, source = config, "given"
    else:
        recorded = log.config
        cfg, source = (recorded, "log") if recorded is not None else (Config(), "default")
    if overrides:
        cfg = cfg.with_overrides(list(overrides) if not isinstance(overrides, dict)
                                 else overrides)
    return cfg, source


# --- the replay ------------------------------------------------------------------------------


def replay_log(
    path: str | os.PathLike[str],
    *,
    out_dir: str | os.PathLike[str],
    config: Config | None = None,
    overrides: Sequence[str] = (),
    version: Version | None = None,
    out_name: str | None = None,
    attachments: dict[str, tuple[str, bytes]] | None = None,
) -> ReplayOutcome:
    """Re-run the pipeline on every scan stored in one log and record a new log.

    Parameters
    ----------
    path : path
        The input log (``.mcap``); opened read-only.
    out_dir : path
        Directory of the new log (created if needed).
    config : Config, optional
        Run with this config instead of the one recorded in the log.
    overrides : sequence of str
        ``key=value`` config overrides applied on top (``alpha=0.05``, ``noise.k2=0.001``).
    version : Version, optional
        :data:`replay.versions.CURRENT` (default: this code, in this process), a
        :class:`replay.versions.GitRevision` (prepared for this call and removed after)
        or a prepared :class:`replay.versions.Worktree` (run in its subprocess).
    out_name : str, optional
        File name of the new log; default ``<input stem>.mcap``.
    attachments : dict, optional
        Attachments for the new log, ``{name: (media type, bytes)}``: the ``--box-sizes``
        file (:func:`recorder.mcap.sink.box_sizes_attachment`), whose sizes come in
        ``overrides`` (:func:`box_sizes_override`). Without one, the input log's carton
        file is carried over when the replay runs with the sizes it recorded. At another
        revision (``version``) the sizes go through the config or ``overrides`` and this
        code adds the file to the revision's log if its recorder did not.

    Returns
    -------
    ReplayOutcome
        Never raises for a bad log or a failing scan: those are the outcome's ``error`` and
        per-scan statuses.

    Raises
    ------
    InputError
        Only for a bad ``config``/``overrides`` with a version that cannot report it
        per log (never for the current code: there it is the outcome's error).
    """
    from replay.versions import CURRENT, CurrentVersion, GitRevision

    v = CURRENT if version is None else version
    if isinstance(v, GitRevision):  # prepared for this call, removed after
        with v.prepare() as wt:
            return _replay_at_revision(wt, Path(path), Path(out_dir), config,
                                       tuple(overrides), out_name, attachments)
    if not isinstance(v, CurrentVersion):
        return _replay_at_revision(v, Path(path), Path(out_dir), config, tuple(overrides),
                                   out_name, attachments)
    return _replay_here(Path(path), Path(out_dir), config, tuple(overrides), out_name,
                        attachments)


def _one_line(e: BaseException) -> str:
    msg = str(e).splitlines()[0] if str(e) else ""
    return msg or type(e).__name__


def _named(path: Path, msg: str) -> str:
    """A log error message that names the log (once)."""
    return msg if str(path) in msg else f"{path}: {msg}"


def _diagnose(path: Path, e: LogError) -> str:
    """The one-line message for a log that does not open: says "truncated" when it is."""
    from recorder.mcap.log import open_log

    try:
        partial = open_log(path, allow_truncated=True)
    except Exception:  # noqa: BLE001 - not even that: the original message says why
        return _named(path, _one_line(e))
    if partial.complete:
        return _named(path, _one_line(e))
    return (f"{path}: truncated log ({partial.truncated or 'it has no summary section'}; its "
            f"recorder was killed or the disk filled up); `boxloc recover {path}` saves the "
            "scans it holds")


def _current_version() -> dict[str, Any]:
    import boxloc
    from recorder.mcap.sink import git_info

    commit, dirty = git_info()
    return {"kind": "current", "boxloc_version": boxloc.__version__, "git_commit": commit,
            "git_dirty": dirty, "source": str(Path(boxloc.__file__).resolve().parent.parent)}


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(path.iterdir()) if path.is_dir() else [path]:  # a rosbag2 directory
        if p.is_file():
            with open(p, "rb") as f:
                for block in iter(lambda: f.read(1 << 20), b""):
                    h.update(block)
    return h.hexdigest()


class _BagInput:
    """A ROS 2 bag as a replay input: its depth frames (:func:`boxloc.io.rosbag.open_bag`,
    the topics chosen by type), no recorded config or run metadata."""

    config = None
    run: dict[str, str] = {}

    def __init__(self, path: Path) -> None:
        from boxloc.io.rosbag import open_bag

        self.bag = open_bag(path)

    def scans(self, cfg: Config) -> Iterator[Scan]:
        self.bag.max_pixels = cfg.max_pixels
        return iter(self.bag)


def _replay_metadata(path: Path, log: Log, cfg: Config, source: str,
                     overrides: Sequence[str], version: dict[str, Any]) -> dict[str, str]:
    run = log.run
    return {
        "input": str(path.resolve()),
        "input_sha256": _sha256(path),
        "input_git_commit": run.get("git_commit", "unknown"),
        "input_boxloc_version": run.get("boxloc_version", "unknown"),
        "input_config_hash": run.get("config_hash", "unknown"),
        "config_source": source,
        "config_hash": cfg.hash,
        "overrides": json.dumps(list(overrides)),
        "replay_version": json.dumps(version, sort_keys=True),
    }


def _stage_error(e: BaseException) -> str:
    tb = traceback.extract_tb(e.__traceback__)
    where = f" ({Path(tb[-1].filename).name}:{tb[-1].lineno})" if tb else ""
    return f"{type(e).__name__}: {_one_line(e)}{where}"


def _carried_attachments(
        log: Any, cfg: Config, given: dict[str, tuple[str, bytes]] | None,
) -> dict[str, tuple[str, bytes]]:
    """The attachments of the new log: those given, else the input log's carton file when
    the replay runs with the carton list the input recorded (the file still describes it)."""
    from recorder.mcap import channels as C

    if given is not None:
        return dict(given)
    names = {a.name for a in log.attachments()} if hasattr(log, "attachments") else set()
    if C.BOX_SIZES_ATTACHMENT not in names:
        return {}
    try:
        recorded = log.config
        data = log.attachment(C.BOX_SIZES_ATTACHMENT)
    except Exception:  # noqa: BLE001 - damaged, or (compat layout) an older Config that
        return {}  # cannot read it: not worth failing the replay for
    if recorded is None or getattr(recorded, "box_sizes", ()) != getattr(cfg, "box_sizes", ()):
        return {}
    return {C.BOX_SIZES_ATTACHMENT: (C.BOX_SIZES_MEDIA_TYPE, data)}


def _replay_here(path: Path, out_dir: Path, config: Config | None,
                 overrides: tuple[str, ...], out_name: str | None,
                 attachments: dict[str, tuple[str, bytes]] | None = None) -> ReplayOutcome:
    """:func:`replay_log` with the code of this process."""
    from boxloc.pipeline import find_graspable_surfaces
    from recorder.mcap.log import open_log
    from recorder.mcap.sink import McapRecorder, RecordingError

    t0, c0 = time.perf_counter(), time.process_time()
    version = _current_version()
    base: dict[str, Any] = {"input": str(path), "version": version}

    def took() -> dict[str, Any]:
        return {"seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0}

    def failed(msg: str, **kw: Any) -> ReplayOutcome:
        return ReplayOutcome(**base, error=msg, **took(), **kw)

    from boxloc.io.rosbag import is_rosbag

    bag = is_rosbag(path)
    try:
        if bag:
            log: Any = _BagInput(path)
        else:
            log = open_log(path)
            check_schema(log)
    except InputError as e:  # a bag without usable depth frames
        return failed(_named(path, _one_line(e)))
    except LogError as e:
        return failed(_diagnose(path, e))
    except OSError as e:
        return failed(f"{path}: cannot read: {e.strerror or e}")
    except Exception as e:  # noqa: BLE001 - whatever a hostile file does, name the log
        return failed(f"{path}: cannot read: {type(e).__name__}: {_one_line(e)}")
    try:
        cfg, source = resolve_config(log, config, overrides)
    except BoxlocError as e:
        return failed(_named(path, _one_line(e)))
    warnings: list[str] = []
    if not log.run and not bag:
        warnings.append(f"{path}: no boxloc.run metadata; replayed with the default config")

    out_dir.mkdir(parents=True, exist_ok=True)
    final = out_dir / (out_name or f"{path.stem}.mcap")
    # A private temporary name per attempt: a retried task never meets its own leftovers.
    tmp = out_dir / f".{final.stem}.{os.getpid()}-{secrets.token_hex(4)}{PARTIAL_SUFFIX}"
    rec: McapRecorder | None = None
    statuses: list[ScanStatus] = []
    error: str | None = None
    try:
        for scan in (log.scans(cfg) if bag else iter_input_scans(log)):
            if rec is None:  # created at the first scan: a log without scans leaves nothing
                rec = McapRecorder(
                    tmp, config=cfg, session=f"replay-{path.stem}", fsync=False,
                    extra_metadata={REPLAY_METADATA: _replay_metadata(
                        path, log, cfg, source, overrides, version)},
                    attachments=_carried_attachments(log, cfg, attachments))
            try:
                result = find_graspable_surfaces(scan, cfg, observer=rec)
            except RecordingError:
                raise
            except Exception as e:  # noqa: BLE001 - the scan's failure is its result
                rec.on_error(scan, e)
                statuses.append(ScanStatus(scan.index, scan.capture_time_ns, False,
                                           error=_stage_error(e)))
            else:
                statuses.append(ScanStatus(scan.index, scan.capture_time_ns, True,
                                           n_surfaces=len(result.surfaces)))
    except LogError as e:
        error = _named(path, _one_line(e))
    except InputError as e:  # a damaged bag: `boxloc import` keeps its readable frames
        error = (_named(path, _one_line(e)) + f" (`boxloc import {path} --out LOG.mcap` "
                 "keeps the readable frames)")
    except BoxlocError as e:  # the recorder could not write
        error = f"{path}: {_one_line(e)}"
    except Exception as e:  # noqa: BLE001 - a reader bug on a hostile file: name the log
        error = f"{path}: cannot read: {type(e).__name__}: {_one_line(e)}"
    finally:  # also on an interrupt: close the file (the CLI removes it)
        if rec is not None:
            try:
                rec.finish()
            except Exception as e:  # noqa: BLE001 - e.g. the disk filled up
                error = error or f"{path}: cannot write the new log: {_one_line(e)}"
    if error is not None or rec is None:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if error is not None:
            return failed(error, n_scans=len(statuses), scans=tuple(statuses),
                          config_hash=cfg.hash, warnings=tuple(warnings))
        warnings.append(f"{path}: no scans in this log; skipped")
        return ReplayOutcome(**base, warnings=tuple(warnings), config_hash=cfg.hash, **took())
    try:
        _publish(tmp, final)
    except InputError as e:
        return failed(str(e), n_scans=len(statuses), scans=tuple(statuses),
                      config_hash=cfg.hash, warnings=tuple(warnings))
    return ReplayOutcome(**base, output=str(final), n_scans=len(statuses),
                         scans=tuple(statuses), warnings=tuple(warnings), config_hash=cfg.hash,
                         **took())


# --- another revision ------------------------------------------------------------------------


@dataclass(frozen=True)
class _RevisionPlan:
    """How one log goes to another revision: what it is sent, what its log must hold.

    Attributes
    ----------
    config : Config, dict or None
        As :meth:`replay.versions.Worktree.replay` takes it.
    overrides : tuple of str
    attachments : dict or None
        ``{name: (media type, bytes)}`` the new log must hold; None when this code could
        not read the input (the revision decides).
    not_applied : dict
        Config keys the revision lacks, with the values it runs without.
    warnings : tuple of str
    older_copy : bool
        The revision cannot read the input's range (log schema 1.6 on): it replays a
        staging copy for older readers, and the new log records the original.
    """

    config: Any
    overrides: tuple[str, ...]
    attachments: dict[str, tuple[str, bytes]] | None
    not_applied: dict[str, Any]
    warnings: tuple[str, ...]
    older_copy: bool = False

    @property
    def completes(self) -> bool:
        """This code may have to add to the revision's log."""
        return bool(self.attachments or self.not_applied or self.older_copy)


def _plan_for_revision(wt: Any, path: Path, config: Config | None,
                       overrides: tuple[str, ...],
                       attachments: dict[str, tuple[str, bytes]] | None) -> _RevisionPlan:
    """Read the input's config and carton file with this code and decide what the revision
    gets. Anything this code cannot read goes to the revision as it is (it reports the
    problem in its own words). A log whose range the revision cannot read (schema 1.6 on,
    :meth:`replay.versions.Worktree.needs_older_log`) goes to it as a copy."""
    from boxloc.io.rosbag import is_rosbag
    from recorder.mcap.log import open_log

    as_given = _RevisionPlan(config, overrides, attachments, {}, ())
    try:
        if is_rosbag(path):
            log: Any = None
            no_log: Any = _NoLog()
            cfg, source = resolve_config(no_log, config, overrides)
        else:
            log = open_log(path)
            check_schema(log)
            cfg, source = resolve_config(log, config, overrides)
        carried = _carried_attachments(log, cfg, attachments) if log is not None \
            else dict(attachments or {})
        older = log is not None and wt.needs_older_log(log.run.get("schema_version"))
    except Exception:  # noqa: BLE001 - a bad log or override: the revision says what
        return as_given
    adapted = wt.adapt_config(cfg, overrides, send_config=source != "default")
    if adapted is None:
        return _RevisionPlan(config, overrides, carried, {}, (), older)
    warnings: tuple[str, ...] = ()
    if adapted.not_applied:
        what = ", ".join(f"{k}={_short(v)}" for k, v in adapted.not_applied.items())
        warnings = (f"{path}: --rev {wt.ref} ({wt.commit[:12]}) predates "
                    f"{', '.join(adapted.not_applied)}: replayed without {what} (recorded in "
                    "the new log)",)
    return _RevisionPlan(adapted.config, adapted.overrides, carried, adapted.not_applied,
                         warnings, older)


class _NoLog:
    """The config source of a bag: nothing recorded."""

    config = None


def _short(v: Any, n: int = 60) -> str:
    text = json.dumps(v, separators=(",", ":"))
    return text if len(text) <= n else text[: n - 3] + "..."


def _replay_at_revision(wt: Any, path: Path, out_dir: Path, config: Config | None,
                        overrides: tuple[str, ...], out_name: str | None,
                        attachments: dict[str, tuple[str, bytes]] | None) -> ReplayOutcome:
    """:func:`replay_log` with a prepared :class:`replay.versions.Worktree`.

    When the new log may need completing (a carton file to keep, a config key the revision
    could not apply, an input it read as a copy), the revision writes it into a private
    staging directory beside the output and this code publishes it, completed, under its
    name. A revision that cannot read the input's range (log schema 1.6 on) replays a copy
    for older readers (:func:`recorder.mcap.sink.copy_log_for_older_readers`) made in that
    directory; the input itself is only read.
    """
    plan = _plan_for_revision(wt, path, config, overrides, attachments)
    if not plan.completes:
        out: ReplayOutcome = wt.replay(path, out_dir=out_dir, config=plan.config,
                                       overrides=plan.overrides, out_name=out_name,
                                       attachments=plan.attachments)
        return out
    name = out_name or f"{path.stem}.mcap"
    final = out_dir / name
    staging = out_dir / f".{final.stem}.{os.getpid()}-{secrets.token_hex(4)}{STAGING_SUFFIX}"
    staging.mkdir(parents=True)
    try:
        src = path
        if plan.older_copy:
            from recorder.mcap.sink import copy_log_for_older_readers

            # same file name: the revision names its session and messages after it
            src = staging / "input" / path.name
            src.parent.mkdir()
            try:
                from replay.versions import schema_tuple

                copy_log_for_older_readers(path, src, schema_tuple(wt.schema_version))
            except Exception as e:  # noqa: BLE001 - a damaged range, a full disk: the log's
                return ReplayOutcome(  # error, as any unreadable log
                    input=str(path), version=wt.version_info(),
                    error=f"{path}: cannot copy it for --rev {wt.ref}, which reads log schema "
                          f"{wt.schema_version or 'before 1.6'}: {type(e).__name__}: "
                          f"{_one_line(e)}")
        o = wt.replay(src, out_dir=staging, config=plan.config, overrides=plan.overrides,
                      out_name=name, attachments=plan.attachments)
        if src != path:
            o = _as_original(o, src, path)
        warnings = (*plan.warnings, *o.warnings)
        if o.output is None:  # an error or no scans: nothing to complete
            return replace(o, warnings=warnings)
        staged = Path(o.output)
        try:
            _complete_and_publish(staged, final, plan, path)
        except InputError as e:  # the name is taken
            return replace(o, output=None, error=str(e), warnings=warnings)
        except Exception as e:  # noqa: BLE001 - e.g. the disk filled up while copying
            # the replay itself is not lost: published as the revision wrote it, and said
            copied = " or of the input it read a copy of" if plan.older_copy else ""
            warnings = (*warnings, f"{path}: the new log is as --rev {wt.ref} wrote it, "
                                   f"without {', '.join(sorted(plan.attachments or {}))}"
                                   f" or the record of what it did not apply{copied}: "
                                   f"{type(e).__name__}: {_one_line(e)}")
            try:
                _publish(staged, final)
            except InputError as e2:
                return replace(o, output=None, error=str(e2), warnings=warnings)
        return replace(o, output=str(final), warnings=warnings)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _as_original(o: ReplayOutcome, copy: Path, path: Path) -> ReplayOutcome:
    """The outcome of a replay of ``copy`` as that of ``path``: its input, and its messages
    naming the input."""
    def named(text: str) -> str:
        for p in {str(copy.resolve()), str(copy)}:
            text = text.replace(p, str(path))
        return text

    return replace(o, input=str(path), error=None if o.error is None else named(o.error),
                   warnings=tuple(named(w) for w in o.warnings),
                   scans=tuple(replace(st, error=None if st.error is None else named(st.error))
                               for st in o.scans))


def _complete_and_publish(staged: Path, final: Path, plan: _RevisionPlan,
                          path: Path) -> None:
    """Publish ``staged`` as ``final``, first adding the attachments it lacks (or holds
    with other bytes) and, if anything was added or not applied or the revision read a
    copy of the input ``path``, the :data:`REPLAY_CARRIED_METADATA` record."""
    from recorder.mcap.log import open_log
    from recorder.mcap.sink import copy_log_adding

    log = open_log(staged)
    have = {a.name for a in log.attachments()}
    add = {n: (m, d) for n, (m, d) in (plan.attachments or {}).items()
           if n not in have or log.attachment(n) != d}
    if not add and not plan.not_applied and not plan.older_copy:
        _publish(staged, final)
        return
    record = {"attachments": json.dumps(sorted(add)),
              "not_applied": json.dumps(plan.not_applied, sort_keys=True),
              "warnings": json.dumps(list(plan.warnings)),
              "by": json.dumps(_current_version(), sort_keys=True)}
    if plan.older_copy:  # the revision's boxloc.replay record names the copy, now gone
        record["input_copy"] = json.dumps(
            {"input": str(path.resolve()), "input_sha256": _sha256(path),
             "copy": "recorder.mcap.sink.copy_log_for_older_readers: float32 arrays as "
                     "float64 for a revision before log schema 1.7, and the range in image "
                     "filter 4 for one before 1.6; the same bits"},
            sort_keys=True)
    tmp = final.parent / f".{final.stem}.{os.getpid()}-{secrets.token_hex(4)}{PARTIAL_SUFFIX}"
    try:
        copy_log_adding(staged, tmp, attachments=add,
                        metadata={REPLAY_CARRIED_METADATA: record})
        _publish(tmp, final)
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()


def _publish(tmp: Path, final: Path) -> None:
    """Give the finished temporary log its name, never replacing an existing file."""
    try:
        os.link(tmp, final)  # atomic, and fails if ``final`` exists
    except FileExistsError:
        tmp.unlink()
        raise InputError(f"{final} exists; refusing to overwrite it") from None
    except OSError:  # a file system without hard links: check, then rename
        if final.exists():
            tmp.unlink()
            raise InputError(f"{final} exists; refusing to overwrite it") from None
        os.replace(tmp, final)
        return
    tmp.unlink()


def remove_partials(out_dir: Path, names: Iterable[str]) -> int:
    """Remove temporary files left in ``out_dir`` by killed attempts at ``names``.

    Call it only when no replay into ``out_dir`` is running. Returns how many were removed.
    """
    n = 0
    for name in names:
        stem = Path(name).stem
        for p in Path(out_dir).glob(f".{glob.escape(stem)}.*{PARTIAL_SUFFIX}"):
            with contextlib.suppress(OSError):
                p.unlink()
                n += 1
        for p in Path(out_dir).glob(f".{glob.escape(stem)}.*{STAGING_SUFFIX}"):
            if p.is_dir() and not p.is_symlink():  # a revision's staging directory
                shutil.rmtree(p, ignore_errors=True)
                n += 1
    return n


@dataclass(frozen=True)
class ReplayJob:
    """``replay_log`` with everything but the log fixed: the picklable ``fn(path)`` the
    executors run.

    Attributes
    ----------
    out_dir : str
    config : Config or None
    overrides : tuple of str
    version : Version or None
    names : dict
        Output file name per input path (as given), from :func:`plan_outputs`.
    attachments : dict or None
        Attachments of every new log (``replay --box-sizes``: the file).
    """

    out_dir: str
    config: Config | None = None
    overrides: tuple[str, ...] = ()
    version: Any = None
    names: dict[str, str] = field(default_factory=dict)
    attachments: dict[str, tuple[str, bytes]] | None = None

    def __call__(self, path: str | os.PathLike[str]) -> ReplayOutcome:
        return replay_log(path, out_dir=self.out_dir, config=self.config,
                          overrides=self.overrides, version=self.version,
                          out_name=self.names.get(str(path)), attachments=self.attachments)

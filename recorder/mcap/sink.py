"""The MCAP recorder: every scan and every product of the pipeline, one chunk per scan.

:class:`McapRecorder` is a :class:`boxloc.observer.Observer`. It collects the messages of a
scan while the pipeline runs and, when the scan ends (``on_result``, or ``on_error``),
writes them as one zstd chunk, flushes and fsyncs. So a crash (SIGKILL, power loss) loses
at most the scan in progress, and ``boxloc recover`` gets every earlier scan back; SIGINT
and SIGTERM are held off while a chunk is being written, so they never tear one.

The messages are made by a :class:`ScanEncoder`, the recorder's pure half (observer calls
in, one :class:`EncodedScan` of bytes per scan out); the recorder writes them. ``boxloc run
--workers N`` runs the encoder in its worker processes and the recorder's
:meth:`McapRecorder.write_encoded` in the parent: the same code makes the same bytes.

Files are chunked, zstd-compressed, indexed, with a summary section, one per recording
session, rotated by size, by log-time duration, or when the config changes (one config per
file). Each file starts with a ``boxloc.run`` metadata record (version, git commit and dirty
flag, the full config and its hash, the sensor model, the host) and the config and the
calibration as attachments.

Example
-------
>>> with McapRecorder("logs/run.mcap") as rec:                     # doctest: +SKIP
...     for scan in scans:
...         find_graspable_surfaces(scan, config, observer=rec)
...     rec.record_outcome(scan.index, 0, ok=True)
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import platform
import secrets
import signal
import socket
import subprocess
import threading
import time
import types
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any

import mcap.writer as _mcap_writer
import numpy as np
import zstandard
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

import boxloc
from boxloc.config import Config
from boxloc.errors import BoxlocError, InputError
from boxloc.observer import NullObserver
from boxloc.products import STAGES
from boxloc.scan import PinholeModel, RayTableModel, Scan, SensorModel
from recorder.mcap import channels as C
from recorder.mcap import encode as E

#: zstd level of the chunks. The mcap writer compresses with ``zstandard.compress(data)``
#: at the library default (3) and offers no level; level 1 halves the compression time (the
#: largest part of recording a scan) for under 1 % more bytes on range images.
ZSTD_LEVEL = 1


class _ZstdAtLevel:
    """Stands in for the ``zstandard`` module inside :class:`ZstdLevelWriter`'s chunk
    finalizer: same ``compress``, our level. Still standard zstd frames, so every reader is
    unaffected."""

    def __init__(self, level: int) -> None:
        self._c = zstandard.ZstdCompressor(level=level)
        self._lock = threading.Lock()

    def compress(self, data: bytes) -> bytes:
        with self._lock:  # a ZstdCompressor is not safe across threads
            return self._c.compress(data)


def _with_zstandard(f: Callable[..., Any], zstd: object) -> Callable[..., Any]:
    """A copy of ``f``, a function of ``mcap.writer``, that sees ``zstd`` as ``zstandard``.

    The copy runs the library's own code (so its chunks are laid out exactly as the
    library's), against a copy of the module's namespace: ``mcap.writer`` itself, and so
    every other Writer in the process, is untouched.
    """
    namespace = {**vars(_mcap_writer), "zstandard": zstd}
    g = types.FunctionType(f.__code__, namespace, f.__name__, f.__defaults__, f.__closure__)
    g.__qualname__ = f.__qualname__
    return g


# The library's chunk finalizer (private: name-mangled ``Writer.__finalize_chunk``), where the
# only zstd call is. None when an mcap release no longer has it or compresses elsewhere; the
# writer then compresses at the library's level (valid logs, other bytes), which
# tests/test_zstd_level.py reports.
_FINALIZE = getattr(Writer, "_Writer__finalize_chunk", None)
if _FINALIZE is not None and "zstandard" not in _FINALIZE.__code__.co_names:
    _FINALIZE = None


class ZstdLevelWriter(Writer):
    """mcap's :class:`~mcap.writer.Writer` with its zstd chunks compressed at
    :data:`ZSTD_LEVEL`; every other argument and method is the library's.

    mcap takes no compression level. Before, importing this module replaced
    ``mcap.writer.zstandard`` for the whole process, so every mcap writer in it (the
    fuzzer's, a user's) wrote other bytes depending on whether the recorder had been
    imported. Now only this class compresses at the recorder's level.
    """

    if _FINALIZE is not None:
        # mcap's Writer calls self._Writer__finalize_chunk (mangled): this copy is found first
        _Writer__finalize_chunk = _with_zstandard(_FINALIZE, _ZstdAtLevel(ZSTD_LEVEL))


#: A chunk is closed by the recorder at the end of each scan, never by size.
_NO_AUTO_CHUNK = 1 << 62
#: Points of the /scan/points view: a preview (the range image is the record).
DEFAULT_MAX_POINTS = 5_000


class RecordingError(BoxlocError):
    """The recorder could not write its log (disk full, I/O error, closed recorder)."""


# --- provenance ------------------------------------------------------------------------------


_GIT: tuple[str, str] | None = None


def _git(root: Path, *args: str) -> str:
    """stdout of ``git args`` in ``root``; raises on failure or after 10 s."""
    return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, timeout=10,
                          check=True).stdout


def git_info() -> tuple[str, str]:
    """(commit, dirty) of the boxloc source tree: ``("unknown", "unknown")`` outside git.

    ``dirty`` is ``"true"`` when tracked files differ from the commit.
    """
    global _GIT
    if _GIT is None:
        root = Path(boxloc.__file__).resolve().parent.parent
        commit, dirty = "unknown", "unknown"
        if (root / ".git").exists():
            try:
                commit = _git(root, "rev-parse", "HEAD").strip()
                st = _git(root, "status", "--porcelain", "--untracked-files=no")
                dirty = "true" if st.strip() else "false"
            except (OSError, subprocess.SubprocessError):
                pass
        _GIT = (commit or "unknown", dirty)
    return _GIT


def _kernels() -> dict[str, str]:
    """How this process runs the kernels (the same products either way; the first scan's
    time differs): ``aot`` or ``jit``, and numba's version. ``unknown`` for a boxloc
    without :mod:`boxloc.kernels` (an older revision under ``replay --rev``)."""
    try:
        from boxloc import kernels
    except ImportError:
        return {"kernels": "unknown", "numba": "unknown"}
    return {"kernels": kernels.mode(), "numba": kernels.build_facts()["numba"] or "none"}


def provenance(config: Config, sensor: SensorModel | None, session: str,
               part: int) -> dict[str, str]:
    """The ``boxloc.run`` metadata record: what made this log and how to redo it."""
    import google.protobuf
    import mcap

    commit, dirty = git_info()
    md = {
        "layout_version": C.LAYOUT_VERSION,
        "schema_version": E.SCHEMA_VERSION,
        "boxloc_version": boxloc.__version__,
        "git_commit": commit,
        "git_dirty": dirty,
        "config": config.canonical_json(),
        "config_hash": config.hash,
        "host": socket.gethostname(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        **_kernels(),
        "mcap": getattr(mcap, "__version__", "unknown"),
        "protobuf": google.protobuf.__version__,
        "session": session,
        "part": str(part),
        "created_utc": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
    }
    if sensor is not None:
        md["sensor"] = json.dumps(sensor.to_dict(), sort_keys=True)
        md["sensor_hash"] = E.sensor_hash(sensor)
    return md


def _calibration_json(sensor: SensorModel) -> bytes:
    d: dict[str, Any] = dict(sensor.to_dict())
    d["sensor_hash"] = E.sensor_hash(sensor)
    if isinstance(sensor, PinholeModel):
        d["K"] = sensor.K.tolist()
    else:
        d["table"] = f"{C.RAYTABLE_ATTACHMENT} (and the {C.SCAN_SENSOR} channel)"
    return (json.dumps(d, indent=2, sort_keys=True) + "\n").encode()


def _npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(a), allow_pickle=False)
    return buf.getvalue()


def box_sizes_attachment(path: str | os.PathLike[str]) -> dict[str, tuple[str, bytes]]:
    """The ``--box-sizes`` file as the recorder's ``attachments`` entry: its bytes as they
    are (:data:`recorder.mcap.channels.BOX_SIZES_ATTACHMENT`, ``text/csv``).

    Read after :func:`boxloc.io.box_sizes.read_box_sizes` accepted the file (which bounds
    its size); a file that cannot be read now is an :class:`InputError` naming it.
    """
    try:
        data = Path(path).read_bytes()
    except OSError as e:
        raise InputError(f"{path}: cannot read box sizes file ({e.strerror or e})") from None
    return {C.BOX_SIZES_ATTACHMENT: (C.BOX_SIZES_MEDIA_TYPE, data)}


def copy_log_adding(
    src: str | os.PathLike[str],
    dst: str | os.PathLike[str],
    *,
    attachments: dict[str, tuple[str, bytes]] | None = None,
    metadata: dict[str, dict[str, str]] | None = None,
    transform: Callable[[str, bytes], bytes] | None = None,
) -> None:
    """Copy the finished log ``src`` to the new file ``dst``, adding attachments and
    metadata records.

    Everything recorded is kept: every message, bit for bit, in a chunk of its own as in
    ``src`` (one per scan), with its log time, publish time and sequence; every metadata
    record and attachment of ``src``, except those named again in ``attachments`` /
    ``metadata``, which the new ones replace (a name is one record in a boxloc log). The
    new records follow the copied ones. ``replay --rev`` uses it to give a log that another
    revision wrote what that revision could not write (the ``--box-sizes`` file).

    Parameters
    ----------
    src : path
        A complete MCAP log (its CRCs are checked); only read.
    dst : path
        The new file; it must not exist.
    attachments : dict, optional
        ``{name: (media type, bytes)}``, logged at the time of ``src``'s first attachment
        (the recorder logs its attachments at the first scan's time), else 0.
    metadata : dict, optional
        ``{name: {key: value}}`` (strings).
    transform : callable, optional
        ``transform(topic, data) -> data``: each message's bytes as the copy holds them
        (default: as they are; :func:`copy_log_for_older_readers` rewrites the range).

    Raises
    ------
    FileExistsError
        ``dst`` exists.
    OSError, mcap.exceptions.McapError
        ``src`` cannot be read or is not a complete MCAP file (``dst`` is then removed).
    """
    from mcap.records import Attachment, Channel, Chunk, DataEnd, Header, Message, Metadata
    from mcap.records import Schema as McapSchema
    from mcap.stream_reader import StreamReader, breakup_chunk

    add = {str(k): (str(m), bytes(d)) for k, (m, d) in (attachments or {}).items()}
    meta = {str(k): {str(a): str(b) for a, b in v.items()} for k, v in (metadata or {}).items()}
    dst = Path(dst)
    out: McapFile | None = None
    schemas: dict[int, McapSchema] = {}
    channels: dict[int, Channel] = {}
    t_attach: int | None = None

    def write(m: Message) -> None:
        assert out is not None
        ch = channels[m.channel_id]
        sc = schemas.get(ch.schema_id)
        cid = out.channel(ch.topic, schema_name=sc.name if sc else "",
                          schema_encoding=sc.encoding if sc else "",
                          schema_data=bytes(sc.data) if sc else b"",
                          message_encoding=ch.message_encoding, metadata=dict(ch.metadata))
        data = bytes(m.data) if transform is None else transform(ch.topic, bytes(m.data))
        out.add(cid, m.log_time, data, publish_time=m.publish_time, sequence=m.sequence)

    with open(src, "rb") as fin:
        stream = open(dst, "xb")
        try:
            for rec in StreamReader(fin, emit_chunks=True, validate_crcs=True).records:
                if isinstance(rec, Header):
                    out = McapFile(dst, stream, library=rec.library, fsync=False,
                                   profile=rec.profile)
                    continue
                if out is None:
                    raise ValueError(f"{src}: no MCAP header")
                if isinstance(rec, Metadata):
                    if rec.name not in meta:
                        out.writer.add_metadata(rec.name, dict(rec.metadata))
                elif isinstance(rec, Attachment):
                    t_attach = rec.log_time if t_attach is None else t_attach
                    if rec.name not in add:
                        out.writer.add_attachment(rec.create_time, rec.log_time, rec.name,
                                                  rec.media_type, bytes(rec.data))
                elif isinstance(rec, McapSchema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message):
                    write(rec)
                elif isinstance(rec, Chunk):
                    for r in breakup_chunk(rec, validate_crc=True):
                        if isinstance(r, McapSchema):
                            schemas[r.id] = r
                        elif isinstance(r, Channel):
                            channels[r.id] = r
                        elif isinstance(r, Message):
                            write(r)
                    out.writer.flush()  # the source's chunk boundaries: one chunk per scan
                elif isinstance(rec, DataEnd):
                    break
            else:
                raise ValueError(f"{src}: the data section does not end (a truncated log)")
            if out is None:
                raise ValueError(f"{src}: not an MCAP file")
            out.writer.flush()
            t = t_attach or 0
            for name, (media, data) in add.items():
                out.writer.add_attachment(t, t, name, media, data)
            for name, md in meta.items():
                out.writer.add_metadata(name, md)
            out.fsync = True
            out.finish()
        except BaseException:
            if out is not None:
                out.abandon()
            stream.close()
            with contextlib.suppress(OSError):
                dst.unlink()
            raise


def copy_log_for_older_readers(src: str | os.PathLike[str], dst: str | os.PathLike[str],
                               reader: tuple[int, int] | None = None) -> None:
    """Copy the finished log ``src`` to the new file ``dst`` so that code of an older record
    schema reads it.

    ``reader``: the schema the code reads up to, as ``(major, minor)``; None for code that
    does not say (before 1.6). Before 1.7, each float64 array stored as float32 (filters 6
    and 7) is stored as float64 (filters 1 and 3); before 1.6, each ``/scan/range``
    record's range is also put in image filter 4 (byte shuffle) instead of 5.

    Everything else is kept as :func:`copy_log_adding` keeps it; every array is the same,
    bit for bit, and the file a few per cent larger (about 3 % for the range; the float64
    edge map, up to 7 % on the matrix suite's scans). For ``replay --rev`` of a revision
    before 1.7.

    Raises
    ------
    LogError
        A record that cannot be decoded (``dst`` is then removed).
    """
    from recorder.mcap.proto import PACKAGE

    products = {c.topic for c in C.CHANNELS if c.schema_name == f"{PACKAGE}.Product"}
    old_range = reader is None or reader < (1, 6)

    def older(topic: str, data: bytes) -> bytes:
        if topic == C.SCAN_RANGE and old_range:
            data = E.legacy_range_message(data)
        return E.legacy_product_message(data) if topic in products else data

    copy_log_adding(src, dst, transform=older)


# --- signals ---------------------------------------------------------------------------------


@contextlib.contextmanager
def defer_signals() -> Iterator[None]:
    """Hold SIGINT and SIGTERM until the block ends, then deliver them.

    A chunk is written with several ``write`` calls; an interrupt between two would leave a
    chunk without its message index, and ``finish`` would then index a torn chunk.
    Only the main thread can handle signals, elsewhere this does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    old: dict[int, Any] = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            old[sig] = signal.signal(sig, lambda s, _f: caught.append(s))
        except (ValueError, OSError):  # not the main interpreter, or no such signal
            pass
    try:
        yield
    finally:
        for signum, handler in old.items():
            signal.signal(signum, handler)
        for signum in caught[:1]:
            handler = old.get(signum)
            if callable(handler):
                handler(signum, None)
            elif handler == signal.SIG_DFL:
                signal.raise_signal(signum)


# --- one MCAP file ---------------------------------------------------------------------------


class McapFile:
    """One MCAP file written in boxloc's layout: channels from :mod:`recorder.mcap.channels`
    (or copied from another log), explicit chunk boundaries, flush + fsync per commit.

    Parameters
    ----------
    path : Path
        Where the file is (for messages; the stream is already open).
    stream : binary file object
        Opened for writing; closed by :meth:`finish` / :meth:`abandon`.
    library : str
        The MCAP header's library string.
    fsync : bool
        fsync the file after each commit.
    """

    def __init__(self, path: Path, stream: IO[bytes], *, library: str, fsync: bool = True,
                 profile: str = C.PROFILE) -> None:
        self.path = path
        self.stream = stream
        self.fsync = fsync
        self.writer = ZstdLevelWriter(stream, chunk_size=_NO_AUTO_CHUNK,
                                      compression=CompressionType.ZSTD)
        self.schema_ids: dict[tuple[str, str, bytes], int] = {}
        self.channel_ids: dict[str, int] = {}
        self.channel_schemas: dict[str, str] = {}
        self.finished = False
        self.n_messages = 0
        self.writer.start(profile=profile, library=library)

    def channel(self, topic: str, *, schema_name: str, schema_encoding: str,
                schema_data: bytes, message_encoding: str,
                metadata: dict[str, str] | None = None) -> int:
        """The channel id of ``topic``, registering schema and channel the first time.

        Raises
        ------
        ValueError
            If ``topic`` was registered with another schema (one type per topic).
        """
        cid = self.channel_ids.get(topic)
        if cid is not None:
            if self.channel_schemas[topic] != schema_name:
                raise ValueError(f"topic {topic!r} has schema {self.channel_schemas[topic]!r}, "
                                 f"cannot write a {schema_name!r}")
            return cid
        key = (schema_name, schema_encoding, schema_data)
        sid = self.schema_ids.get(key)
        if sid is None:
            sid = self.writer.register_schema(schema_name, schema_encoding, schema_data)
            self.schema_ids[key] = sid
        cid = self.writer.register_channel(topic, message_encoding, sid, dict(metadata or {}))
        self.channel_ids[topic] = cid
        self.channel_schemas[topic] = schema_name
        return cid

    def spec_channel(self, topic: str) -> int:
        s = C.spec(topic)
        return self.channel(topic, schema_name=s.schema_name, schema_encoding=s.schema_encoding,
                            schema_data=s.schema_data(), message_encoding=s.message_encoding,
                            metadata=s.channel_metadata())

    def add(self, channel_id: int, log_time: int, data: bytes, *, publish_time: int | None = None,
            sequence: int = 0) -> None:
        self.n_messages += 1
        self.writer.add_message(channel_id=channel_id, log_time=log_time, data=data,
                                publish_time=log_time if publish_time is None else publish_time,
                                sequence=sequence & 0xFFFFFFFF)

    def commit(self) -> None:
        """Close the current chunk, write it, flush and fsync: everything so far is durable."""
        self.writer.flush()
        self.sync()

    def sync(self) -> None:
        self.stream.flush()
        if self.fsync:
            fileno = getattr(self.stream, "fileno", None)
            if fileno is not None:
                try:
                    fd = fileno()
                except (OSError, io.UnsupportedOperation):
                    return
                os.fsync(fd)

    @property
    def size(self) -> int:
        return int(self.stream.tell())

    def finish(self) -> None:
        """Write the summary section and the footer, fsync and close. Idempotent."""
        if self.finished:
            return
        self.finished = True
        if self.n_messages == 0 and hasattr(self.writer, "_Writer__use_summary_offsets"):
            # The mcap writer indexes empty schema/channel/chunk groups with summary offsets
            # that point at nothing, which strict checkers reject; a log without messages
            # (metadata and attachments only) is valid without summary offsets.
            self.writer._Writer__use_summary_offsets = False
        self.writer.finish()
        self.sync()
        self.stream.close()

    def abandon(self) -> None:
        """Close without writing anything more (after a write error)."""
        self.finished = True
        with contextlib.suppress(Exception):
            self.stream.close()


def _fsync_dir(path: Path) -> None:
    """Make a new file's directory entry durable (best effort: not every FS allows it)."""
    try:
        fd = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


# --- the recorder ----------------------------------------------------------------------------


@dataclass
class _Pending:
    """The messages of the scan in progress, written when it ends."""

    scan: Scan
    log_time: int
    config: Config
    sensor_hash: str
    messages: list[tuple[str, bytes]] = field(default_factory=list)
    products: dict[str, Any] = field(default_factory=dict)
    last_stage: str = "scan"
    record_s: float = 0.0
    #: the Result's ambiguous regions (on_result); None until then
    ambiguous: Any = None

    def encoded(self) -> EncodedScan:
        """The scan's messages as they are now, without its products."""
        n_surf = len(self.products["surfaces"]) if "surfaces" in self.products else 0
        return EncodedScan(index=self.scan.index, capture_time_ns=self.scan.capture_time_ns,
                           sensor=self.scan.sensor, log_time=self.log_time, config=self.config,
                           sensor_hash=self.sensor_hash, messages=tuple(self.messages),
                           n_surfaces=n_surf, encode_s=self.record_s)


@dataclass(frozen=True)
class EncodedScan:
    """One scan's messages, encoded, in the order the recorder writes them as one chunk.

    Made by a :class:`ScanEncoder` (the recorder's own, or one in a worker process of
    ``boxloc run --workers N``) and written by :meth:`McapRecorder.write_encoded`. It holds
    bytes and a few scalars, not the products: cheap to send between processes.

    Attributes
    ----------
    index, capture_time_ns : int
        The scan's index and capture time, ns.
    sensor : SensorModel
        The scan's sensor (its ``/scan/sensor`` record and the calibration attachments are
        written by the recorder, once per file).
    log_time : int
        The scan's log time, ns (:func:`recorder.mcap.channels.scan_log_time`).
    config : Config
        The config the scan ran with (one config per file).
    sensor_hash : str
    messages : tuple of (str, bytes)
        Topic and encoded message, in order; the last one is ``/boxloc/result`` or
        ``/boxloc/error``.
    n_surfaces : int
    encode_s : float
        Wall time spent encoding, s (what ``/boxloc/timing`` reports as the recorder's).
    """

    index: int
    capture_time_ns: int
    sensor: SensorModel
    log_time: int
    config: Config
    sensor_hash: str
    messages: tuple[tuple[str, bytes], ...]
    n_surfaces: int
    encode_s: float


class ScanEncoder(NullObserver):
    """Encode the pipeline's calls about each scan into the messages the recorder writes:
    the pure half of :class:`McapRecorder` (no file, no clock but the timing it reports).

    When a scan ends (``on_result``, ``on_error``, or the next ``on_scan`` without either)
    its messages go to ``emit`` as one :class:`EncodedScan`. :class:`McapRecorder` writes
    what its own encoder emits; ``boxloc run --workers N`` runs one in each worker process
    and its parent writes what they emit, in scan order, with
    :meth:`McapRecorder.write_encoded`. The same code makes the bytes either way.

    Parameters
    ----------
    emit : callable
        ``emit(encoded)``, once per scan, in the order the scans end.
    max_points : int
        Points of the decimated ``/scan/points`` view (0: no point cloud).
    config : Config, optional
        The config of a scan that ends in ``on_error`` without an ``on_scan`` first.
    lock : RLock, optional
        Held while the scan in progress is handed over (the recorder's:
        :meth:`McapRecorder.record_outcome` adds to that scan from other threads).
    """

    def __init__(self, emit: Callable[[EncodedScan], None], *,
                 max_points: int = DEFAULT_MAX_POINTS, config: Config | None = None,
                 lock: Any = None) -> None:
        self.emit = emit
        self.max_points = int(max_points)
        self.config = config
        self.lock = lock if lock is not None else threading.RLock()
        self.pending: _Pending | None = None

    def on_scan(self, scan: Scan, config: Config) -> None:
        t0 = time.perf_counter()
        if self.pending is not None:
            # The previous scan never got its result: the pipeline raised and nobody told us.
            self.end(self.pending, error=("Incomplete", self.pending.last_stage,
                                          "the pipeline did not finish this scan"))
        t = C.scan_log_time(scan.capture_time_ns, scan.index)
        digest = E.sensor_hash(scan.sensor)
        p = _Pending(scan=scan, log_time=t, config=config, sensor_hash=digest)
        self.pending = p
        p.messages.append((C.SCAN_INFO, E.encode_scan_info(scan, digest)))
        p.messages.append((C.SCAN_RANGE, E.encode_range(scan, t)))
        p.messages.append((C.SCAN_PREVIEW, E.encode_range_preview(scan, t)))
        if isinstance(scan.sensor, PinholeModel):
            p.messages.append((C.SCAN_CALIBRATION, E.encode_calibration(scan.sensor, t)))
        if scan.sensor_to_base is not None:
            p.messages.append((C.SCAN_POSE, E.encode_pose(scan.sensor_to_base, t)))
        if self.max_points > 0:
            p.messages.append((C.SCAN_POINTS, E.encode_points(scan, t, self.max_points)))
        p.record_s += time.perf_counter() - t0

    def _pending_for(self, scan: Scan, what: str) -> _Pending:
        p = self.pending
        if p is None or p.scan is not scan:
            raise ValueError(f"on_{what} for scan {scan.index} without on_scan first")
        return p

    def stage(self, stage: str, scan: Scan, product: Any) -> None:
        """Encode one stage's product (``on_<stage>``)."""
        t0 = time.perf_counter()
        p = self._pending_for(scan, stage)
        p.products[stage] = product
        p.last_stage = stage
        p.messages.append((C.STAGE_TOPICS[stage],
                           E.encode_product(stage, product, scan.index, scan.capture_time_ns)))
        if stage == "edges":
            p.messages.append((C.EDGE_MAP, E.encode_edge_map(product, p.log_time)))
            p.messages.append((C.EDGE_POINTS, E.encode_edge_points(product, p.log_time)))
        p.record_s += time.perf_counter() - t0

    def on_noise(self, scan: Scan, noise: Any) -> None:
        self.stage("noise", scan, noise)

    def on_edges(self, scan: Scan, edges: Any) -> None:
        self.stage("edges", scan, edges)

    def on_lines(self, scan: Scan, lines: Any) -> None:
        self.stage("lines", scan, lines)

    def on_vertices(self, scan: Scan, vertices: Any) -> None:
        self.stage("vertices", scan, vertices)

    def on_hypotheses(self, scan: Scan, hypotheses: Any) -> None:
        self.stage("hypotheses", scan, hypotheses)

    def on_verification(self, scan: Scan, verification: Any) -> None:
        self.stage("verification", scan, verification)

    def on_selection(self, scan: Scan, selection: Any) -> None:
        self.stage("selection", scan, selection)

    def on_surfaces(self, scan: Scan, surfaces: Any) -> None:
        self.stage("surfaces", scan, surfaces)

    def on_result(self, scan: Scan, result: Any) -> None:
        t0 = time.perf_counter()
        p = self._pending_for(scan, "result")
        missing = [s for s in STAGES
                   if s not in p.products and getattr(result, s) is not None]
        for s in missing:  # a caller that skipped on_<stage>: the Result has them all
            self.stage(s, scan, getattr(result, s))
        amb = getattr(result, "ambiguous", None)
        if amb is not None:  # written even when empty: the set reads back bit for bit
            p.ambiguous = amb
            p.messages.append((C.AMBIGUOUS, E.encode_ambiguous(amb, scan.index,
                                                               scan.capture_time_ns)))
        p.record_s += time.perf_counter() - t0
        self.end(p, result=result)

    def on_error(self, scan: Scan, exc: BaseException, stage: str | None = None) -> None:
        """End the scan in progress as failed: its products so far and the error.

        Parameters
        ----------
        scan : Scan
        exc : BaseException
            What the pipeline raised.
        stage : str, optional
            The stage that raised; default: the one after the last product received.
        """
        with self.lock:
            p = self.pending
            if p is None or p.scan is not scan:
                self.on_scan(scan, self.config or Config())
                p = self.pending
            assert p is not None
            if stage is None:
                # the stage after the last product received
                nxt = max((STAGES.index(s) + 1 for s in p.products), default=0)
                stage = STAGES[nxt] if nxt < len(STAGES) else "result"
            msg = str(exc).splitlines()[0] if str(exc) else ""
            self.end(p, error=(type(exc).__name__, stage, msg[:2000]))

    def end(self, p: _Pending, *, result: Any = None,
            error: tuple[str, str, str] | None = None) -> None:
        """Add the end-of-scan messages to scan ``p`` and emit it.

        The last message of a scan is its ``/boxloc/result`` or ``/boxloc/error``: a
        reader knows a scan is whole when it sees one.
        """
        with self.lock:  # a pick outcome reported now goes in this chunk or the next
            if self.pending is p:
                self.pending = None
        t0 = time.perf_counter()
        idx, t = p.scan.index, p.log_time
        tables = {s: p.products[s].tests for s in STAGES
                  if s in p.products and hasattr(p.products[s], "tests")}
        if p.ambiguous is not None:
            tables[E.AMBIGUOUS_STAGE] = p.ambiguous.tests
        if "surfaces" in p.products:  # written here: the ambiguous regions come with the result
            p.messages.append((C.LOCATE, E.encode_locate_json(idx, p.products["surfaces"],
                                                              p.ambiguous)))
        p.messages.append((C.TESTS, E.encode_test_rows(idx, tables)))
        p.messages.append((C.SCENE, E.encode_scene({**p.products, "ambiguous": p.ambiguous},
                                                   idx, t)))
        timing = dict(result.timing_ms) if result is not None else {}
        p.record_s += time.perf_counter() - t0
        p.messages.append((C.TIMING, E.encode_timing(idx, timing, p.record_s * 1e3)))
        if result is not None:
            p.messages.append((C.RESULT, E.encode_result_info(result)))
        else:
            etype, stage, msg = error or ("Incomplete", p.last_stage, "")
            p.messages.append((C.ERROR, E.encode_error(idx, stage, etype, msg)))
        self.emit(p.encoded())


@dataclass
class _Part:
    file: McapFile
    index: int
    config_hash: str
    sensor_hash: str | None = None
    n_scans: int = 0
    first_log_time: int | None = None
    last_log_time: int = 0


@dataclass(frozen=True)
class ScanWritten:
    """Where a recorded scan went (for pick outcomes and reports)."""

    index: int
    path: Path
    log_time: int
    n_surfaces: int


Opener = Callable[[Path], IO[bytes]]


class McapRecorder(NullObserver):
    """Record every scan and product of the pipeline to MCAP.

    Parameters
    ----------
    target : str or Path
        A file ``NAME.mcap`` (rotated parts are ``NAME-001.mcap``, ...), or a directory
        (created if needed) that receives ``<session>-000.mcap``, ``-001``, ...
    config : Config, optional
        Written as provenance if no scan ever arrives; otherwise each scan's config is.
    rotate_bytes : int, optional
        Start a new file once the current one reaches this size, bytes.
    rotate_seconds : float, optional
        Start a new file when a scan's log time is this far past the file's first scan.
    overwrite : bool
        Replace existing files (by default an existing file is never touched).
    session : str, optional
        Session name (file names in a directory; the ``session`` metadata); default
        ``boxloc-<UTC time>-<random>``.
    max_points : int
        Points of the decimated ``/scan/points`` view (0: no point cloud).
    fsync : bool
        fsync after each scan (turn off only for benchmarks of the encoder).
    opener : callable, optional
        ``opener(path) -> binary file``; for tests that simulate a full disk.
    extra_metadata : dict, optional
        More metadata records for every file, ``{name: {key: value}}`` (strings), written
        after ``boxloc.run`` (e.g. ``boxloc.replay``: what a replayed log was made from).
    attachments : dict, optional
        More attachments for every file, ``{name: (media type, bytes)}``, written once per
        file after the config and the calibration (e.g. :data:`recorder.mcap.channels.
        BOX_SIZES_ATTACHMENT`: the ``--box-sizes`` file as it was given).

    Notes
    -----
    Thread safety: the pipeline calls the ``on_*`` methods from one thread;
    :meth:`record_outcome` may be called from any thread.
    """

    def __init__(
        self,
        target: str | os.PathLike[str],
        *,
        config: Config | None = None,
        rotate_bytes: int | None = None,
        rotate_seconds: float | None = None,
        overwrite: bool = False,
        session: str | None = None,
        max_points: int = DEFAULT_MAX_POINTS,
        fsync: bool = True,
        opener: Opener | None = None,
        extra_metadata: dict[str, dict[str, str]] | None = None,
        attachments: dict[str, tuple[str, bytes]] | None = None,
    ) -> None:
        t = Path(target)
        self._dir_mode = t.suffix.lower() != ".mcap"
        if rotate_bytes is not None and rotate_bytes <= 0:
            raise InputError(f"rotate_bytes must be > 0, got {rotate_bytes}")
        if rotate_seconds is not None and rotate_seconds <= 0:
            raise InputError(f"rotate_seconds must be > 0, got {rotate_seconds}")
        self.target = t
        self.session = session or (
            f"boxloc-{datetime.now(UTC).strftime('%Y%m%dT%H%M%SZ')}-{secrets.token_hex(2)}")
        self.config = config
        self.rotate_bytes = rotate_bytes
        self.rotate_ns = None if rotate_seconds is None else int(rotate_seconds * 1e9)
        self.overwrite = overwrite
        self.max_points = int(max_points)
        self.fsync = fsync
        self._opener = opener
        self.extra_metadata = {str(k): {str(kk): str(vv) for kk, vv in v.items()}
                               for k, v in (extra_metadata or {}).items()}
        fixed = {C.CONFIG_ATTACHMENT, C.CALIBRATION_ATTACHMENT, C.RAYTABLE_ATTACHMENT}
        for name, (_media, data) in (attachments or {}).items():
            if name in fixed or not isinstance(data, bytes | bytearray):
                raise ValueError(f"attachment {name!r}: a name of the recorder's own, or not "
                                 "bytes")
        self.attachments = {str(k): (str(m), bytes(d)) for k, (m, d) in
                            (attachments or {}).items()}
        self._lock = threading.RLock()
        self._part: _Part | None = None
        self._n_parts = 0
        self._enc = ScanEncoder(self._write_scan, max_points=self.max_points, config=config,
                                lock=self._lock)
        self._broken: str | None = None
        self._finished = False
        self.paths: list[Path] = []
        self.scans: list[ScanWritten] = []
        self._by_index: dict[int, ScanWritten] = {}
        #: seconds spent in the recorder (encoding + writing), for overhead reports
        self.record_seconds = 0.0
        if self._dir_mode:
            if t.exists() and not t.is_dir():
                raise InputError(f"--record {t}: not a directory (name a file NAME.mcap)")
        else:
            if t.exists() and not overwrite:
                raise InputError(f"{t} exists; refusing to overwrite a log (pick another name)")
            if not t.parent.exists():
                raise InputError(f"directory {t.parent} does not exist")

    # --- context manager -------------------------------------------------------------------

    def __enter__(self) -> McapRecorder:
        return self

    def __exit__(self, exc_type: object, exc: BaseException | None, tb: object) -> None:
        p = self._pending
        if exc is not None and p is not None and self._broken is None \
                and not isinstance(exc, RecordingError):
            # The scan in progress ends with what stopped it (a bug, Ctrl-C, ...).
            with contextlib.suppress(Exception):
                self.on_error(p.scan, exc)
        self.finish()

    # --- observer --------------------------------------------------------------------------
    # The messages are made by self._enc (a ScanEncoder, the same code a worker of
    # `boxloc run --workers N` encodes with); it hands each scan to _write_scan.

    @property
    def _pending(self) -> _Pending | None:
        return self._enc.pending

    def on_scan(self, scan: Scan, config: Config) -> None:
        self._check_open()
        self._enc.on_scan(scan, config)

    def _stage(self, stage: str, scan: Scan, product: Any) -> None:
        self._check_open()
        self._enc.stage(stage, scan, product)

    def on_noise(self, scan: Scan, noise: Any) -> None:
        self._stage("noise", scan, noise)

    def on_edges(self, scan: Scan, edges: Any) -> None:
        self._stage("edges", scan, edges)

    def on_lines(self, scan: Scan, lines: Any) -> None:
        self._stage("lines", scan, lines)

    def on_vertices(self, scan: Scan, vertices: Any) -> None:
        self._stage("vertices", scan, vertices)

    def on_hypotheses(self, scan: Scan, hypotheses: Any) -> None:
        self._stage("hypotheses", scan, hypotheses)

    def on_verification(self, scan: Scan, verification: Any) -> None:
        self._stage("verification", scan, verification)

    def on_selection(self, scan: Scan, selection: Any) -> None:
        self._stage("selection", scan, selection)

    def on_surfaces(self, scan: Scan, surfaces: Any) -> None:
        self._stage("surfaces", scan, surfaces)

    def on_result(self, scan: Scan, result: Any) -> None:
        self._check_open()
        self._enc.on_result(scan, result)

    def on_error(self, scan: Scan, exc: BaseException, stage: str | None = None) -> None:
        """Close the scan in progress as failed: its products so far and the error.

        Parameters
        ----------
        scan : Scan
        exc : BaseException
            What the pipeline raised.
        stage : str, optional
            The stage that raised; default: the one after the last product received.
        """
        with self._lock:
            self._check_open()
            self._enc.config = self.config
            self._enc.on_error(scan, exc, stage)

    def write_encoded(self, encoded: EncodedScan) -> None:
        """Write a scan a :class:`ScanEncoder` encoded elsewhere (a worker process), as if
        it had been recorded here: the same bytes, one chunk, flushed and fsynced.

        Raises
        ------
        ValueError
            If this recorder has a scan of its own in progress (the order would mix).
        RecordingError
            If the log cannot be written.
        """
        with self._lock:
            self._check_open()
            if self._enc.pending is not None:
                raise ValueError(f"scan {self._enc.pending.scan.index} is in progress; "
                                 f"cannot write scan {encoded.index} before it ends")
            self._write_scan(encoded)

    # --- scans without a pipeline run ------------------------------------------------------

    def record_scan(self, scan: Scan, config: Config | None = None, *,
                    labels: np.ndarray | None = None, origin: str = "import") -> ScanWritten:
        """Record a scan without running the pipeline (``boxloc import``), as one chunk.

        The scan's messages are those of :meth:`on_scan` (range bit for bit, sensor model,
        pose, views), then its ``labels`` if given (``/scan/labels``), closed by a
        ``/scan/end`` record instead of a result: readers yield it as a whole scan with
        ``scan_only`` set, and ``boxloc run LOG.mcap`` runs the pipeline on it later.

        Parameters
        ----------
        scan : Scan
        config : Config, optional
            The config stored as the log's provenance (what ``boxloc run LOG.mcap`` will use
            unless given another); default the recorder's, else ``Config()``.
        labels : ndarray, shape (H, W), int, optional
            Per-pixel segment labels that came with the scan (e.g. mOSD ground truth).
        origin : str
            What recorded the scan, stored in the end record.

        Raises
        ------
        InputError
            If ``labels`` does not have the scan's shape or is not an integer array.
        """
        if labels is not None:
            lab = np.asarray(labels)
            if lab.shape != scan.shape or lab.dtype.kind not in "iu":
                raise InputError(f"labels must be an integer array of the scan's shape "
                                 f"{scan.shape}, got {lab.dtype} {lab.shape}")
        with self._lock:
            self.on_scan(scan, config or self.config or Config())
            p = self._enc.pending
            assert p is not None
            self._enc.pending = None
            if labels is not None:
                p.messages.append((C.SCAN_LABELS, E.encode_labels(lab, scan.index,
                                                                  scan.capture_time_ns)))
            p.messages.append((C.SCAN_END, E.encode_scan_end(scan.index, scan.capture_time_ns,
                                                             origin)))
            self._write_scan(p.encoded())
            return self.scans[-1]

    # --- pick outcomes ---------------------------------------------------------------------

    def record_outcome(self, scan_index: int, surface_id: int, ok: bool, reason: str = "", *,
                       source: str = "robot") -> E.PickOutcome:
        """Record whether the robot picked surface ``surface_id`` of scan ``scan_index``.

        While a scan is being recorded (the usual case: the robot reports on scan N while
        the pipeline works on scan N + 1), the outcome is written on the log's
        ``/pick/outcome`` channel with that scan's chunk. Otherwise (between scans, or for
        a scan in an earlier, closed file of the session) it is appended at once to the
        log's sidecar (see :mod:`recorder.annotate`). Either way it is durable once the
        scan resp. the call returns, and every reader merges both.

        Raises
        ------
        InputError
            If this recorder did not record that scan, or it has no such surface.
        """
        from recorder import annotate

        outcome = E.PickOutcome(scan_index=int(scan_index), surface_id=int(surface_id),
                                ok=bool(ok), reason=str(reason), source=source,
                                wall_time_ns=time.time_ns(), origin="log")
        with self._lock:
            self._check_open()
            p = self._pending
            if p is not None and p.scan.index == scan_index and "surfaces" in p.products:
                _check_surface(surface_id, len(p.products["surfaces"]), scan_index)
                p.messages.append((C.PICK_OUTCOME, E.encode_outcome(outcome)))
                return outcome
            w = self._by_index.get(int(scan_index))
            if w is None:
                raise InputError(f"scan {scan_index} was not recorded by this recorder")
            _check_surface(surface_id, w.n_surfaces, scan_index)
            part = self._part
            if (p is not None and part is not None and w.path == part.file.path
                    and not self._rotates_before(p)):
                p.messages.append((C.PICK_OUTCOME, E.encode_outcome(outcome)))
                return outcome
        return annotate.append_outcome(w.path, scan_index, surface_id, ok, reason,
                                       source=source, check=False)

    # --- closing ---------------------------------------------------------------------------

    def finish(self) -> None:
        """Write the scan in progress (marked interrupted), the summary and the footer.

        Safe to call more than once; after a write error it only closes the file.
        """
        with self._lock:
            if self._finished:
                return
            self._finished = True
            try:
                p = self._enc.pending
                if p is not None and self._broken is None:
                    self._enc.end(p, error=("Interrupted", p.last_stage,
                                            "recording ended before the scan's result"))
                if self._part is None and not self.paths and self._broken is None \
                        and self.config is not None:
                    # Nothing was recorded: still leave a valid log with its provenance.
                    self._open_part(self.config, None, 0)
            finally:
                self._enc.pending = None
                self._close_part()

    close = finish

    @property
    def n_scans(self) -> int:
        return len(self.scans)

    # --- internals -------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._broken is not None:
            raise RecordingError(f"the recorder stopped after an error: {self._broken}")
        if self._finished:
            raise RecordingError("the recorder is finished")

    def _write_scan(self, enc: EncodedScan) -> None:
        """Write one scan's messages as one chunk (after the sensor record, when the file
        has not had this sensor yet); flush and fsync."""
        t0 = time.perf_counter()
        try:
            with self._lock, defer_signals():
                self._check_broken()
                part = self._part_for(enc)
                f = part.file
                try:
                    if part.sensor_hash != enc.sensor_hash:
                        f.add(f.spec_channel(C.SCAN_SENSOR), enc.log_time,
                              E.encode_sensor(enc.sensor, enc.index, enc.capture_time_ns),
                              sequence=enc.index)
                        part.sensor_hash = enc.sensor_hash
                    for topic, data in enc.messages:
                        f.add(f.spec_channel(topic), enc.log_time, data, sequence=enc.index)
                    f.commit()
                except OSError as e:
                    self._fail(part, e)
                part.n_scans += 1
                if part.first_log_time is None:
                    part.first_log_time = enc.log_time
                part.last_log_time = max(part.last_log_time, enc.log_time)
                w = ScanWritten(index=enc.index, path=f.path, log_time=enc.log_time,
                                n_surfaces=enc.n_surfaces)
                self.scans.append(w)
                self._by_index[w.index] = w
                if self.rotate_bytes is not None and f.size >= self.rotate_bytes:
                    self._close_part()
        finally:
            self.record_seconds += enc.encode_s + (time.perf_counter() - t0)

    def _check_broken(self) -> None:
        if self._broken is not None:
            raise RecordingError(f"the recorder stopped after an error: {self._broken}")

    def _rotates_before(self, p: _Pending | EncodedScan) -> bool:
        """Whether scan ``p`` will start a new file (log-time span, or a new config)."""
        part = self._part
        if part is None:
            return True
        too_long = (self.rotate_ns is not None and part.first_log_time is not None
                    and p.log_time - part.first_log_time >= self.rotate_ns)
        return too_long or part.config_hash != p.config.hash

    def _part_for(self, p: EncodedScan) -> _Part:
        part = self._part
        if part is not None and self._rotates_before(p):
            self._close_part()
            part = None
        if part is None:
            part = self._open_part(p.config, p.sensor, p.log_time)
        return part

    def _path(self, k: int) -> Path:
        if self._dir_mode:
            return self.target / f"{self.session}-{k:03d}.mcap"
        if k == 0:
            return self.target
        return self.target.with_name(f"{self.target.stem}-{k:03d}.mcap")

    def _open_stream(self, path: Path) -> IO[bytes]:
        if self._opener is not None:
            return self._opener(path)
        try:
            return open(path, "wb" if self.overwrite else "xb")
        except FileExistsError:
            raise InputError(f"{path} exists; refusing to overwrite a log") from None

    def _open_part(self, config: Config, sensor: SensorModel | None, log_time: int) -> _Part:
        k = self._n_parts
        path = self._path(k)
        if self._dir_mode:
            path.parent.mkdir(parents=True, exist_ok=True)
        stream = self._open_stream(path)
        self._n_parts += 1
        self.paths.append(path)
        library = f"boxloc-recorder/{boxloc.__version__} {LIBRARY_IDENTIFIER}"
        f = McapFile(path, stream, library=library, fsync=self.fsync)
        part = _Part(file=f, index=k, config_hash=config.hash)
        self._part = part
        try:
            f.writer.add_metadata(C.RUN_METADATA, provenance(config, sensor, self.session, k))
            for name, md in self.extra_metadata.items():
                f.writer.add_metadata(name, md)
            f.writer.add_attachment(log_time, log_time, C.CONFIG_ATTACHMENT, "application/toml",
                                    config.to_toml().encode())
            if sensor is not None:
                f.writer.add_attachment(log_time, log_time, C.CALIBRATION_ATTACHMENT,
                                        "application/json", _calibration_json(sensor))
                if isinstance(sensor, RayTableModel):
                    f.writer.add_attachment(log_time, log_time, C.RAYTABLE_ATTACHMENT,
                                            "application/x-npy", _npy_bytes(sensor.table))
            for name, (media, data) in self.attachments.items():
                f.writer.add_attachment(log_time, log_time, name, media, data)
            f.sync()
        except OSError as e:
            self._fail(part, e)
        _fsync_dir(path)
        return part

    def _close_part(self) -> None:
        part, self._part = self._part, None
        if part is None or part.file.finished:
            return
        if self._broken is not None:
            part.file.abandon()
            return
        with defer_signals():
            try:
                part.file.finish()
            except OSError as e:
                self._fail(part, e)

    def _fail(self, part: _Part, e: OSError) -> None:
        """A write failed: close the file as it is and explain what is left."""
        part.file.abandon()
        if self._part is part:
            self._part = None
        n = part.n_scans
        what = ("no space left on device" if e.errno == errno.ENOSPC
                else (e.strerror or str(e)).lower())
        self._broken = f"{what} writing {part.file.path}"
        raise RecordingError(
            f"cannot write {part.file.path}: {what}; the {n} scan(s) written before are "
            f"recoverable with `boxloc recover {part.file.path}`"
        ) from e


def _check_surface(surface_id: int, n: int, scan_index: int) -> None:
    if not 0 <= int(surface_id) < n:
        raise InputError(
            f"scan {scan_index} has {n} surface(s); no surface {surface_id}"
            + (" (ids are 0-based)" if n else ""))

"""Reading boxloc logs: scans bit for bit, products, provenance, pick outcomes.

>>> log = open_log("logs/sample.mcap")                              # doctest: +SKIP
>>> log.config.alpha, log.run["git_commit"]                         # doctest: +SKIP
>>> for rec in log:                                                 # doctest: +SKIP
...     rec.scan            # the recorded Scan: range, sensor model, pose, time, index
...     rec.products        # {"edges": EdgeMap, ..., "surfaces": SurfaceSet}
...     rec.result          # a Result equal to the recorded one (timing aside)

Records are read in file order with a record scanner of our own, which treats the file as
untrusted: every record and chunk is bounded (:class:`recorder.mcap.encode.DecodeLimits`), chunk
CRCs are checked, and a truncated or damaged file ends the data cleanly at the last good
record (``allow_truncated=True``) instead of raising half-way. A log without a summary (a
recorder that was killed) is refused unless ``allow_truncated`` is set; ``boxloc recover``
rebuilds a complete one.
"""

from __future__ import annotations

import io
import os
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import (
    Attachment,
    Channel,
    Chunk,
    DataEnd,
    Footer,
    Header,
    Message,
    Metadata,
    Schema,
)
from mcap.stream_reader import breakup_chunk
from mcap.summary import Summary

from boxloc.config import Config
from boxloc.errors import LogError
from boxloc.products import OPTIONAL_STAGES, STAGES, AmbiguousSet, Result
from boxloc.scan import Scan, SensorModel
from boxloc.stats import TestTable
from recorder.annotate import latest_outcomes, read_sidecar
from recorder.mcap import channels as C
from recorder.mcap import encode as E
from recorder.mcap.encode import DEFAULT_LIMITS, DecodeLimits, PickOutcome

_MAGIC = b"\x89MCAP0\r\n"


# --- the record scanner ----------------------------------------------------------------------


@dataclass
class LogMessage:
    """One message as stored: ``topic``, times (ns), ``sequence`` and raw ``data``."""

    topic: str
    log_time: int
    publish_time: int
    sequence: int
    data: bytes
    channel: Channel
    schema: Schema | None


@dataclass
class ScanState:
    """What a scan of the records found: where good data ends and why."""

    end_offset: int = 0
    complete_data: bool = False
    damage: list[str] = field(default_factory=list)
    truncated: str | None = None
    chunks: int = 0
    skipped_chunks: int = 0


_READERS = {
    Opcode.HEADER: Header.read,
    Opcode.SCHEMA: Schema.read,
    Opcode.CHANNEL: Channel.read,
    Opcode.CHUNK: Chunk.read,
    Opcode.METADATA: Metadata.read,
    Opcode.ATTACHMENT: Attachment.read,
    Opcode.DATA_END: DataEnd.read,
    Opcode.FOOTER: Footer.read,
}


def scan_records(
    f: IO[bytes],
    state: ScanState,
    limits: DecodeLimits = DEFAULT_LIMITS,
    *,
    want_chunk: Any = None,
) -> Iterator[tuple[int, Any]]:
    """Yield ``(offset, record)`` of the data section in file order, chunks opened.

    Stops at the end of the data section, at a truncation, or at a record whose framing
    is broken; ``state`` says which. A chunk that fails its CRC or does not decompress is
    skipped (its framing is intact) and noted in ``state.damage``.

    Parameters
    ----------
    want_chunk : callable, optional
        ``want_chunk(offset) -> bool``; chunks it rejects are not decompressed.
    """
    head = f.read(len(_MAGIC))
    if head != _MAGIC:
        raise LogError("not an MCAP file (bad magic)")
    size = _file_size(f)
    off = len(_MAGIC)
    state.end_offset = off
    while True:
        hdr = f.read(9)
        if len(hdr) < 9:
            state.truncated = f"file ends at byte {off + len(hdr)} inside the data section"
            return
        opcode, length = struct.unpack("<BQ", hdr)
        if length > limits.max_record_bytes:
            state.truncated = f"record at byte {off} claims {length} bytes (corrupt)"
            return
        if size is not None and off + 9 + length > size:
            # Checked before reading: a corrupt length must not make us allocate it.
            state.truncated = (f"file ends at byte {size} inside a record of {length} bytes "
                               f"starting at byte {off}")
            return
        body = f.read(length)
        if len(body) < length:
            state.truncated = (f"file ends at byte {off + 9 + len(body)} inside a record of "
                               f"{length} bytes starting at byte {off}")
            return
        rec_off, off = off, off + 9 + length
        reader = _READERS.get(opcode)
        if reader is None and opcode != Opcode.MESSAGE:
            # message indexes and unknown records: nothing we need
            state.end_offset = off
            continue
        try:
            # no reader: a message (the other records without one were skipped above)
            rec: Any = (Message.read(ReadDataStream(io.BytesIO(body)), length)
                        if reader is None else reader(ReadDataStream(io.BytesIO(body))))
        except Exception as e:  # noqa: BLE001 - the mcap readers raise many kinds
            why = str(e)[:200] or type(e).__name__
            state.truncated = f"record at byte {rec_off} is malformed: {why}"
            return
        if isinstance(rec, Attachment) and not _attachment_crc_ok(body):
            state.damage.append(f"attachment {rec.name!r} at byte {rec_off} fails its CRC")
            state.end_offset = off
            continue
        if isinstance(rec, Chunk):
            state.chunks += 1
            if want_chunk is not None and not want_chunk(rec_off):
                state.end_offset = off
                continue
            inner = _open_chunk(rec, rec_off, state, limits)
            state.end_offset = off
            for r in inner:
                yield rec_off, r
            continue
        state.end_offset = off
        if isinstance(rec, DataEnd | Footer):
            state.complete_data = True
            return
        yield rec_off, rec


def _file_size(f: IO[bytes]) -> int | None:
    """Size of the file behind ``f`` (None for a stream without one)."""
    try:
        return os.fstat(f.fileno()).st_size
    except (OSError, AttributeError, ValueError, io.UnsupportedOperation):
        return None


def _attachment_crc_ok(body: bytes) -> bool:
    if len(body) < 4:
        return False
    (crc,) = struct.unpack("<I", body[-4:])
    return crc == 0 or crc == zlib.crc32(body[:-4])


def _open_chunk(chunk: Chunk, offset: int, state: ScanState,
                limits: DecodeLimits) -> list[Any]:
    if chunk.uncompressed_size > limits.max_record_bytes:
        state.damage.append(f"chunk at byte {offset} claims {chunk.uncompressed_size} bytes")
        state.skipped_chunks += 1
        return []
    try:
        return breakup_chunk(chunk, validate_crc=True)
    except Exception as e:  # CRC, zstd, or a malformed inner record
        state.damage.append(f"chunk at byte {offset} is damaged: {str(e)[:200]}")
        state.skipped_chunks += 1
        return []


def iter_messages(
    f: IO[bytes],
    state: ScanState,
    limits: DecodeLimits = DEFAULT_LIMITS,
    *,
    summary: Summary | None = None,
    topics: set[str] | None = None,
) -> Iterator[LogMessage]:
    """Messages in file order; with a summary, chunks without wanted topics are skipped."""
    schemas: dict[int, Schema] = dict(summary.schemas) if summary else {}
    channels: dict[int, Channel] = dict(summary.channels) if summary else {}
    want_chunk = None
    if summary is not None and topics is not None:
        wanted_ids = {cid for cid, ch in summary.channels.items() if ch.topic in topics}
        keep = {ci.chunk_start_offset for ci in summary.chunk_indexes
                if wanted_ids & set(ci.message_index_offsets)}
        want_chunk = keep.__contains__
    for _, rec in scan_records(f, state, limits, want_chunk=want_chunk):
        if isinstance(rec, Schema):
            schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            channels[rec.id] = rec
        elif isinstance(rec, Message):
            ch = channels.get(rec.channel_id)
            if ch is None:
                state.damage.append(f"message on unknown channel {rec.channel_id}")
                continue
            if topics is not None and ch.topic not in topics:
                continue
            yield LogMessage(ch.topic, rec.log_time, rec.publish_time, rec.sequence, rec.data,
                             ch, schemas.get(ch.schema_id))


# --- records of a scan -----------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ScanRecord:
    """One recorded scan and everything the pipeline made of it.

    Attributes
    ----------
    scan : Scan
        The scan as recorded: range bit for bit, sensor model (ray table included), pose,
        capture time, index, source.
    log_time_ns : int
    products : dict
        ``{stage: product}`` for the stages that ran (all of them unless ``error``), and
        ``"ambiguous"``: the :class:`~boxloc.products.AmbiguousSet` of the result, where the
        log records one (schema 1.5 on; see :attr:`ambiguous`).
    result_info : dict or None
        The Result's own fields (seed, config hash, version); None if the scan failed.
    timing_ms : dict
        Wall-clock ms per stage (never compare these).
    record_ms : float
        Time the recorder spent encoding this scan, ms.
    error : dict or None
        ``{"stage", "error_type", "message"}`` if the pipeline raised or was interrupted.
    labels : ndarray, shape (H, W), int, or None
        Segment labels recorded with the scan (``boxloc import`` of labelled PCD/PLY).
    scan_only : bool
        The scan was recorded without running the pipeline (``boxloc import``): no
        products, no result, and that is not an error.
    """

    scan: Scan
    log_time_ns: int
    products: dict[str, Any]
    result_info: dict[str, Any] | None
    timing_ms: dict[str, float]
    record_ms: float
    error: dict[str, Any] | None
    labels: np.ndarray | None = None
    scan_only: bool = False

    @property
    def index(self) -> int:
        return self.scan.index

    @property
    def complete(self) -> bool:
        return self.result_info is not None and all(
            s in self.products for s in STAGES if s not in OPTIONAL_STAGES)

    @property
    def surfaces(self) -> Any:
        return self.products.get("surfaces")

    @property
    def ambiguous(self) -> AmbiguousSet:
        """The flat regions the run could not split into boxes (an empty set for a log
        written before they were recorded, or a scan that failed before its result)."""
        a = self.products.get(E.AMBIGUOUS_STAGE)
        return a if a is not None else AmbiguousSet()

    @property
    def result(self) -> Result | None:
        """The recorded :class:`Result` (equal to the original with ``products_equal``)."""
        if not self.complete:
            return None
        ri = self.result_info
        assert ri is not None
        products: dict[str, Any] = {s: self.products.get(s) for s in STAGES}
        return Result(scan_index=ri["scan_index"], capture_time_ns=ri["capture_time_ns"],
                      seed=ri["seed"], config_hash=ri["config_hash"], version=ri["version"],
                      timing_ms=dict(self.timing_ms), ambiguous=self.ambiguous,
                      **products)

    @property
    def tests(self) -> dict[str, TestTable]:
        """Every statistical test of the scan, by stage."""
        return {s: p.tests for s, p in self.products.items() if hasattr(p, "tests")}


@dataclass
class _Builder:
    info: E.ScanInfo
    log_time: int
    range_: np.ndarray | None = None
    raw_products: dict[str, bytes] = field(default_factory=dict)
    raw_tests: bytes | None = None
    raw_ambiguous: bytes | None = None
    result_info: dict[str, Any] | None = None
    timing: dict[str, float] = field(default_factory=dict)
    record_ms: float = 0.0
    error: dict[str, Any] | None = None
    labels: np.ndarray | None = None
    scan_only: bool = False

    def build(self, sensors: dict[str, SensorModel], limits: DecodeLimits,
              incomplete: str | None = None) -> ScanRecord:
        i = self.info
        sensor = sensors.get(i.sensor_hash)
        if sensor is None:
            raise LogError(f"scan {i.index} uses sensor model {i.sensor_hash}, which is not "
                           "in the log")
        if self.range_ is None:
            raise LogError(f"scan {i.index} has no range image")
        if self.labels is not None and self.labels.shape != i.shape:
            raise LogError(f"scan {i.index}: labels {self.labels.shape} do not match the scan "
                           f"{i.shape}")
        err = self.error
        if err is None and incomplete:
            err = {"scan_index": i.index, "stage": "", "error_type": "Incomplete",
                   "message": incomplete}
        # Products are decoded last: their tests arrive after them, on /boxloc/tests.
        tests = E.decode_test_columns(self.raw_tests) if self.raw_tests is not None else None
        products = {
            stage: E.decode_product(
                stage, data, None if tests is None else tests.get(stage, E.empty_test_columns()),
                limits)
            for stage, data in self.raw_products.items()}
        if self.raw_ambiguous is not None:
            products[E.AMBIGUOUS_STAGE] = E.decode_ambiguous(
                self.raw_ambiguous, None if tests is None else tests.get(
                    E.AMBIGUOUS_STAGE, E.empty_test_columns()), limits)
        return ScanRecord(scan=E.build_scan(i, self.range_, sensor), log_time_ns=self.log_time,
                          products=products, result_info=self.result_info,
                          timing_ms=self.timing, record_ms=self.record_ms, error=err,
                          labels=self.labels, scan_only=self.scan_only and err is None)


@dataclass(frozen=True)
class ScanSummary:
    """A scan as ``boxloc info`` lists it (nothing large decoded)."""

    index: int
    log_time_ns: int
    n_surfaces: int
    error: str | None


@dataclass(frozen=True)
class ChannelInfo:
    topic: str
    schema_name: str
    message_encoding: str
    message_count: int
    record: str


@dataclass(frozen=True)
class AttachmentInfo:
    name: str
    media_type: str
    size: int
    log_time: int


# --- the log ---------------------------------------------------------------------------------


class Log:
    """A boxloc MCAP log opened for reading (see :func:`open_log`)."""

    def __init__(self, path: str | os.PathLike[str], *, limits: DecodeLimits = DEFAULT_LIMITS,
                 allow_truncated: bool = False) -> None:
        self.path = Path(path)
        self.limits = limits
        self.allow_truncated = allow_truncated
        if not self.path.is_file():
            raise LogError(f"log not found: {self.path}")
        self.size = self.path.stat().st_size
        self.summary: Summary | None = None
        self.damage: list[str] = []
        self.truncated: str | None = None
        with self._open() as f:
            if f.read(len(_MAGIC)) != _MAGIC:
                raise LogError(f"{self.path} is not an MCAP file")
            f.seek(0)
            try:
                # No record is larger than the file: a corrupt length never allocates more.
                reader = SeekingReader(f, record_size_limit=min(limits.max_record_bytes,
                                                                self.size))
                self.header: Header = reader.get_header()
            except Exception as e:
                raise LogError(f"{self.path}: cannot read the MCAP header: {e}") from None
            try:
                self.summary = reader.get_summary()
            except Exception:
                self.summary = None
        self.complete = self.summary is not None
        if not self.complete and not allow_truncated:
            raise LogError(
                f"{self.path} has no summary (its recorder was killed or the disk filled "
                f"up); `boxloc recover {self.path}` rebuilds a complete log"
            )
        self.metadata: dict[str, dict[str, str]] = {}
        self._attachments: dict[str, tuple[AttachmentInfo, int | None]] = {}
        self._read_metadata()

    def _open(self) -> IO[bytes]:
        return open(self.path, "rb")

    def _read_metadata(self) -> None:
        if self.summary is not None:
            with self._open() as f:
                for mi in self.summary.metadata_indexes:
                    rec = self._record_at(f, mi.offset, Opcode.METADATA)
                    self.metadata[rec.name] = dict(rec.metadata)
            for ai in self.summary.attachment_indexes:
                info = AttachmentInfo(ai.name, ai.media_type, ai.data_size, ai.log_time)
                self._attachments.setdefault(ai.name, (info, ai.offset))
            return
        # No summary: one pass over the data section (metadata precede the first scan).
        state = ScanState()
        with self._open() as f:
            for off, rec in scan_records(f, state, self.limits,
                                         want_chunk=lambda _o: False):
                if isinstance(rec, Metadata):
                    self.metadata[rec.name] = dict(rec.metadata)
                elif isinstance(rec, Attachment):
                    info = AttachmentInfo(rec.name, rec.media_type, len(rec.data), rec.log_time)
                    self._attachments.setdefault(rec.name, (info, off))
        self.truncated = state.truncated
        self.damage.extend(state.damage)

    def _record_at(self, f: IO[bytes], offset: int, opcode: int) -> Any:
        f.seek(offset)
        hdr = f.read(9)
        if len(hdr) < 9:
            raise LogError(f"{self.path}: index points past the end of the file")
        op, length = struct.unpack("<BQ", hdr)
        if op != opcode or length > self.limits.max_record_bytes:
            raise LogError(f"{self.path}: index points at a wrong record (byte {offset})")
        if offset + 9 + length > self.size:
            raise LogError(f"{self.path}: record at byte {offset} is cut short")
        body = f.read(length)
        if len(body) < length:
            raise LogError(f"{self.path}: record at byte {offset} is cut short")
        if op == Opcode.ATTACHMENT and not _attachment_crc_ok(body):
            raise LogError(f"{self.path}: attachment at byte {offset} fails its CRC")
        try:
            return _READERS[op](ReadDataStream(io.BytesIO(body)))
        except Exception as e:  # noqa: BLE001 - the mcap readers raise many kinds
            raise LogError(f"{self.path}: record at byte {offset} is malformed: "
                           f"{str(e)[:200]}") from None

    # --- provenance ------------------------------------------------------------------------

    @property
    def run(self) -> dict[str, str]:
        """The ``boxloc.run`` metadata: versions, git commit, config, sensor, host."""
        return self.metadata.get(C.RUN_METADATA, {})

    @property
    def config(self) -> Config | None:
        """The config the scans were run with (None for a log without provenance)."""
        text = self.run.get("config")
        if not text:
            return None
        try:
            return Config.from_recorded(E.parse_json(text, "the recorded config"))
        except (ValueError, TypeError, LogError) as e:
            raise LogError(f"{self.path}: recorded config is invalid: {e}") from None

    @property
    def version(self) -> str:
        return self.run.get("boxloc_version", "unknown")

    def attachments(self) -> list[AttachmentInfo]:
        return [info for info, _ in self._attachments.values()]

    def attachment(self, name: str) -> bytes:
        """The data of attachment ``name`` (an exact name; never used as a path here)."""
        if name not in self._attachments:
            raise LogError(f"{self.path} has no attachment {name!r}")
        _, offset = self._attachments[name]
        with self._open() as f:
            rec = self._record_at(f, int(offset or 0), Opcode.ATTACHMENT)
        return bytes(rec.data)

    # --- messages and scans ----------------------------------------------------------------

    def messages(self, topics: set[str] | None = None) -> Iterator[LogMessage]:
        """Every message in file order (optionally only ``topics``)."""
        state = ScanState()
        with self._open() as f:
            yield from iter_messages(f, state, self.limits, summary=self.summary, topics=topics)
        self._note(state)

    def _note(self, state: ScanState) -> None:
        for d in state.damage:
            if d not in self.damage:
                self.damage.append(d)
        if state.truncated and not self.complete:
            self.truncated = state.truncated
        if (state.damage or state.truncated) and not self.allow_truncated:
            first = state.damage[0] if state.damage else state.truncated
            raise LogError(f"{self.path} is damaged: {first}; "
                           f"`boxloc recover {self.path}` saves what is left")

    def scans(self, *, views: bool = False) -> Iterator[ScanRecord]:
        """Every recorded scan, in file order, with its products.

        Raises
        ------
        LogError
            An unknown schema major version, a malformed record, or (unless the log was
            opened with ``allow_truncated``) damage.
        """
        sensors: dict[str, SensorModel] = {}
        cur: _Builder | None = None
        lim = self.limits
        for m in self.messages():
            topic = m.topic
            spec = C.BY_TOPIC.get(topic)
            if spec is None or spec.role is C.Role.VIEW or topic == C.PICK_OUTCOME:
                continue
            if topic == C.SCAN_SENSOR:
                digest, model = E.decode_sensor(m.data, lim)
                sensors[digest] = model
                continue
            if topic == C.START_TOPIC:
                if cur is not None:
                    yield cur.build(sensors, lim, incomplete="no end of scan record")
                cur = _Builder(E.decode_scan_info(m.data, lim), m.log_time)
                continue
            if cur is None:
                raise LogError(f"{self.path}: a {topic} message outside any scan")
            if m.sequence != cur.info.index & 0xFFFFFFFF:
                raise LogError(f"{self.path}: a {topic} message of sequence {m.sequence} "
                               f"inside scan {cur.info.index}")
            if topic == C.SCAN_RANGE:
                cur.range_ = E.decode_range(m.data, lim)
            elif topic in C.TOPIC_STAGES:
                cur.raw_products[C.TOPIC_STAGES[topic]] = m.data
            elif topic == C.TESTS:
                cur.raw_tests = m.data
            elif topic == C.AMBIGUOUS:
                cur.raw_ambiguous = m.data
            elif topic == C.TIMING:
                cur.timing, cur.record_ms = E.decode_timing(m.data)
            elif topic == C.SCAN_LABELS:
                cur.labels = E.decode_labels(m.data, lim)
            elif topic in C.END_TOPICS:
                if topic == C.RESULT:
                    cur.result_info = E.decode_result_info(m.data, lim)
                elif topic == C.SCAN_END:
                    E.decode_scan_end(m.data, lim)  # checks the record
                    cur.scan_only = True
                else:
                    cur.error = E.decode_error(m.data)
                yield cur.build(sensors, lim)
                cur = None
        if cur is not None:
            yield cur.build(sensors, lim, incomplete="the log ends inside this scan")

    __iter__ = scans

    def scan(self, index: int) -> ScanRecord:
        """The (last) recorded scan of index ``index``."""
        found = None
        for rec in self.scans():
            if rec.index == index:
                found = rec
        if found is None:
            raise LogError(f"{self.path} has no scan {index}")
        return found

    def index(self) -> list[ScanSummary]:
        """Every scan with its surface count and error, decoding only small records."""
        out: list[ScanSummary] = []
        cur: dict[str, Any] | None = None
        topics = {C.SCAN_INFO, C.SURFACES, *C.END_TOPICS}
        for m in self.messages(topics):
            if m.topic == C.SCAN_INFO:
                if cur is not None:
                    out.append(ScanSummary(cur["index"], cur["t"], cur["n"], "incomplete"))
                info = E.decode_scan_info(m.data, self.limits)
                cur = {"index": info.index, "t": m.log_time, "n": 0}
            elif cur is None:
                continue
            elif m.topic == C.SURFACES:
                # only the count: the surfaces' tests (on /boxloc/tests) are not read here
                cur["n"] = len(E.decode_product("surfaces", m.data, E.empty_test_columns(),
                                                self.limits))
            else:
                err = None
                if m.topic == C.ERROR:
                    e = E.decode_error(m.data)
                    err = f"{e['error_type']} in {e['stage']}: {e['message']}".rstrip(": ")
                out.append(ScanSummary(cur["index"], cur["t"], cur["n"], err))
                cur = None
        if cur is not None:
            out.append(ScanSummary(cur["index"], cur["t"], cur["n"], "incomplete"))
        return out

    def channels(self) -> list[ChannelInfo]:
        """The channels with their message counts (from the summary, else by reading)."""
        counts: dict[int, int] = {}
        chans: dict[int, Channel] = {}
        schemas: dict[int, Schema] = {}
        if self.summary is not None:
            chans, schemas = dict(self.summary.channels), dict(self.summary.schemas)
            st = self.summary.statistics
            counts = dict(st.channel_message_counts) if st else {}
        else:
            for m in self.messages():
                chans[m.channel.id] = m.channel
                if m.schema is not None:
                    schemas[m.schema.id] = m.schema
                counts[m.channel.id] = counts.get(m.channel.id, 0) + 1
        out = []
        for cid, ch in sorted(chans.items()):
            sch = schemas.get(ch.schema_id)
            out.append(ChannelInfo(ch.topic, sch.name if sch else "", ch.message_encoding,
                                   counts.get(cid, 0), ch.metadata.get("boxloc.record", "")))
        return out

    def time_span(self) -> tuple[int, int] | None:
        """(first, last) message log time, ns."""
        if self.summary is not None and self.summary.statistics is not None:
            st = self.summary.statistics
            return (st.message_start_time, st.message_end_time) if st.message_count else None
        times = [m.log_time for m in self.messages({C.SCAN_INFO})]
        return (min(times), max(times)) if times else None

    # --- outcomes --------------------------------------------------------------------------

    def outcomes(self) -> list[PickOutcome]:
        """Every pick outcome: the log's ``/pick/outcome`` channel, then its sidecar."""
        out = [E.decode_outcome(m.data) for m in self.messages({C.PICK_OUTCOME})]
        return out + read_sidecar(self.path)

    def latest_outcomes(self) -> dict[tuple[int, int], PickOutcome]:
        """The last outcome reported for each (scan, surface)."""
        return latest_outcomes(self.outcomes())


def open_log(path: str | os.PathLike[str], *, limits: DecodeLimits = DEFAULT_LIMITS,
             allow_truncated: bool = False) -> Log:
    """Open a boxloc MCAP log for reading.

    Parameters
    ----------
    path : path
        The ``.mcap`` file.
    limits : DecodeLimits
        Bounds on every decoded array, image and record.
    allow_truncated : bool
        Read a log without summary (or with damaged chunks) up to its last good record
        instead of refusing it.

    Raises
    ------
    LogError
        Not a file, not MCAP, no summary (unless allowed).
    """
    return Log(path, limits=limits, allow_truncated=allow_truncated)

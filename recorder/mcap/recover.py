"""Rebuild a complete log from a truncated or damaged one, into a new file.

A recorder killed with SIGKILL (or stopped by a full disk) leaves a log without its summary
section, possibly ending inside a chunk. Every scan it flushed is whole on disk, since each
scan is one chunk that was fsync'd. :func:`recover_log` reads the source up to its last good
record, keeps every complete scan (from ``/scan/info`` to ``/boxloc/result`` or
``/boxloc/error``), every session message (sensor models, pick outcomes: written with the
next complete scan), the metadata and the attachments, and writes them to a new log with
one chunk per scan and a full summary. The sidecar of pick outcomes is copied too.
The source is opened read-only and never modified; the output appears atomically (written
under a temporary name, then renamed).
"""

from __future__ import annotations

import contextlib
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema

from boxloc.errors import InputError
from recorder.annotate import sidecar_path
from recorder.mcap import channels as C
from recorder.mcap.encode import DEFAULT_LIMITS, DecodeLimits
from recorder.mcap.log import ScanState, scan_records
from recorder.mcap.sink import McapFile


@dataclass
class RecoveryReport:
    """What :func:`recover_log` did.

    Attributes
    ----------
    source, output : Path
    source_complete : bool
        The source had a complete data section (it needed no recovery, only a rewrite).
    scans : int
        Complete scans written to the output.
    dropped_scans : int
        Scans cut off by the truncation (or in a damaged chunk), not written.
    session_messages : int
        Sensor models, pick outcomes and other messages outside scans, written.
    truncated : str or None
        Where and how the source ends early.
    damage : list of str
        Damaged chunks or records skipped.
    """

    source: Path
    output: Path
    source_complete: bool = False
    scans: int = 0
    dropped_scans: int = 0
    session_messages: int = 0
    truncated: str | None = None
    damage: list[str] = field(default_factory=list)
    scan_indices: list[int] = field(default_factory=list)

    def summary(self) -> str:
        what = "complete" if self.source_complete else (self.truncated or "damaged")
        line = (f"recovered {self.scans} scan(s) from {self.source} ({what}) into {self.output}")
        if self.dropped_scans:
            line += f"; {self.dropped_scans} incomplete scan(s) dropped"
        if self.damage:
            line += f"; {len(self.damage)} damaged record(s) skipped"
        return line


@dataclass
class _Msg:
    channel: Channel
    schema: Schema | None
    message: Message


def default_output(src: Path) -> Path:
    """``run.mcap`` -> ``run.recovered.mcap``."""
    return src.with_name(f"{src.stem}.recovered.mcap")


def recover_log(
    src: str | os.PathLike[str],
    dst: str | os.PathLike[str] | None = None,
    *,
    overwrite: bool = False,
    limits: DecodeLimits = DEFAULT_LIMITS,
) -> RecoveryReport:
    """Write every complete scan of ``src`` into a new, complete log ``dst``.

    Parameters
    ----------
    src : path
        The (possibly truncated) log. Only read.
    dst : path, optional
        The new log; default ``<src stem>.recovered.mcap`` next to ``src``.
    overwrite : bool
        Replace ``dst`` if it exists.

    Raises
    ------
    InputError
        ``src`` missing, ``dst`` exists (without ``overwrite``) or is ``src``.
    LogError
        ``src`` is not an MCAP file.
    """
    src = Path(src)
    if not src.is_file():
        raise InputError(f"log not found: {src}")
    out = Path(dst) if dst is not None else default_output(src)
    if out.exists():
        if out.resolve() == src.resolve() or os.path.samefile(out, src):
            raise InputError(f"the output {out} is the input; recovery never modifies its input")
        if not overwrite:
            raise InputError(f"{out} exists; pick another output or pass --force")
    report = RecoveryReport(source=src, output=out)
    tmp = out.with_name(out.name + ".partial")
    with contextlib.suppress(FileNotFoundError):
        tmp.unlink()
    try:
        with open(src, "rb") as fh:
            _copy(fh, tmp, report, limits)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
    os.replace(tmp, out)
    side = sidecar_path(src)
    if side.is_file():
        shutil.copyfile(side, sidecar_path(out))
    return report


class _Out:
    """The output log, opened when the source's header has been read; one chunk per
    :meth:`write`."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.file: McapFile | None = None

    def open(self, header: Header | None) -> McapFile:
        if self.file is None:
            library = f"{header.library} +boxloc-recover" if header else "boxloc-recover"
            self.file = McapFile(self.path, open(self.path, "xb"), library=library, fsync=False,
                                 profile=header.profile if header else C.PROFILE)
        return self.file

    def write(self, unit: list[_Msg]) -> None:
        f = self.open(None)
        for m in unit:
            s = m.schema
            cid = f.channel(m.channel.topic, schema_name=s.name if s else "",
                            schema_encoding=s.encoding if s else "",
                            schema_data=s.data if s else b"",
                            message_encoding=m.channel.message_encoding,
                            metadata=dict(m.channel.metadata))
            mm = m.message
            f.add(cid, mm.log_time, mm.data, publish_time=mm.publish_time, sequence=mm.sequence)
        f.writer.flush()  # one chunk per unit (a scan), as recorded


def _copy(fh: IO[bytes], tmp: Path, report: RecoveryReport, limits: DecodeLimits) -> None:
    """One streaming pass: copy metadata, attachments and every complete unit (a whole
    scan, or a session message) to the output as soon as it is complete."""
    out = _Out(tmp)
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    state = ScanState()
    scan: list[_Msg] | None = None  # the scan being collected
    pre: list[_Msg] = []  # session messages: written in the chunk of the next whole scan
    held: list[_Msg] = []  # the last whole scan, written once we know what follows it
    topic_schema: dict[str, str] = {}  # one schema per topic in the output, as recorded
    try:
        for _, rec in scan_records(fh, state, limits):
            if isinstance(rec, Header):
                out.open(rec)
            elif isinstance(rec, Metadata):
                out.open(None).writer.add_metadata(rec.name, dict(rec.metadata))
            elif isinstance(rec, Attachment):
                out.open(None).writer.add_attachment(rec.create_time, rec.log_time, rec.name,
                                                     rec.media_type, rec.data)
            elif isinstance(rec, Schema):
                schemas[rec.id] = rec
            elif isinstance(rec, Channel):
                channels[rec.id] = rec
            elif isinstance(rec, Message):
                ch = channels.get(rec.channel_id)
                if ch is None:
                    report.damage.append(f"message on unknown channel {rec.channel_id} dropped")
                    continue
                m = _Msg(ch, schemas.get(ch.schema_id), rec)
                sname = m.schema.name if m.schema is not None else ""
                first = topic_schema.setdefault(ch.topic, sname)
                if sname != first:  # a damaged or foreign log reusing a topic
                    note = (f"messages on {ch.topic!r} with schema {sname!r} dropped (the "
                            f"topic has schema {first!r})")
                    if note not in report.damage:
                        report.damage.append(note)
                    continue
                spec = C.BY_TOPIC.get(ch.topic)
                if ch.topic == C.START_TOPIC:
                    if scan is not None:
                        report.dropped_scans += 1
                    scan = [m]
                elif spec is None or spec.scope is C.Scope.SESSION:
                    # sensor models, pick outcomes, foreign topics: always kept
                    pre.append(m)
                    report.session_messages += 1
                elif scan is None:
                    report.damage.append(f"a {ch.topic} message outside any scan dropped")
                else:
                    scan.append(m)
                    if ch.topic in C.END_TOPICS:
                        if held:
                            out.write(held)
                        held, pre = pre + scan, []
                        report.scans += 1
                        report.scan_indices.append(int(scan[0].message.sequence))
                        scan = None
        if scan is not None:
            report.dropped_scans += 1
        # Leftover session messages go with the last scan: a chunk of a single small
        # message would not compress (strict checkers flag that).
        if held or pre:
            out.write(held + pre)
        report.source_complete = state.complete_data and not state.damage
        report.truncated = state.truncated
        report.damage.extend(state.damage)
        f = out.open(None)
        f.writer.add_metadata(C.RECOVERY_METADATA, {
            "source": report.source.name,
            "source_bytes": str(state.end_offset),
            "source_complete": str(report.source_complete).lower(),
            "truncated": report.truncated or "",
            "damage": "; ".join(report.damage)[:4000],
            "scans": str(report.scans),
            "dropped_scans": str(report.dropped_scans),
        })
        f.fsync = True
        f.finish()
    except BaseException:
        if out.file is not None:
            out.file.abandon()
        raise

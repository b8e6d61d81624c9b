"""The raw messages of a bag: through ``rosbags``, or record by record for a damaged bag.

rosbags refuses an MCAP file without its footer and a sqlite3 file shorter than its header
says. The fallback walks the MCAP records (chunks decompressed and CRC-checked with rosbags'
own ``decompress``; a bad chunk is skipped) or reads the sqlite3 rows in file order with
SQLite's ``writable_schema`` (which makes SQLite use the pages that exist), up to the
damage, which :class:`_Damage` keeps as one line.
"""

from __future__ import annotations

import io
import sqlite3
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from boxloc.errors import InputError
from boxloc.io.common import _one_line
from boxloc.io.rosbag.detect import _MCAP_MAGIC

#: A chunk larger than this (uncompressed) is treated as damage, not allocated: rosbag2
#: writes chunks of about 1 MB; a 640x480 float image is 1.2 MB.
_MAX_CHUNK = 1 << 30


@dataclass(frozen=True)
class _Topic:
    name: str
    msgtype: str
    count: int | None  # messages, when the bag's index says


@dataclass(frozen=True)
class _Raw:
    topic: str
    log_time_ns: int
    data: bytes


class _Damage:
    """What a read lost, as one line (the first problem; more are counted)."""

    def __init__(self) -> None:
        self.first: str | None = None
        self.seen: set[str] = set()

    @property
    def n(self) -> int:
        return len(self.seen)

    def add(self, what: str) -> None:
        if what not in self.seen:  # the same damage met by two passes is one problem
            self.seen.add(what)
            self.first = self.first or what


def _storage_files(p: Path) -> list[Path]:
    """The storage files of a bag (a directory's, in its metadata's order when readable)."""
    if not p.is_dir():
        return [p]
    names: list[str] = []
    try:
        from ruamel.yaml import YAML  # rosbags' own YAML reader

        meta = YAML(typ="safe").load((p / "metadata.yaml").read_text())
        names = [Path(str(x)).name for x in
                 meta["rosbag2_bagfile_information"]["relative_file_paths"]]
    except Exception:  # noqa: BLE001 - damaged metadata: fall back to the files present
        names = []
    files = [p / n for n in names if (p / n).is_file()]
    return files or sorted(q for q in p.iterdir()
                           if q.is_file() and q.suffix.lower() in (".mcap", ".db3"))


class _Bag:
    """The raw messages of a bag: through rosbags, else record by record (damage noted)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.damage = _Damage()
        self.opened_by = "rosbags"
        self.topics: dict[str, _Topic] = {}
        try:
            from rosbags.rosbag2 import Reader

            with Reader(path) as r:
                for c in r.connections:
                    t = self.topics.get(c.topic)
                    n = None if c.msgcount is None else int(c.msgcount)
                    if t is not None and t.count is not None and n is not None:
                        n += t.count
                    self.topics[c.topic] = _Topic(c.topic, c.msgtype, n)
        except Exception as e:  # noqa: BLE001 - rosbags refuses a damaged bag: read what is there
            self.opened_by = "records"
            self.topics = {}
            self._first_error = _one_line(e)
            for f in _storage_files(path):
                try:
                    for t in _fallback_topics(f):
                        self.topics.setdefault(t.name, t)
                except Exception as e2:  # noqa: BLE001
                    self.damage.add(f"{f.name}: {_one_line(e2)}")
            if not self.topics:
                raise InputError(f"{path}: not a readable ROS 2 bag: {self._first_error}"
                                 ) from None

    def messages(self, topics: Iterable[str], damage: _Damage | None = None) -> Iterator[_Raw]:
        """The messages of ``topics`` (rosbags: in receive-time order; a damaged bag: in file
        order). A problem met on the way is added to ``damage`` and ends the read (rosbags:
        the rest is read record by record)."""
        want = set(topics)
        dmg = damage if damage is not None else self.damage
        seen: set[tuple[str, int, int]] = set()
        if self.opened_by == "rosbags":
            try:
                from rosbags.rosbag2 import Reader

                with Reader(self.path) as r:
                    conns = [c for c in r.connections if c.topic in want]
                    if not conns:
                        return
                    for c, t, data in r.messages(connections=conns):
                        seen.add((c.topic, int(t), len(data)))
                        yield _Raw(c.topic, int(t), bytes(data))
                return
            except Exception as e:  # noqa: BLE001 - damage past the index: go on by records
                dmg.add(_one_line(e))
        for f in _storage_files(self.path):
            try:
                for m in _fallback_messages(f, want):
                    if (m.topic, m.log_time_ns, len(m.data)) not in seen:
                        yield m
            except _Stop as e:
                dmg.add(f"{f.name}: {e}")
            except Exception as e:  # noqa: BLE001 - whatever the file does: stop this file
                dmg.add(f"{f.name}: {_one_line(e)}")


class _Stop(Exception):
    """The damage point of a storage file read record by record."""


def _fallback_topics(f: Path) -> list[_Topic]:
    if f.suffix.lower() == ".db3":
        with _sqlite(f) as con:
            rows = con.execute("SELECT name, type FROM topics").fetchall()
        return [_Topic(str(n), str(t), None) for n, t in rows]
    out: dict[str, _Topic] = {}
    try:
        for rec in _mcap_records(f, want=None):
            if isinstance(rec, _Topic):
                out.setdefault(rec.name, rec)
    except _Stop:  # the message pass meets and reports the same damage
        pass
    return list(out.values())


def _fallback_messages(f: Path, want: set[str]) -> Iterator[_Raw]:
    if f.suffix.lower() == ".db3":
        yield from _sqlite_messages(f, want)
        return
    for rec in _mcap_records(f, want=want):
        if isinstance(rec, _Raw):
            yield rec


class _sqlite:
    """A read-only connection to a bag's sqlite3 file that reads a truncated file's pages:
    ``writable_schema`` makes SQLite take the file's size instead of refusing the file."""

    def __init__(self, f: Path) -> None:
        self.f = f

    def __enter__(self) -> sqlite3.Connection:
        uri = f"file:{self.f.resolve().as_posix()}?mode=ro"
        try:
            self.con = sqlite3.connect(uri, uri=True)
            self.con.execute("PRAGMA writable_schema=ON")
        except sqlite3.Error as e:
            raise _Stop(_one_line(e)) from None
        return self.con

    def __exit__(self, *exc: object) -> None:
        self.con.close()


def _sqlite_messages(f: Path, want: set[str]) -> Iterator[_Raw]:
    with _sqlite(f) as con:
        try:
            ids = {int(i): str(n) for i, n in con.execute("SELECT id, name FROM topics")}
            cur = con.execute("SELECT topic_id, timestamp, data FROM messages")
            for tid, t, data in cur:
                name = ids.get(int(tid))
                if name in want and isinstance(data, bytes):
                    yield _Raw(name, int(t), data)
        except sqlite3.Error as e:
            raise _Stop(f"damaged from here on ({_one_line(e)})") from None


def _read_exact(f: io.BufferedReader, n: int, what: str) -> bytes:
    b = f.read(n)
    if len(b) != n:
        raise _Stop(f"truncated inside {what}")
    return b


class _Rec:
    """Little-endian fields of one MCAP record's body."""

    def __init__(self, b: bytes) -> None:
        self.b, self.i = b, 0

    def take(self, n: int) -> bytes:
        if self.i + n > len(self.b):
            raise ValueError("record shorter than its fields")
        out = self.b[self.i : self.i + n]
        self.i += n
        return out

    def u16(self) -> int:
        return int(struct.unpack("<H", self.take(2))[0])

    def u32(self) -> int:
        return int(struct.unpack("<I", self.take(4))[0])

    def u64(self) -> int:
        return int(struct.unpack("<Q", self.take(8))[0])

    def str(self) -> str:
        return self.take(self.u32()).decode("utf-8", "replace")


def _mcap_records(f: Path, want: set[str] | None) -> Iterator[_Topic | _Raw]:
    """Schemas, channels (as topics) and messages (``want``: topics kept) of an MCAP file,
    in file order, chunks included; stops with :class:`_Stop` at the damage point; a chunk
    that does not decompress or fails its CRC is skipped (recorded as lost)."""
    schemas: dict[int, str] = {}
    channels: dict[int, str] = {}
    lost: list[str] = []
    with open(f, "rb") as fh:
        if fh.read(8) != _MCAP_MAGIC:
            raise _Stop("not an MCAP file")
        yield from _walk(fh, None, schemas, channels, want, lost)
    if lost:
        raise _Stop(f"{len(lost)} chunk(s) unreadable ({lost[0]})")


def _walk(fh: io.BufferedReader | None, buf: bytes | None, schemas: dict[int, str],
          channels: dict[int, str], want: set[str] | None, lost: list[str]
          ) -> Iterator[_Topic | _Raw]:
    """Records of a file (``fh``) or of a decompressed chunk (``buf``)."""
    src: Any = fh if fh is not None else io.BytesIO(buf or b"")
    end = None if buf is None else len(buf)
    while True:
        pos = src.tell()
        if end is not None and pos >= end:
            return
        head = src.read(9)
        if not head:
            raise _Stop("truncated: the file ends without its footer")
        if len(head) != 9:
            raise _Stop("truncated inside a record header")
        op, n = head[0], struct.unpack("<Q", head[1:])[0]
        if op in (0x02, 0x0F):  # footer, data end: the summary repeats what was read
            return
        if op == 0x05 and want is not None:
            body = _read_exact(src, n, "a message")
            r = _Rec(body)
            cid, _seq, t = r.u16(), r.u32(), r.u64()
            r.u64()
            topic = channels.get(cid)
            if topic is not None and topic in want:
                yield _Raw(topic, t, body[r.i :])
        elif op == 0x03:
            r = _Rec(_read_exact(src, n, "a schema"))
            sid = r.u16()
            schemas[sid] = r.str()
        elif op == 0x04:
            r = _Rec(_read_exact(src, n, "a channel"))
            cid, sid, topic = r.u16(), r.u16(), r.str()
            channels[cid] = topic
            yield _Topic(topic, schemas.get(sid, ""), None)
        elif op == 0x06 and fh is not None:
            body = src.read(n)
            if len(body) < n:  # the file ends inside this chunk: what it holds so far
                try:
                    inner = _partial_chunk(body)
                except Exception:  # noqa: BLE001 - nothing readable in it
                    inner = b""
                yield from _walk(None, inner, schemas, channels, want, lost)
                raise _Stop("truncated inside a chunk: the file ends without its footer")
            try:
                inner = _chunk(body)
            except Exception as e:  # noqa: BLE001 - a bad chunk is lost, the next may be fine
                lost.append(_one_line(e))
                continue
            yield from _walk(None, inner, schemas, channels, want, lost)
        else:
            if fh is not None:
                here = src.tell()
                src.seek(0, 2)
                size = src.tell()
                if here + n > size:
                    raise _Stop("truncated inside a record")
                src.seek(here + n)
            else:
                _read_exact(src, n, "a record")


def _partial_chunk(body: bytes) -> bytes:
    """The records of the start of an uncompressed chunk cut short (no CRC: the chunk is not
    whole; a record cut short is not read, a damaged message does not decode). A compressed
    chunk cut short is lost: a zstd frame written in one piece (single segment, as rosbag2's
    and rosbags' writers do) gives nothing until it is whole."""
    r = _Rec(body)
    r.u64()
    r.u64()
    size, _crc = r.u64(), r.u32()
    compression = r.str()
    r.u64()
    if compression != "":
        raise ValueError(f"a {compression} chunk cut short")
    return body[r.i :][: min(size, _MAX_CHUNK)]


def _chunk(body: bytes) -> bytes:
    from rosbags.rosbag2.storage_mcap import decompress

    r = _Rec(body)
    r.u64()
    r.u64()
    size, crc = r.u64(), r.u32()
    compression = r.str()
    n = r.u64()
    if size > _MAX_CHUNK:
        raise ValueError(f"chunk claims {size} bytes")
    return bytes(decompress(r.take(n), compression, size, crc))

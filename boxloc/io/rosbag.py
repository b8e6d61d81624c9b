"""Depth scans from ROS 2 bags (rosbag2), and small bags written for tests and samples.

A bag is a rosbag2 directory (``metadata.yaml`` beside its storage files) or one storage
file: ``.mcap`` (profile ``ros2``, CDR messages) or ``.db3`` (sqlite3). :func:`is_rosbag`
tells a bag from boxloc's own MCAP logs by the MCAP header's profile.

What is read
------------
Topics are found by type. A depth ``sensor_msgs/msg/Image`` (``16UC1`` millimetres or
``32FC1`` metres, REP 118; the first message of each Image topic tells depth from colour)
with its ``sensor_msgs/msg/CameraInfo``, or an organized ``sensor_msgs/msg/PointCloud2``
(``height > 1``, float ``x``, ``y``, ``z``). When several qualify, ``depth_topic`` chooses;
the CameraInfo is ``info_topic``, else the depth topic's sibling ``camera_info``, else the
bag's only CameraInfo topic.

- The CameraInfo of an image has the image's header stamp, or is the latest before it.
  ``K`` gives the pinhole; ``binning`` and ``roi`` are applied. Distortion ``plumb_bob``
  with non-zero coefficients gives a per-pixel ray table (OpenCV's undistortion of every
  pixel centre); any other model with non-zero coefficients is refused.
- The depth is scaled once, ``z = raw * scale`` in float64 (``scale`` 0.001 for 16UC1,
  1 for 32FC1, or ``depth_scale``), 0, NaN, inf and negative depths are no return, and
  ``z`` becomes range along each pixel's ray with :func:`boxloc.io.range_from_depth` (the
  depth-PNG reader's conversion), so a recorded frame and the same frame in a PNG give the
  same scan bit for bit.
- The capture time is the header stamp (the bag's receive time when the stamp is 0).
- The sensor pose is looked up in ``/tf_static`` and ``/tf`` along the frame chain from the
  header's ``frame_id`` (an optical frame: x right, y down, z forward, as boxloc's sensor
  frame) up to ``base_frame`` (default: the root of the tree), at the stamp (dynamic
  transforms interpolated between the samples around it, never extrapolated): the scan's
  ``sensor_to_base``, so "up" is the base's z.
- Every scan's ``source`` is the bag and its ``meta["rosbag"]`` holds the topic, the
  message's receive time (the bag's timestamp of the message) and header stamp, the frame,
  the encoding and scale, and the CameraInfo used: enough to find the frame in the bag again.

A damaged bag (a truncated or corrupt MCAP file, a truncated sqlite3 file) is read record by
record: every frame that decodes is yielded, then one :class:`~boxloc.errors.InputError`
line says what was lost. In MCAP the unit of loss is the chunk (about 1 MB): a damaged
chunk, or a compressed chunk cut short, loses its frames; an uncompressed chunk cut short
keeps the frames before the cut. Nothing from ``rosbags`` or the bag escapes as another exception.

The library
-----------
`rosbags <https://gitlab.com/ternaris/rosbags>`_ (Ternaris, Apache-2.0, maintained): pure
Python, no ROS installation, reads rosbag2 directories and bare ``.mcap`` and ``.db3`` files
of every rosbag2 version, both storages, zstd file/message compression, decodes CDR into
NumPy-backed messages, and writes bags (tests, samples, ``--publish-ros2``).
``mcap-ros2-support`` reads only MCAP (no sqlite3) and needs the ``mcap`` package, which
``boxloc`` does not import. Messages are decoded with rosbags' built-in type store, never
with the bag's own definitions: rosbags turns definitions into Python source that it
executes, and the types read here (Image, CameraInfo, PointCloud2, TFMessage) have one CDR
layout in every ROS 2 distribution. ``rosbags`` is imported on first use only, so
``boxloc --help`` does not pay for it.

The damaged-bag fallback is ours: rosbags refuses an MCAP file without its footer and a
sqlite3 file shorter than its header says. It walks the MCAP records (chunks decompressed
and CRC-checked with rosbags' own ``decompress``; a bad chunk is skipped) or reads the
sqlite3 rows in file order with SQLite's ``writable_schema`` (which makes SQLite use the
pages that exist), up to the damage.
"""

from __future__ import annotations

import io
import os
import shutil
import sqlite3
import struct
import tempfile
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from boxloc.errors import InputError
from boxloc.scan import PinholeModel, RayTableModel, Scan, SensorModel

__all__ = [
    "IMAGE", "CAMERA_INFO", "POINT_CLOUD", "TF_MESSAGE",
    "is_rosbag", "open_bag", "BagScans", "BagWriter", "write_depth_bag", "depth_raw",
]

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POINT_CLOUD = "sensor_msgs/msg/PointCloud2"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TF_TOPICS = ("/tf", "/tf_static")

#: Depth encodings (REP 118) and their default metres per unit.
DEPTH_ENCODINGS: dict[str, float] = {"16UC1": 0.001, "32FC1": 1.0}
#: Distortion models read as they are when every coefficient is zero; plumb_bob also with
#: non-zero coefficients (a ray table).
_PINHOLE_MODELS = ("", "none", "plumb_bob")

_MCAP_MAGIC = b"\x89MCAP0\r\n"
#: A chunk larger than this (uncompressed) is treated as damage, not allocated: rosbag2
#: writes chunks of about 1 MB; a 640x480 float image is 1.2 MB.
_MAX_CHUNK = 1 << 30
#: Longest chain of frames followed in /tf (a robot arm has tens; a cycle is damage).
_MAX_TF_DEPTH = 64

PathLike = str | os.PathLike[str]


# --- which files are bags ---------------------------------------------------------------


def _mcap_profile(p: Path) -> str | None:
    """The profile of an MCAP file's header record, or None when it is not MCAP."""
    try:
        with open(p, "rb") as f:
            head = f.read(8 + 1 + 8 + 4 + 64)
    except OSError:
        return None
    if len(head) < 21 or head[:8] != _MCAP_MAGIC or head[8] != 0x01:
        return None
    (n,) = struct.unpack_from("<I", head, 17)
    return head[21 : 21 + n].decode("utf-8", "replace") if n <= 64 else None


def is_rosbag(path: PathLike) -> bool:
    """Whether ``path`` is a ROS 2 bag: a directory with ``metadata.yaml``, a ``.db3`` file,
    or an ``.mcap`` file whose header profile is ``ros2`` (boxloc's logs have none)."""
    p = Path(path)
    if p.is_dir():
        return (p / "metadata.yaml").is_file()
    if not p.is_file():
        return False
    suffix = p.suffix.lower()
    if suffix == ".db3":
        return True
    return suffix == ".mcap" and _mcap_profile(p) == "ros2"


# --- raw messages: rosbags, or record by record for a damaged bag -------------------------


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


def _one_line(e: BaseException) -> str:
    s = str(e).strip().splitlines()
    return s[0] if s else type(e).__name__


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


# --- decoding ---------------------------------------------------------------------------


_TYPESTORE: Any = None


def _typestore() -> Any:
    global _TYPESTORE
    if _TYPESTORE is None:
        from rosbags.typesys import Stores, get_typestore

        _TYPESTORE = get_typestore(Stores.LATEST)
    return _TYPESTORE


def _decode(raw: _Raw, msgtype: str) -> Any:
    """The message, or :class:`_Stop` naming it when its bytes do not decode."""
    try:
        return _typestore().deserialize_cdr(raw.data, msgtype)
    except Exception as e:  # noqa: BLE001 - a corrupt message: this frame is lost
        raise _Stop(f"{raw.topic} message at {raw.log_time_ns} ns does not decode "
                    f"({_one_line(e)})") from None


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _frame(name: str) -> str:
    return str(name).lstrip("/")


# --- transforms -------------------------------------------------------------------------


def _transform(tr: Any) -> np.ndarray:
    """4x4 parent_from_child of a geometry_msgs/Transform; ValueError if not a rotation."""
    from scipy.spatial.transform import Rotation

    q = tr.rotation
    t = tr.translation
    v = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    xyz = np.array([t.x, t.y, t.z], dtype=np.float64)
    if not (np.isfinite(v).all() and np.isfinite(xyz).all()) or np.linalg.norm(v) < 1e-9:
        raise ValueError("transform is not finite or its quaternion is zero")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(v).as_matrix()
    T[:3, 3] = xyz
    return T


def _interpolate(a: np.ndarray, b: np.ndarray, w: float) -> np.ndarray:
    """The transform a fraction ``w`` of the way from ``a`` to ``b`` (slerp, lerp)."""
    from scipy.spatial.transform import Rotation, Slerp

    s = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]])))
    T = np.eye(4)
    T[:3, :3] = s([w]).as_matrix()[0]
    T[:3, 3] = (1 - w) * a[:3, 3] + w * b[:3, 3]
    return T


@dataclass
class TfTree:
    """The transforms of a bag's ``/tf_static`` and ``/tf``: parent and 4x4 parent_from_child
    per child frame (static), or time-stamped samples (dynamic)."""

    static: dict[str, tuple[str, np.ndarray]] = field(default_factory=dict)
    dynamic: dict[str, tuple[str, list[tuple[int, np.ndarray]]]] = field(default_factory=dict)

    def add(self, msg: Any, static: bool) -> None:
        for ts in msg.transforms:
            child, parent = _frame(ts.child_frame_id), _frame(ts.header.frame_id)
            if not child or not parent or child == parent:
                continue
            try:
                T = _transform(ts.transform)
            except ValueError:
                continue
            if static:
                self.static[child] = (parent, T)
            else:
                _, samples = self.dynamic.setdefault(child, (parent, []))
                samples.append((_stamp_ns(ts.header), T))

    def __bool__(self) -> bool:
        return bool(self.static or self.dynamic)

    def _edge(self, child: str, t_ns: int) -> tuple[str, np.ndarray] | None:
        if child in self.static:
            return self.static[child]
        if child not in self.dynamic:
            return None
        parent, samples = self.dynamic[child]
        samples.sort(key=lambda s: s[0])
        times = [s[0] for s in samples]
        k = int(np.searchsorted(times, t_ns, side="right"))
        if k == 0:
            return None  # every sample is after the stamp: no extrapolation
        t0, a = samples[k - 1]
        if t0 == t_ns or k == len(samples):
            return parent, a
        t1, b = samples[k]
        return parent, _interpolate(a, b, (t_ns - t0) / (t1 - t0))

    def chain(self, frame: str, t_ns: int) -> tuple[str, np.ndarray]:
        """The root reached from ``frame`` at ``t_ns`` and root_from_frame (4x4)."""
        T = np.eye(4)
        f = frame
        for _ in range(_MAX_TF_DEPTH):
            e = self._edge(f, t_ns)
            if e is None:
                return f, T
            f, T = e[0], e[1] @ T
        raise InputError(f"/tf: the frame chain from {frame!r} is longer than "
                         f"{_MAX_TF_DEPTH} links (a cycle?)")

    def lookup(self, base: str | None, frame: str, t_ns: int) -> tuple[str, np.ndarray] | None:
        """``(base, base_from_frame)`` at ``t_ns``; ``base`` None: the root of ``frame``'s
        tree. None when the frames are not connected at that time."""
        root, root_from_frame = self.chain(frame, t_ns)
        if base is None:
            return None if root == frame else (root, root_from_frame)
        broot, root_from_base = self.chain(base, t_ns)
        if broot != root:
            return None
        return base, np.linalg.inv(root_from_base) @ root_from_frame


# --- camera models ----------------------------------------------------------------------


@dataclass(frozen=True)
class _Camera:
    """The sensor model of a CameraInfo for one image size."""

    sensor: SensorModel
    stretch: np.ndarray | None  # range / z per pixel for a ray table (None: pinhole)
    description: dict[str, Any]


def _camera(info: Any, H: int, W: int, where: str) -> _Camera:
    """The sensor model of a CameraInfo for an (H, W) image.

    Raises
    ------
    InputError
        Uncalibrated K, a size that does not match, or a distortion model other than
        plumb_bob/none with non-zero coefficients.
    """
    K = np.asarray(info.k, dtype=np.float64).reshape(-1)
    D = np.asarray(info.d, dtype=np.float64).reshape(-1)
    model = str(info.distortion_model).strip().lower()
    if K.size != 9 or not np.isfinite(K).all() or K[0] <= 0 or K[4] <= 0:
        raise InputError(f"{where}: CameraInfo K is not a calibrated camera matrix "
                         f"(fx={K[0] if K.size else None}); the camera was not calibrated")
    if not np.isfinite(D).all():
        raise InputError(f"{where}: CameraInfo distortion coefficients are not finite")
    distorted = bool(np.any(D != 0))
    if distorted and model not in _PINHOLE_MODELS:
        raise InputError(f"{where}: distortion model {info.distortion_model!r} with non-zero "
                         "coefficients is not supported (only plumb_bob or none); rectify the "
                         "depth image first")
    fx, fy, cx, cy = K[0], K[4], K[2], K[5]
    bx, by = max(int(info.binning_x), 1), max(int(info.binning_y), 1)
    roi = info.roi
    x0, y0 = int(roi.x_offset), int(roi.y_offset)
    full_w = int(roi.width) or int(info.width)
    full_h = int(roi.height) or int(info.height)
    want = (full_h // by, full_w // bx)
    if (full_w or full_h) and want != (H, W):
        raise InputError(f"{where}: CameraInfo is for {want[0]}x{want[1]} images (after roi "
                         f"and binning), the depth image is {H}x{W}")
    fx, fy, cx, cy = fx / bx, fy / by, (cx - x0) / bx, (cy - y0) / by
    desc = {"fx": float(fx), "fy": float(fy), "cx": float(cx), "cy": float(cy),
            "distortion_model": str(
        info.distortion_model), "d": [float(x) for x in D], "binning": [bx, by],
        "roi": [x0, y0, int(roi.width), int(roi.height)]}
    try:
        pin = PinholeModel(float(fx), float(fy), float(cx), float(cy), W, H)
    except InputError as e:
        raise InputError(f"{where}: {e}") from None
    if not distorted:
        return _Camera(pin, None, desc)
    import cv2

    # Pixel centres of the image (binned/ROI coordinates) in the calibrated image, undistorted
    # to normalized coordinates: every pixel's ray.
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    pts = np.stack([u * bx + x0 + (bx - 1) / 2, v * by + y0 + (by - 1) / 2], -1)
    Kfull = np.array([[K[0], 0, K[2]], [0, K[4], K[5]], [0, 0, 1]], dtype=np.float64)
    xy = cv2.undistortPoints(pts.reshape(-1, 1, 2), Kfull, D).reshape(H, W, 2)
    d = np.concatenate([xy, np.ones((H, W, 1))], -1)
    stretch = np.linalg.norm(d, axis=-1)
    return _Camera(RayTableModel(d / stretch[..., None]), stretch, desc)


def depth_raw(msg: Any, where: str, max_pixels: int) -> np.ndarray:
    """The depth values of a ``sensor_msgs/msg/Image`` exactly as recorded, (H, W), in the
    image's dtype (uint16 for 16UC1, float32 for 32FC1), native byte order.

    Raises
    ------
    InputError
        Not a depth encoding, a size above ``max_pixels``.
    _Stop
        Data shorter than ``step * height`` or a step shorter than a row (a damaged frame).
    """
    from boxloc.io import _check_size

    enc = str(msg.encoding)
    if enc not in DEPTH_ENCODINGS:
        raise InputError(f"{where}: depth image encoding {enc!r} is not 16UC1 (millimetres) "
                         "or 32FC1 (metres)")
    H, W, step = int(msg.height), int(msg.width), int(msg.step)
    _check_size(Path(where), H, W, max_pixels)
    item = 2 if enc == "16UC1" else 4
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if step < W * item or data.size < step * H:
        raise _Stop(f"{where}: image data of {data.size} bytes does not hold {H} rows of "
                    f"step {step} >= {W * item}")
    kind = "u2" if item == 2 else "f4"
    dt = np.dtype((">" if msg.is_bigendian else "<") + kind)
    rows = data[: step * H].reshape(H, step)[:, : W * item]
    return np.ascontiguousarray(rows).view(dt).reshape(H, W).astype(dt.newbyteorder("="))


def _cloud_points(msg: Any, where: str, max_pixels: int) -> np.ndarray:
    """Organized points (H, W, 3) float64 of a PointCloud2 (its frame), NaN for no return."""
    from boxloc.io import _check_size

    H, W = int(msg.height), int(msg.width)
    if H <= 1:
        raise InputError(f"{where}: PointCloud2 is not organized (height {H}); boxloc needs "
                         "an organized cloud (height x width pixels)")
    _check_size(Path(where), H, W, max_pixels)
    fields = {str(f.name): f for f in msg.fields}
    types = {7: "f4", 8: "f8"}
    if not all(k in fields for k in "xyz"):
        raise InputError(f"{where}: PointCloud2 has no x, y, z fields")
    bo = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for k in "xyz":
        f = fields[k]
        if int(f.datatype) not in types:
            raise InputError(f"{where}: PointCloud2 field {k} is not float32 or float64")
        names.append(k)
        formats.append(bo + types[int(f.datatype)])
        offsets.append(int(f.offset))
    step, row = int(msg.point_step), int(msg.row_step)
    size = max(o + np.dtype(t).itemsize for o, t in zip(offsets, formats))
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if step < size or row < step * W or data.size < row * H:
        raise _Stop(f"{where}: PointCloud2 data of {data.size} bytes does not hold {H} rows "
                    f"of {W} points (point_step {step}, row_step {row})")
    dt = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    rows = np.ascontiguousarray(data[: row * H].reshape(H, row)[:, : step * W])
    rec = rows.view(dt).reshape(H, W)
    P = np.stack([rec[k].astype(np.float64) for k in "xyz"], -1)
    return np.where(np.isfinite(P), P, np.nan)


# --- the scans of a bag -----------------------------------------------------------------


@dataclass
class BagScans:
    """The depth frames of one bag, topics chosen and CameraInfo and /tf read
    (:func:`open_bag`). Iterating yields one :class:`~boxloc.scan.Scan` per readable frame
    and then raises one :class:`~boxloc.errors.InputError` if any frame was lost.

    Attributes
    ----------
    path : Path
    depth_topic : str
    kind : str
        ``"image"`` or ``"cloud"``.
    info_topic : str or None
    count : int or None
        Messages on the depth topic, when the bag's index says.
    """

    path: Path
    depth_topic: str
    kind: str
    info_topic: str | None
    count: int | None
    base_frame: str | None
    tf: TfTree
    infos: list[tuple[int, Any]]
    intrinsics: tuple[float, float, float, float] | None
    depth_scale: float | None
    max_pixels: int
    index: int
    bag: Any
    damage: Any

    def __iter__(self) -> Iterator[Scan]:
        n_read = n_lost = 0
        cameras: dict[tuple[int, int, int], _Camera] = {}
        for raw in self.bag.messages([self.depth_topic], self.damage):
            try:
                scan = self._scan(raw, self.index + n_read, cameras)
            except _Stop as e:
                n_lost += 1
                self.damage.add(str(e))
                continue
            except InputError:
                raise
            except Exception as e:  # noqa: BLE001 - a hostile message: this frame is lost
                n_lost += 1
                self.damage.add(f"{self.depth_topic} message at {raw.log_time_ns} ns: "
                                f"{type(e).__name__}: {_one_line(e)}")
                continue
            n_read += 1
            yield scan
        if self.damage.first is not None:
            lost = f"{n_lost} frame(s) lost, " if n_lost else ""
            more = f" (and {self.damage.n - 1} more)" if self.damage.n > 1 else ""
            raise InputError(f"{self.path}: damaged bag: {n_read} frame(s) of "
                             f"{self.depth_topic} read, {lost}the rest unreadable: "
                             f"{self.damage.first}{more}")

    def _scan(self, raw: _Raw, index: int,
              cameras: dict[tuple[int, int, int], _Camera]) -> Scan:
        where = f"{self.path}: {self.depth_topic}"
        msgtype = IMAGE if self.kind == "image" else POINT_CLOUD
        msg = _decode(raw, msgtype)
        stamp = _stamp_ns(msg.header)
        t = stamp if 0 < stamp < 2**63 else raw.log_time_ns
        frame = _frame(msg.header.frame_id)
        meta: dict[str, Any] = {
            "bag": str(self.path), "topic": self.depth_topic, "type": msgtype,
            "log_time_ns": raw.log_time_ns, "stamp_ns": stamp,
            "capture_time": "header.stamp" if t == stamp else "log_time", "frame_id": frame,
        }
        try:
            pose = self._pose(frame, t, meta)
            if self.kind == "cloud":
                P = _cloud_points(msg, where, self.max_pixels)
                meta["encoding"] = "PointCloud2"
                scan = Scan.from_points(P, None, capture_time_ns=t, index=index,
                                        sensor_to_base=pose, source=str(self.path),
                                        meta={"rosbag": meta})
                if isinstance(scan.sensor, RayTableModel):
                    scan.meta["sensor_fit"] = "raytable"
                return scan
            raw_depth = depth_raw(msg, where, self.max_pixels)
            enc = str(msg.encoding)
            scale = self.depth_scale if self.depth_scale is not None else DEPTH_ENCODINGS[enc]
            H, W = raw_depth.shape
            cam = self._camera_for(stamp or t, H, W, meta, cameras)
            with np.errstate(invalid="ignore", over="ignore"):
                z = raw_depth.astype(np.float64) * scale  # the one scaling
            z[~(z > 0) | ~np.isfinite(z)] = np.nan
            meta.update(encoding=enc, depth_scale=scale)
            if cam.stretch is None:
                from boxloc.io import range_from_depth

                assert isinstance(cam.sensor, PinholeModel)
                r = range_from_depth(z, cam.sensor)
            else:
                r = (z * cam.stretch).astype(np.float32)
            return Scan(range=r, sensor=cam.sensor, capture_time_ns=t, index=index,
                        sensor_to_base=pose, source=str(self.path), meta={"rosbag": meta})
        except InputError as e:
            msg_ = str(e)
            raise InputError(msg_ if str(self.path) in msg_ else f"{where}: {msg_}") from None

    def _pose(self, frame: str, t: int, meta: dict[str, Any]) -> np.ndarray | None:
        if not self.tf:
            if self.base_frame is not None:
                raise InputError(f"{self.path}: --base-frame {self.base_frame}: the bag has no "
                                 "/tf or /tf_static")
            return None
        found = self.tf.lookup(self.base_frame, frame, t)
        if found is None:
            if self.base_frame is not None:
                raise InputError(f"{self.path}: no transform from {frame!r} to "
                                 f"{self.base_frame!r} in /tf, /tf_static at {t} ns")
            meta["pose"] = f"no transform from {frame!r} to a parent frame at {t} ns"
            return None
        meta["base_frame"] = found[0]
        return found[1]

    def _camera_for(self, stamp: int, H: int, W: int, meta: dict[str, Any],
                    cameras: dict[tuple[int, int, int], _Camera]) -> _Camera:
        if self.intrinsics is not None:
            key = (-1, H, W)
            if key not in cameras:
                try:
                    cameras[key] = _Camera(PinholeModel(*self.intrinsics, width=W, height=H),
                                           None, {"intrinsics": list(self.intrinsics)})
                except InputError as e:
                    raise InputError(f"{self.path}: {e}") from None
            meta["camera"] = cameras[key].description
            return cameras[key]
        k = _match_info(self.infos, stamp)
        if k is None:
            raise _Stop(f"{self.depth_topic} frame at stamp {stamp} ns has no CameraInfo on "
                        f"{self.info_topic} at or before its stamp")
        t_info, info = self.infos[k]
        key = (k, H, W)
        if key not in cameras:
            cameras[key] = _camera(info, H, W, f"{self.path}: {self.info_topic}")
        meta["info_topic"] = self.info_topic
        meta["info_stamp_ns"] = t_info
        meta["camera"] = cameras[key].description
        return cameras[key]


def _match_info(infos: list[tuple[int, Any]], stamp: int) -> int | None:
    """Index in ``infos`` (sorted by stamp) of the CameraInfo with ``stamp``, else the latest
    before it; None when all are after it."""
    times = [t for t, _ in infos]
    k = int(np.searchsorted(times, stamp, side="right"))
    return None if k == 0 else k - 1


def _sibling_info(depth_topic: str, infos: Sequence[str]) -> str | None:
    ns = depth_topic.rsplit("/", 1)[0]
    for name in infos:
        if name == f"{ns}/camera_info":
            return name
    return None


def open_bag(
    path: PathLike,
    *,
    depth_topic: str | None = None,
    info_topic: str | None = None,
    base_frame: str | None = None,
    intrinsics: Any = None,
    depth_scale: float | None = None,
    max_pixels: int | None = None,
    index: int = 0,
) -> BagScans:
    """Open a ROS 2 bag for its depth scans: choose the topics, read CameraInfo and /tf.

    Parameters
    ----------
    path : str or Path
        A rosbag2 directory, or an ``.mcap`` / ``.db3`` storage file.
    depth_topic : str, optional
        The depth Image or PointCloud2 topic; needed when the bag has several.
    info_topic : str, optional
        The CameraInfo topic of a depth Image; default its sibling ``camera_info``, else the
        bag's only CameraInfo topic.
    base_frame : str, optional
        The frame of ``sensor_to_base``; default the root of the camera frame's /tf tree.
    intrinsics : str or 4 floats, optional
        ``fx, fy, cx, cy`` pixels: used instead of CameraInfo (a bag without one).
    depth_scale : float, optional
        Metres per depth unit instead of the encoding's (0.001 for 16UC1, 1 for 32FC1).
    max_pixels : int, optional
        Largest image accepted (default :data:`boxloc.io.DEFAULT_MAX_PIXELS`).
    index : int
        ``Scan.index`` of the first frame; the next ones count up.

    Returns
    -------
    BagScans
        Iterate it for the scans.

    Raises
    ------
    InputError
        Not a readable bag; no depth topic, or several without ``depth_topic``; no CameraInfo
        for a depth image; an unknown topic; bad intrinsics or depth scale.
    """
    from boxloc.io import DEFAULT_MAX_PIXELS, _check_depth_scale, parse_intrinsics

    p = Path(path)
    if not p.exists():
        raise InputError(f"bag not found: {p}")
    intr = parse_intrinsics(intrinsics)
    scale = _check_depth_scale(depth_scale)
    mp = DEFAULT_MAX_PIXELS if max_pixels is None else max_pixels
    if not isinstance(mp, int) or mp <= 0:
        raise InputError(f"max_pixels must be a positive integer, got {mp!r}")
    try:
        bag = _Bag(p)
    except InputError:
        raise
    except Exception as e:  # noqa: BLE001 - a library error on a hostile file
        raise InputError(f"{p}: not a readable ROS 2 bag: {_one_line(e)}") from None
    damage = bag.damage
    topics = bag.topics
    images = [t for t in topics.values() if t.msgtype == IMAGE]
    clouds = [t for t in topics.values() if t.msgtype == POINT_CLOUD]
    info_names = sorted(t.name for t in topics.values() if t.msgtype == CAMERA_INFO)

    # The first message of each Image/PointCloud2 topic tells depth from colour, organized
    # from not.
    firsts: dict[str, Any] = {}
    probe = _Damage()
    for raw in bag.messages([t.name for t in images + clouds], probe):
        if raw.topic in firsts:
            if len(firsts) == len(images) + len(clouds):
                break
            continue
        try:
            firsts[raw.topic] = _decode(raw, topics[raw.topic].msgtype)
        except _Stop as e:
            probe.add(str(e))
    if damage.first is None and probe.first is not None:
        damage.add(probe.first)

    def is_depth(t: _Topic) -> bool:
        m = firsts.get(t.name)
        if m is None:
            return False
        if t.msgtype == IMAGE:
            return str(m.encoding) in DEPTH_ENCODINGS
        return int(m.height) > 1

    if depth_topic is not None:
        chosen = topics.get(depth_topic)
        if chosen is None or chosen.msgtype not in (IMAGE, POINT_CLOUD):
            have = ", ".join(sorted(t.name for t in images + clouds)) or "none"
            raise InputError(f"{p}: --depth-topic {depth_topic}: no Image or PointCloud2 topic "
                             f"of that name (Image/PointCloud2 topics: {have})")
    else:
        candidates = [t for t in images + clouds if is_depth(t)]
        if not candidates and (probe.first or damage.first):
            raise InputError(f"{p}: damaged bag: no depth frame is readable "
                             f"({probe.first or damage.first})")
        if not candidates:
            listed = ", ".join(f"{t.name} ({t.msgtype})" for t in topics.values()) or "none"
            raise InputError(f"{p}: no depth Image (16UC1 or 32FC1) or organized PointCloud2 "
                             f"topic (topics: {listed})")
        if len(candidates) > 1:
            names = ", ".join(sorted(t.name for t in candidates))
            raise InputError(f"{p}: several depth topics ({names}); choose one with "
                             "--depth-topic")
        chosen = candidates[0]
    kind = "image" if chosen.msgtype == IMAGE else "cloud"

    want_info: str | None = None
    if kind == "image" and intr is None:
        if info_topic is not None:
            if info_topic not in info_names:
                raise InputError(f"{p}: --info-topic {info_topic}: no CameraInfo topic of that "
                                 f"name (CameraInfo topics: {', '.join(info_names) or 'none'})")
            want_info = info_topic
        elif not info_names:
            raise InputError(f"{p}: no sensor_msgs/msg/CameraInfo topic for the depth images "
                             f"of {chosen.name}: the camera's intrinsics are unknown (record "
                             "its camera_info, or pass --intrinsics FX,FY,CX,CY)")
        else:
            want_info = _sibling_info(chosen.name, info_names) or (
                info_names[0] if len(info_names) == 1 else None)
            if want_info is None:
                raise InputError(f"{p}: several CameraInfo topics ({', '.join(info_names)}) "
                                 f"and none beside {chosen.name}; choose one with "
                                 "--info-topic")

    tf = TfTree()
    infos: list[tuple[int, Any]] = []
    side = [*([want_info] if want_info else []), *(t for t in TF_TOPICS if t in topics)]
    if side:
        for raw in bag.messages(side, damage):
            try:
                if raw.topic == want_info:
                    m = _decode(raw, CAMERA_INFO)
                    infos.append((_stamp_ns(m.header), m))
                elif topics[raw.topic].msgtype == TF_MESSAGE:
                    tf.add(_decode(raw, TF_MESSAGE), static=raw.topic == "/tf_static")
            except _Stop as e:
                damage.add(str(e))
        infos.sort(key=lambda x: x[0])
        if want_info is not None and not infos:
            raise InputError(f"{p}: CameraInfo topic {want_info} has no readable message: the "
                             "camera's intrinsics are unknown (pass --intrinsics FX,FY,CX,CY)")
    if base_frame is not None and not base_frame.strip("/"):
        raise InputError("--base-frame must name a frame")
    return BagScans(path=p, depth_topic=chosen.name, kind=kind, info_topic=want_info,
                    count=chosen.count, base_frame=None if base_frame is None else
                    _frame(base_frame), tf=tf, infos=infos, intrinsics=intr,
                    depth_scale=scale, max_pixels=mp, index=int(index), bag=bag,
                    damage=damage)


# --- writing bags (tests, samples, published results) -----------------------------------


class BagWriter:
    """A rosbag2 bag written with rosbags: topics are added on their first message.

    Parameters
    ----------
    path : str or Path
        A new directory (rosbag2 layout: ``metadata.yaml`` and ``<name>_0.mcap``/``.db3``)
        or, with ``single_file``, a new ``.mcap``/``.db3`` file (written in a temporary
        directory beside it and moved there when closed).
    storage : str
        ``"mcap"`` or ``"sqlite3"``.
    compress : bool
        zstd chunk compression (MCAP only; readers decompress it transparently).
    """

    def __init__(self, path: PathLike, *, storage: str = "mcap", compress: bool = False,
                 single_file: bool = False) -> None:
        from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

        if storage not in ("mcap", "sqlite3"):
            raise InputError(f"bag storage must be mcap or sqlite3, got {storage!r}")
        self.path = Path(path)
        if self.path.exists():
            raise InputError(f"{self.path} exists; refusing to overwrite it")
        if not self.path.parent.is_dir():
            raise InputError(f"cannot write {self.path}: no directory {self.path.parent}")
        self.single_file = single_file
        self._tmp: Path | None = None
        target = self.path
        if single_file:
            self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.",
                                              dir=self.path.parent))
            target = self._tmp / self.path.stem
        self._target = target
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        self._writer = Writer(target, version=9, storage_plugin=plugin)
        if compress and storage == "mcap":
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        try:
            self._writer.open()
        except Exception as e:
            self._cleanup()
            raise InputError(f"cannot write {self.path}: {_one_line(e)}") from None
        self._conns: dict[str, Any] = {}
        self.types = _typestore().types

    def write(self, topic: str, msg: Any, log_time_ns: int) -> None:
        """Serialize ``msg`` (a rosbags message object) on ``topic`` at ``log_time_ns``."""
        ts = _typestore()
        msgtype = msg.__msgtype__
        c = self._conns.get(topic)
        if c is None:
            c = self._conns[topic] = self._writer.add_connection(topic, msgtype, typestore=ts)
        self._writer.write(c, int(log_time_ns), bytes(ts.serialize_cdr(msg, msgtype)))

    def close(self) -> None:
        """Finish the bag (metadata, index); for a single file, move it into place."""
        self._writer.close()
        if self._tmp is not None:
            try:
                (f,) = [q for q in (self._tmp / self.path.stem).iterdir()
                        if q.suffix in (".mcap", ".db3")]
                os.replace(f, self.path)
            finally:
                shutil.rmtree(self._tmp, ignore_errors=True)

    def abort(self) -> None:
        """Stop writing and remove what was written (nothing half-written is left)."""
        try:
            self._writer.abort()
        finally:
            self._cleanup()

    def _cleanup(self) -> None:
        shutil.rmtree(self._tmp if self._tmp is not None else self._target, ignore_errors=True)

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, exc_type: object, *rest: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def header(types: Any, stamp_ns: int, frame_id: str) -> Any:
    """A std_msgs/Header at ``stamp_ns`` (integer nanoseconds) in ``frame_id``."""
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id)


def image_message(types: Any, raw: np.ndarray, stamp_ns: int, frame_id: str) -> Any:
    """A depth Image of ``raw`` (H, W): uint16 -> 16UC1, float32 -> 32FC1 (little-endian)."""
    a = np.asarray(raw)
    enc = {np.dtype(np.uint16): "16UC1", np.dtype(np.float32): "32FC1"}[a.dtype]
    a = np.ascontiguousarray(a.astype(a.dtype.newbyteorder("<")))
    H, W = a.shape
    return types[IMAGE](header=header(types, stamp_ns, frame_id), height=H, width=W,
                        encoding=enc, is_bigendian=0, step=W * a.itemsize,
                        data=np.frombuffer(a.tobytes(), np.uint8))


def camera_info_message(types: Any, sensor: PinholeModel, stamp_ns: int, frame_id: str, *,
                        distortion_model: str = "plumb_bob",
                        d: Sequence[float] = (0.0,) * 5) -> Any:
    """The CameraInfo of a pinhole ``sensor``."""
    K = sensor.K
    P = np.zeros((3, 4))
    P[:, :3] = K
    return types[CAMERA_INFO](
        header=header(types, stamp_ns, frame_id), height=sensor.height, width=sensor.width,
        distortion_model=distortion_model, d=np.asarray(d, np.float64),
        k=K.reshape(-1).astype(np.float64), r=np.eye(3).reshape(-1), p=P.reshape(-1),
        binning_x=0, binning_y=0,
        roi=types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0,
                                                      width=0, do_rectify=False))


def cloud_message(types: Any, points: npt.ArrayLike, stamp_ns: int, frame_id: str) -> Any:
    """An organized PointCloud2 of ``points`` (H, W, 3) float32 x, y, z; NaN for no return."""
    P = np.ascontiguousarray(np.asarray(points, dtype="<f4"))
    H, W = P.shape[:2]
    PF = types["sensor_msgs/msg/PointField"]
    fields = [PF(name=k, offset=4 * i, datatype=7, count=1) for i, k in enumerate("xyz")]
    return types[POINT_CLOUD](header=header(types, stamp_ns, frame_id), height=H, width=W,
                              fields=fields, is_bigendian=False, point_step=12,
                              row_step=12 * W, data=np.frombuffer(P.tobytes(), np.uint8),
                              is_dense=False)


def tf_message(types: Any, parent: str, child: str, parent_from_child: np.ndarray,
               stamp_ns: int) -> Any:
    """A TFMessage of one transform: the pose of ``child`` in ``parent`` (4x4)."""
    from scipy.spatial.transform import Rotation

    T = np.asarray(parent_from_child, dtype=np.float64)
    x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
    tr = types["geometry_msgs/msg/Transform"](
        translation=types["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
        rotation=types["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))
    ts = types["geometry_msgs/msg/TransformStamped"](header=header(types, stamp_ns, parent),
                                                      child_frame_id=child, transform=tr)
    return types[TF_MESSAGE](transforms=[ts])


def depth_of(scan: Scan, encoding: str) -> np.ndarray:
    """The z depth of a pinhole scan as a camera would record it: uint16 millimetres (0 for
    no return) for 16UC1, float32 metres (NaN) for 32FC1."""
    z = scan.points[..., 2].astype(np.float64)
    if encoding == "16UC1":
        return np.where(np.isfinite(z), np.round(z * 1000.0), 0).clip(0, 65535).astype(
            np.uint16)
    if encoding == "32FC1":
        return np.where(np.isfinite(z), z, np.nan).astype(np.float32)
    raise InputError(f"depth encoding must be 16UC1 or 32FC1, got {encoding!r}")


def write_depth_bag(
    path: PathLike,
    scans: Sequence[Scan],
    *,
    storage: str = "mcap",
    encoding: str = "16UC1",
    namespace: str = "/camera/depth",
    frame_id: str = "camera_depth_optical_frame",
    base_frame: str = "base_link",
    tf: bool = True,
    camera_info: bool = True,
    compress: bool = False,
    single_file: bool = False,
    stamps_ns: Sequence[int] | None = None,
    extra: Callable[[BagWriter, int, int], None] | None = None,
) -> Path:
    """Write simulated scans as a camera driver records them: a small bag for tests/samples.

    Parameters
    ----------
    path : str or Path
        The new bag (a directory, or with ``single_file`` an ``.mcap``/``.db3`` file).
    scans : sequence of Scan
        Pinhole scans (the simulator's).
    storage : ``"mcap"`` or ``"sqlite3"``
    encoding : ``"16UC1"``, ``"32FC1"`` or ``"cloud"``
        Depth image in millimetres or metres on ``<namespace>/image_raw`` with CameraInfo on
        ``<namespace>/camera_info``, or an organized PointCloud2 on ``<namespace>/points``.
    frame_id, base_frame : str
        The optical frame, and the parent frame of its transform (the scan's
        ``sensor_to_base``; scans without one are written without).
    tf, camera_info : bool
        Write the poses (on ``/tf_static`` when every scan has the same, else on ``/tf`` at
        each frame's stamp), the CameraInfo messages.
    stamps_ns : sequence of int, optional
        Header stamps; default each scan's capture time, else 1 s apart from 1.7e18 ns.
    extra : callable, optional
        ``extra(writer, i, stamp_ns)`` writes more messages after frame ``i``.

    Returns
    -------
    Path
    """
    p = Path(path)
    with BagWriter(p, storage=storage, compress=compress, single_file=single_file) as w:
        T = w.types
        pose = scans[0].sensor_to_base if scans else None
        static = pose is not None and all(
            s.sensor_to_base is not None and np.array_equal(s.sensor_to_base, pose)
            for s in scans)
        if tf and static and pose is not None:
            w.write("/tf_static", tf_message(T, base_frame, frame_id, pose, 0), 1)
        for i, scan in enumerate(scans):
            t = int(stamps_ns[i]) if stamps_ns is not None else (
                scan.capture_time_ns or 1_700_000_000_000_000_000 + i * 1_000_000_000)
            if tf and not static and scan.sensor_to_base is not None:
                w.write("/tf", tf_message(T, base_frame, frame_id, scan.sensor_to_base, t), t)
            if encoding == "cloud":
                w.write(f"{namespace}/points", cloud_message(T, scan.points, t, frame_id), t)
            else:
                assert isinstance(scan.sensor, PinholeModel)
                if camera_info:
                    w.write(f"{namespace}/camera_info",
                            camera_info_message(T, scan.sensor, t, frame_id), t)
                w.write(f"{namespace}/image_raw",
                        image_message(T, depth_of(scan, encoding), t, frame_id), t)
            if extra is not None:
                extra(w, i, t)
    return p


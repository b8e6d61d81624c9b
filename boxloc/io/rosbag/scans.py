"""The depth frames of a bag as scans: :func:`open_bag` chooses the topics and reads the
CameraInfo and /tf; :class:`BagScans` yields one scan per readable frame.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from boxloc.errors import InputError
from boxloc.io.common import DEFAULT_MAX_PIXELS, _check_depth_scale, _one_line, parse_intrinsics
from boxloc.io.depth_image import range_from_depth
from boxloc.io.rosbag.camera import _Camera, _camera
from boxloc.io.rosbag.decode import (
    CAMERA_INFO,
    DEPTH_ENCODINGS,
    IMAGE,
    POINT_CLOUD,
    TF_MESSAGE,
    TF_TOPICS,
    _cloud_points,
    _decode,
    _frame,
    _stamp_ns,
    depth_raw,
)
from boxloc.io.rosbag.detect import PathLike
from boxloc.io.rosbag.records import _Bag, _Damage, _Raw, _Stop, _Topic
from boxloc.io.rosbag.tf import TfTree
from boxloc.scan import PinholeModel, RayTableModel, Scan


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

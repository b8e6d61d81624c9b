"""Writing small ROS 2 bags with rosbags (tests, samples, ``--publish-ros2``): the writer,
the message builders, and :func:`write_depth_bag` for simulated scans.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from boxloc.errors import InputError
from boxloc.io.common import _one_line
from boxloc.io.rosbag.decode import CAMERA_INFO, IMAGE, POINT_CLOUD, TF_MESSAGE, _typestore
from boxloc.io.rosbag.detect import PathLike
from boxloc.scan import PinholeModel, Scan


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

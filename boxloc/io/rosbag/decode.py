"""CDR decoding with rosbags' built-in type store, and the arrays of depth Images and
organized PointCloud2 messages.

Messages are never decoded with the bag's own definitions: rosbags turns definitions into
Python source that it executes, and the types read here (Image, CameraInfo, PointCloud2,
TFMessage) have one CDR layout in every ROS 2 distribution.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from boxloc.errors import InputError
from boxloc.io.common import _check_size, _one_line
from boxloc.io.rosbag.records import _Raw, _Stop

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POINT_CLOUD = "sensor_msgs/msg/PointCloud2"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TF_TOPICS = ("/tf", "/tf_static")

#: Depth encodings (REP 118) and their default metres per unit.
DEPTH_ENCODINGS: dict[str, float] = {"16UC1": 0.001, "32FC1": 1.0}


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

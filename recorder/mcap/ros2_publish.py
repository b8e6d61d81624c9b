"""``boxloc run --publish-ros2 OUT.mcap``: the graspable surfaces as a ROS 2 bag a cell can use.

One MCAP file (profile ``ros2``, CDR messages, ``ros2msg`` schemas, the rosbag2 metadata
record inside, written by :class:`boxloc.io.rosbag.BagWriter` with ``rosbags``), readable by
``ros2 bag play OUT.mcap`` (Iron and later; Humble with ``-s mcap``), Foxglove and RViz, and
any MCAP reader. Per scan, on the scan's stamp (its header stamp when it came from a bag) and
in its frame (the bag's ``frame_id``, else boxloc's ``sensor``):

``/boxloc/grasp_poses`` (``geometry_msgs/msg/PoseArray``)
    One pose per surface in pick order (the first is picked first): the position is the
    grasp point; the orientation's z axis is the surface normal (toward the sensor, out of
    the box's top), its x axis runs along the width, y = z x x along the length.
``/boxloc/surfaces`` (``visualization_msgs/msg/MarkerArray``)
    A ``DELETEALL`` (the previous scan's rectangles go), then per surface a closed
    ``LINE_STRIP`` of its four corners (namespace ``boxloc/rectangles``, id = pick order;
    green for the first pick, orange for the others) and its pick order as text
    (``boxloc/pick_order``).

``/boxloc/ambiguous`` (``visualization_msgs/msg/MarkerArray``)
    The flat regions that may hold several boxes but that no evidence splits
    (:class:`boxloc.products.AmbiguousSet`, the ``ambiguous`` list of ``locate``): never
    surfaces, so the cell can push, re-scan or ask. A ``DELETEALL``, then per region a
    closed magenta ``LINE_STRIP`` of its outline (namespace ``boxloc/ambiguous``, id = the
    region's ``id`` in the ``locate`` JSON) and its reason as text at its centre
    (``boxloc/ambiguous_reason``, same id; the lower-case
    :class:`boxloc.products.AmbiguityReason` name, e.g. ``larger_than_max_box``).

A scan with no surface gets an empty PoseArray and only the ``DELETEALL``s; a scan whose
pipeline failed gets nothing (all three are written when the scan's result is complete).
The log time of every message is the scan's capture time
(:func:`recorder.mcap.channels.scan_log_time`), so the bag lines up with the original one.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from boxloc.errors import InputError
from boxloc.observer import NullObserver
from boxloc.scan import Scan

__all__ = ["AMBIGUOUS_NS", "AMBIGUOUS_REASON_NS", "AMBIGUOUS_TOPIC", "GRASP_TOPIC",
           "MARKER_TOPIC", "Ros2Publisher", "grasp_orientation"]

GRASP_TOPIC = "/boxloc/grasp_poses"
MARKER_TOPIC = "/boxloc/surfaces"
AMBIGUOUS_TOPIC = "/boxloc/ambiguous"
#: Marker namespaces of the ambiguous regions: outlines, reasons.
AMBIGUOUS_NS, AMBIGUOUS_REASON_NS = "boxloc/ambiguous", "boxloc/ambiguous_reason"
#: Line width of the rectangles, metres: visible at a few metres, thinner than a box edge.
LINE_WIDTH_M = 0.005
#: Height of the pick-order text, metres.
TEXT_HEIGHT_M = 0.04
# visualization_msgs/msg/Marker constants
_ARROW, _LINE_STRIP, _TEXT = 0, 4, 9
_ADD, _DELETEALL = 0, 3
_FIRST = (0.1, 0.9, 0.2, 1.0)
_OTHER = (1.0, 0.55, 0.0, 1.0)
#: magenta, as the Rerun view draws them (world/ambiguous): not a pick, look before acting
_AMBIGUOUS = (1.0, 0.0, 1.0, 1.0)


def grasp_orientation(x_axis: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """The grasp frame's rotation (3, 3), columns x, y, z: z the normal, x the width axis
    (made orthogonal to z), y = z x x."""
    z = np.asarray(normal, np.float64)
    z = z / np.linalg.norm(z)
    x = np.asarray(x_axis, np.float64)
    x = x - (x @ z) * z
    x = x / np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], -1)


def _frame_of(scan: Scan) -> str:
    from recorder.mcap.encode import SENSOR_FRAME

    bag = scan.meta.get("rosbag") if isinstance(scan.meta, dict) else None
    if isinstance(bag, dict) and isinstance(bag.get("frame_id"), str) and bag["frame_id"]:
        return str(bag["frame_id"])
    return SENSOR_FRAME


class Ros2Publisher(NullObserver):
    """An observer that writes each scan's surfaces to a ROS 2 bag (see the module).

    Parameters
    ----------
    path : str or Path
        The ``.mcap`` file to write; it must not exist unless ``overwrite``.
    overwrite : bool
        Replace an existing file.
    """

    def __init__(self, path: str | os.PathLike[str], *, overwrite: bool = False) -> None:
        from boxloc.io.rosbag import BagWriter

        self.path = Path(path)
        if self.path.suffix.lower() != ".mcap":
            raise InputError(f"--publish-ros2 needs an .mcap file name, got {self.path}")
        if self.path.is_dir():
            raise InputError(f"--publish-ros2 {self.path} is a directory")
        if self.path.exists():
            if not overwrite:
                raise InputError(f"{self.path} exists; refusing to overwrite it (--force)")
            self.path.unlink()
        self._w = BagWriter(self.path, storage="mcap", single_file=True)
        self.n_scans = 0
        self._closed = False

    def on_result(self, scan: Scan, result: Any) -> None:
        """Write the scan's grasp poses, rectangles and ambiguous regions (all or nothing:
        only a scan whose pipeline finished has a result)."""
        from boxloc.io.rosbag import header
        from recorder.mcap.channels import scan_log_time

        t = scan_log_time(scan.capture_time_ns, scan.index)
        hdr = header(self._w.types, t, _frame_of(scan))
        self._surfaces(hdr, t, result.surfaces)
        self._ambiguous(hdr, t, result.ambiguous)
        self.n_scans += 1

    def _surfaces(self, hdr: Any, t: int, surfaces: Any) -> None:
        from scipy.spatial.transform import Rotation

        T = self._w.types
        order = np.argsort(np.asarray(surfaces.pick_order), kind="stable")
        poses, markers = [], [self._marker(hdr, "", 0, _ARROW, _DELETEALL, (0, 0, 0, 0))]
        Point, Quat = T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"]
        for k in order:
            R = grasp_orientation(surfaces.x_axis[k], surfaces.normals[k])
            qx, qy, qz, qw = Rotation.from_matrix(R).as_quat()
            g = surfaces.grasp_points[k]
            poses.append(T["geometry_msgs/msg/Pose"](
                position=Point(x=float(g[0]), y=float(g[1]), z=float(g[2])),
                orientation=Quat(x=float(qx), y=float(qy), z=float(qz), w=float(qw))))
            rank = int(surfaces.pick_order[k])
            color = _FIRST if rank == 0 else _OTHER
            ring = np.asarray(surfaces.corners[k], np.float64)
            line = self._marker(hdr, "boxloc/rectangles", rank, _LINE_STRIP, _ADD, color)
            line.points = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2]))
                           for p in (*ring, ring[0])]
            line.scale.x = LINE_WIDTH_M
            markers.append(line)
            text = self._marker(hdr, "boxloc/pick_order", rank, _TEXT, _ADD, color)
            c = np.asarray(surfaces.centers[k], np.float64) + 0.03 * R[:, 2]
            text.pose.position = Point(x=float(c[0]), y=float(c[1]), z=float(c[2]))
            text.scale.z = TEXT_HEIGHT_M
            text.text = str(rank)
            markers.append(text)
        self._w.write(GRASP_TOPIC, T["geometry_msgs/msg/PoseArray"](header=hdr, poses=poses), t)
        self._w.write(MARKER_TOPIC, T["visualization_msgs/msg/MarkerArray"](markers=markers), t)

    def _ambiguous(self, hdr: Any, t: int, ambiguous: Any) -> None:
        from boxloc.products import AmbiguityReason

        T = self._w.types
        Point = T["geometry_msgs/msg/Point"]
        markers = [self._marker(hdr, "", 0, _ARROW, _DELETEALL, (0, 0, 0, 0))]
        for k in range(len(ambiguous)):
            ring = np.asarray(ambiguous.corners[k], np.float64)
            line = self._marker(hdr, AMBIGUOUS_NS, k, _LINE_STRIP, _ADD, _AMBIGUOUS)
            line.points = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2]))
                           for p in (*ring, ring[0])]
            line.scale.x = LINE_WIDTH_M
            markers.append(line)
            text = self._marker(hdr, AMBIGUOUS_REASON_NS, k, _TEXT, _ADD, _AMBIGUOUS)
            c = ring.mean(axis=0)
            text.pose.position = Point(x=float(c[0]), y=float(c[1]), z=float(c[2]))
            text.scale.z = TEXT_HEIGHT_M
            text.text = AmbiguityReason(int(ambiguous.reason[k])).name.lower()
            markers.append(text)
        self._w.write(AMBIGUOUS_TOPIC, T["visualization_msgs/msg/MarkerArray"](markers=markers),
                      t)

    def _marker(self, hdr: Any, ns: str, ident: int, kind: int, action: int,
                color: tuple[float, float, float, float]) -> Any:
        T = self._w.types
        V3, Pt, Q = (T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Point"],
                     T["geometry_msgs/msg/Quaternion"])
        return T["visualization_msgs/msg/Marker"](
            header=hdr, ns=ns, id=ident, type=kind, action=action,
            pose=T["geometry_msgs/msg/Pose"](position=Pt(x=0.0, y=0.0, z=0.0),
                                             orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0)),
            scale=V3(x=0.0, y=0.0, z=0.0),
            color=T["std_msgs/msg/ColorRGBA"](r=color[0], g=color[1], b=color[2], a=color[3]),
            lifetime=T["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
            frame_locked=False, points=[], colors=[], texture_resource="",
            texture=T["sensor_msgs/msg/CompressedImage"](
                header=hdr, format="", data=np.zeros(0, np.uint8)),
            uv_coordinates=[], text="", mesh_resource="",
            mesh_file=T["visualization_msgs/msg/MeshFile"](filename="",
                                                           data=np.zeros(0, np.uint8)),
            mesh_use_embedded_materials=False)

    def close(self) -> None:
        """Finish the bag (its index and metadata); safe to call twice."""
        if not self._closed:
            self._closed = True
            self._w.close()

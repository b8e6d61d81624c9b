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

Modules
-------
:mod:`~boxloc.io.rosbag.detect`
    :func:`is_rosbag`: which files are bags.
:mod:`~boxloc.io.rosbag.records`
    The raw messages, through rosbags or record by record (the damaged-bag fallback).
:mod:`~boxloc.io.rosbag.decode`
    CDR decoding; the arrays of depth Images and PointCloud2 messages.
:mod:`~boxloc.io.rosbag.tf`, :mod:`~boxloc.io.rosbag.camera`
    The sensor pose from /tf; the sensor model from a CameraInfo.
:mod:`~boxloc.io.rosbag.scans`
    :func:`open_bag` and :class:`BagScans`: the scans of a bag.
:mod:`~boxloc.io.rosbag.write`
    :class:`BagWriter`, the message builders and :func:`write_depth_bag`.
"""

from __future__ import annotations

from boxloc.io.rosbag.decode import (
    CAMERA_INFO,
    DEPTH_ENCODINGS,
    IMAGE,
    POINT_CLOUD,
    TF_MESSAGE,
    TF_TOPICS,
    depth_raw,
)
from boxloc.io.rosbag.detect import PathLike, is_rosbag
from boxloc.io.rosbag.scans import BagScans, open_bag
from boxloc.io.rosbag.tf import TfTree
from boxloc.io.rosbag.write import (
    BagWriter,
    camera_info_message,
    cloud_message,
    depth_of,
    header,
    image_message,
    tf_message,
    write_depth_bag,
)

__all__ = [
    "IMAGE", "CAMERA_INFO", "POINT_CLOUD", "TF_MESSAGE", "TF_TOPICS", "DEPTH_ENCODINGS",
    "PathLike", "TfTree",
    "is_rosbag", "open_bag", "BagScans", "BagWriter", "write_depth_bag", "depth_raw",
    "header", "image_message", "camera_info_message", "cloud_message", "tf_message", "depth_of",
]
